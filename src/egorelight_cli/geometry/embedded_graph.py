"""The embedded deformation graph (Sumner et al. 2007) as used by DDC, and character posing.

The paper's geometry model (Sec. "Mesh-based Geometry Model") is
``V = W(E(V_bar, alpha, beta, o), K(theta, B), W)``:

* ``E``: embedded deformation in the canonical (rest) space. Node k sits on template vertex
  ``g_k = V_bar[node_vertex[k]]`` and has an Euler rotation ``alpha_k`` (``Rz @ Ry @ Rx``,
  radians) and a translation ``beta_k`` (metres). A vertex moves to
  ``sum_k w_vk [R_k (v - g_k) + g_k + t_k]``; the per-vertex offsets ``o`` are then added, still
  in canonical space (DDC: ``delta_canonical = eg_canonical + o``).
* ``W``: skinning. Either per vertex (DQS/LBS with the skin weights) or, as DDC does, *through
  the graph*: the skinning transform is evaluated at each node's vertex and spread to the mesh
  with the graph weights (``x'_v = sum_k w_vk M_k x_v``); the two differ by a few mm at the hands.

Graph construction follows the DDC rule (``build_embedded_graph``); graph-weighted blends use a
sparse (V,N) matrix, so the cost is linear in the number of vertex-node links.
"""

from __future__ import annotations

import weakref

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.rotations import euler_to_matrix, transform_points
from egorelight_cli.geometry.skeleton import bone_transforms
from egorelight_cli.geometry.skinning import (
    SKINNING_METHODS,
    append_homogeneous_row,
    skin_points,
    skinning_transforms,
    sparse_blend,
)
from egorelight_cli.structures.character import Character, EmbeddedGraph

MIN_NODE_RADIUS = 3  # hops; DDC's lower bound on a node's radius
FALLBACK_RADIUS_FACTOR = 2.0  # DDC reader: a vertex within no radius links to nodes within 2 radii


# ----------------------------------------------------------------------------------------------
# Construction
# ----------------------------------------------------------------------------------------------


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges of a triangle mesh.

    Args:
        faces: (F,3) int vertex indices.
    Returns:
        (E,2) int64 with ``i < j``, sorted.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.sort(e, axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0) if len(e) else np.zeros((0, 2), np.int64)


def mesh_adjacency(faces: np.ndarray, num_vertices: int) -> sp.csr_matrix:
    """Symmetric (V,V) 0/1 adjacency of the mesh's edge graph (for hop distances)."""
    e = mesh_edges(faces)
    data = np.ones(2 * len(e), dtype=np.float64)
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    return sp.csr_matrix((data, (rows, cols)), shape=(num_vertices, num_vertices))


def hop_distances(faces: np.ndarray, num_vertices: int, sources: np.ndarray) -> np.ndarray:
    """BFS hop distances on the mesh edge graph from each source vertex.

    Args:
        faces: (F,3) template triangles.
        num_vertices: V.
        sources: (N,) vertex indices.
    Returns:
        (N,V) float64 hop counts, ``inf`` where unreachable.
    """
    adj = mesh_adjacency(faces, num_vertices)
    return csgraph.shortest_path(adj, method="D", directed=False, unweighted=True, indices=np.asarray(sources, np.int64))


def _graph_edges(num_nodes: int, node_edges: np.ndarray, node_faces: np.ndarray | None) -> np.ndarray:
    edges = [np.asarray(node_edges, dtype=np.int64).reshape(-1, 2)]
    if node_faces is not None and len(node_faces):
        edges.append(mesh_edges(node_faces))
    e = np.sort(np.concatenate(edges), axis=1)
    e = e[e[:, 0] != e[:, 1]]
    if len(e) and (e.min() < 0 or e.max() >= num_nodes):
        raise EgorelightError(f"embedded graph edges index nodes out of range (0..{num_nodes - 1})")
    return np.unique(e, axis=0) if len(e) else np.zeros((0, 2), np.int64)


