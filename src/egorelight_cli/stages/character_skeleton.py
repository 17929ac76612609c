"""The default character's skeleton: joints and DoFs built from MakeHuman rig points.

:func:`build_skeleton` turns the midline and (symmetrised) left-side rig points found by
:func:`egorelight_cli.stages.character.character_from_makehuman` into the DDC-style skeleton
documented in :mod:`egorelight_cli.stages.character` (names, axes, limits and sign conventions);
the right side is the mirror image of the left.
"""

from __future__ import annotations

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.structures.skeleton import PRISMATIC, REVOLUTE, Skeleton

FINGERS = ("Thumb", "Index", "Middle", "Ring", "Pinky")


# --------------------------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------------------------

def mirror_x(p: np.ndarray) -> np.ndarray:
    """Mirror points (..., 3) across the x = 0 plane (left <-> right side of the body)."""
    return np.asarray(p, dtype=np.float64) * np.array([-1.0, 1.0, 1.0])


def _mirror_axis(a: np.ndarray) -> np.ndarray:
    """Axis of the mirrored revolute joint such that equal angles give mirrored motions."""
    return np.asarray(a, dtype=np.float64) * np.array([1.0, -1.0, -1.0])


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v)
    if n < 1e-12:
        raise EgorelightError("degenerate MakeHuman rig: zero-length direction")
    return v / n


def _perp(d: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Component of ``d`` perpendicular to the unit vector ``b``."""
    b = _unit(b)
    return d - np.dot(d, b) * b


def _toward(b: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Axis about which a positive rotation turns direction ``b`` towards direction ``d``."""
    b = _unit(b)
    return _unit(np.cross(b, _perp(np.asarray(d, dtype=np.float64), b)))


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(np.dot(_unit(a), _unit(b)), -1.0, 1.0)))


# --------------------------------------------------------------------------------------------
# skeleton construction
# --------------------------------------------------------------------------------------------

class _SkeletonBuilder:
    def __init__(self) -> None:
        self.names: list[str] = []
        self.parents: list[int] = []
        self.types: list[int] = []
        self.axes: list[np.ndarray] = []
        self.positions: list[np.ndarray] = []
        self.dofs: list[tuple[str, list[tuple[str, float]], tuple[float, float]]] = []

    def joint(self, name: str, parent: str | None, position, axis, kind: int = REVOLUTE) -> str:
        if name in self.names:
            raise EgorelightError(f"duplicate joint {name}")
        self.names.append(name)
        self.parents.append(-1 if parent is None else self.names.index(parent))
        self.types.append(kind)
        axis = np.asarray(axis, dtype=np.float64)
        self.axes.append(axis / np.linalg.norm(axis) if kind == REVOLUTE else axis)
        self.positions.append(np.asarray(position, dtype=np.float64))
        return name

    def dof(self, name: str, joints: list[tuple[str, float]], limits: tuple[float, float]) -> None:
        self.dofs.append((name, joints, (float(limits[0]), float(limits[1]))))

    def build(self) -> Skeleton:
        J = len(self.names)
        pos = np.array(self.positions)
        parents = np.array(self.parents)
        offsets = np.where(parents[:, None] < 0, pos, pos - pos[np.maximum(parents, 0)])
        W = np.zeros((len(self.dofs), J))
        for d, (_, joints, _) in enumerate(self.dofs):
            for joint, weight in joints:
                W[d, self.names.index(joint)] += weight
        return Skeleton(
            joint_names=tuple(self.names), parents=parents, joint_types=np.array(self.types),
            axes=np.array(self.axes), offsets=offsets, dof_names=tuple(d[0] for d in self.dofs),
            dof_joint_weights=W, dof_limits=np.array([d[2] for d in self.dofs]),
        )


_UP = np.array([0.0, 1.0, 0.0])
_FORWARD = np.array([0.0, 0.0, -1.0])
_BACK = -_FORWARD
_LEFT = np.array([-1.0, 0.0, 0.0])  # the character's left (lateral for the left limbs)


