"""Loop subdivision of a triangle mesh with per-corner UVs.

Each face ``(a, b, c)`` splits into four: ``(a, ab, ca)``, ``(ab, b, bc)``, ``(ca, bc, c)``,
``(ab, bc, ca)`` where ``ab`` is the new vertex on edge ``a-b``. New face ``4 f + k`` comes from
face ``f``. Original vertices keep their indices ``0..V-1``; the vertex of edge ``e`` is
``V + e`` with ``edges[e] = (i, j)``, so per-vertex attributes extend by averaging the two
endpoints (:meth:`Subdivision.extend`).

Positions follow Loop's rules (Loop 1987): an interior edge vertex is ``3/8 (a + b) + 1/8 (c + d)``
(``c, d`` opposite), an old vertex of valence ``n`` moves to ``(1 - n beta) v + beta sum(neighbours)``
with Loop's ``beta = (5/8 - (3/8 + cos(2 pi / n) / 4)^2) / n``. Boundary (and non-manifold) edges take
their midpoint and their vertices stay in place, so open meshes keep their borders.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Subdivision:
    """One level of Loop subdivision.

    Attributes:
        vertices: (V + E,3) float64 new positions.
        faces: (4F,3) int64.
        face_uvs: (4F,3,2) per-corner UVs (midpoints of the parent's corner UVs) or None.
        edges: (E,2) int64 endpoints of the edge each new vertex ``V + e`` sits on.
        num_original: V.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_uvs: np.ndarray | None
    edges: np.ndarray
    num_original: int

    @property
    def parent_face(self) -> np.ndarray:
        """(4F,) index of the face each new face came from."""
        return np.arange(len(self.faces)) // 4

    def extend(self, values: np.ndarray) -> np.ndarray:
        """Per-vertex values (V,...) extended to (V + E,...) by averaging each edge's endpoints."""
        values = np.asarray(values)
        mid = 0.5 * (values[self.edges[:, 0]] + values[self.edges[:, 1]])
        return np.concatenate([values, mid.astype(values.dtype, copy=False)])

    def extend_labels(self, labels: np.ndarray) -> np.ndarray:
        """Integer labels (V,) extended to (V + E,): an edge vertex takes its first endpoint's label."""
        labels = np.asarray(labels)
        return np.concatenate([labels, labels[self.edges[:, 0]]])


def unique_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges of a triangle mesh.

    Returns:
        edges (E,2) int64 with ``edges[:, 0] < edges[:, 1]``, and face_edges (F,3): the edge of
        each face side ``(a,b), (b,c), (c,a)``.
    """
    faces = np.asarray(faces, dtype=np.int64)
    sides = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1).reshape(-1, 2)
    edges, inverse = np.unique(np.sort(sides, axis=1), axis=0, return_inverse=True)
    return edges, inverse.reshape(-1, 3)


def loop_subdivide(vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray | None = None) -> Subdivision:
    """One level of Loop subdivision (see the module docstring).

    Args:
        vertices: (V,3) positions.
        faces: (F,3) triangles.
        face_uvs: optional (F,3,2) per-corner UVs.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    V = len(vertices)
    edges, face_edges = unique_edges(faces)
    E = len(edges)
    # Opposite corners of every face side: side (a,b) of face (a,b,c) is opposite c.
    opposite = faces[:, [2, 0, 1]]
    edge_faces = np.bincount(face_edges.ravel(), minlength=E)
    opposite_sum = np.zeros((E, 3))
    np.add.at(opposite_sum, face_edges.ravel(), vertices[opposite.ravel()])
    interior = edge_faces == 2
    endpoint_sum = vertices[edges[:, 0]] + vertices[edges[:, 1]]
    edge_points = np.where(interior[:, None], 0.375 * endpoint_sum + 0.125 * opposite_sum, 0.5 * endpoint_sum)

    valence = np.bincount(edges.ravel(), minlength=V).astype(np.float64)
    neighbour_sum = np.zeros((V, 3))
    np.add.at(neighbour_sum, edges[:, 0], vertices[edges[:, 1]])
    np.add.at(neighbour_sum, edges[:, 1], vertices[edges[:, 0]])
    on_border = np.zeros(V, dtype=bool)
    on_border[edges[~interior].ravel()] = True
    n = np.maximum(valence, 1)
    beta = (0.625 - (0.375 + 0.25 * np.cos(2 * np.pi / n)) ** 2) / n
    moved = (1.0 - valence * beta)[:, None] * vertices + beta[:, None] * neighbour_sum
    old_points = np.where((on_border | (valence < 3))[:, None], vertices, moved)

    a, b, c = faces.T
    ab, bc, ca = (V + face_edges[:, k] for k in range(3))
    new_faces = np.stack([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                          np.stack([ab, bc, ca], 1)], axis=1).reshape(-1, 3)
    new_uvs = None
    if face_uvs is not None:
        uv = np.asarray(face_uvs, dtype=np.float64)
        ua, ub, uc = uv[:, 0], uv[:, 1], uv[:, 2]
        uab, ubc, uca = 0.5 * (ua + ub), 0.5 * (ub + uc), 0.5 * (uc + ua)
        new_uvs = np.stack([np.stack([ua, uab, uca], 1), np.stack([uab, ub, ubc], 1), np.stack([uca, ubc, uc], 1),
                            np.stack([uab, ubc, uca], 1)], axis=1).reshape(-1, 3, 2)
    return Subdivision(vertices=np.concatenate([old_points, edge_points]), faces=new_faces, face_uvs=new_uvs,
                       edges=edges, num_original=V)