def node_radii(hops: np.ndarray, node_vertex: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """DDC node radius in hops, as the DDC reference builds it:
    ``r_k = max(max_{u in one-ring(node_vertex[k])} hops(k, u) // 2, 3)``.

    The maximum runs over the *template* one-ring of the node's vertex, whose vertices are one hop
    away, so every node of a connected template gets the minimum radius of 3 hops (the DDC
    example: all 852 nodes). An isolated node vertex (no edge) gets the minimum as well.

    Args:
        hops: (N,V) hop distances from each node's vertex.
        node_vertex: (N,) template vertex of each node.
        faces: (F,3) template triangles (for the one-rings).
    Returns:
        (N,) float64 integer-valued radii in hops.
    """
    N = len(node_vertex)
    e = mesh_edges(faces)
    far = np.zeros(N)
    if len(e):
        owner = np.full(hops.shape[1], -1, dtype=np.int64)
        owner[node_vertex] = np.arange(N)
        for a, b in ((e[:, 0], e[:, 1]), (e[:, 1], e[:, 0])):  # (node vertex, its one-ring neighbour)
            k = owner[a]
            mask = k >= 0
            d = hops[k[mask], b[mask]]
            np.maximum.at(far, k[mask], np.where(np.isfinite(d), d, 0.0))
    return np.maximum(np.floor(far / 2.0), MIN_NODE_RADIUS).astype(np.float64)


def _pad_rows(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray, num_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """COO (row, col, val) -> padded (num_rows, K) index/value arrays sorted by decreasing value."""
    order = np.lexsort((-vals, rows))
    rows, cols, vals = rows[order], cols[order], vals[order]
    counts = np.bincount(rows, minlength=num_rows)
    K = max(int(counts.max()) if len(counts) else 0, 1)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(rows)) - start[rows]
    index = np.full((num_rows, K), -1, dtype=np.int64)
    value = np.zeros((num_rows, K), dtype=np.float64)
    index[rows, slot] = cols
    value[rows, slot] = vals
    return index, value


def vertex_node_links(hops: np.ndarray, radius: np.ndarray, vertices: np.ndarray | None = None,
                      node_vertex: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """DDC vertex-node links and weights.

    With ``d = hops(k, v) / r_k``, vertex v links to node k when ``d <= 1`` with weight
    ``exp(-0.5 d^2)``. A vertex within no node's radius links to the nodes with ``d <= 2``
    (the DDC reader's fallback); one still without a node links to its nearest node by hops
    (smallest ``d``) with weight 1; one unreachable from every node (a mesh component without
    nodes) links to the Euclidean-nearest node when ``vertices`` and ``node_vertex`` are given.
    Weights are normalised per vertex.

    Args:
        hops: (N,V) hop distances, ``inf`` where unreachable.
        radius: (N,) node radii in hops.
        vertices: optional (V,3) positions for the unreachable-vertex fallback.
        node_vertex: optional (N,) node vertices for that fallback.
    Returns:
        ``(vertex, node, weight)`` COO arrays of all links.
    """
    V = hops.shape[1]
    d = hops / radius[:, None]
    linked = d <= 1.0
    lonely = ~linked.any(0)
    if lonely.any():
        linked[:, lonely] = d[:, lonely] <= FALLBACK_RADIUS_FACTOR
        lonely = ~linked.any(0)
    if lonely.any():
        cols = np.nonzero(lonely)[0]
        nearest = np.argmin(d[:, cols], axis=0)
        reachable = np.isfinite(d[nearest, cols])
        linked[nearest[reachable], cols[reachable]] = True
        unreachable = cols[~reachable]
        if len(unreachable):
            if vertices is None or node_vertex is None:
                raise EgorelightError(f"{len(unreachable)} template vertices are not connected to any embedded graph node")
            tree = cKDTree(np.asarray(vertices, np.float64)[node_vertex])
            _, nn = tree.query(np.asarray(vertices, np.float64)[unreachable])
            linked[nn, unreachable] = True
            d[nn, unreachable] = 0.0
    node, vertex = np.nonzero(linked)
    dist = d[node, vertex]
    weight = np.exp(-0.5 * dist * dist)
    weight = weight / np.bincount(vertex, weights=weight, minlength=V)[vertex]
    return vertex, node, weight


def build_embedded_graph(faces: np.ndarray, num_vertices: int, node_vertex: np.ndarray, node_edges: np.ndarray,
                         node_faces: np.ndarray | None = None, *, vertices: np.ndarray | None = None) -> EmbeddedGraph:
    """Build a DDC embedded graph over a template mesh.

    Hop distances are BFS distances on the template's edge graph from every node's vertex.
    Node radii follow the DDC reference (:func:`node_radii`: 3 hops on a connected template).
    Vertex v links to node k when ``d = hops(k, v) / r_k <= 1`` with weight ``exp(-0.5 d^2)``,
    normalised per vertex; a vertex with no node in reach links within ``d <= 2`` (see
    :func:`vertex_node_links` for vertices reached by no node even then). The node edges
    (``node_edges`` and the edges of ``node_faces``) are the graph's own connectivity (ARAP
    terms), not part of the links.

    Before issue 21 the radius was taken over the *graph* neighbours' vertices (halved), which
    gave 245 vertices of the DDC example other links than the reference.

    Args:
        faces: (F,3) template triangles.
        num_vertices: V.
        node_vertex: (N,) template vertex bound to each node.
        node_edges: (E,2) node pairs (graph mesh edges).
        node_faces: optional (Fg,3) graph mesh triangles (edges are added; stored for export).
        vertices: optional (V,3) template positions, only for vertices unreachable from every node.
    Returns:
        The :class:`EmbeddedGraph` with padded (V,K) links sorted by decreasing weight.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    node_vertex = np.asarray(node_vertex, dtype=np.int64).reshape(-1)
    V, N = int(num_vertices), len(node_vertex)
    if N == 0:
        raise EgorelightError("embedded graph has no nodes")
    if node_vertex.min() < 0 or node_vertex.max() >= V:
        raise EgorelightError(f"embedded graph node vertices out of range (0..{V - 1})")
    if len(faces) and (faces.min() < 0 or faces.max() >= V):
        raise EgorelightError("template faces index vertices out of range")
    edges = _graph_edges(N, node_edges, node_faces)
    hops = hop_distances(faces, V, node_vertex)
    radius = node_radii(hops, node_vertex, faces)
    vertex, node, weight = vertex_node_links(hops, radius, vertices, node_vertex)
    index, value = _pad_rows(vertex, node, weight, V)
    return EmbeddedGraph(
        node_vertex=node_vertex, node_radius=radius, edges=edges,
        vertex_node_index=index, vertex_node_weight=value,
        faces=None if node_faces is None else np.asarray(node_faces, dtype=np.int64).reshape(-1, 3),
    )


def bind_nodes_to_vertices(node_positions: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Bind each node (in order) to the closest template vertex not yet used (DDC rule).

    Args:
        node_positions: (N,3) graph mesh vertices.
        vertices: (V,3) template vertices, V >= N.
    Returns:
        (N,) int64 distinct template vertex indices.
    """
    node_positions = np.asarray(node_positions, np.float64)
    vertices = np.asarray(vertices, np.float64)
    N, V = len(node_positions), len(vertices)
    if N > V:
        raise EgorelightError(f"embedded graph has more nodes ({N}) than the template has vertices ({V})")
    tree = cKDTree(vertices)
    used = np.zeros(V, dtype=bool)
    out = np.empty(N, dtype=np.int64)
    for k, p in enumerate(node_positions):
        kq = 8
        while True:
            _, cand = tree.query(p, k=min(kq, V))
            cand = np.atleast_1d(cand)
            free = cand[~used[cand]]
            if len(free):
                out[k] = free[0]
                break
            if kq >= V:
                raise EgorelightError("no free template vertex to bind an embedded graph node")
            kq *= 4
        used[out[k]] = True
    return out


def _fps_nodes(vertices: np.ndarray, faces: np.ndarray, num_nodes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    V = len(vertices)
    chosen = np.empty(num_nodes, dtype=np.int64)
    chosen[0] = int(np.argmax(vertices[:, 1]))  # deterministic start: the highest vertex
    dist = np.linalg.norm(vertices - vertices[chosen[0]], axis=1)
    for k in range(1, num_nodes):
        chosen[k] = int(np.argmax(dist))
        dist = np.minimum(dist, np.linalg.norm(vertices - vertices[chosen[k]], axis=1))
    adj = mesh_adjacency(faces, V)
    _, _, source = csgraph.dijkstra(adj, directed=False, unweighted=True, indices=chosen, min_only=True,
                                    return_predecessors=True)
    owner = np.full(V, -1, dtype=np.int64)
    owner[chosen] = np.arange(num_nodes)
    cell = np.where(source >= 0, owner[np.clip(source, 0, V - 1)], -1)
    e = mesh_edges(faces)
    ce = cell[e]
    ce = ce[(ce[:, 0] != ce[:, 1]) & (ce >= 0).all(1)]
    node_edges = np.unique(np.sort(ce, axis=1), axis=0) if len(ce) else np.zeros((0, 2), np.int64)
    cf = cell[np.asarray(faces, np.int64)]
    distinct = (cf[:, 0] != cf[:, 1]) & (cf[:, 1] != cf[:, 2]) & (cf[:, 0] != cf[:, 2]) & (cf >= 0).all(1)
    cf = cf[distinct]
    if len(cf):
        _, first = np.unique(np.sort(cf, axis=1), axis=0, return_index=True)
        node_faces = cf[np.sort(first)]
    else:
        node_faces = np.zeros((0, 3), np.int64)
    return chosen, node_edges, node_faces


def _decimate_nodes(vertices: np.ndarray, faces: np.ndarray, num_nodes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    import pymeshlab  # optional heavy import

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=np.asarray(faces, np.int32)))
    target = max(round(num_nodes * len(faces) / max(len(vertices), 1)), 4)
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=target, preservetopology=True, preserveboundary=True,
                                                optimalplacement=False, planarquadric=True)
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    graph_vertices = np.asarray(m.vertex_matrix(), np.float64)
    graph_faces = np.asarray(m.face_matrix(), np.int64)
    node_vertex = bind_nodes_to_vertices(graph_vertices, vertices)
    return node_vertex, mesh_edges(graph_faces), graph_faces


def choose_graph_nodes(vertices: np.ndarray, faces: np.ndarray, num_nodes: int,
                       method: str = "fps") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pick graph nodes for a character that has no embedded graph.

    * ``"fps"`` (default, deterministic, exactly ``num_nodes``): Euclidean farthest point
      sampling over the template vertices (starting at the highest vertex); node edges join
      nodes whose geodesic (hop) Voronoi cells touch along a mesh edge, node faces are the
      mesh triangles spanning three cells (a dual Delaunay triangulation on the surface).
    * ``"decimate"`` (as DDC graphs were made): pymeshlab quadric edge-collapse decimation to
      about ``num_nodes`` vertices, each bound to the closest unused template vertex; edges and
      faces from the decimated mesh. The node count is approximate.

    Args:
        vertices: (V,3) template positions, metres.
        faces: (F,3) template triangles.
        num_nodes: wanted number of nodes (<= V).
        method: ``"fps"`` or ``"decimate"``.
    Returns:
        ``(node_vertex (N,), node_edges (E,2), node_faces (Fg,3))`` int64, ready for
        :func:`build_embedded_graph`.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if not 1 <= num_nodes <= len(vertices):
        raise EgorelightError(f"cannot choose {num_nodes} graph nodes on a mesh of {len(vertices)} vertices")
    if method == "fps":
        return _fps_nodes(vertices, faces, int(num_nodes))
    if method == "decimate":
        return _decimate_nodes(vertices, faces, int(num_nodes))
    raise EgorelightError(f"unknown graph node method {method!r}, expected 'fps' or 'decimate'")


# ----------------------------------------------------------------------------------------------
# Deformation
# ----------------------------------------------------------------------------------------------

_SPARSE_CACHE: weakref.WeakKeyDictionary[EmbeddedGraph, dict] = weakref.WeakKeyDictionary()


def graph_weight_matrix(graph: EmbeddedGraph, dtype: torch.dtype, device: torch.device | str) -> torch.Tensor:
    """Sparse (V,N) vertex-node weight matrix (COO, coalesced), cached per graph/dtype/device."""
    device = torch.device(device)
    per_graph = _SPARSE_CACHE.setdefault(graph, {})
    key = (dtype, device)
    if key not in per_graph:
        idx, w = graph.vertex_node_index, graph.vertex_node_weight
        rows, slots = np.nonzero(idx >= 0)
        indices = torch.as_tensor(np.stack([rows, idx[rows, slots]]), dtype=torch.int64)
        values = torch.as_tensor(w[rows, slots], dtype=dtype)
        per_graph[key] = torch.sparse_coo_tensor(indices, values, (idx.shape[0], graph.num_nodes), check_invariants=True).coalesce().to(device)
    return per_graph[key]


def blend_node_values(values: torch.Tensor, graph: EmbeddedGraph) -> torch.Tensor:
    """Per-vertex graph-weighted sums of per-node values: ``out_v = sum_k w_vk values_k``.

    Args:
        values: (...,N,C).
        graph: the embedded graph.
    Returns:
        (...,V,C).
    """
    return sparse_blend(graph_weight_matrix(graph, values.dtype, values.device), values)


def _as_tensor(x, like: torch.Tensor) -> torch.Tensor:
    """``x`` (numpy or tensor) as a tensor of ``like``'s dtype and device."""
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)


