"""Re-placing a character's skeleton after its template surface was deformed (same topology).

Each skin bone's region moves by a regularised affine map fitted to the displacement of the
vertices skinned to it (skin-weight-weighted, :func:`bone_affines`). A joint moves with the maps
of the bones around it: the bones attached to it (or to joints at the same rest position, such as
the three single-axis joints of a ball joint) and the bones of the joint group above it, so an
elbow is placed by both the upper arm and the forearm. Joint orientations (axes, rest rotations)
are kept; offsets are recomputed in the skeleton's own parameterisation
(``G_j = G_parent @ translate(offset_j) @ motion_j``, :func:`offsets_for_positions`), and
keypoints are moved by their joint's map and re-expressed in its frame.

Positions are metres, (.,3) float64, in the character's rest (rigging) pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from egorelight_cli.geometry.skeleton import forward_kinematics
from egorelight_cli.structures.character import Character
from egorelight_cli.structures.skeleton import Skeleton

COINCIDENT_M = 1e-6  # joints closer than this at rest form one group (one anatomical joint)


def regularised_affine(source: np.ndarray, target: np.ndarray, weights: np.ndarray, prior: np.ndarray,
                       reg_length: float) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares affine map ``x -> A x + c`` from source (n,3) to target (n,3).

    Minimises ``sum_i w_i |A s_i + c - t_i|^2 + reg_length^2 * sum_i w_i * |A - prior|_F^2``:
    directions along which the weighted points spread less than about ``reg_length`` metres
    keep the prior's linear part (a thin finger's girth, a bone with few vertices).

    Args:
        source, target: (n,3) metres.
        weights: (n,) >= 0, not all zero.
        prior: (3,3) linear part to fall back on.
        reg_length: metres.
    Returns:
        A (3,3), c (3,).
    """
    w = weights / weights.sum()
    ms, mt = w @ source, w @ target
    S, T = source - ms, target - mt
    cov = (S * w[:, None]).T @ S  # (3,3)
    cross = (T * w[:, None]).T @ S
    lam = reg_length ** 2
    A = np.linalg.solve(cov + lam * np.eye(3), (cross + lam * prior).T).T
    return A, mt - A @ ms


