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
* :func:`fit_head_to_hmd`: per frame with a valid HMD pose, the chain's DoFs by bounded least squares
  so that the head joint lands on ``T_world_from_hmd @ T_hmd_from_head`` (position in cm, rotation in
  degrees, a weak pull to the incoming values), every other DoF unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.skeleton import forward_kinematics
from egorelight_cli.structures.character import Character


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
    ancestors = _ancestor_mask(skeleton.parents)
    driven = ancestors[:, moved].any(axis=1)  # joints below one of them (or the joint itself)
    weight = np.zeros(len(skeleton.joint_names))
    np.add.at(weight, character.skin_bone_joints, character.skin_weights.sum(axis=0))
    weight[~driven] = -1.0
    joint = int(np.argmax(weight))
    on_chain = ancestors[joint]
    dofs = np.array([d for d in hidden if (np.abs(skeleton.dof_joint_weights[d]) > 0)[on_chain].any()], np.int64)
    return HeadChain(joint, dofs)


def _ancestor_mask(parents: np.ndarray) -> np.ndarray:
    """(J,J) bool: ``[j, a]`` is True where ``a`` is ``j`` or one of its ancestors."""
    J = len(parents)
    out = np.eye(J, dtype=bool)
    for j in range(J):  # parents come before children
        if parents[j] >= 0:
            out[j] |= out[parents[j]]
    return out


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


def fit_head_to_hmd(character: Character, theta: np.ndarray, targets: dict[int, np.ndarray],
                    chain: HeadChain) -> tuple[np.ndarray, dict]:
    """``theta`` (T,D) with the chain's DoFs of each row in ``targets`` (row -> ``T_world_from_head``
    (4,4) wanted) fitted by bounded least squares; the rest unchanged. Returns the new theta and the
    mean head position / rotation error (cm / deg) before and after."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    out = np.array(theta, np.float64)
    lo, hi = character.skeleton.dof_limits[chain.dofs].T

    def residual(values: np.ndarray, row: int, target: np.ndarray) -> np.ndarray:
        th = out[row].copy()
        th[chain.dofs] = values
        T = head_transforms(character, th, chain.joint)
        rotation = Rotation.from_matrix(target[:3, :3].T @ T[:3, :3]).as_rotvec()
        return np.concatenate([100.0 * (T[:3, 3] - target[:3, 3]), np.degrees(rotation),
                               0.1 * (values - theta[row, chain.dofs])])

    errors = []
    for row, target in sorted(targets.items()):
        start = np.clip(out[row, chain.dofs], lo, hi)
        before = residual(start, row, target)
        fit = least_squares(residual, start, bounds=(lo, hi), x_scale=0.1, args=(row, target))
        out[row, chain.dofs] = fit.x
        errors.append([np.linalg.norm(before[:3]), np.linalg.norm(fit.fun[:3]),
                       np.linalg.norm(before[3:6]), np.linalg.norm(fit.fun[3:6])])
    e = np.mean(errors, axis=0) if errors else np.full(4, np.nan)
    return out.astype(np.float32), {"hmd_head_frames": len(errors),
                                    "hmd_head_offset_cm_before": float(e[0]), "hmd_head_offset_cm_after": float(e[1]),
                                    "hmd_head_angle_deg_before": float(e[2]), "hmd_head_angle_deg_after": float(e[3])}