def node_positions(vertices_rest: torch.Tensor, graph: EmbeddedGraph) -> torch.Tensor:
    """Rest positions of the nodes, ``g_k = vertices_rest[node_vertex[k]]``; (...,V,3) -> (...,N,3)."""
    idx = torch.as_tensor(graph.node_vertex, device=vertices_rest.device)
    return vertices_rest.index_select(-2, idx)


def deformed_node_positions(vertices_rest: torch.Tensor, graph: EmbeddedGraph, node_translation: torch.Tensor) -> torch.Tensor:
    """Deformed node positions ``g_k + t_k`` (canonical space).

    Args:
        vertices_rest: (V,3) or (...,V,3) rest template, metres.
        graph: the embedded graph.
        node_translation: (...,N,3) metres.
    Returns:
        (...,N,3) metres.
    """
    vertices_rest = _as_tensor(vertices_rest, like=node_translation)
    return node_positions(vertices_rest, graph) + node_translation


def embedded_deformation(vertices_rest: torch.Tensor, graph: EmbeddedGraph, node_euler: torch.Tensor,
                         node_translation: torch.Tensor, vertex_offsets: torch.Tensor | None = None) -> torch.Tensor:
    """The paper's ``E(V_bar, alpha, beta, o)`` in canonical space.

    ``v' = sum_k w_vk [R_k (v - g_k) + g_k + t_k] + o_v`` with ``R_k = euler_to_matrix(alpha_k)``
    (``Rz @ Ry @ Rx``) and ``g_k`` the rest position of node k's vertex. Computed as the
    graph-weighted blend of per-node affine maps ``[R_k | g_k + t_k - R_k g_k]``.

    Args:
        vertices_rest: (V,3) (or (...,V,3)) rest template, metres; numpy is accepted.
        graph: the embedded graph.
        node_euler: (...,N,3) node rotations ``alpha`` (rx, ry, rz) radians.
        node_translation: (...,N,3) node translations ``beta``, metres.
        vertex_offsets: optional (...,V,3) per-vertex offsets ``o``, metres.
    Returns:
        (...,V,3) deformed canonical vertices, metres.
    """
    node_translation = torch.as_tensor(node_translation)
    node_euler = torch.as_tensor(node_euler, dtype=node_translation.dtype, device=node_translation.device)
    vertices_rest = _as_tensor(vertices_rest, like=node_translation)
    g = node_positions(vertices_rest, graph)
    R = euler_to_matrix(node_euler)
    c = g + node_translation - (R @ g[..., None])[..., 0]
    affine = torch.cat([R, c[..., None]], -1).flatten(-2)  # (...,N,12)
    M = blend_node_values(affine, graph).unflatten(-1, (3, 4))
    out = transform_points(M, vertices_rest)
    if vertex_offsets is not None:
        out = out + vertex_offsets
    return out