def _left_limb_specs(g: dict[str, np.ndarray]):
    """Joints and DoFs of the left clavicle/arm/hand and leg from left-side points ``g``.

    Returns (joints, dofs): joints = [(name, parent, position, axis)], dofs = [(name, [(joint,
    weight)], limits)]; names use ``Left``/``left_``; the right side is their mirror image.
    """
    J, D = [], []
    # clavicle and arm
    C, A, E, W = g["clavicle"], g["shoulder"], g["elbow"], g["wrist"]
    bc, bu, bf = A - C, E - A, W - E
    J += [("LeftShoulder_ry", "Spine4_rx", C, _toward(bc, _FORWARD)),
          ("LeftShoulder_rz", "LeftShoulder_ry", C, _toward(bc, _UP))]
    D += [("left_clavicle_protract", [("LeftShoulder_ry", 1.0)], (-0.3, 0.35)),
          ("left_clavicle_elevate", [("LeftShoulder_rz", 1.0)], (-0.15, 0.5))]
    abd0 = _angle(bu, -_UP)  # the rest (A-pose) abduction of the upper arm
    J += [("LeftArm_rz", "LeftShoulder_rz", A, _toward(bu, _LEFT)),
          ("LeftArm_rx", "LeftArm_rz", A, _toward(bu, _FORWARD)),
          ("LeftArm_ry", "LeftArm_rx", A, _unit(bu))]
    D += [("left_shoulder_abduct", [("LeftArm_rz", 1.0)], (-abd0 - 0.3, np.pi - abd0)),
          ("left_shoulder_flex", [("LeftArm_rx", 1.0)], (-1.0, 2.9)),
          ("left_shoulder_twist", [("LeftArm_ry", 1.0)], (-1.3, 1.3))]
    flex0 = _angle(bu, bf)  # rest elbow flexion
    J += [("LeftForeArm_rx", "LeftArm_ry", E, np.cross(_unit(_perp(-bu, bf)), _unit(bf))),
          ("LeftForeArmRoll", "LeftForeArm_rx", E, _unit(bf))]
    D += [("left_elbow", [("LeftForeArm_rx", 1.0)], (-(2.6 - flex0), flex0)),
          ("left_forearm_twist", [("LeftForeArmRoll", 1.0)], (-1.4, 1.4))]
    # hand frame: h along the hand, t towards the thumb side, n out of the palm
    h = _unit(g["Middle1"] - W)
    t = _unit(_perp(g["Index1"] - g["Pinky1"], h))
    n = _unit(np.cross(h, t))
    J += [("LeftHand_rx", "LeftForeArmRoll", W, np.cross(n, h)),
          ("LeftHand_rz", "LeftHand_rx", W, _toward(h, t))]
    D += [("left_wrist_flex", [("LeftHand_rx", 1.0)], (-1.2, 1.0)),
          ("left_wrist_deviate", [("LeftHand_rz", 1.0)], (-0.6, 0.35))]

    def curl_axis(p0, p1, towards):  # negative angles curl p0->p1 towards ``towards``
        b = _unit(p1 - p0)
        return np.cross(_unit(_perp(towards, b)), b)

    # thumb: CMC (abduct + flex/opposition), MCP, IP, tip
    T1, T2, T3, TE, P1 = g["Thumb1"], g["Thumb2"], g["Thumb3"], g["ThumbEE"], g["Pinky1"]
    J += [("LeftHandThumb1_rz", "LeftHand_rz", T1, _toward(T2 - T1, n)),
          ("LeftHandThumb1", "LeftHandThumb1_rz", T1, curl_axis(T1, T2, P1 - T1)),
          ("LeftHandThumb2", "LeftHandThumb1", T2, curl_axis(T2, T3, P1 - T2)),
          ("LeftHandThumb3", "LeftHandThumb2", T3, curl_axis(T3, TE, P1 - T3)),
          ("LeftHandThumbEE", "LeftHandThumb3", TE, _UP)]
    D += [("left_thumb_abduct", [("LeftHandThumb1_rz", 1.0)], (-0.3, 0.8)),
          ("left_thumb_flex1", [("LeftHandThumb1", 1.0)], (-0.8, 0.4)),
          ("left_thumb_flex2", [("LeftHandThumb2", 1.0)], (-1.0, 0.2)),
          ("left_thumb_flex3", [("LeftHandThumb3", 1.0)], (-1.3, 0.3))]
    spread_dir = {"Index": t, "Ring": -t, "Pinky": -t}
    for finger in FINGERS[1:]:
        P = [g[f"{finger}{k}"] for k in ("1", "2", "3", "EE")]
        parent = "LeftHand_rz"
        if finger in spread_dir:
            J.append((f"LeftHand{finger}1_ry", "LeftHand_rz", P[0], _toward(P[1] - P[0], spread_dir[finger])))
            parent = f"LeftHand{finger}1_ry"
        J += [(f"LeftHand{finger}1", parent, P[0], curl_axis(P[0], P[1], n)),
              (f"LeftHand{finger}2", f"LeftHand{finger}1", P[1], curl_axis(P[1], P[2], n)),
              (f"LeftHand{finger}3", f"LeftHand{finger}2", P[2], curl_axis(P[2], P[3], n)),
              (f"LeftHand{finger}EE", f"LeftHand{finger}3", P[3], _UP)]
        lower = finger.lower()
        D += [(f"left_{lower}_flex1", [(f"LeftHand{finger}1", 1.0)], (-1.6, 0.35)),
              (f"left_{lower}_flex2", [(f"LeftHand{finger}2", 1.0), (f"LeftHand{finger}3", 2.0 / 3.0)],
               (-1.75, 0.05))]
    D += [("left_index_spread", [("LeftHandIndex1_ry", 1.0)], (-0.3, 0.45)),
          ("left_pinky_spread", [("LeftHandPinky1_ry", 1.0), ("LeftHandRing1_ry", 0.5)], (-0.3, 0.6))]
    # leg
    U, K, F, TB = g["hip"], g["knee"], g["ankle"], g["toe"]
    bt, bs = K - U, F - K
    foot = _perp(TB - F, _UP)  # horizontal foot direction (towards the toes)
    J += [("LeftUpLeg_rx", "Root_rx", U, _toward(bt, _FORWARD)),
          ("LeftUpLeg_rz", "LeftUpLeg_rx", U, _toward(bt, _LEFT)),
          ("LeftUpLeg_ry", "LeftUpLeg_rz", U, _unit(bt)),
          ("LeftLeg_rx", "LeftUpLeg_ry", K, np.cross(_unit(_perp(_BACK, bs)), _unit(bs))),
          ("LeftLeg_ry", "LeftLeg_rx", K, _unit(bs)),
          ("LeftFoot_rx", "LeftLeg_ry", F, _toward(TB - F, _UP)),
          ("LeftFoot_ry", "LeftFoot_rx", F, _unit(bs)),
          ("LeftFoot_rz", "LeftFoot_ry", F, -_unit(foot)),
          ("LeftToeBase_rx", "LeftFoot_rz", TB, np.cross(_unit(_perp(-_UP, foot)), _unit(foot)))]
    D += [("left_hip_flex", [("LeftUpLeg_rx", 1.0)], (-0.5, 2.2)),
          ("left_hip_abduct", [("LeftUpLeg_rz", 1.0)], (-0.5, 0.8)),
          ("left_hip_twist", [("LeftUpLeg_ry", 1.0)], (-0.7, 0.7)),
          ("left_knee", [("LeftLeg_rx", 1.0)], (-2.5, 0.05)),
          ("left_knee_twist", [("LeftLeg_ry", 1.0)], (-0.4, 0.4)),
          ("left_ankle_flex", [("LeftFoot_rx", 1.0)], (-0.8, 0.4)),
          ("left_ankle_twist", [("LeftFoot_ry", 1.0)], (-0.4, 0.4)),
          ("left_ankle_invert", [("LeftFoot_rz", 1.0)], (-0.3, 0.5)),
          ("left_toes", [("LeftToeBase_rx", 1.0)], (-0.6, 0.8))]
    return J, D


