"""BVH motion capture clips: reading, writing, forward kinematics and the keypoint mapping.

A BVH file has a ``HIERARCHY`` (``ROOT``/``JOINT``/``End Site`` blocks with ``OFFSET`` and
``CHANNELS``) and a ``MOTION`` section (``Frames:``, ``Frame Time:``, one row of channel values
per frame). Semantics (the common reading, as in Biovision's and Blender's importers):

* a joint's local transform is ``translate(offset + position channels) @ R``, where ``R`` is the
  product of its rotation channels *in the order listed* (``Zrotation Yrotation Xrotation`` ->
  ``Rz @ Ry @ Rx``), angles in degrees;
* ``global = parent_global @ local``;
* ``End Site`` blocks become joints named ``<parent>_End`` without channels.

Units vary between files (the shared CMU clip is metres; many are centimetres or inches); the
keypoint mapping takes a ``unit_scale`` and the ``ik`` stage can fit a per-sequence scale to the
character. Up axis: +Y by default; ``up_axis="z"`` converts a Z-up clip to our +Y up.

Joint names map to the 57-keypoint layout by name, case-insensitively, after dropping a
namespace (``mixamorig:``) and non-alphanumerics, with aliases for the common conventions: the
DDC/MotionBuilder names our keypoints use (``LeftArm`` = shoulder joint, ``LeftShoulder`` =
clavicle), and the CMU/ASF names (``LeftHip``, ``LeftKnee``, ``LeftAnkle``, ``LeftToe``,
``LeftShoulder`` = shoulder joint, ``LeftElbow``, ``LeftWrist``, ``lowerneck``). Keypoints with no
joint (usually the fingers) get confidence 0.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.keypoints import Keypoints
from egorelight_cli.structures.keypoints import FINGERS, KEYPOINT_NAMES

POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")
END_SUFFIX = "_End"


@dataclass(frozen=True, eq=False)
class BvhClip:
    """A parsed BVH clip.

    Attributes:
        joint_names: (J,) names, parents before children (End Sites as ``<parent>_End``).
        parents: (J,) int64, -1 for the root.
        offsets: (J,3) float64 offsets from the parent, file units.
        channels: per joint, its channel names in file order (empty for End Sites).
        motion: (F,C) float64 channel values, C = total channel count.
        frame_time: seconds per frame.
    """

    joint_names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    motion: np.ndarray
    frame_time: float

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def channel_offsets(self) -> np.ndarray:
        """(J,) index of each joint's first channel in a motion row."""
        counts = np.array([len(c) for c in self.channels], dtype=np.int64)
        return np.concatenate([[0], np.cumsum(counts)[:-1]])


class _Tokens:
    def __init__(self, text: str, path: str | Path):
        self.path = path
        self.items: list[tuple[str, int]] = []
        for number, line in enumerate(text.splitlines(), start=1):
            self.items.extend((tok, number) for tok in line.split())
        self.pos = 0

    def error(self, message: str) -> EgorelightError:
        line = self.items[min(self.pos, len(self.items) - 1)][1] if self.items else 0
        return EgorelightError(f"invalid BVH at line {line}: {message}", self.path)

    def next(self, what: str) -> str:
        if self.pos >= len(self.items):
            raise self.error(f"file ends where {what} was expected")
        token = self.items[self.pos][0]
        self.pos += 1
        return token

    def expect(self, word: str) -> None:
        token = self.next(repr(word))
        if token != word:
            self.pos -= 1
            raise self.error(f"expected {word!r}, found {token!r}")

    def float(self, what: str) -> float:
        token = self.next(what)
        try:
            return float(token)
        except ValueError:
            self.pos -= 1
            raise self.error(f"{what} is not a number: {token!r}") from None


