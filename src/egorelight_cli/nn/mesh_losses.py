"""Losses of the animation model (supplement "Loss Functions and Training Details").

* :func:`filtered_chamfer`: a two-sided Chamfer distance between a predicted mesh and the
  multi-view reconstruction (its own topology), whose nearest-neighbour pairs are dropped when
  their normals disagree (``n_a . n_b < min_normal_dot``) or they are farther apart than
  ``max_distance``. The reconstruction only holds the outer surface, so under self-contact (arm
  against torso) the inner template surface would otherwise be pulled outward onto the wrong
  side.
* :func:`graph_arap`: the embedded-deformation rigidity term over graph edges,
  ``|R_k (g_j - g_k) + g_k + t_k - (g_j + t_j)|^2`` in both directions.
* :func:`offset_smoothness`: ``|o_i - o_j|^2`` over mesh edges (spatial smoothness).
* :func:`offset_isometry`: ``(|e_ij(deformed + o)| - |e_ij(deformed)|)^2`` over mesh edges: the
  offsets must not stretch the surface.

Distances are returned in centimetres (squared terms in cm^2) so the loss weights are O(1).
Nearest neighbours are found with a KD-tree on detached coordinates; the loss is differentiable
in the predicted vertices (and through them in the network).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from egorelight_cli.geometry.rotations import euler_to_matrix

CM = 100.0


def _robust_norm(d: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    return torch.sqrt((d * d).sum(-1) + eps)


def filtered_pairs(source: np.ndarray, source_normals: np.ndarray, target_tree: cKDTree, target_normals: np.ndarray,
                   min_normal_dot: float, max_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest target of each source point, kept when within ``max_distance`` and normals agree.

    Returns:
        ``(source index (K,), target index (K,))`` int64.
    """
    distance, nearest = target_tree.query(source, k=1, distance_upper_bound=max_distance)
    found = np.isfinite(distance)
    nearest = np.where(found, nearest, 0)
    keep = found & (np.sum(source_normals * target_normals[nearest], axis=-1) >= min_normal_dot)
    index = np.flatnonzero(keep)
    return index, nearest[index]


def filtered_chamfer(vertices: torch.Tensor, normals: torch.Tensor, target: torch.Tensor, target_normals: torch.Tensor,
                     target_tree: cKDTree | None = None, min_normal_dot: float = 0.5,
                     max_distance: float = 0.1, point_to_plane: bool = False) -> torch.Tensor:
    """Normal-filtered two-sided Chamfer distance, mean pair distance in cm (each side averaged).

    With ``point_to_plane`` each pair's distance is measured along the normal of the point it
    was matched to (the target's normal for predicted vertices, the predicted vertex normal,
    detached, for target points): the sampling density of either mesh then no longer biases the
    distance (a reconstruction with fewer vertices than the template otherwise pulls vertices
    into clumps at its samples).

    Args:
        vertices: (V,3) predicted positions, metres (differentiable).
        normals: (V,3) their unit normals (select pairs; planes for ``point_to_plane``).
        target: (M,3) reconstruction points, metres.
        target_normals: (M,3) their unit normals.
        target_tree: optional prebuilt KD-tree of ``target``.
        min_normal_dot: pairs whose normals have a smaller dot product are dropped.
        max_distance: pairs farther apart are dropped, metres.
        point_to_plane: measure along the matched normal instead of the full 3D distance.
    Returns:
        () tensor, centimetres; 0 when no pair survives.
    """
    pred = vertices.detach().cpu().numpy().astype(np.float64)
    pred_n = normals.detach().cpu().numpy().astype(np.float64)
    tgt = target.detach().cpu().numpy().astype(np.float64)
    tgt_n = target_normals.detach().cpu().numpy().astype(np.float64)
    tree = target_tree if target_tree is not None else cKDTree(tgt)
    terms = []
    target = target.to(vertices)

    def distance(i: np.ndarray, j: np.ndarray, plane: torch.Tensor | None) -> torch.Tensor:
        d = vertices[i] - target[j]
        if plane is None:
            return _robust_norm(d).mean()
        along = (d * plane.to(vertices)).sum(-1, keepdim=True)
        return _robust_norm(along).mean()

    i, j = filtered_pairs(pred, pred_n, tree, tgt_n, min_normal_dot, max_distance)
    if len(i):
        terms.append(distance(i, j, target_normals[j] if point_to_plane else None))
    j2, i2 = filtered_pairs(tgt, tgt_n, cKDTree(pred), pred_n, min_normal_dot, max_distance)
    if len(j2):
        terms.append(distance(i2, j2, normals[i2].detach() if point_to_plane else None))
    if not terms:
        return vertices.sum() * 0.0
    return CM * torch.stack(terms).mean()


def graph_arap(node_rest: torch.Tensor, node_euler: torch.Tensor, node_translation: torch.Tensor,
               edges: torch.Tensor) -> torch.Tensor:
    """Embedded-graph rigidity, mean over directed edges, cm^2.

    Args:
        node_rest: (N,3) rest node positions g, metres.
        node_euler: (...,N,3) rotations alpha, radians.
        node_translation: (...,N,3) translations beta, metres.
        edges: (E,2) int64 undirected node pairs.
    """
    R = euler_to_matrix(node_euler)
    g = node_rest.to(node_translation)
    a = torch.cat([edges[:, 0], edges[:, 1]])
    b = torch.cat([edges[:, 1], edges[:, 0]])
    d = g[b] - g[a]
    predicted = (R[..., a, :, :] @ d[..., None])[..., 0] + g[a] + node_translation[..., a, :]
    actual = g[b] + node_translation[..., b, :]
    return CM * CM * ((predicted - actual) ** 2).sum(-1).mean()


def offset_smoothness(offsets: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Mean ``|o_i - o_j|^2`` over mesh edges (E,2), cm^2; offsets (...,V,3) metres."""
    d = offsets[..., edges[:, 0], :] - offsets[..., edges[:, 1], :]
    return CM * CM * (d * d).sum(-1).mean()


def offset_isometry(deformed: torch.Tensor, offsets: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Mean squared change of mesh edge lengths caused by the offsets, cm^2.

    Args:
        deformed: (...,V,3) canonical mesh after the graph deformation (no offsets), metres.
        offsets: (...,V,3) canonical offsets, metres.
        edges: (E,2) mesh edges.
    """
    with_offsets = deformed + offsets
    before = _robust_norm(deformed[..., edges[:, 0], :] - deformed[..., edges[:, 1], :])
    after = _robust_norm(with_offsets[..., edges[:, 0], :] - with_offsets[..., edges[:, 1], :])
    return CM * CM * ((after - before) ** 2).mean()