def _to_right(name: str) -> str:
    if name.startswith("Left"):
        return "Right" + name[4:]
    if name.startswith("left_"):
        return "right_" + name[5:]
    return name


def build_skeleton(P: dict[str, np.ndarray], left: dict[str, np.ndarray]) -> Skeleton:
    """The DDC-style skeleton from midline points ``P`` and (symmetrised) left-side points."""
    sk = _SkeletonBuilder()
    root = P["pelvis"]
    sk.joint("Root_tx", None, root, [1, 0, 0], PRISMATIC)
    sk.joint("Root_ty", "Root_tx", root, [0, 1, 0], PRISMATIC)
    sk.joint("Root_tz", "Root_ty", root, [0, 0, 1], PRISMATIC)
    sk.joint("Root_ry", "Root_tz", root, [0, 1, 0])
    sk.joint("Root_rz", "Root_ry", root, [0, 0, 1])
    sk.joint("Root_rx", "Root_rz", root, [1, 0, 0])
    inf = np.inf
    for axis in "xyz":
        sk.dof(f"translate_{axis}", [(f"Root_t{axis}", 1.0)], (-inf, inf))
    for axis in "yzx":
        sk.dof(f"rotate_{axis}", [(f"Root_r{axis}", 1.0)], (-inf, inf))

    # spine, neck, head: twist (+Y: turn left), lean (+Z: tilt left), bend (-X: flex forward)
    def ball(base, parent, pos, dof_prefix, limits):
        sk.joint(f"{base}_ry", parent, pos, [0, 1, 0])
        sk.joint(f"{base}_rz", f"{base}_ry", pos, [0, 0, 1])
        sk.joint(f"{base}_rx", f"{base}_rz", pos, [-1, 0, 0])
        bend, lean, twist = limits
        sk.dof(f"{dof_prefix}_bend", [(f"{base}_rx", 1.0)], bend)
        sk.dof(f"{dof_prefix}_lean", [(f"{base}_rz", 1.0)], lean)
        sk.dof(f"{dof_prefix}_twist", [(f"{base}_ry", 1.0)], twist)
        return f"{base}_rx"

    spine_limits = ((-0.2, 0.35), (-0.2, 0.2), (-0.2, 0.2))
    parent = "Root_rx"
    for i, base in enumerate(("Spine", "Spine1", "Spine2", "Spine3", "Spine4")):
        parent = ball(base, parent, P[f"spine{i}"], f"spine{i}", spine_limits)
    neck = ball("Neck", "Spine4_rx", P["neck"], "neck", ((-0.6, 0.7), (-0.5, 0.5), (-0.8, 0.8)))
    head = ball("Head", neck, P["head"], "head", ((-0.4, 0.4), (-0.3, 0.3), (-0.5, 0.5)))
    sk.joint("HeadEE", head, P["head_top"], [0, 1, 0])
    chin = P["chin"] - P["jaw"]
    sk.joint("Jaw_rx", head, P["jaw"], _toward(chin, _BACK))  # positive: the chin swings down/back
    sk.dof("jaw_open", [("Jaw_rx", 1.0)], (-0.05, 0.45))

    joints, dofs = _left_limb_specs(left)
    arm = [j for j in joints if not j[0].startswith(("LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToe"))]
    leg = [j for j in joints if j not in arm]
    for group in (arm, leg):
        for side in ("Left", "Right"):
            for name, parent_name, pos, axis in group:
                if side == "Right":
                    name, parent_name = _to_right(name), _to_right(parent_name)
                    pos, axis = mirror_x(pos), _mirror_axis(axis)
                sk.joint(name, parent_name, pos, axis)
    for side in ("left", "right"):
        for name, targets, limits in dofs:
            if side == "right":
                name, targets = _to_right(name), [(_to_right(j), w) for j, w in targets]
            sk.dof(name, targets, limits)
    return sk.build()
