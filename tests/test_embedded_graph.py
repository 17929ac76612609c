"""Embedded graph construction (DDC rule), embedded deformation and character posing."""

from __future__ import annotations

import geometry_synthetic as synth
import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry import rotations as rot
from egorelight_cli.geometry.embedded_graph import (
    build_embedded_graph,
    choose_graph_nodes,
    deformed_node_positions,
    embedded_deformation,
    graph_skinning_transforms,
    hop_distances,
    pose_character,
    pose_through_graph,
)
from egorelight_cli.geometry.skeleton import bone_transforms
from egorelight_cli.geometry.skinning import inverse_skinning_points, skin_points


def strip(cols: int) -> tuple[np.ndarray, np.ndarray]:
    """A 2 x cols triangle strip; vertex (c, r) has index r * cols + c; diagonals (c,0)-(c+1,1)."""
    verts = np.array([[c, r, 0.0] for r in range(2) for c in range(cols)])
    faces = []
    for c in range(cols - 1):
        a, b, d, e = c, c + 1, cols + c, cols + c + 1  # (c,0) (c+1,0) (c,1) (c+1,1)
        faces += [(a, b, e), (a, e, d)]
    return verts, np.array(faces)


def bfs(faces, V, src):
    return synth.bfs_hops(synth.one_rings(faces, V), src)


def dense_weights(graph, V):
    W = np.zeros((V, graph.num_nodes))
    for v in range(V):
        for k, w in zip(graph.vertex_node_index[v], graph.vertex_node_weight[v]):
            if k >= 0:
                W[v, k] += w
    return W


def test_hop_distances_match_bfs():
    verts, faces = strip(21)
    hops = hop_distances(faces, len(verts), np.array([10, 30]))
    np.testing.assert_array_equal(hops[0], bfs(faces, len(verts), 10))
    np.testing.assert_array_equal(hops[1], bfs(faces, len(verts), 30))
    # by hand: along row 0 the hop count is the column difference
    np.testing.assert_array_equal(hops[0, :21], np.abs(np.arange(21) - 10))


def _w(*d):
    """Normalised exp(-0.5 d^2) weights."""
    w = np.exp(-0.5 * np.square(d))
    return w / w.sum()


def test_build_on_strip_by_hand():
    verts, faces = strip(21)
    V = len(verts)
    node_vertex = np.array([0, 10, 14])  # row 0, columns 0, 10, 14
    g = build_embedded_graph(faces, V, node_vertex, np.array([[0, 1], [1, 2]]))
    # the DDC reference's radius: max(one-ring hops // 2, 3) = 3 for every node; the graph edges
    # (node 0 is 10 hops from node 1) do not widen it
    np.testing.assert_array_equal(g.node_radius, [3, 3, 3])
    np.testing.assert_array_equal(g.edges, [[0, 1], [1, 2]])
    W = dense_weights(g, V)
    np.testing.assert_allclose(W.sum(1), 1.0)
    # vertex (8,0): node 1 at d = 2/3 only
    np.testing.assert_allclose(W[8], [0.0, 1.0, 0.0])
    # vertex (12,0): nodes 1 and 2 both 2 hops away
    np.testing.assert_allclose(W[12], [0.0, 0.5, 0.5])
    # vertex (5,0): 5 hops from nodes 0 and 1, no node within d <= 1; DDC fallback d <= 2
    np.testing.assert_allclose(W[5], [0.5, 0.5, 0.0])
    # vertex (17,0): node 2 at d = 3/3, node 1 at 7/3 > 1
    np.testing.assert_allclose(W[17], [0.0, 0.0, 1.0])
    # vertex (20,0): node 2 at 6/3 = 2 (fallback), node 1 at 10/3
    np.testing.assert_allclose(W[20], [0.0, 0.0, 1.0])
    # row 1: (5,1) is 5 hops from node 0 (via the diagonal (0,0)-(1,1)) and 6 from node 1: fallback
    assert [bfs(faces, V, n)[21 + 5] for n in node_vertex] == [5, 6, 10]
    np.testing.assert_allclose(W[21 + 5], [*_w(5 / 3, 6 / 3), 0.0])
    # (12,1): 2 hops from node 1, 3 from node 2
    assert [bfs(faces, V, n)[21 + 12] for n in node_vertex] == [12, 2, 3]
    np.testing.assert_allclose(W[21 + 12], [0.0, *_w(2 / 3, 3 / 3)])
    # padded layout: -1 / 0 padding, sorted by decreasing weight
    assert g.vertex_node_index.shape == (V, 2)
    assert np.all((g.vertex_node_index >= 0) == (g.vertex_node_weight > 0))
    assert np.all(g.vertex_node_weight[:, 0] >= g.vertex_node_weight[:, 1])


