"""A parameterised library of the paper's motion types, written against the default character's
semantic DoF names (see the docstring of :mod:`egorelight_cli.stages.character`).

The paper (supplement, Table "List of motions") records T-pose, jogging, walking, picking up,
waving, celebrating, boxing, kicking, golfing, bicep curls, drinking, typing, stretching,
raising legs, ... for 20 s each in training and 5 s each in testing, with *different instances*
of the same types, and ends the test sequence with unscripted "casual" motion. Here every type is
a function of time and a random generator (amplitudes, frequencies, phases, the active side,
finger curls), so two seeds give two instances of the same type. :func:`compose_motion` strings
segments together with smooth cross-fades, keeps the feet on the floor (root height from forward
kinematics) and clips every DoF to the character's limits.

Sign conventions (the default character): it faces -Z, its left is -X; hinges (elbow, knee,
finger flexion) curl with **negative** values; positive ``shoulder_abduct`` raises the arm
sideways (about 0.85 rad from the rest A-pose gives a T-pose), positive ``shoulder_flex`` raises
it forwards, positive ``hip_flex`` lifts the thigh forwards, positive spine ``bend`` bends forward.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.structures.character import Character

SIDES = ("left", "right")
FINGER_NAMES = ("index", "middle", "ring", "pinky")

#: DoFs every motion here relies on (a character lacking them needs ``--motion``).
REQUIRED_DOFS = (
    "translate_x", "translate_y", "translate_z", "rotate_y", "rotate_z", "rotate_x",
    "spine1_bend", "neck_bend", "head_twist", "left_shoulder_abduct", "left_shoulder_flex",
    "left_elbow", "left_hip_flex", "left_knee", "left_index_flex1", "right_index_flex2",
    "right_thumb_flex1",
)

Pose = dict[str, np.ndarray]
MotionFn = Callable[[np.ndarray, np.random.Generator], Pose]

#: Rest-pose (theta = 0) heights of the ankle and toe keypoints above the floor, metres
#: (the default character's feet touch y = 0 at rest).
_ANKLE_HEIGHT = 0.072
_TOE_HEIGHT = 0.016
_CLIP_MARGIN = 0.02  # rad/m kept inside every DoF limit


# --------------------------------------------------------------------------------- building blocks
def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _const(t: np.ndarray, value: float) -> np.ndarray:
    return np.full_like(t, value, dtype=np.float64)


def smooth_noise(t: np.ndarray, rng: np.random.Generator, scale: float, cutoff_hz: float = 0.6,
                 components: int = 4) -> np.ndarray:
    """Band-limited random signal: a sum of a few random sinusoids below ``cutoff_hz``, RMS ~ scale."""
    out = np.zeros_like(t, dtype=np.float64)
    for _ in range(components):
        freq = rng.uniform(0.1, 1.0) * cutoff_hz
        out += np.sin(2 * np.pi * freq * t + rng.uniform(0, 2 * np.pi))
    return scale * out * np.sqrt(2.0 / components)


def relaxed_pose(t: np.ndarray) -> Pose:
    """Standing relaxed: arms hanging by the sides, elbows and fingers slightly bent."""
    pose: Pose = {}
    for side in SIDES:
        pose[f"{side}_shoulder_abduct"] = _const(t, -0.55)
        pose[f"{side}_elbow"] = _const(t, -0.25)
        pose.update(hand_pose(side, t, curl=0.25))
    return pose


def hand_pose(side: str, t: np.ndarray, curl=0.0, spread=0.0, thumb=None) -> Pose:
    """Finger DoFs of one hand: ``curl`` 0 (open) .. 1 (fist), ``spread`` -1..1, scalars or arrays."""
    curl = np.broadcast_to(np.asarray(curl, dtype=np.float64), t.shape)
    spread = np.broadcast_to(np.asarray(spread, dtype=np.float64), t.shape)
    thumb = curl if thumb is None else np.broadcast_to(np.asarray(thumb, dtype=np.float64), t.shape)
    pose: Pose = {}
    for i, finger in enumerate(FINGER_NAMES):
        lag = 1.0 + 0.05 * i  # outer fingers curl a little more
        pose[f"{side}_{finger}_flex1"] = -1.35 * np.clip(curl * lag, 0, 1)
        pose[f"{side}_{finger}_flex2"] = -1.5 * np.clip(curl * lag, 0, 1)
    pose[f"{side}_thumb_abduct"] = 0.2 + 0.3 * thumb
    pose[f"{side}_thumb_flex1"] = -0.3 * thumb
    pose[f"{side}_thumb_flex2"] = -0.6 * thumb
    pose[f"{side}_thumb_flex3"] = -0.8 * thumb
    pose[f"{side}_index_spread"] = 0.3 * spread
    pose[f"{side}_pinky_spread"] = 0.4 * spread
    return pose


def _other(side: str) -> str:
    return "right" if side == "left" else "left"


def _breathing(t: np.ndarray, rng: np.random.Generator) -> Pose:
    f = _u(rng, 0.2, 0.35)
    return {"spine3_bend": 0.02 * np.sin(2 * np.pi * f * t + _u(rng, 0, 6.3)),
            "neck_bend": 0.05 * np.sin(2 * np.pi * 0.5 * f * t + _u(rng, 0, 6.3))}


def _gait(t: np.ndarray, rng: np.random.Generator, freq: float, hip: float, knee: float, arm: float,
          elbow: float) -> Pose:
    """Leg and arm swing of walking/jogging at stride frequency ``freq`` (Hz)."""
    phase = 2 * np.pi * freq * t + _u(rng, 0, 2 * np.pi)
    pose: Pose = {}
    for side, shift in (("left", 0.0), ("right", np.pi)):
        s = np.sin(phase + shift)
        pose[f"{side}_hip_flex"] = 0.1 + hip * s
        pose[f"{side}_knee"] = -0.1 - knee * np.clip(np.sin(phase + shift + 1.2), 0, None)
        pose[f"{side}_ankle_flex"] = 0.15 * np.sin(phase + shift - 0.8)
        pose[f"{side}_shoulder_flex"] = -arm * s  # arms swing opposite to the legs
        pose[f"{side}_shoulder_abduct"] = _const(t, -0.5)
        pose[f"{side}_elbow"] = -elbow - 0.15 * np.clip(-s, 0, None)
    pose["spine2_twist"] = 0.06 * np.sin(phase)
    pose["spine0_lean"] = 0.03 * np.sin(phase)
    return pose


def _circle_path(t: np.ndarray, rng: np.random.Generator, speed: float) -> Pose:
    """Walk on a circle of radius 0.3-0.5 m around the origin, facing along the path.

    At t = 0 the walker faces -Z (heading 0); :func:`segment_theta` turns the whole path about
    the vertical axis through the origin to the segment's heading.
    """
    radius = _u(rng, 0.3, 0.5)
    direction = rng.choice([-1.0, 1.0])
    # Position on the circle; the heading is the tangent. The character faces -Z at rotate_y 0,
    # and rotate_y turns it counter-clockwise seen from above (facing -X at +pi/2).
    angle = direction * (np.pi / 2 + speed / radius * t)
    x, z = radius * np.sin(angle), radius * np.cos(angle)
    tangent = direction * np.stack([np.cos(angle), -np.sin(angle)])
    heading = np.arctan2(-tangent[0], -tangent[1])
    return {"translate_x": x, "translate_z": z, "rotate_y": np.unwrap(heading)}


# ------------------------------------------------------------------------------------ motion types
def t_pose(t, rng):
    pose = {f"{s}_shoulder_abduct": _const(t, _u(rng, 0.8, 0.9)) for s in SIDES}
    for s in SIDES:
        pose[f"{s}_elbow"] = _const(t, -0.05)
        pose.update(hand_pose(s, t, curl=_u(rng, 0.0, 0.15), spread=_u(rng, 0, 0.5)))
    pose.update(_breathing(t, rng))
    return pose


def walking(t, rng):
    pose = _gait(t, rng, _u(rng, 0.8, 1.0), hip=_u(rng, 0.3, 0.42), knee=_u(rng, 0.5, 0.75),
                 arm=_u(rng, 0.2, 0.35), elbow=0.25)
    pose.update(_circle_path(t, rng, _u(rng, 0.45, 0.65)))
    for s in SIDES:
        pose.update(hand_pose(s, t, curl=_u(rng, 0.15, 0.4)))
    return pose


def jogging(t, rng):
    pose = _gait(t, rng, _u(rng, 1.3, 1.5), hip=_u(rng, 0.45, 0.6), knee=_u(rng, 1.1, 1.4),
                 arm=_u(rng, 0.4, 0.6), elbow=1.3)
    pose.update(_circle_path(t, rng, _u(rng, 0.9, 1.2)))
    pose["spine1_bend"] = _const(t, 0.08)
    for s in SIDES:
        pose.update(hand_pose(s, t, curl=_u(rng, 0.5, 0.8)))
    return pose


def waving(t, rng):
    side = rng.choice(SIDES)
    pose = relaxed_pose(t)
    f = _u(rng, 1.2, 2.0)
    wave = np.sin(2 * np.pi * f * t + _u(rng, 0, 6.3))
    pose[f"{side}_shoulder_abduct"] = _const(t, _u(rng, 1.9, 2.3))
    pose[f"{side}_shoulder_flex"] = _const(t, _u(rng, 0.0, 0.4))
    pose[f"{side}_elbow"] = -_u(rng, 0.6, 1.0) + 0.45 * wave
    pose[f"{side}_forearm_twist"] = 0.3 * wave
    pose[f"{side}_wrist_deviate"] = 0.2 * wave
    pose.update(hand_pose(side, t, curl=0.05, spread=_u(rng, 0.4, 1.0)))
    pose["head_twist"] = _const(t, _u(rng, -0.3, 0.3))
    pose.update(_breathing(t, rng))
    return pose


def boxing(t, rng):
    pose: Pose = {}
    period = _u(rng, 0.7, 1.0)
    for i, side in enumerate(SIDES):
        phase = (t / period + 0.5 * i + _u(rng, 0, 0.2)) % 1.0
        punch = np.exp(-((phase - 0.3) / 0.09) ** 2)  # a short extension once per period
        pose[f"{side}_shoulder_flex"] = 0.9 + 0.55 * punch
        pose[f"{side}_shoulder_abduct"] = -0.3 - 0.2 * punch
        pose[f"{side}_elbow"] = -1.65 + 1.45 * punch
        pose[f"{side}_forearm_twist"] = 0.6 * punch
        pose.update(hand_pose(side, t, curl=0.95, thumb=0.8))
        pose[f"{side}_hip_flex"] = _const(t, 0.2)
        pose[f"{side}_knee"] = _const(t, -0.35)
    pose["spine2_twist"] = 0.15 * np.sin(2 * np.pi * t / period)
    pose["spine1_bend"] = _const(t, 0.1)
    pose["neck_bend"] = _const(t, -0.05)
    return pose


def picking_up(t, rng):
    period = _u(rng, 2.5, 3.5)
    s = 0.5 - 0.5 * np.cos(2 * np.pi * t / period + _u(rng, 0, 0.5))  # 0 upright .. 1 down
    side = rng.choice(SIDES)
    pose = relaxed_pose(t)
    for k in range(5):
        pose[f"spine{k}_bend"] = 0.28 * s
    for sd in SIDES:
        pose[f"{sd}_hip_flex"] = 0.9 * s
        pose[f"{sd}_knee"] = -1.1 * s
        pose[f"{sd}_ankle_flex"] = 0.25 * s
    pose[f"{side}_shoulder_flex"] = 1.0 * s
    pose[f"{side}_elbow"] = -0.2 - 0.2 * s
    pose.update(hand_pose(side, t, curl=0.1 + 0.8 * np.clip(2 * s - 1, 0, 1)))
    pose["neck_bend"] = -0.3 * s
    return pose


def stretching(t, rng):
    period = _u(rng, 3.0, 4.0)
    s = np.sin(2 * np.pi * t / period)
    pose: Pose = {}
    for side in SIDES:
        pose[f"{side}_shoulder_flex"] = _const(t, _u(rng, 0.2, 0.5))
        pose[f"{side}_shoulder_abduct"] = _const(t, _u(rng, 2.1, 2.3))
        pose[f"{side}_elbow"] = _const(t, -0.15)
        pose.update(hand_pose(side, t, curl=0.05, spread=0.8))
    for k in range(1, 5):
        pose[f"spine{k}_lean"] = 0.13 * s
    pose["neck_bend"] = _const(t, -0.2)
    return pose


def typing(t, rng):
    pose = relaxed_pose(t)
    for side in SIDES:
        pose[f"{side}_shoulder_flex"] = _const(t, _u(rng, 0.15, 0.3))
        pose[f"{side}_shoulder_abduct"] = _const(t, -0.55)
        pose[f"{side}_shoulder_twist"] = _const(t, 0.2)
        pose[f"{side}_elbow"] = _const(t, -_u(rng, 0.75, 0.95)) + smooth_noise(t, rng, 0.03, 1.0)
        pose[f"{side}_forearm_twist"] = _const(t, 0.9)
        pose[f"{side}_wrist_flex"] = _const(t, 0.2)
        for finger in FINGER_NAMES:  # fingers tap independently
            f = _u(rng, 2.0, 4.0)
            tap = np.clip(np.sin(2 * np.pi * f * t + _u(rng, 0, 6.3)), 0, None) ** 4
            pose[f"{side}_{finger}_flex1"] = -0.3 - 0.5 * tap
            pose[f"{side}_{finger}_flex2"] = -0.5 - 0.4 * tap
    pose["neck_bend"] = _const(t, 0.35)
    pose["head_bend"] = _const(t, 0.2)
    return pose


def celebrating(t, rng):
    f = _u(rng, 1.5, 2.2)
    pump = 0.5 + 0.5 * np.sin(2 * np.pi * f * t)
    pose: Pose = {}
    for side in SIDES:
        pose[f"{side}_shoulder_abduct"] = 1.8 + 0.5 * pump
        pose[f"{side}_shoulder_flex"] = _const(t, 0.3)
        pose[f"{side}_elbow"] = -0.3 - 0.9 * (1 - pump)
        pose.update(hand_pose(side, t, curl=0.9))
    pose["jump"] = 0.06 * np.clip(np.sin(2 * np.pi * f * t), 0, None)
    pose["neck_bend"] = _const(t, -0.3)
    return pose


def kicking(t, rng):
    side = rng.choice(SIDES)
    period = _u(rng, 1.5, 2.0)
    phase = (t / period) % 1.0
    kick = np.exp(-((phase - 0.5) / 0.12) ** 2)
    chamber = np.exp(-((phase - 0.38) / 0.1) ** 2)  # the knee folds before the leg extends
    pose = relaxed_pose(t)
    pose[f"{side}_hip_flex"] = -0.2 + 1.4 * kick + 0.4 * chamber
    pose[f"{side}_knee"] = -0.1 - 1.2 * chamber
    pose[f"{_other(side)}_knee"] = _const(t, -0.2)
    for s in SIDES:
        pose[f"{s}_shoulder_abduct"] = -0.1 + 0.4 * kick
    pose["spine1_bend"] = -0.1 * kick
    return pose


def golfing(t, rng):
    period = _u(rng, 2.0, 2.8)
    swing = np.sin(2 * np.pi * t / period)
    pose: Pose = {}
    for side in SIDES:
        pose[f"{side}_shoulder_flex"] = 0.7 + 0.4 * np.abs(swing)
        pose[f"{side}_shoulder_abduct"] = _const(t, -0.4)
        pose[f"{side}_elbow"] = _const(t, -0.2)
        pose.update(hand_pose(side, t, curl=0.9))
        pose[f"{side}_knee"] = _const(t, -0.3)
        pose[f"{side}_hip_flex"] = _const(t, 0.35)
    pose["left_shoulder_flex"] = pose["left_shoulder_flex"] + 0.3 * swing
    pose["right_shoulder_flex"] = pose["right_shoulder_flex"] - 0.3 * swing
    for k in range(1, 4):
        pose[f"spine{k}_twist"] = 0.18 * swing
        pose[f"spine{k}_bend"] = _const(t, 0.12)
    pose["neck_bend"] = _const(t, 0.3)
    return pose


def bicep_curls(t, rng):
    f = _u(rng, 0.5, 0.8)
    pose = relaxed_pose(t)
    for i, side in enumerate(SIDES):
        c = 0.5 - 0.5 * np.cos(2 * np.pi * f * t + np.pi * i)
        pose[f"{side}_elbow"] = -0.2 - 1.45 * c
        pose[f"{side}_shoulder_abduct"] = _const(t, -0.6)
        pose[f"{side}_forearm_twist"] = _const(t, -0.6)
        pose.update(hand_pose(side, t, curl=0.9))
    return pose


def drinking(t, rng):
    side = rng.choice(SIDES)
    period = _u(rng, 2.5, 3.5)
    s = np.clip(1.6 * (0.5 - 0.5 * np.cos(2 * np.pi * t / period)), 0, 1)
    pose = relaxed_pose(t)
    pose[f"{side}_shoulder_flex"] = 0.2 + 0.6 * s
    pose[f"{side}_shoulder_abduct"] = -0.55 + 0.3 * s
    pose[f"{side}_elbow"] = -0.3 - 1.4 * s
    pose.update(hand_pose(side, t, curl=0.6, thumb=0.3))
    pose["neck_bend"] = -0.25 * s
    return pose


def raising_legs(t, rng):
    f = _u(rng, 0.5, 0.8)
    pose = relaxed_pose(t)
    for i, side in enumerate(SIDES):
        c = np.clip(np.sin(2 * np.pi * f * t + np.pi * i), 0, None)
        pose[f"{side}_hip_flex"] = 1.3 * c
        pose[f"{side}_knee"] = -1.6 * c - 0.05
        pose[f"{side}_shoulder_abduct"] = _const(t, -0.2)
    return pose


def turning_scan(t, rng, duration: float = 10.0):
    """Turning in place (~1.1 turns over ``duration`` seconds) while looking around: the in-the-wild
    scan (the paper: about 10 s)."""
    turns = _u(rng, 1.05, 1.15) * rng.choice([-1.0, 1.0])
    pose = relaxed_pose(t)
    pose["rotate_y"] = 2 * np.pi * turns * t / max(float(duration), 1e-3)
    step = np.sin(2 * np.pi * 1.2 * t)
    for side, shift in (("left", 0.0), ("right", np.pi)):
        lift = np.clip(np.sin(2 * np.pi * 1.2 * t + shift), 0, None)
        pose[f"{side}_hip_flex"] = 0.25 * lift
        pose[f"{side}_knee"] = -0.5 * lift
    pose["head_bend"] = 0.15 * smooth_noise(t, rng, 1.0, 0.4)
    pose["neck_twist"] = 0.1 * step
    return pose


def handeye_looking(t, rng):
    """Standing in front of a calibration board, moving the head in every direction (hand-eye)."""
    pose = relaxed_pose(t)
    pose["neck_bend"] = 0.3 + smooth_noise(t, rng, 0.1, 0.5)
    pose["neck_twist"] = smooth_noise(t, rng, 0.18, 0.5)
    pose["neck_lean"] = smooth_noise(t, rng, 0.12, 0.5)
    pose["head_bend"] = smooth_noise(t, rng, 0.08, 0.5)
    pose["head_lean"] = smooth_noise(t, rng, 0.1, 0.5)
    pose["spine2_twist"] = smooth_noise(t, rng, 0.05, 0.3)
    pose["spine1_bend"] = 0.05 + smooth_noise(t, rng, 0.06, 0.3)
    return pose


#: Leaves drawn on by the casual motion: DoF name -> (centre, amplitude) relative to relaxed.
_CASUAL_DOFS = {
    "neck_twist": (0.0, 0.35), "neck_bend": (0.1, 0.2), "head_lean": (0.0, 0.15),
    "spine1_bend": (0.1, 0.15), "spine2_twist": (0.0, 0.15), "spine3_lean": (0.0, 0.08),
    "{s}_shoulder_abduct": (-0.1, 0.7), "{s}_shoulder_flex": (0.5, 0.7), "{s}_shoulder_twist": (0.0, 0.4),
    "{s}_elbow": (-0.8, 0.6), "{s}_forearm_twist": (0.2, 0.6), "{s}_wrist_flex": (0.0, 0.4),
    "{s}_hip_flex": (0.15, 0.2), "{s}_knee": (-0.3, 0.25),
}


def casual(t, rng):
    """Unscripted motion: a random smooth combination of a scripted type and free limb motion."""
    base_type = rng.choice([n for n in SCRIPTED if n not in ("t_pose",)])
    pose = MOTIONS[base_type](t, rng)
    weight = _u(rng, 0.3, 0.6)
    for template, (centre, amplitude) in _CASUAL_DOFS.items():
        for side in SIDES if "{s}" in template else ("",):
            name = template.format(s=side)
            free = centre + smooth_noise(t, rng, 0.5 * amplitude, 0.5)
            pose[name] = (1 - weight) * pose.get(name, free) + weight * free
    for side in SIDES:
        pose.update(hand_pose(side, t, curl=np.clip(0.4 + smooth_noise(t, rng, 0.35, 0.6), 0, 1),
                              spread=smooth_noise(t, rng, 0.4, 0.5)))
    return pose


MOTIONS: dict[str, MotionFn] = {
    "t_pose": t_pose, "walking": walking, "jogging": jogging, "waving": waving, "boxing": boxing,
    "picking_up": picking_up, "stretching": stretching, "typing": typing, "celebrating": celebrating,
    "kicking": kicking, "golfing": golfing, "bicep_curls": bicep_curls, "drinking": drinking,
    "raising_legs": raising_legs, "turning_scan": turning_scan, "handeye_looking": handeye_looking,
    "casual": casual,
}
#: The paper's scripted types (training and test), in the order of its table.
SCRIPTED = ("t_pose", "jogging", "walking", "picking_up", "waving", "celebrating", "boxing", "kicking",
            "golfing", "bicep_curls", "drinking", "typing", "stretching", "raising_legs")


# ------------------------------------------------------------------------------------- composition
@dataclass(frozen=True)
class Segment:
    """One motion instance: ``motion`` (a key of :data:`MOTIONS`) for ``duration_s`` seconds."""

    motion: str
    duration_s: float


def check_motion_dofs(character: Character) -> None:
    """Raise a clear error when the character lacks the DoF names the motion library drives."""
    names = set(character.skeleton.dof_names)
    missing = [n for n in REQUIRED_DOFS if n not in names]
    if missing:
        raise EgorelightError(
            f"character {character.name!r} lacks the default character's DoF names ({', '.join(missing[:5])}"
            f"{', ...' if len(missing) > 5 else ''}); the built-in motion library cannot drive it: pass "
            "--motion PATH (a motion artifact) instead")


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _pose_to_theta(pose: Pose, dof_names: Sequence[str], n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n,D) theta from a pose dict (missing DoFs 0) and the extra ``jump`` height (n,)."""
    index = {name: i for i, name in enumerate(dof_names)}
    theta = np.zeros((n, len(dof_names)))
    for name, value in pose.items():
        if name in index:
            theta[:, index[name]] = np.broadcast_to(value, (n,))
    jump = np.broadcast_to(pose.get("jump", 0.0), (n,)).astype(np.float64)
    return theta, jump