def parse_bvh(text: str, path: str | Path = "<bvh>") -> BvhClip:
    """Parse BVH text (see the module docstring); errors name the line."""
    tokens = _Tokens(text, path)
    tokens.expect("HIERARCHY")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []

    def block(parent: int, name: str, end_site: bool) -> None:
        index = len(names)
        names.append(name)
        parents.append(parent)
        tokens.expect("{")
        tokens.expect("OFFSET")
        offsets.append([tokens.float("an OFFSET value") for _ in range(3)])
        chans: tuple[str, ...] = ()
        if not end_site:
            tokens.expect("CHANNELS")
            count_token = tokens.next("a channel count")
            if not count_token.isdigit():
                raise tokens.error(f"channel count is not an integer: {count_token!r}")
            chans = tuple(tokens.next("a channel name") for _ in range(int(count_token)))
            for chan in chans:
                if chan not in POSITION_CHANNELS + ROTATION_CHANNELS:
                    raise tokens.error(f"unknown channel {chan!r}")
        channels.append(chans)
        while True:
            token = tokens.next("'}', JOINT or End Site")
            if token == "}":
                return
            if end_site:
                raise tokens.error(f"an End Site holds only an OFFSET, found {token!r}")
            if token == "JOINT":
                block(index, tokens.next("a joint name"), False)
            elif token == "End":
                tokens.expect("Site")
                block(index, name + END_SUFFIX, True)
            else:
                raise tokens.error(f"expected JOINT, End Site or '}}', found {token!r}")

    tokens.expect("ROOT")
    block(-1, tokens.next("the root joint name"), False)
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise EgorelightError(f"BVH joint name {dup!r} is used twice", path)
    tokens.expect("MOTION")
    tokens.expect("Frames:")
    frames_token = tokens.next("the frame count")
    if not frames_token.isdigit():
        raise tokens.error(f"frame count is not an integer: {frames_token!r}")
    num_frames = int(frames_token)
    tokens.expect("Frame")
    tokens.expect("Time:")
    frame_time = tokens.float("the frame time")
    if not frame_time > 0:
        raise tokens.error(f"frame time must be positive, got {frame_time}")
    num_channels = sum(len(c) for c in channels)
    values = tokens.items[tokens.pos:]
    if len(values) != num_frames * num_channels:
        raise EgorelightError(f"BVH motion holds {len(values)} values, expected {num_frames} frames x "
                              f"{num_channels} channels = {num_frames * num_channels}", path)
    try:
        motion = np.array([float(v) for v, _ in values], dtype=np.float64).reshape(num_frames, num_channels)
    except ValueError:
        bad = next((v, n) for v, n in values if not _is_float(v))
        raise EgorelightError(f"invalid BVH at line {bad[1]}: motion value is not a number: {bad[0]!r}", path) from None
    if not np.isfinite(motion).all():
        raise EgorelightError("BVH motion holds NaN/inf values", path)
    return BvhClip(tuple(names), np.array(parents, dtype=np.int64), np.array(offsets, dtype=np.float64),
                   tuple(channels), motion, frame_time)


