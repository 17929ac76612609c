"""The 57-keypoint layout shared by egopose, ik and every keypoints artifact.

57 = 15 body keypoints (the Mo2Cap2 set: neck, shoulders, elbows, wrists, hips, knees, ankles,
toes) + 2 x 21 hand keypoints (wrist, then 4 per finger from the base to the tip). Names follow
DDC skeleton joint base names (the part before the first ``_``). The body wrist and the hand
wrist sit on the same joint; the hand one is named ``<Side>HandWrist`` to keep names unique.
"""

from __future__ import annotations

BODY_KEYPOINTS: tuple[str, ...] = (
    "Neck",
    "LeftArm", "RightArm",            # shoulders
    "LeftForeArm", "RightForeArm",    # elbows
    "LeftHand", "RightHand",          # wrists
    "LeftUpLeg", "RightUpLeg",        # hips
    "LeftLeg", "RightLeg",            # knees
    "LeftFoot", "RightFoot",          # ankles
    "LeftToeBase", "RightToeBase",    # toes
)

FINGERS: tuple[str, ...] = ("Thumb", "Index", "Middle", "Ring", "Pinky")
FINGER_SEGMENTS: tuple[str, ...] = ("1", "2", "3", "EE")  # base, middle, distal, tip


def hand_keypoints(side: str) -> tuple[str, ...]:
    """The 21 keypoint names of one hand; ``side`` is ``"Left"`` or ``"Right"``."""
    names = [f"{side}HandWrist"]
    for finger in FINGERS:
        names += [f"{side}Hand{finger}{seg}" for seg in FINGER_SEGMENTS]
    return tuple(names)


KEYPOINT_NAMES: tuple[str, ...] = BODY_KEYPOINTS + hand_keypoints("Left") + hand_keypoints("Right")
NUM_KEYPOINTS = len(KEYPOINT_NAMES)
BODY_SLICE = slice(0, len(BODY_KEYPOINTS))
LEFT_HAND_SLICE = slice(len(BODY_KEYPOINTS), len(BODY_KEYPOINTS) + 21)
RIGHT_HAND_SLICE = slice(len(BODY_KEYPOINTS) + 21, len(BODY_KEYPOINTS) + 42)

assert NUM_KEYPOINTS == 57
