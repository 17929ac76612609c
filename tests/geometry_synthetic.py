"""A tiny synthetic rigged character for the geometry tests: a tube around a 3-bone chain.

Skeleton (DDC semantics, metres/radians): root prismatic tx, ty, tz, revolute ry; then three
bones stacked along +y, each of length ``BONE_LENGTH``::

    bone0_rz (revolute z, at the origin) -> bone1_rz (revolute z, +L y) -> bone2_ry (revolute y, +2L y)

DoFs: tx, ty, tz, ry, bend0, bend1, twist2 (D = 7), each driving one joint with weight 1.
The mesh is an open tube of radius ``RADIUS`` from y = 0 to y = 3L; skin weights blend linearly
between neighbouring bones within ``BLEND`` of each joint.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from egorelight_cli.geometry.embedded_graph import (
    build_embedded_graph,
    choose_graph_nodes,
)
from egorelight_cli.structures.character import Character
from egorelight_cli.structures.skeleton import PRISMATIC, REVOLUTE, Skeleton

BONE_LENGTH = 0.2
RADIUS = 0.05
BLEND = 0.05

JOINTS = (
    # name, parent, type, offset, axis
    ("root_tx", -1, PRISMATIC, (0, 0, 0), (1, 0, 0)),
    ("root_ty", 0, PRISMATIC, (0, 0, 0), (0, 1, 0)),
    ("root_tz", 1, PRISMATIC, (0, 0, 0), (0, 0, 1)),
    ("root_ry", 2, REVOLUTE, (0, 0, 0), (0, 1, 0)),
    ("bone0_rz", 3, REVOLUTE, (0, 0, 0), (0, 0, 1)),
    ("bone1_rz", 4, REVOLUTE, (0, BONE_LENGTH, 0), (0, 0, 1)),
    ("bone2_ry", 5, REVOLUTE, (0, BONE_LENGTH, 0), (0, 1, 0)),
)
DOFS = ("tx", "ty", "tz", "ry", "bend0", "bend1", "twist2")
BONE_JOINTS = (4, 5, 6)


def make_skeleton() -> Skeleton:
    J = len(JOINTS)
    return Skeleton(
        joint_names=tuple(j[0] for j in JOINTS),
        parents=np.array([j[1] for j in JOINTS]),
        joint_types=np.array([j[2] for j in JOINTS]),
        axes=np.array([j[4] for j in JOINTS], dtype=float),
        offsets=np.array([j[3] for j in JOINTS], dtype=float),
        dof_names=DOFS,
        dof_joint_weights=np.eye(len(DOFS), J),
        dof_limits=np.tile([-np.inf, np.inf], (len(DOFS), 1)),
    )


def make_tube(rings: int = 25, segments: int = 12, length: float = 3 * BONE_LENGTH,
              radius: float = RADIUS) -> tuple[np.ndarray, np.ndarray]:
    """Open tube along +y: vertices (rings*segments, 3), counter-clockwise (outward) faces."""
    y = np.linspace(0.0, length, rings)
    a = 2 * np.pi * np.arange(segments) / segments
    verts = np.stack([
        np.repeat(np.zeros(rings), segments) + radius * np.tile(np.cos(a), rings),
        np.repeat(y, segments),
        radius * np.tile(np.sin(a), rings),
    ], 1)
    faces = []
    for r in range(rings - 1):
        for s in range(segments):
            i0, i1 = r * segments + s, r * segments + (s + 1) % segments
            j0, j1 = i0 + segments, i1 + segments
            faces += [(i0, j0, i1), (i1, j0, j1)]
    return verts, np.array(faces, dtype=np.int64)


def tube_skin_weights(vertices: np.ndarray) -> np.ndarray:
    """(V,3) weights over the three bones, linear ramps of half-width BLEND at each joint."""
    y = vertices[:, 1]
    W = np.zeros((len(y), 3))
    for v, h in enumerate(y):
        w = np.zeros(3)
        seg = min(int(h // BONE_LENGTH), 2)
        w[seg] = 1.0
        for k in (1, 2):  # joints at y = k L between bone k-1 and bone k
            d = h - k * BONE_LENGTH
            if abs(d) < BLEND:
                t = 0.5 + 0.5 * d / BLEND
                w[:] = 0.0
                w[k - 1], w[k] = 1.0 - t, t
        W[v] = w / w.sum()
    return W


def make_character(rest_theta: np.ndarray | None = None, num_nodes: int = 20, rings: int = 25,
                   segments: int = 12) -> Character:
    """The tube character; ``rest_theta`` defaults to zeros (template modelled at theta = 0).

    With a non-zero ``rest_theta`` the template vertices are the tube *posed* by that theta
    (so that skinning at ``rest_theta`` returns the template).
    """
    skeleton = make_skeleton()
    verts, faces = make_tube(rings, segments)
    weights = tube_skin_weights(verts)
    rest = np.zeros(len(DOFS)) if rest_theta is None else np.asarray(rest_theta, dtype=float)
    if rest_theta is not None:
        import torch

        from egorelight_cli.geometry.skeleton import forward_kinematics
        from egorelight_cli.geometry.skinning import dual_quaternion_skinning

        G = forward_kinematics(torch.as_tensor(rest), skeleton)[list(BONE_JOINTS)]
        G0 = forward_kinematics(torch.zeros(len(DOFS), dtype=torch.float64), skeleton)[list(BONE_JOINTS)]
        verts = dual_quaternion_skinning(torch.as_tensor(verts), G @ torch.linalg.inv(G0), weights).numpy()
    node_vertex, node_edges, node_faces = choose_graph_nodes(verts, faces, num_nodes)
    graph = build_embedded_graph(faces, len(verts), node_vertex, node_edges, node_faces)
    V, F = len(verts), len(faces)
    return Character(
        name="tube",
        skeleton=skeleton,
        rest_theta=rest,
        vertices=verts,
        faces=faces,
        face_uvs=np.zeros((F, 3, 2)),
        skin_bone_names=("bone0", "bone1", "bone2"),
        skin_bone_joints=np.array(BONE_JOINTS),
        skin_weights=weights,
        keypoint_names=("base", "middle", "tip"),
        keypoint_joints=np.array([4, 5, 6]),
        keypoint_offsets=np.array([[0, 0, 0], [0, 0, 0], [0, BONE_LENGTH, 0]], dtype=float),
        graph=graph,
        segmentation=np.zeros(V, np.int64),
        segmentation_names={0: "background"},
        hand_segmentation=np.zeros(V, np.int64),
    )


def one_rings(faces: np.ndarray, num_vertices: int) -> list[set[int]]:
    """Each vertex's neighbours along the triangles' edges (a plain reference, no scipy)."""
    rings = [set() for _ in range(num_vertices)]
    for a, b, c in np.asarray(faces, dtype=np.int64).tolist():
        rings[a] |= {b, c}
        rings[b] |= {a, c}
        rings[c] |= {a, b}
    return rings


def bfs_hops(rings: list[set[int]], source: int) -> np.ndarray:
    """(V,) breadth-first hop counts from ``source`` over ``rings`` (``inf`` where unreachable)."""
    hops = np.full(len(rings), np.inf)
    hops[source] = 0
    queue = deque([source])
    while queue:
        u = queue.popleft()
        for w in rings[u]:
            if hops[w] == np.inf:
                hops[w] = hops[u] + 1
                queue.append(w)
    return hops
