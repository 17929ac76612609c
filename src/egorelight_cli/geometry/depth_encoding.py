"""The paper's depth encoding ``xi`` (Sec. "Depth-conditioned Animatable Avatar", Eq. depth-encoding).

For every template vertex ``v_i`` posed by skinning (``W(V_bar)``, no graph deformation, no
offsets), take the nearest point ``z_j`` of the egocentric point cloud; keep the pair only when

* ``|z_j - v_i| < eps_d`` (metres), and
* the normals agree: ``1 - n_v . n_z < eps_n`` (the paper writes the normal disparity as
  ``||n_v . n_z|| < eps_n``; we read it as "disparity = 1 - cosine", so ``eps_n = 0.5`` keeps
  normals within 60 degrees and an opposite-facing point is always rejected),

and encode ``xi_i = W^-1 (z_j - v_i)``: the posed-space residual unwarped to the canonical space
with the inverse of the vertex's own skinning rotation (the gradient direction of a
point-to-surface loss). Rejected vertices get ``xi_i = 0`` and ``mask_i = False``.

Skinning here is the character model's: DDC graph posing with DQS at the nodes
(:func:`~egorelight_cli.geometry.embedded_graph.graph_skinning_transforms`), whose per-vertex
transforms are affine; ``W^-1`` uses their rotation (polar decomposition), so ``|xi| = |z - v|``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.embedded_graph import graph_skinning_transforms
from egorelight_cli.geometry.normals import vertex_normals
from egorelight_cli.geometry.rotations import transform_points
from egorelight_cli.geometry.rigid import project_to_rotation
from egorelight_cli.geometry.skeleton import bone_transforms
from egorelight_cli.geometry.skinning import inverse_skinning_directions
from egorelight_cli.structures.character import Character


@dataclass(frozen=True, eq=False)
class SkinnedTemplate:
    """The template posed by skinning only, per frame.

    Attributes:
        vertices: (T,V,3) float64 posed positions, metres.
        normals: (T,V,3) float64 unit vertex normals of the posed mesh.
        vertex_T: (T,V,4,4) float64 per-vertex rest -> posed transforms (affine).
    """

    vertices: np.ndarray
    normals: np.ndarray
    vertex_T: np.ndarray


def skinned_template(character: Character, theta: np.ndarray, skinning: str = "dqs") -> SkinnedTemplate:
    """Pose the rest template with ``theta`` (T,D) by the character's graph skinning.

    Equal to ``pose_character(character, theta)`` (no graph deformation, no offsets).
    """
    theta = torch.as_tensor(np.asarray(theta, np.float64).reshape(-1, character.skeleton.num_dofs))
    with torch.no_grad():
        M = graph_skinning_transforms(bone_transforms(theta, character), character.skin_weights, character.graph,
                                      skinning)
        rest = torch.as_tensor(character.vertices, dtype=torch.float64)
        vertices = transform_points(M, rest)
        normals = vertex_normals(vertices, character.faces)
    return SkinnedTemplate(vertices.numpy(), normals.numpy(), M.numpy())


def normals_agree(vertex_normals_: np.ndarray, point_normals: np.ndarray, eps_n: float) -> np.ndarray:
    """(...,) bool: normal disparity ``1 - n_v . n_z`` below ``eps_n`` (both unit (...,3))."""
    return 1.0 - np.sum(vertex_normals_ * point_normals, axis=-1) < eps_n


def encode_depth_frame(vertices: np.ndarray, normals: np.ndarray, vertex_T: np.ndarray, points: np.ndarray,
                       point_normals: np.ndarray, eps_d: float, eps_n: float) -> tuple[np.ndarray, np.ndarray]:
    """``xi`` of one frame.

    Args:
        vertices: (V,3) skinned template, metres.
        normals: (V,3) its unit vertex normals.
        vertex_T: (V,4,4) (or (V,3,3)) per-vertex skinning transforms; ``W^-1`` applies the
            transpose of their nearest rotation (:func:`~egorelight_cli.geometry.rigid.project_to_rotation`).
        points: (P,3) valid cloud points, world metres (P may be 0).
        point_normals: (P,3) their unit normals.
        eps_d: distance threshold, metres.
        eps_n: normal-disparity threshold (``1 - cos``).
    Returns:
        ``(xi (V,3) float32 canonical-space offsets in metres, mask (V,) bool)``.
    """
    V = len(vertices)
    if eps_d <= 0:
        raise EgorelightError(f"depth encoding eps_d must be positive, got {eps_d}")
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros((V, 3), np.float32), np.zeros(V, bool)
    distance, nearest = cKDTree(points).query(vertices, k=1, distance_upper_bound=eps_d)
    found = np.isfinite(distance) & (distance < eps_d)
    nearest = np.where(found, nearest, 0)
    mask = found & normals_agree(normals, np.asarray(point_normals, np.float64)[nearest], eps_n)
    xi = np.zeros((V, 3), np.float32)
    rows = np.flatnonzero(mask)
    if rows.size:
        R = torch.as_tensor(project_to_rotation(np.asarray(vertex_T)[rows, :3, :3]))
        residual = torch.as_tensor(points[nearest[rows]] - vertices[rows])
        xi[rows] = inverse_skinning_directions(residual, R, rigid=True).numpy()
    return xi, mask


def encode_depth(template: SkinnedTemplate, clouds: list[tuple[np.ndarray, np.ndarray] | None], eps_d: float,
                 eps_n: float) -> tuple[np.ndarray, np.ndarray]:
    """``xi`` for every frame; ``clouds[t]`` is ``(points, normals)`` or None (no depth: xi = 0).

    Returns:
        ``(xi (T,V,3) float32, mask (T,V) bool)``.
    """
    T, V = template.vertices.shape[:2]
    if len(clouds) != T:
        raise EgorelightError(f"depth encoding got {len(clouds)} point clouds for {T} frames")
    xi = np.zeros((T, V, 3), np.float32)
    mask = np.zeros((T, V), bool)
    for t, cloud in enumerate(clouds):
        if cloud is None:
            continue
        xi[t], mask[t] = encode_depth_frame(template.vertices[t], template.normals[t], template.vertex_T[t],
                                            cloud[0], cloud[1], eps_d, eps_n)
    return xi, mask