def test_minimum_radius_and_fallbacks():
    verts, faces = strip(21)
    V = len(verts)
    # nodes at columns 0 and 4: 4 // 2 = 2 -> clamped to 3
    g = build_embedded_graph(faces, V, np.array([0, 4]), np.array([[0, 1]]))
    np.testing.assert_array_equal(g.node_radius, [3, 3])
    W = dense_weights(g, V)
    np.testing.assert_allclose(W.sum(1), 1.0)
    # vertex (10,0): 6 hops = 2 radii from node 1 -> DDC fallback (d <= 2) links it to node 1 only
    np.testing.assert_allclose(W[10], [0.0, 1.0])
    # vertex (20,0): 16 hops away: linked to the nearest node by hops
    np.testing.assert_allclose(W[20], [0.0, 1.0])


def test_node_faces_add_edges_and_are_stored():
    verts, faces = strip(21)
    g = build_embedded_graph(faces, len(verts), np.array([0, 10, 31]), np.zeros((0, 2)), np.array([[0, 1, 2]]))
    np.testing.assert_array_equal(g.edges, [[0, 1], [0, 2], [1, 2]])
    np.testing.assert_array_equal(g.faces, [[0, 1, 2]])


def test_unreachable_vertices():
    verts, faces = strip(5)
    verts = np.concatenate([verts, [[100.0, 0, 0]]])  # an isolated vertex
    with pytest.raises(EgorelightError, match="not connected"):
        build_embedded_graph(faces, len(verts), np.array([0, 4]), np.array([[0, 1]]))
    g = build_embedded_graph(faces, len(verts), np.array([0, 4]), np.array([[0, 1]]), vertices=verts)
    np.testing.assert_allclose(dense_weights(g, len(verts))[-1], [0.0, 1.0])


def test_bad_inputs_raise():
    verts, faces = strip(5)
    with pytest.raises(EgorelightError):
        build_embedded_graph(faces, len(verts), np.array([0, 99]), np.array([[0, 1]]))
    with pytest.raises(EgorelightError):
        build_embedded_graph(faces, len(verts), np.array([0, 3]), np.array([[0, 5]]))


@pytest.mark.parametrize("method", ["fps", "decimate"])
def test_choose_graph_nodes(method):
    verts, faces = synth.make_tube(rings=30, segments=16)
    node_vertex, node_edges, node_faces = choose_graph_nodes(verts, faces, 40, method=method)
    assert len(np.unique(node_vertex)) == len(node_vertex)
    if method == "fps":
        assert len(node_vertex) == 40
    else:
        assert 20 <= len(node_vertex) <= 80
    assert node_edges.max() < len(node_vertex) and len(node_edges) >= len(node_vertex) - 1
    g = build_embedded_graph(faces, len(verts), node_vertex, node_edges, node_faces)
    np.testing.assert_allclose(g.vertex_node_weight.sum(1), 1.0)
    # the node graph is connected (as the tube is)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(node_vertex)
    adj = coo_matrix((np.ones(len(node_edges)), (node_edges[:, 0], node_edges[:, 1])), shape=(n, n))
    assert connected_components(adj, directed=False)[0] == 1


@pytest.fixture(scope="module")
def tube():
    return synth.make_character()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_identity_parameters_give_rest_vertices(tube, dtype):
    N = tube.graph.num_nodes
    zeros = torch.zeros(2, N, 3, dtype=dtype)
    out = embedded_deformation(tube.vertices, tube.graph, zeros, zeros)
    assert out.shape == (2, tube.num_vertices, 3) and out.dtype == dtype
    torch.testing.assert_close(out, torch.as_tensor(tube.vertices, dtype=dtype).expand_as(out))


def test_global_translation_and_rigid_motion(tube):
    N = tube.graph.num_nodes
    rest = torch.as_tensor(tube.vertices)
    t = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    out = embedded_deformation(rest, tube.graph, torch.zeros(N, 3, dtype=torch.float64), t.expand(N, 3))
    torch.testing.assert_close(out, rest + t)
    torch.testing.assert_close(deformed_node_positions(rest, tube.graph, t.expand(N, 3)), rest[tube.graph.node_vertex] + t)
    # same rotation R everywhere with t_k = R g_k - g_k + t is the rigid motion v -> R v + t
    euler = torch.tensor([0.3, -0.5, 1.1], dtype=torch.float64)
    R = rot.euler_to_matrix(euler)
    g = rest[tube.graph.node_vertex]
    tk = g @ R.T - g + t
    out = embedded_deformation(rest, tube.graph, euler.expand(N, 3), tk)
    torch.testing.assert_close(out, rest @ R.T + t)
    # offsets are added in canonical space
    o = torch.randn(tube.num_vertices, 3, dtype=torch.float64)
    torch.testing.assert_close(embedded_deformation(rest, tube.graph, euler.expand(N, 3), tk, o), rest @ R.T + t + o)


