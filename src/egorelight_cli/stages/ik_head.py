"""The head from the headset (ours; ``ik --hmd-reference``): the neck and head DoFs no keypoint sees.

The paper's keypoints stop at the neck, so IK leaves the neck and head DoFs at the mean pose
(:func:`~egorelight_cli.stages.ik_model.classify_dofs`: *unobservable*) and the skinned face and
hair sit where the mean pose puts them (on the cpu capture 4-5 cm from the simulator's, whatever
the keypoints' quality). The headset is worn rigidly on the head and its pose is tracked
(``calibrate``'s head poses), so the head follows it:

* :func:`head_chain`: the head joint (the skin bone with the most skin weight among those the
  unobservable DoFs move, so neither jaw nor toes) and the unobservable DoFs on its chain;
* :func:`calibrate_hmd_from_head`: ``T_hmd_from_head``, the mounting, from frames of a motion whose
  torso was fitted to the reconstruction (``ik --fit-recon``) and the HMD poses of those frames:
  the chordal mean of ``inv(T_world_from_hmd) @ T_world_from_head`` (rotations projected back onto
  SO(3) by SVD, translations averaged), with its spread;
* :func:`with_head_markers` / :func:`head_marker_keypoints`: the HMD as an observation *inside* the
  keypoint IK: three virtual keypoints fixed on the head joint (its origin and points
  ``marker_spacing_m`` along its x and y axes), observed where ``T_world_from_hmd @ T_hmd_from_head``
  puts them and weighted ``hmd.weight`` times a keypoint. The neck and head DoFs become observable,
  so the body stage turns spine, neck and head together (with the prior's regulariser) to meet
  both the keypoints and the headset, where a head fitted afterwards makes the neck alone absorb
  the torso's error. On the cpu capture's ``test``, skinned P2S against the truth: IK of the true
  keypoints 1.005 cm (head fitted after) -> 0.930 (markers, weight 10), estimated 2.641 -> 2.563;
  spine DoFs 6.95 -> 5.06 deg off the simulator's;
* :func:`fit_head_to_hmd`: for an input without keypoints (a motion given as DoFs), per frame with a
  valid HMD pose, the chain's DoFs by bounded least squares so that the head joint lands on
  ``T_world_from_hmd @ T_hmd_from_head`` (position in cm, rotation in degrees, a weak pull to the
  incoming values), every other DoF unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial

import numpy as np
import torch

from egorelight_cli.config import check_settings, setting, settings_from_config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.ik_jacobian import ancestor_matrix
from egorelight_cli.geometry.skeleton import forward_kinematics
from egorelight_cli.structures.character import Character
from egorelight_cli.structures.keypoints import Keypoints

_key = partial(setting, "ik")

#: the virtual keypoints :func:`with_head_markers` adds: the head joint's origin, and points along its x and y axes
HEAD_MARKER_NAMES = ("hmd_head_origin", "hmd_head_x", "hmd_head_y")


@dataclass(frozen=True)
class HMDSettings:
    """``hmd.*`` of ``stages/ik.yaml``."""

    weight: float = _key("hmd.weight")
    marker_spacing_m: float = _key("hmd.marker_spacing_m")

    def __post_init__(self) -> None:
        check_settings(self)

    @classmethod
    def from_config(cls, cfg) -> "HMDSettings":
        return settings_from_config(cls, cfg)


@dataclass(frozen=True)
class HeadChain:
    """``joint``: index of the head joint; ``dofs`` (K,) the unobservable DoFs that move it."""

    joint: int
    dofs: np.ndarray


def head_chain(character: Character) -> HeadChain:
    """The head joint and the DoFs IK cannot see that move it (see the module docstring)."""
    from egorelight_cli.stages.ik_model import classify_dofs

    skeleton = character.skeleton
    hidden = classify_dofs(character).unobservable
    if len(hidden) == 0:
        raise EgorelightError("the character has no neck or head DoF that keypoints leave free: nothing for "
                              "the headset to place")
    moved = (np.abs(skeleton.dof_joint_weights[hidden]) > 0).any(axis=0)  # (J,) joints they drive
    ancestors = ancestor_matrix(skeleton.parents)
    driven = ancestors[:, moved].any(axis=1)  # joints below one of them (or the joint itself)
    weight = np.zeros(len(skeleton.joint_names))
    np.add.at(weight, character.skin_bone_joints, character.skin_weights.sum(axis=0))
    weight[~driven] = -1.0
    joint = int(np.argmax(weight))
    on_chain = ancestors[joint]
    dofs = np.array([d for d in hidden if (np.abs(skeleton.dof_joint_weights[d]) > 0)[on_chain].any()], np.int64)
    return HeadChain(joint, dofs)


def head_transforms(character: Character, theta: np.ndarray, joint: int) -> np.ndarray:
    """(T,4,4) ``T_world_from_head`` of the head ``joint`` under ``theta`` (T,D), metres."""
    with torch.no_grad():
        T = forward_kinematics(torch.as_tensor(np.asarray(theta, np.float64)), character.skeleton)
    return T[..., joint, :, :].numpy()


def calibrate_hmd_from_head(T_world_from_hmd: np.ndarray, T_world_from_head: np.ndarray) -> tuple[np.ndarray, dict]:
    """``T_hmd_from_head`` (4,4) from N >= 1 paired poses (N,4,4), and its spread: the mean distance
    (cm) and angle (deg) of the per-frame transforms from it."""
    X = np.linalg.inv(T_world_from_hmd) @ T_world_from_head
    U, _, Vt = np.linalg.svd(X[:, :3, :3].sum(axis=0))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, X[:, :3, 3].mean(axis=0)
    cos = np.clip((np.einsum("ij,nij->n", R, X[:, :3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return T, {"hmd_mount_frames": int(len(X)),
               "hmd_mount_spread_cm": float(100 * np.linalg.norm(X[:, :3, 3] - T[:3, 3], axis=1).mean()),
               "hmd_mount_spread_deg": float(np.degrees(np.arccos(cos)).mean())}


def _head_error(T_world_from_head: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(6,) position (cm) and rotation-vector (deg) error of a head pose (4,4) from the wanted one."""
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_matrix(target[:3, :3].T @ T_world_from_head[:3, :3]).as_rotvec()
    return np.concatenate([100.0 * (T_world_from_head[:3, 3] - target[:3, 3]), np.degrees(rotation)])