# ----------------------------------------------------------------------------------------------
# Posing
# ----------------------------------------------------------------------------------------------


def _node_skin_weights(skin_weights, graph: EmbeddedGraph):
    """Rows of the skin weights at the node vertices; for numpy, one cached array per graph."""
    if torch.is_tensor(skin_weights):
        return skin_weights.index_select(0, torch.as_tensor(graph.node_vertex, device=skin_weights.device))
    skin_weights = np.asarray(skin_weights)
    per_graph = _SPARSE_CACHE.setdefault(graph, {})
    entry = per_graph.get("node_skin_weights")
    if entry is None or entry[0]() is not skin_weights:
        entry = (weakref.ref(skin_weights), skin_weights[graph.node_vertex])
        per_graph["node_skin_weights"] = entry
    return entry[1]


def node_skinning_transforms(bone_T: torch.Tensor, skin_weights, graph: EmbeddedGraph, method: str = "dqs") -> torch.Tensor:
    """Skinning transforms evaluated at the node vertices (DQS or LBS of their skin weights).

    Args:
        bone_T: (...,B,4,4) bone skinning transforms.
        skin_weights: (V,B) skinning weights.
        graph: the embedded graph.
        method: 'dqs' or 'lbs'.
    Returns:
        (...,N,4,4).
    """
    return skinning_transforms(bone_T, _node_skin_weights(skin_weights, graph), method)