def _is_float(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def read_bvh(path: str | Path) -> BvhClip:
    """Read a BVH file."""
    path = Path(path)
    if not path.is_file():
        raise EgorelightError("BVH file not found", path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        raise EgorelightError("BVH file is not text", path) from None
    return parse_bvh(text, path)


def format_bvh(clip: BvhClip) -> str:
    """BVH text for ``clip`` (inverse of :func:`parse_bvh`)."""
    children: dict[int, list[int]] = {j: [] for j in range(len(clip.joint_names))}
    for j, p in enumerate(clip.parents):
        if p >= 0:
            children[int(p)].append(j)
    lines = ["HIERARCHY"]

    def emit(j: int, depth: int) -> None:
        pad = "\t" * depth
        name = clip.joint_names[j]
        is_end = not clip.channels[j] and name.endswith(END_SUFFIX) and clip.parents[j] >= 0
        head = "End Site" if is_end else ("ROOT " if clip.parents[j] < 0 else "JOINT ") + name
        lines.append(pad + head)
        lines.append(pad + "{")
        lines.append(pad + "\tOFFSET " + " ".join(f"{v:.6f}" for v in clip.offsets[j]))
        if not is_end:
            lines.append(pad + f"\tCHANNELS {len(clip.channels[j])} " + " ".join(clip.channels[j]))
        for c in children[j]:
            emit(c, depth + 1)
        lines.append(pad + "}")

    emit(0, 0)
    lines += ["MOTION", f"Frames: {clip.num_frames}", f"Frame Time: {clip.frame_time:.6f}"]
    lines += [" ".join(f"{v:.6f}" for v in row) for row in clip.motion]
    return "\n".join(lines) + "\n"


def write_bvh(clip: BvhClip, path: str | Path) -> Path:
    path = Path(path)
    path.write_text(format_bvh(clip))
    return path


def _axis_rotation(axis: str, degrees: np.ndarray) -> np.ndarray:
    """(F,3,3) rotations about the x, y or z axis."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    i = "xyz".index(axis)
    j, k = (i + 1) % 3, (i + 2) % 3
    R[..., i, i] = 1.0
    R[..., j, j] = c
    R[..., j, k] = -s
    R[..., k, j] = s
    R[..., k, k] = c
    return R


def bvh_global_transforms(clip: BvhClip) -> np.ndarray:
    """World transforms of every joint: (F,J,4,4), file units."""
    F, J = clip.num_frames, len(clip.joint_names)
    start = clip.channel_offsets()
    G = np.zeros((F, J, 4, 4))
    for j in range(J):
        R = np.broadcast_to(np.eye(3), (F, 3, 3)).copy()
        t = np.broadcast_to(clip.offsets[j], (F, 3)).copy()
        for c, name in enumerate(clip.channels[j]):
            values = clip.motion[:, start[j] + c]
            if name in POSITION_CHANNELS:
                t[:, POSITION_CHANNELS.index(name)] += values
            else:
                R = R @ _axis_rotation(name[0].lower(), values)
        local = np.zeros((F, 4, 4))
        local[:, :3, :3] = R
        local[:, :3, 3] = t
        local[:, 3, 3] = 1.0
        G[:, j] = local if clip.parents[j] < 0 else G[:, clip.parents[j]] @ local
    return G


def bvh_joint_positions(clip: BvhClip) -> np.ndarray:
    """(F,J,3) world joint positions, file units."""
    return bvh_global_transforms(clip)[..., :3, 3]


# ------------------------------------------------------------------------------ keypoint mapping
def _normalise(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.split(":")[-1].lower())


def _side_candidates(side: str, suffixes: tuple[str, ...]) -> tuple[str, ...]:
    prefixes = (side.lower(), side[0].lower())
    return tuple(p + s.lower() for p in prefixes for s in suffixes)


#: keypoint (side-free suffix for sided ones) -> BVH joint names, best first.
_BODY_ALIASES: dict[str, tuple[str, ...]] = {
    "Arm": ("Arm", "UpperArm", "Shoulder"),  # MotionBuilder/DDC: Arm; CMU/ASF: Shoulder (after Arm)
    "ForeArm": ("ForeArm", "LowerArm", "Elbow"),
    "Hand": ("Hand", "Wrist"),
    "UpLeg": ("UpLeg", "UpperLeg", "Thigh", "Hip"),
    "Leg": ("Leg", "LowerLeg", "Knee", "Shin", "Calf"),
    "Foot": ("Foot", "Ankle"),
    "ToeBase": ("ToeBase", "Toe", "Toes"),
}


def keypoint_candidates(keypoint: str) -> tuple[str, ...]:
    """Normalised BVH joint names that may carry ``keypoint``, best first."""
    if keypoint == "Neck":
        return ("lowerneck", "neck", "neck1")
    side = "Left" if keypoint.startswith("Left") else "Right" if keypoint.startswith("Right") else ""
    rest = keypoint[len(side):]
    if rest in _BODY_ALIASES:
        return _side_candidates(side, _BODY_ALIASES[rest])
    if rest == "HandWrist":
        return _side_candidates(side, _BODY_ALIASES["Hand"])
    for finger in FINGERS:  # MotionBuilder/Mixamo fingers: <Side>Hand<Finger>1..4 (4 = tip)
        if rest.startswith(f"Hand{finger}"):
            seg = rest[len(f"Hand{finger}"):]
            names = (f"Hand{finger}{seg}",) if seg != "EE" else (f"Hand{finger}4", f"Hand{finger}3{END_SUFFIX}")
            return _side_candidates(side, names)
    return (_normalise(keypoint),)


def map_bvh_joints(joint_names, keypoint_names=KEYPOINT_NAMES) -> dict[str, int]:
    """keypoint name -> BVH joint index for every keypoint that has a joint."""
    index = {}
    for j, name in enumerate(joint_names):
        index.setdefault(_normalise(name), j)
    mapping = {}
    for keypoint in keypoint_names:
        for candidate in keypoint_candidates(keypoint):
            if candidate in index:
                mapping[keypoint] = index[candidate]
                break
    return mapping


def bvh_keypoints(clip: BvhClip, unit_scale: float = 1.0, up_axis: str = "y",
                  keypoint_names=KEYPOINT_NAMES) -> tuple[Keypoints, dict[str, str]]:
    """The clip's joints as a :class:`Keypoints` sequence (metres, +Y up).

    Args:
        clip: the BVH clip.
        unit_scale: metres per file unit (1 for the shared CMU clip, 0.01 for centimetres).
        up_axis: ``"y"`` (BVH default) or ``"z"`` (converted to +Y up).
        keypoint_names: the layout to fill.
    Returns:
        keypoints (frame ids 0..F-1, fps from the frame time; unmapped keypoints NaN with
        confidence 0) and the mapping keypoint -> BVH joint name.
    """
    if up_axis not in ("y", "z"):
        raise EgorelightError(f"BVH up axis must be 'y' or 'z', got {up_axis!r}")
    mapping = map_bvh_joints(clip.joint_names, keypoint_names)
    if not mapping:
        raise EgorelightError("no BVH joint maps to a keypoint (unknown joint naming)")
    positions = bvh_joint_positions(clip) * float(unit_scale)
    if up_axis == "z":
        positions = np.stack([positions[..., 0], positions[..., 2], -positions[..., 1]], axis=-1)
    F, K = clip.num_frames, len(keypoint_names)
    xyz = np.full((F, K, 3), np.nan)
    confidence = np.zeros((F, K))
    for k, name in enumerate(keypoint_names):
        if name in mapping:
            xyz[:, k] = positions[:, mapping[name]]
            confidence[:, k] = 1.0
    keypoints = Keypoints(xyz, confidence, np.arange(F, dtype=np.int64), tuple(keypoint_names), fps=clip.fps)
    return keypoints, {k: clip.joint_names[j] for k, j in mapping.items()}