def test_single_node_rotation_matches_formula(tube):
    """v' = sum_k w_vk [R_k (v - g_k) + g_k + t_k], evaluated densely."""
    N, V = tube.graph.num_nodes, tube.num_vertices
    gen = torch.Generator().manual_seed(0)
    euler = torch.randn(N, 3, generator=gen, dtype=torch.float64) * 0.3
    trans = torch.randn(N, 3, generator=gen, dtype=torch.float64) * 0.01
    rest = torch.as_tensor(tube.vertices)
    g = rest[tube.graph.node_vertex]
    R = rot.euler_to_matrix(euler)
    W = torch.as_tensor(dense_weights(tube.graph, V))
    per_node = torch.einsum("kij,vkj->vki", R, rest[:, None] - g[None]) + g + trans  # (V,N,3)
    expected = (W[..., None] * per_node).sum(1)
    torch.testing.assert_close(embedded_deformation(rest, tube.graph, euler, trans), expected)


def test_embedded_deformation_gradcheck():
    verts, faces = strip(9)
    g = build_embedded_graph(faces, len(verts), np.array([0, 4, 8]), np.array([[0, 1], [1, 2]]))
    rest = torch.as_tensor(verts)
    euler = (0.2 * torch.randn(3, 3, dtype=torch.float64)).requires_grad_(True)
    trans = (0.1 * torch.randn(3, 3, dtype=torch.float64)).requires_grad_(True)
    offsets = (0.1 * torch.randn(len(verts), 3, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda e, t, o: embedded_deformation(rest, g, e, t, o), (euler, trans, offsets))


def test_pose_through_graph(tube):
    rest = torch.as_tensor(tube.vertices)
    # at the rest pose: the template
    T0 = bone_transforms(torch.as_tensor(tube.rest_theta), tube)
    torch.testing.assert_close(pose_through_graph(rest, T0, tube.skin_weights, tube.graph), rest)
    # a pure root motion moves every bone rigidly: graph posing == per-vertex skinning == rigid motion
    theta = torch.tensor([0.1, 0.2, 0.3, 0.7, 0.0, 0.0, 0.0], dtype=torch.float64)
    T = bone_transforms(theta, tube)
    for method in ("dqs", "lbs"):
        a = pose_through_graph(rest, T, tube.skin_weights, tube.graph, method)
        torch.testing.assert_close(a, rot.transform_points(T[0], rest))
    # a bent pose: close to per-vertex skinning but not identical
    theta = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.4, 0.6, 0.5], dtype=torch.float64)
    T = bone_transforms(theta, tube)
    a = pose_through_graph(rest, T, tube.skin_weights, tube.graph)
    b = skin_points(rest, T, tube.skin_weights)
    diff = (a - b).norm(dim=-1)
    assert 0 < diff.max() < 0.05 and diff.mean() < 0.01
    # its per-vertex transforms invert (W^-1)
    M = graph_skinning_transforms(T, tube.skin_weights, tube.graph)
    torch.testing.assert_close(inverse_skinning_points(a, M), rest)


@pytest.mark.parametrize("through_graph", [True, False])
def test_pose_character_composes_E_then_W(tube, through_graph):
    N = tube.graph.num_nodes
    rest = torch.as_tensor(tube.vertices)
    theta0 = torch.as_tensor(tube.rest_theta)
    torch.testing.assert_close(pose_character(tube, theta0, through_graph=through_graph), rest)
    # node translation t at the rest pose, then a root translation s
    t = torch.tensor([0.01, 0.02, -0.03], dtype=torch.float64)
    s = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    theta = theta0.clone()
    theta[:3] += s
    out = pose_character(tube, theta, node_translation=t.expand(N, 3), through_graph=through_graph)
    torch.testing.assert_close(out, rest + t + s)
    # root rotation applies after the canonical deformation: R (v + t)
    theta = theta0.clone()
    theta[3] = 0.9
    o = 0.01 * torch.randn(tube.num_vertices, 3, dtype=torch.float64)
    out = pose_character(tube, theta, vertex_offsets=o, skinning="lbs", through_graph=through_graph)
    Ry = rot.axis_angle_to_matrix(torch.tensor([0.0, 0.9, 0.0], dtype=torch.float64))
    torch.testing.assert_close(out, (rest + o) @ Ry.T)
    # batched, float32
    theta = torch.zeros(4, 2, 7)
    out = pose_character(tube, theta, node_euler=torch.zeros(4, 2, N, 3), through_graph=through_graph)
    assert out.shape == (4, 2, tube.num_vertices, 3) and out.dtype == torch.float32


@pytest.mark.parametrize("through_graph", [True, False])
def test_pose_character_gradcheck(through_graph):
    char = synth.make_character(num_nodes=6, rings=6, segments=5)
    N = char.graph.num_nodes
    gen = torch.Generator().manual_seed(0)
    theta = torch.tensor([0.0, 0.0, 0.0, 0.2, 0.3, -0.2, 0.4], dtype=torch.float64, requires_grad=True)
    euler = (0.1 * torch.randn(N, 3, generator=gen, dtype=torch.float64)).requires_grad_(True)
    trans = (0.01 * torch.randn(N, 3, generator=gen, dtype=torch.float64)).requires_grad_(True)

    def posed(th, e, t):
        return pose_character(char, th, node_euler=e, node_translation=t, through_graph=through_graph)

    assert torch.autograd.gradcheck(posed, (theta, euler, trans), fast_mode=True)