def _graph_blended_top(bone_T: torch.Tensor, skin_weights, graph: EmbeddedGraph, method: str) -> torch.Tensor:
    """(...,V,3,4) top rows of ``sum_k w_vk M_k``."""
    M = node_skinning_transforms(bone_T, skin_weights, graph, method)
    return blend_node_values(M[..., :3, :].flatten(-2), graph).unflatten(-1, (3, 4))


def graph_skinning_transforms(bone_T: torch.Tensor, skin_weights, graph: EmbeddedGraph, method: str = "dqs") -> torch.Tensor:
    """Per-vertex posing transforms of DDC graph posing: ``M_v = sum_k w_vk M_k``.

    ``M_k`` are the skinning transforms at the node vertices (:func:`node_skinning_transforms`);
    the result is affine (not rigid) in general. Feed it to
    :func:`egorelight_cli.geometry.skinning.inverse_skinning_points` for ``W^-1``.

    Args:
        bone_T: (...,B,4,4) bone skinning transforms.
        skin_weights: (V,B).
        graph: the embedded graph.
        method: 'dqs' or 'lbs'.
    Returns:
        (...,V,4,4).
    """
    return append_homogeneous_row(_graph_blended_top(bone_T, skin_weights, graph, method))


def pose_through_graph(points: torch.Tensor, bone_T: torch.Tensor, skin_weights, graph: EmbeddedGraph,
                       method: str = "dqs") -> torch.Tensor:
    """DDC posing: skinning at the node vertices, spread to the points with the graph weights.

    ``x'_v = sum_k w_vk M_k x_v`` with ``M_k`` the DQS (or LBS) skinning transform of node k's
    vertex.

    Args:
        points: (...,V,3) canonical (rest-space) positions, metres.
        bone_T: (...,B,4,4) bone skinning transforms.
        skin_weights: (V,B).
        graph: the embedded graph.
        method: 'dqs' or 'lbs'.
    Returns:
        (...,V,3) posed positions, metres.
    """
    return transform_points(_graph_blended_top(bone_T, skin_weights, graph, method), points)