def segment_theta(character: Character, segment: Segment, t: np.ndarray, rng: np.random.Generator,
                  heading: float = 0.0, origin=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """(n,D) theta and (n,) jump height of one motion instance at local times ``t`` (s).

    Non-locomotion motions are placed at ``origin`` (x, z) facing ``heading`` (rotate_y, rad);
    locomotion paths are turned by ``heading`` about the vertical axis through the origin.
    """
    if segment.motion not in MOTIONS:
        raise EgorelightError(f"unknown motion type {segment.motion!r}; known: {', '.join(MOTIONS)}")
    pose = dict(relaxed_pose(t))
    if segment.motion == "turning_scan":
        pose.update(turning_scan(t, rng, duration=segment.duration_s))
    else:
        pose.update(MOTIONS[segment.motion](t, rng))
    pose.update(_breathing(t, rng) if "spine3_bend" not in pose else {})
    if "translate_x" not in pose:
        pose["translate_x"] = _const(t, origin[0])
        pose["translate_z"] = _const(t, origin[1])
    else:
        x, z = np.asarray(pose["translate_x"]), np.asarray(pose["translate_z"])
        c, s = np.cos(heading), np.sin(heading)
        pose["translate_x"], pose["translate_z"] = c * x + s * z, -s * x + c * z
    pose["rotate_y"] = heading + np.asarray(pose.get("rotate_y", 0.0))
    return _pose_to_theta(pose, character.skeleton.dof_names, len(t))


def compose_motion(character: Character, segments: Sequence[Segment], fps: float, num_frames: int,
                   seed: int, crossfade_s: float = 0.4, heading_range: float = 0.7,
                   start_s: float = 0.0, origin_range: float = 0.1) -> np.ndarray:
    """Theta (num_frames, D) of ``segments`` played in order at ``fps``, cross-faded, grounded, clipped.

    Segments shorter than the requested span are repeated in order; each (segment, repetition)
    draws its own instance from ``seed``. Frame ``i`` is at time ``start_s + i / fps``. Each
    instance turns by up to ``heading_range`` (rad) from where the previous one ended and stands
    within ``origin_range`` (m) of the dome centre.
    """
    check_motion_dofs(character)
    if not segments:
        raise EgorelightError("a motion needs at least one segment")
    t = start_s + np.arange(num_frames) / float(fps)
    total = float(t[-1]) + 1.0 / fps if num_frames else 0.0
    rng = np.random.default_rng(seed)
    # Lay out segment instances until the span is covered.
    starts: list[float] = []
    instances: list[Segment] = []
    clock, k = 0.0, 0
    while clock < total or not instances:
        segment = segments[k % len(segments)]
        starts.append(clock)
        instances.append(segment)
        clock += max(segment.duration_s, 1e-3)
        k += 1
    D = character.skeleton.num_dofs
    theta = np.zeros((num_frames, D))
    jump = np.zeros(num_frames)
    rotate_y = character.skeleton.dof_index("rotate_y")
    last_heading = 0.0
    weight_sum = np.zeros(num_frames)
    for i, (segment, start) in enumerate(zip(instances, starts)):
        end = start + segment.duration_s
        fade_in = _smoothstep((t - (start - crossfade_s / 2)) / crossfade_s) if i > 0 else np.ones_like(t)
        fade_out = (1 - _smoothstep((t - (end - crossfade_s / 2)) / crossfade_s)) if i < len(instances) - 1 \
            else np.ones_like(t)
        w = fade_in * fade_out
        active = w > 1e-6
        sub_rng = np.random.default_rng(rng.integers(1 << 62))
        # Each instance faces near where the previous one ended, drifting back towards -Z.
        wrapped = (last_heading + np.pi) % (2 * np.pi) - np.pi
        heading = float(last_heading - 0.3 * wrapped + sub_rng.uniform(-heading_range, heading_range))
        origin = sub_rng.uniform(-origin_range, origin_range, size=2)
        # Evaluate at the frames and at the segment's end (sorted: paths unwrap their heading).
        local_t = np.append(t - start, end - start)
        order = np.argsort(local_t, kind="stable")
        seg_theta, seg_jump = np.empty((len(local_t), D)), np.empty(len(local_t))
        seg_theta[order], seg_jump[order] = segment_theta(character, segment, local_t[order], sub_rng, heading, origin)
        last_heading = float(seg_theta[-1, rotate_y])
        seg_theta, seg_jump = seg_theta[:-1], seg_jump[:-1]
        if not active.any():
            continue
        theta[active] += w[active, None] * seg_theta[active]
        jump[active] += w[active] * seg_jump[active]
        weight_sum[active] += w[active]
    theta /= np.maximum(weight_sum, 1e-9)[:, None]
    jump /= np.maximum(weight_sum, 1e-9)
    theta = clip_to_limits(character, theta)
    return ground_motion(character, theta, jump)


def clip_to_limits(character: Character, theta: np.ndarray, margin: float = _CLIP_MARGIN) -> np.ndarray:
    """Theta with every limited DoF clipped ``margin`` inside its [min, max]."""
    limits = character.skeleton.dof_limits
    lo = np.where(np.isfinite(limits[:, 0]), limits[:, 0] + margin, -np.inf)
    hi = np.where(np.isfinite(limits[:, 1]), limits[:, 1] - margin, np.inf)
    return np.clip(theta, lo, np.maximum(lo, hi))


def ground_motion(character: Character, theta: np.ndarray, jump: np.ndarray | None = None) -> np.ndarray:
    """Set ``translate_y`` so that the lowest foot point touches the floor (y = 0), plus ``jump``."""
    from egorelight_cli.geometry.skeleton import keypoint_positions

    names = character.keypoint_names
    index = character.skeleton.dof_index("translate_y")
    theta = theta.copy()
    theta[:, index] = 0.0
    kp = keypoint_positions(torch.as_tensor(theta), character).numpy()
    heights = []
    for side in ("Left", "Right"):
        heights.append(kp[:, names.index(f"{side}Foot"), 1] - _ANKLE_HEIGHT)
        heights.append(kp[:, names.index(f"{side}ToeBase"), 1] - _TOE_HEIGHT)
    lowest = np.min(np.stack(heights, axis=1), axis=1)
    theta[:, index] = -lowest + (0.0 if jump is None else jump)
    return theta
