"""Point-cloud operations of the egocentric depth stage: fusion of views, sampling to a fixed
size P, normals by local PCA (Hoppe et al. 1992) over a KD-tree neighbourhood, orientation
towards the viewpoint, and point-to-surface distances to a triangle mesh.

All points are (N,3) metres; normals are unit (N,3).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from egorelight_cli.errors import EgorelightError


def fuse_views(points: Sequence[np.ndarray], valid: Sequence[np.ndarray],
               viewpoints: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate the valid points of several views (already in one world frame).

    Args:
        points: per view (...,3) points.
        valid: per view (...) bool.
        viewpoints: per view (3,) camera centre in the same frame.

    Returns:
        points (N,3) float64 and, per point, the centre of the camera that saw it (N,3).
    """
    if not (len(points) == len(valid) == len(viewpoints)):
        raise EgorelightError("fuse_views needs as many validity masks and viewpoints as point maps")
    fused, seen_from = [], []
    for p, v, c in zip(points, valid, viewpoints):
        p = np.asarray(p, np.float64).reshape(-1, 3)
        v = np.asarray(v, bool).reshape(-1)
        if len(p) != len(v):
            raise EgorelightError(f"point map with {len(p)} points has {len(v)} validity flags")
        fused.append(p[v])
        seen_from.append(np.broadcast_to(np.asarray(c, np.float64), (int(v.sum()), 3)))
    if not fused:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(fused), np.concatenate(seen_from)


def sample_indices(count: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Up to ``size`` distinct indices into ``count`` items, uniformly at random, sorted."""
    if count <= size:
        return np.arange(count)
    return np.sort(rng.choice(count, size=size, replace=False))


def hoppe_normals(points: np.ndarray, neighbours: int = 16) -> np.ndarray:
    """Unoriented unit normals (N,3): the smallest-eigenvalue eigenvector of the covariance of each
    point's ``neighbours`` nearest points (itself included). Points with fewer than 3 points get
    the +z axis."""
    points = np.asarray(points, np.float64)
    n = len(points)
    if n < 3:
        return np.tile([0.0, 0.0, 1.0], (n, 1))
    k = int(min(max(neighbours, 3), n))
    _, index = cKDTree(points).query(points, k=k)
    local = points[index]  # (N,k,3)
    local = local - local.mean(axis=1, keepdims=True)
    covariance = np.einsum("nki,nkj->nij", local, local)
    _, vectors = np.linalg.eigh(covariance)  # ascending eigenvalues
    return vectors[:, :, 0]


def orient_towards(normals: np.ndarray, points: np.ndarray, viewpoints: np.ndarray) -> np.ndarray:
    """Flip normals (N,3) so each points towards its viewpoint (N,3) or (3,)."""
    to_view = np.asarray(viewpoints, np.float64) - np.asarray(points, np.float64)
    sign = np.where(np.sum(normals * to_view, axis=-1) < 0, -1.0, 1.0)
    return normals * sign[:, None]


def fixed_size_cloud(points: np.ndarray, viewpoints: np.ndarray, size: int, neighbours: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample ``size`` points and give them oriented Hoppe normals.

    Args:
        points: (N,3) fused points.
        viewpoints: (N,3) centre of the camera that saw each point.
        size: P.
        neighbours: KD-tree neighbourhood for the normals.

    Returns:
        points (P,3) float32, normals (P,3) float32, valid (P,) bool; when N < P the first N
        rows hold the points and the rest are zero and invalid.
    """
    keep = sample_indices(len(points), size, rng)
    chosen = points[keep]
    normals = orient_towards(hoppe_normals(chosen, neighbours), chosen, viewpoints[keep])
    out_p = np.zeros((size, 3), np.float32)
    out_n = np.zeros((size, 3), np.float32)
    valid = np.zeros(size, bool)
    out_p[:len(keep)] = chosen
    out_n[:len(keep)] = normals
    valid[:len(keep)] = True
    return out_p, out_n, valid


class SurfaceDistance:
    """Exact distance from points to a triangle mesh (closest point on any face).

    Candidate faces come from a KD-tree over dense surface samples (``samples_per_face`` per face
    plus the centroids); the exact point-triangle distance is then taken over the faces of the
    ``candidates`` nearest samples. It is exact whenever the closest face is among them, which
    dense sampling makes the rule.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, samples_per_face: int = 4, candidates: int = 16,
                 seed: int = 0):
        vertices = np.asarray(vertices, np.float64)
        faces = np.asarray(faces, np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3 or not len(faces):
            raise EgorelightError(f"surface mesh must be vertices (V,3) and faces (F,3), got {vertices.shape} "
                                  f"and {faces.shape}")
        self.triangles = vertices[faces]  # (F,3,3)
        rng = np.random.default_rng(seed)
        F = len(faces)
        bary = rng.dirichlet(np.ones(3), size=(F, samples_per_face))  # (F,S,3)
        samples = np.einsum("fsk,fkd->fsd", bary, self.triangles).reshape(-1, 3)
        samples = np.concatenate([self.triangles.mean(axis=1), samples])
        self.sample_face = np.concatenate([np.arange(F), np.repeat(np.arange(F), samples_per_face)])
        self.tree = cKDTree(samples)
        self.candidates = int(candidates)

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface points of points (N,3): (points (N,3), face index (N,) int64, distance (N,) metres)."""
        from trimesh.triangles import closest_point

        points = np.asarray(points, np.float64).reshape(-1, 3)
        if len(points) == 0:
            return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0)
        _, index = self.tree.query(points, k=min(self.candidates, self.tree.n))
        faces = self.sample_face[index.reshape(len(points), -1)]  # (N,k)
        rows = np.arange(len(points))
        # a face is usually among a point's candidates several times (its samples lie together):
        # each distinct (point, face) pair is measured once (on dense meshes ~6 of 16)
        pairs, pair_of = np.unique(rows[:, None] * len(self.triangles) + faces, return_inverse=True)
        pair_points = points[pairs // len(self.triangles)]
        pair_closest = closest_point(self.triangles[pairs % len(self.triangles)], pair_points)
        pair_of = pair_of.reshape(faces.shape)
        distance = np.linalg.norm(pair_closest - pair_points, axis=1)[pair_of]  # (N,k)
        best = distance.argmin(axis=1)
        return pair_closest[pair_of[rows, best]], faces[rows, best], distance[rows, best]

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N,) distances (metres) of points (N,3) to the surface."""
        return self.closest(points)[2]