def head_offset_summary(character: Character, before: np.ndarray, after: np.ndarray, targets: dict[int, np.ndarray],
                        joint: int) -> dict:
    """The mean distance (cm) and angle (deg) of the head ``joint`` from ``targets`` (row ->
    ``T_world_from_head`` (4,4)) under the motions ``before`` and ``after`` (T,D), over those rows."""
    rows = sorted(targets)
    errors = {}
    for name, theta in (("before", before), ("after", after)):
        heads = head_transforms(character, np.asarray(theta)[rows], joint) if rows else []
        e = np.array([_head_error(T, targets[r]) for T, r in zip(heads, rows)]).reshape(-1, 6)
        errors[f"hmd_head_offset_cm_{name}"] = float(np.linalg.norm(e[:, :3], axis=1).mean()) if rows else float("nan")
        errors[f"hmd_head_angle_deg_{name}"] = float(np.linalg.norm(e[:, 3:], axis=1).mean()) if rows else float("nan")
    return {"hmd_head_frames": len(rows), **errors}


def fit_head_to_hmd(character: Character, theta: np.ndarray, targets: dict[int, np.ndarray],
                    chain: HeadChain) -> tuple[np.ndarray, dict]:
    """``theta`` (T,D) with the chain's DoFs of each row in ``targets`` (row -> ``T_world_from_head``
    (4,4) wanted) fitted by bounded least squares; the rest unchanged. Returns the new theta and
    :func:`head_offset_summary`."""
    from scipy.optimize import least_squares

    out = np.array(theta, np.float64)
    lo, hi = character.skeleton.dof_limits[chain.dofs].T

    def residual(values: np.ndarray, row: int, target: np.ndarray) -> np.ndarray:
        th = out[row].copy()
        th[chain.dofs] = values
        error = _head_error(head_transforms(character, th, chain.joint), target)
        return np.concatenate([error, 0.1 * (values - theta[row, chain.dofs])])

    for row, target in sorted(targets.items()):
        start = np.clip(out[row, chain.dofs], lo, hi)
        out[row, chain.dofs] = least_squares(residual, start, bounds=(lo, hi), x_scale=0.1, args=(row, target)).x
    return out.astype(np.float32), head_offset_summary(character, theta, out, targets, chain.joint)


def head_marker_offsets(spacing_m: float) -> np.ndarray:
    """(3,3) the :data:`HEAD_MARKER_NAMES` markers in the head joint's frame, metres."""
    return np.array([[0.0, 0.0, 0.0], [spacing_m, 0.0, 0.0], [0.0, spacing_m, 0.0]])


def with_head_markers(character: Character, joint: int, spacing_m: float) -> Character:
    """``character`` with the three :data:`HEAD_MARKER_NAMES` keypoints more, fixed on ``joint``
    (:func:`head_marker_offsets`); skeleton, mesh and the first K keypoints unchanged."""
    return replace(character, keypoint_names=tuple(character.keypoint_names) + HEAD_MARKER_NAMES,
                   keypoint_joints=np.concatenate([character.keypoint_joints, np.full(3, joint, np.int64)]),
                   keypoint_offsets=np.concatenate([character.keypoint_offsets, head_marker_offsets(spacing_m)]))


def head_marker_keypoints(keypoints: Keypoints, targets: dict[int, np.ndarray], spacing_m: float) -> Keypoints:
    """``keypoints`` (T frames, K names) with the :data:`HEAD_MARKER_NAMES` observations appended:
    where the wanted head pose of each row in ``targets`` (row -> ``T_world_from_head`` (4,4))
    puts the markers, confidence 1; missing (NaN, confidence 0) in the other rows."""
    T = keypoints.num_frames
    xyz = np.full((T, 3, 3), np.nan, np.float32)
    confidence = np.zeros((T, 3), np.float32)
    offsets = head_marker_offsets(spacing_m)
    for row, head in targets.items():
        xyz[row] = offsets @ head[:3, :3].T + head[:3, 3]
        confidence[row] = 1.0
    return Keypoints(np.concatenate([keypoints.xyz, xyz], axis=1),
                     np.concatenate([keypoints.confidence, confidence], axis=1), keypoints.frame_ids,
                     tuple(keypoints.names) + HEAD_MARKER_NAMES, keypoints.fps)