def bone_affines(rest: np.ndarray, fitted: np.ndarray, skin_weights: np.ndarray, prior: np.ndarray,
                 reg_length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per skin bone, the affine map of its vertices' displacement (:func:`regularised_affine`).

    Args:
        rest: (V,3) template before the fit.
        fitted: (V,3) the fitted template.
        skin_weights: (V,B).
        prior: (3,3) linear part for bones with too little support (the similarity's ``s R``).
        reg_length: metres.
    Returns:
        A (B,3,3), c (B,3), mass (B,) total skin weight of each bone (0: the bone has no vertices
        and its map is the prior about the mean displacement).
    """
    B = skin_weights.shape[1]
    A = np.tile(prior, (B, 1, 1))
    c = np.tile(np.mean(fitted - rest @ prior.T, axis=0), (B, 1))
    mass = skin_weights.sum(axis=0)
    for b in np.nonzero(mass > 0)[0]:
        m = skin_weights[:, b] > 0
        A[b], c[b] = regularised_affine(rest[m], fitted[m], skin_weights[m, b], prior, reg_length)
    return A, c, mass


def joint_groups(positions: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(J,) group id: a joint joins its parent's group when it sits at the same rest position."""
    group = np.arange(len(parents))
    for j, p in enumerate(parents):
        if p >= 0 and np.linalg.norm(positions[j] - positions[p]) < COINCIDENT_M:
            group[j] = group[p]
    return group


def _group_bones(character: Character, group: np.ndarray) -> dict[int, list[int]]:
    bones: dict[int, list[int]] = {}
    for b, j in enumerate(character.skin_bone_joints):
        bones.setdefault(int(group[j]), []).append(b)
    return bones


def joint_maps(character: Character, positions: np.ndarray, A: np.ndarray, c: np.ndarray,
               mass: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The affine map (A (J,3,3), c (J,3)) that moves each joint and its keypoints, from the bone
    maps (A (B,3,3), c (B,3), mass (B,)) and the joints' rest positions (J,3).

    A joint group takes the mass-weighted mean of the maps of its own bones and of the nearest
    group above that has bones; a group without bones of its own (an end effector) the maps of that
    group above alone; a joint with neither, the mean of all bone maps.
    """
    parents = character.skeleton.parents
    group = joint_groups(positions, parents)
    bones = _group_bones(character, group)

    def bones_above(g: int) -> list[int]:
        p = parents[g]
        while p >= 0:
            if bones.get(int(group[p])):
                return bones[int(group[p])]
            p = parents[group[p]]
        return []

    def blend(used: list[int]) -> tuple[np.ndarray, np.ndarray]:
        w = mass[used] / mass[used].sum()
        return np.einsum("b,bij->ij", w, A[used]), w @ c[used]

    everything = blend([int(b) for b in np.nonzero(mass > 0)[0]])
    out_A = np.tile(everything[0], (len(parents), 1, 1))
    out_c = np.tile(everything[1], (len(parents), 1))
    for g in np.unique(group):
        own = [b for b in bones.get(int(g), []) if mass[b] > 0]
        above = [b for b in bones_above(int(g)) if mass[b] > 0]
        used = own + above if own else above
        if used:
            members = group == g
            out_A[members], out_c[members] = blend(used)
    return out_A, out_c


def offsets_for_positions(skeleton: Skeleton, rest_globals: np.ndarray, new_positions: np.ndarray) -> np.ndarray:
    """Joint offsets (J,3) that put the joints at ``new_positions`` (J,3) in the rest pose, joint
    rotations unchanged: ``offset_j += R_parent^T (dp_j - dp_parent)`` (``R_parent`` the parent's
    rest rotation; identity and ``dp_parent = 0`` for a root)."""
    dp = new_positions - rest_globals[:, :3, 3]
    offsets = skeleton.offsets.copy()
    for j, p in enumerate(skeleton.parents):
        if p < 0:
            offsets[j] += dp[j]
        else:
            offsets[j] += rest_globals[p, :3, :3].T @ (dp[j] - dp[p])
    return offsets


def with_offsets(skeleton: Skeleton, offsets: np.ndarray) -> Skeleton:
    """A copy of ``skeleton`` with other joint offsets."""
    return Skeleton(skeleton.joint_names, skeleton.parents, skeleton.joint_types, skeleton.axes, offsets,
                    skeleton.dof_names, skeleton.dof_joint_weights, skeleton.dof_limits, skeleton.joint_scales)


@dataclass(frozen=True)
class RigRefit:
    """A re-placed rig: ``skeleton``, ``keypoint_offsets`` (K,3), and the joints' rest positions
    ``joints_before`` / ``joints_after`` (J,3) metres."""

    skeleton: Skeleton
    keypoint_offsets: np.ndarray
    joints_before: np.ndarray
    joints_after: np.ndarray


def refit_rig(character: Character, fitted: np.ndarray, prior: np.ndarray, reg_length: float = 0.02) -> RigRefit:
    """The skeleton and keypoint offsets of ``character`` re-placed for its fitted template.

    Args:
        character: the template character (its ``vertices`` are the rest template before the fit).
        fitted: (V,3) fitted template, metres, same topology.
        prior: (3,3) linear part of the coarse alignment (``scale * R``) for bones without support.
        reg_length: see :func:`regularised_affine`.
    Returns:
        the :class:`RigRefit`.
    """
    rest_theta = torch.as_tensor(character.rest_theta, dtype=torch.float64)
    G = forward_kinematics(rest_theta, character.skeleton).numpy()
    positions = G[:, :3, 3]
    A, c, mass = bone_affines(character.vertices, fitted, character.skin_weights, prior, reg_length)
    JA, Jc = joint_maps(character, positions, A, c, mass)
    new_positions = np.einsum("jab,jb->ja", JA, positions) + Jc
    skeleton = with_offsets(character.skeleton, offsets_for_positions(character.skeleton, G, new_positions))
    G_new = forward_kinematics(rest_theta, skeleton).numpy()
    # keypoints: their rest position mapped like their joint, re-expressed in the joint's frame
    kj = character.keypoint_joints
    kp = np.einsum("kij,kj->ki", G[kj, :3, :3], character.keypoint_offsets) + positions[kj]
    kp_new = np.einsum("kab,kb->ka", JA[kj], kp) + Jc[kj]
    offsets = np.einsum("kji,kj->ki", G_new[kj, :3, :3], kp_new - G_new[kj, :3, 3])
    return RigRefit(skeleton, offsets, positions, G_new[:, :3, 3])
