"""The 57-keypoint layout shared by egopose, ik and every keypoints artifact, and the
:class:`Keypoints` sequence (the payload of :mod:`egorelight_cli.io.keypoints`).

57 = 15 body keypoints (the Mo2Cap2 set: neck, shoulders, elbows, wrists, hips, knees, ankles,
toes) + 2 x 21 hand keypoints (wrist, then 4 per finger from the base to the tip). Names follow
DDC skeleton joint base names (the part before the first ``_``). The body wrist and the hand
wrist sit on the same joint; the hand one is named ``<Side>HandWrist`` to keep names unique.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError

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
HANDS_SLICE = slice(len(BODY_KEYPOINTS), NUM_KEYPOINTS)
LEFT_HAND_SLICE = slice(len(BODY_KEYPOINTS), len(BODY_KEYPOINTS) + 21)
RIGHT_HAND_SLICE = slice(len(BODY_KEYPOINTS) + 21, len(BODY_KEYPOINTS) + 42)


def keypoint_edges() -> list[tuple[int, int]]:
    """Pairs of keypoint indices drawn as bones (body chains, each finger from the wrist)."""
    index = {n: i for i, n in enumerate(KEYPOINT_NAMES)}
    pairs = [("Neck", "LeftArm"), ("Neck", "RightArm"), ("LeftUpLeg", "RightUpLeg")]
    for side in ("Left", "Right"):
        pairs += [(f"{side}Arm", f"{side}ForeArm"), (f"{side}ForeArm", f"{side}Hand"), ("Neck", f"{side}UpLeg"),
                  (f"{side}UpLeg", f"{side}Leg"), (f"{side}Leg", f"{side}Foot"), (f"{side}Foot", f"{side}ToeBase")]
        for finger in FINGERS:
            chain = [f"{side}HandWrist"] + [f"{side}Hand{finger}{s}" for s in FINGER_SEGMENTS]
            pairs += list(zip(chain[:-1], chain[1:]))
    return [(index[a], index[b]) for a, b in pairs]


assert NUM_KEYPOINTS == 57

KEYPOINTS_UNITS = {"xyz": "m", "confidence": "1"}


@dataclass(frozen=True, eq=False)
class Keypoints:
    """A keypoint sequence (arrays in :mod:`egorelight_cli.io.keypoints`).

    Construction validates shapes and values: ``xyz`` must be (T,K,3) with K = len(names),
    ``confidence`` (T,K) finite in [0,1], ``frame_ids`` (T,) strictly increasing. Entries whose
    ``xyz`` is not finite get confidence 0 (and xyz NaN), so consumers only need ``confidence``.
    """

    xyz: np.ndarray
    confidence: np.ndarray
    frame_ids: np.ndarray
    names: tuple[str, ...] = KEYPOINT_NAMES
    fps: float | None = None

    def __post_init__(self) -> None:
        xyz = np.array(self.xyz, dtype=np.float32)
        conf = np.array(self.confidence, dtype=np.float32)
        ids = np.asarray(self.frame_ids)
        names = tuple(str(n) for n in self.names)
        K = len(names)
        if xyz.ndim != 3 or xyz.shape[1:] != (K, 3):
            raise EgorelightError(f"keypoints xyz has shape {xyz.shape}, expected (T, {K}, 3)")
        T = xyz.shape[0]
        if conf.shape != (T, K):
            raise EgorelightError(f"keypoints confidence has shape {conf.shape}, expected ({T}, {K})")
        if ids.shape != (T,) or not np.issubdtype(ids.dtype, np.integer):
            raise EgorelightError(f"keypoints frame_ids has shape {ids.shape} and dtype {ids.dtype}, expected ({T},) integers")
        ids = ids.astype(np.int64)
        if T > 1 and np.any(np.diff(ids) <= 0):
            raise EgorelightError("keypoints frame_ids are not strictly increasing")
        if np.isnan(conf).any():
            raise EgorelightError(f"keypoints confidence holds {int(np.isnan(conf).sum())} NaN values")
        if conf.size and (conf.min() < 0 or conf.max() > 1):
            raise EgorelightError(f"keypoints confidence outside [0, 1] (range {conf.min():.3g}..{conf.max():.3g})")
        missing = ~np.isfinite(xyz).all(axis=-1)
        if missing.any():
            xyz[missing] = np.nan
            conf[missing] = 0.0
        if self.fps is not None and not (np.isfinite(self.fps) and self.fps > 0):
            raise EgorelightError(f"keypoints fps must be positive, got {self.fps}")
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "confidence", conf)
        object.__setattr__(self, "frame_ids", ids)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "fps", None if self.fps is None else float(self.fps))

    @property
    def num_frames(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def has_standard_layout(self) -> bool:
        return self.names == KEYPOINT_NAMES

    def require_standard_layout(self, path: str | Path | None = None) -> "Keypoints":
        """Raise unless the names are the 57-keypoint layout (in order)."""
        if len(self.names) != NUM_KEYPOINTS:
            raise EgorelightError(f"keypoints have {len(self.names)} keypoints, expected {NUM_KEYPOINTS}", path)
        if not self.has_standard_layout:
            bad = next(i for i, (a, b) in enumerate(zip(self.names, KEYPOINT_NAMES)) if a != b)
            raise EgorelightError(f"keypoint {bad} is named {self.names[bad]!r}, expected {KEYPOINT_NAMES[bad]!r}", path)
        return self

    def select(self, rows) -> "Keypoints":
        """The frames at positions ``rows`` (slice, index array or boolean mask)."""
        return Keypoints(self.xyz[rows], self.confidence[rows], self.frame_ids[rows], self.names, self.fps)

    def arrays(self) -> dict[str, np.ndarray]:
        """The payload arrays (float32 xyz/confidence, int64 frame ids, str names)."""
        return {"xyz": self.xyz, "confidence": self.confidence, "frame_ids": self.frame_ids,
                "names": np.array(self.names, dtype=str)}

    def meta(self) -> dict:
        """``__meta__`` extras: units and, when known, fps."""
        meta: dict = {"units": dict(KEYPOINTS_UNITS)}
        if self.fps is not None:
            meta["fps"] = self.fps
        return meta