def pose_character(character: Character, theta: torch.Tensor, node_euler: torch.Tensor | None = None,
                   node_translation: torch.Tensor | None = None, vertex_offsets: torch.Tensor | None = None,
                   skinning: str = "dqs", through_graph: bool = True) -> torch.Tensor:
    """The paper's ``V = W(E(V_bar, alpha, beta, o), K(theta, B), W)``.

    Args:
        character: the character (rest vertices, skeleton, skin weights, graph).
        theta: (...,D) DoF values; its dtype/device are used throughout (numpy -> float64).
        node_euler: optional (...,N,3) graph rotations (rx, ry, rz), radians; 0 when omitted.
        node_translation: optional (...,N,3) graph translations, metres; 0 when omitted.
        vertex_offsets: optional (...,V,3) canonical per-vertex offsets, metres.
        skinning: 'dqs' (the paper) or 'lbs'.
        through_graph: pose through the graph as DDC does (default); False skins every vertex
            with its own skin weights.
    Returns:
        (...,V,3) posed vertices, metres.
    """
    if skinning not in SKINNING_METHODS:
        raise EgorelightError(f"unknown skinning method {skinning!r}, expected one of {SKINNING_METHODS}")
    theta = theta if torch.is_tensor(theta) else torch.as_tensor(np.asarray(theta), dtype=torch.float64)
    if not theta.is_floating_point():
        theta = theta.to(torch.float64)
    rest = _as_tensor(character.vertices, like=theta)
    if node_euler is None and node_translation is None:
        canonical = rest if vertex_offsets is None else rest + vertex_offsets
    else:
        zeros = torch.zeros(character.graph.num_nodes, 3, dtype=theta.dtype, device=theta.device)
        canonical = embedded_deformation(
            rest, character.graph,
            zeros if node_euler is None else node_euler,
            zeros if node_translation is None else node_translation,
            vertex_offsets,
        )
    bone_T = bone_transforms(theta, character)
    if through_graph:
        return pose_through_graph(canonical, bone_T, character.skin_weights, character.graph, skinning)
    return skin_points(canonical, bone_T, character.skin_weights, skinning)
