"""Registration of a template mesh to a scan: similarity alignment, non-rigid ICP through an
embedded graph, per-vertex refinement with a Laplacian regulariser.

All positions are metres, (N,3) float64. The scan is any triangle mesh (its own tessellation,
noise, holes). Correspondences go both ways and are re-found at every step:

* template -> scan: each template vertex to its closest point on the scan;
* scan -> template: area-uniform samples of the scan to their closest point on the current
  template surface (a barycentric combination of three template vertices).

A pair is rejected when it is farther apart than a distance threshold or when the two surface
normals differ by more than the normal threshold (``dot < min_normal_dot``). Residuals are
point-to-plane along the scan's normal plus a small point-to-point part; each direction's rows
are weighted by ``1/sqrt(count)`` so that its term is a mean.

The three steps:

1. :func:`align_similarity`: ICP for a scale, a translation and (optionally) a rotation
   (Umeyama's closed form on the pairs of both directions).
2. :func:`fit_embedded_graph`: Gauss-Newton on the nodes' rotations and translations of an
   embedded deformation graph (Sumner et al. 2007), ``v' = sum_k w_vk [R_k (v - g_k) + g_k + t_k]``,
   with the graph's as-rigid-as-possible term ``|R_k (g_l - g_k) + g_k + t_k - (g_l + t_l)|^2``
   over its edges; rotations are updated multiplicatively (``R <- exp([w]x) R``, so they stay
   rotations) and the stiffness decreases level by level.
3. :func:`refine_vertices`: free per-vertex positions with a uniform-Laplacian term on the
   displacement from the graph fit (detail the graph cannot express, without noise-chasing).

Linear systems are sparse normal equations solved with SciPy (SuperLU), on the CPU.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import spsolve
from scipy.spatial.transform import Rotation

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.embedded_graph import mesh_adjacency
from egorelight_cli.geometry.normals import face_normals, vertex_normals
from egorelight_cli.geometry.pointcloud_ops import SurfaceDistance
from egorelight_cli.geometry.rotations import skew
from egorelight_cli.structures.character import EmbeddedGraph


# ----------------------------------------------------------------------------------- the scan
def outward_face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit face normals (F,3) of a mesh, all flipped when most of the area faces inwards
    (area-weighted ``n . (centroid - mesh centre)`` summed below zero): scans come with either
    winding."""
    normals = face_normals(vertices, faces)
    centroids = vertices[faces].mean(axis=1)
    areas = 0.5 * np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                          vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    centre = (areas @ centroids) / max(areas.sum(), 1e-300)
    outward = float(np.sum(areas * np.einsum("fi,fi->f", normals, centroids - centre)))
    return -normals if outward < 0 else normals


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points uniformly by area on a mesh: (points (count,3), face index (count,))."""
    tri = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(faces), size=int(count), p=areas / areas.sum())
    bary = rng.dirichlet(np.ones(3), size=int(count))
    return np.einsum("nk,nkd->nd", bary, tri[face]), face


@dataclass(frozen=True, eq=False)
class ScanTarget:
    """A scan made ready for registration.

    Attributes:
        vertices: (M,3) scan vertices, metres.
        faces: (G,3) int64 scan triangles.
        face_normals: (G,3) unit, oriented outwards (:func:`outward_face_normals`).
        samples: (S,3) area-uniform surface samples (the scan -> template points).
        sample_normals: (S,3) the normals of the faces they lie on.
        surface: closest-point queries on the scan.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_normals: np.ndarray
    samples: np.ndarray
    sample_normals: np.ndarray
    surface: SurfaceDistance

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, faces: np.ndarray, num_samples: int, seed: int = 0) -> "ScanTarget":
        vertices = np.asarray(vertices, np.float64)
        faces = np.asarray(faces, np.int64)
        normals = outward_face_normals(vertices, faces)
        samples, face = sample_surface(vertices, faces, num_samples, np.random.default_rng(seed))
        return cls(vertices, faces, normals, samples, normals[face], SurfaceDistance(vertices, faces, seed=seed))


# ---------------------------------------------------------------------------- correspondences
@dataclass(frozen=True)
class PairRules:
    """Which closest-point pairs count: ``max_distance`` metres, ``min_normal_dot`` (cosine),
    ``point_weight`` (weight of the point-to-point part next to point-to-plane)."""

    max_distance: float
    min_normal_dot: float = 0.5
    point_weight: float = 0.1


@dataclass(frozen=True)
class Pairs:
    """Closest-point pairs of both directions as one linear residual ``C @ x.ravel() - d``.

    Attributes:
        C: (R,3V) sparse, over the flattened template positions x (V,3).
        d: (R,) metres.
        template_points: (P,3) template-side positions of all pairs (for a similarity fit).
        scan_points: (P,3) scan-side positions of the same pairs.
        counts: (template -> scan, scan -> template) pairs kept.
    """

    C: sp.csr_matrix
    d: np.ndarray
    template_points: np.ndarray
    scan_points: np.ndarray
    counts: tuple[int, int]


def _residual_rows(bary: np.ndarray, verts: np.ndarray, targets: np.ndarray, normals: np.ndarray,
                   weight: float, point_weight: float, num_vertices: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """Rows of point-to-plane (+ ``point_weight`` x point-to-point) residuals of points
    ``sum_i bary[:, i] x[verts[:, i]]`` (bary (P,k), verts (P,k)) against targets (P,3) with normals (P,3)."""
    P, k = bary.shape
    cols = (3 * verts[:, :, None] + np.arange(3)).reshape(P, 3 * k)  # (P,3k)
    plane_vals = (bary[:, :, None] * normals[:, None, :]).reshape(P, 3 * k)
    plane = sp.csr_matrix((weight * plane_vals.ravel(), cols.ravel(), np.arange(P + 1) * 3 * k),
                          shape=(P, 3 * num_vertices))
    rows = [plane]
    rhs = [weight * np.einsum("pi,pi->p", normals, targets)]
    if point_weight > 0:
        pw = weight * np.sqrt(point_weight)
        point_cols = (3 * verts[:, None, :] + np.arange(3)[None, :, None]).reshape(3 * P, k)
        point_vals = np.repeat(bary, 3, axis=0) * pw
        rows.append(sp.csr_matrix((point_vals.ravel(), point_cols.ravel(), np.arange(3 * P + 1) * k),
                                  shape=(3 * P, 3 * num_vertices)))
        rhs.append(pw * targets.ravel())
    return sp.vstack(rows, format="csr"), np.concatenate(rhs)


def _template_to_scan(vertices: np.ndarray, faces: np.ndarray, scan: ScanTarget, rules: PairRules):
    """Each template vertex paired with its closest scan point: (rows, rhs, template points,
    scan points) of the kept pairs (:func:`_residual_rows` along the scan's normals)."""
    q, qface, qdist = scan.surface.closest(vertices)
    qn = scan.face_normals[qface]
    keep = (qdist < rules.max_distance) & (np.einsum("vi,vi->v", vertex_normals(vertices, faces), qn) >= rules.min_normal_dot)
    n = int(keep.sum())
    C, d = _residual_rows(np.ones((n, 1)), np.nonzero(keep)[0][:, None], q[keep], qn[keep], np.sqrt(0.5 / max(n, 1)),
                          rules.point_weight, len(vertices))
    return C, d, vertices[keep], q[keep]


def _scan_to_template(vertices: np.ndarray, faces: np.ndarray, scan: ScanTarget, rules: PairRules):
    """Each scan sample paired with its closest point on the template surface (barycentric in a
    template face): (rows, rhs, template points, scan points) of the kept pairs."""
    from trimesh.triangles import points_to_barycentric

    p, pface, pdist = SurfaceDistance(vertices, faces, samples_per_face=2, candidates=8).closest(scan.samples)
    tn = face_normals(vertices, faces)[pface]
    keep = (pdist < rules.max_distance) & (np.einsum("si,si->s", tn, scan.sample_normals) >= rules.min_normal_dot)
    n = int(keep.sum())
    tri = faces[pface[keep]]
    bary = points_to_barycentric(vertices[tri], p[keep]) if n else np.zeros((0, 3))
    C, d = _residual_rows(bary, tri, scan.samples[keep], scan.sample_normals[keep], np.sqrt(0.5 / max(n, 1)),
                          rules.point_weight, len(vertices))
    return C, d, p[keep], scan.samples[keep]


def find_pairs(vertices: np.ndarray, faces: np.ndarray, scan: ScanTarget, rules: PairRules) -> Pairs:
    """Closest-point pairs between the template (vertices (V,3), faces (F,3)) and the scan, both
    ways, filtered by ``rules``; see :class:`Pairs`."""
    C1, d1, t1, s1 = _template_to_scan(vertices, faces, scan, rules)
    C2, d2, t2, s2 = _scan_to_template(vertices, faces, scan, rules)
    return Pairs(sp.vstack([C1, C2], format="csr"), np.concatenate([d1, d2]), np.concatenate([t1, t2]),
                 np.concatenate([s1, s2]), (len(t1), len(t2)))


@dataclass
class FitLog:
    """What a fit did: its steps and the pair counts (template -> scan, scan -> template) of each."""

    steps: int = 0
    pair_counts: list[tuple[int, int]] = field(default_factory=list)

    def record(self, pairs: Pairs) -> None:
        self.steps += 1
        self.pair_counts.append(pairs.counts)


# --------------------------------------------------------------------------------- similarity
@dataclass(frozen=True)
class Similarity:
    """``x -> scale * R @ x + t`` (scale dimensionless, R (3,3), t (3,) metres)."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * points @ self.R.T + self.t

    @property
    def rotation_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(Rotation.from_matrix(self.R).as_rotvec())))

    def then(self, other: "Similarity") -> "Similarity":
        """``other`` applied after ``self``."""
        return Similarity(other.scale * self.scale, other.R @ self.R, other.scale * other.R @ self.t + other.t)


def similarity_transform(source: np.ndarray, target: np.ndarray, rotation: bool = True) -> Similarity:
    """Least-squares similarity (Umeyama 1991) mapping points source (N,3) onto target (N,3);
    ``rotation=False`` fits only a scale and a translation."""
    ms, mt = source.mean(0), target.mean(0)
    S, T = source - ms, target - mt
    if rotation:
        U, sigma, Vt = np.linalg.svd(T.T @ S / len(S))
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        R = U @ D @ Vt
        scale = float(np.trace(np.diag(sigma) @ D) / max(np.mean(np.sum(S * S, axis=1)), 1e-300))
    else:
        R = np.eye(3)
        scale = float(np.sum(S * T) / max(np.sum(S * S), 1e-300))
    return Similarity(scale, R, mt - scale * R @ ms)


def initial_similarity(vertices: np.ndarray, scan: ScanTarget) -> Similarity:
    """Scale by the ratio of heights (y extents), then bounding-box centres made to coincide."""
    height = float(np.ptp(vertices[:, 1]))
    scale = float(np.ptp(scan.vertices[:, 1])) / max(height, 1e-300)
    centre = lambda x: 0.5 * (x.min(0) + x.max(0))  # noqa: E731
    return Similarity(scale, np.eye(3), centre(scan.vertices) - scale * centre(vertices))


def align_similarity(vertices: np.ndarray, faces: np.ndarray, scan: ScanTarget, iterations: int,
                     rules: PairRules, rotation: bool = True, log: FitLog | None = None) -> Similarity:
    """Similarity ICP of the template (V,3)/(F,3) to the scan from :func:`initial_similarity`.

    Every iteration re-pairs both ways (the distance threshold starts at 4x ``rules.max_distance``
    and halves down to it) and refits the similarity to all kept pairs; it stops early when
    fewer than 10 pairs are left.
    """
    total = initial_similarity(vertices, scan)
    for it in range(int(iterations)):
        current = total.apply(vertices)
        level = PairRules(rules.max_distance * max(4.0 / 2 ** it, 1.0), rules.min_normal_dot, rules.point_weight)
        pairs = find_pairs(current, faces, scan, level)
        if len(pairs.template_points) < 10:
            break
        total = total.then(similarity_transform(pairs.template_points, pairs.scan_points, rotation))
        if log is not None:
            log.record(pairs)
    return total


# ----------------------------------------------------------------------- embedded-graph fitting
@dataclass
class GraphState:
    """Node rotations R (N,3,3) and translations t (N,3) of an embedded graph over rest positions."""

    R: np.ndarray
    t: np.ndarray

    @classmethod
    def identity(cls, num_nodes: int) -> "GraphState":
        return cls(np.tile(np.eye(3), (num_nodes, 1, 1)), np.zeros((num_nodes, 3)))


@dataclass(frozen=True)
class _Links:
    """Vertex-node links of a graph as flat arrays: vertex (L,), node (L,), weight (L,)."""

    vertex: np.ndarray
    node: np.ndarray
    weight: np.ndarray

    @classmethod
    def of(cls, graph: EmbeddedGraph) -> "_Links":
        v, slot = np.nonzero(graph.vertex_node_index >= 0)
        return cls(v, graph.vertex_node_index[v, slot], graph.vertex_node_weight[v, slot])


def _arms(rest: np.ndarray, nodes: np.ndarray, links: _Links, state: GraphState) -> np.ndarray:
    """``R_k (v - g_k)`` per link; (L,3)."""
    return np.einsum("lij,lj->li", state.R[links.node], rest[links.vertex] - nodes[links.node])


def deform(rest: np.ndarray, nodes: np.ndarray, links: _Links, state: GraphState) -> np.ndarray:
    """Embedded deformation of rest vertices (V,3) with node rest positions (N,3); (V,3) metres."""
    per_link = _arms(rest, nodes, links, state) + nodes[links.node] + state.t[links.node]
    out = np.zeros_like(rest)
    np.add.at(out, links.vertex, links.weight[:, None] * per_link)
    return out


def _skew_blocks(a: np.ndarray) -> np.ndarray:
    """(n,3,3) cross-product matrices ``[a]x`` of vectors (n,3)."""
    return skew(torch.as_tensor(a)).numpy()


def _block_matrix(row_block: np.ndarray, col_block: np.ndarray, blocks: np.ndarray, shape: tuple[int, int],
                  col_offset: int = 0) -> sp.csr_matrix:
    """Sparse matrix from 3x3 blocks (n,3,3) at block rows/cols (n,) (columns in blocks of 6 + offset)."""
    r = (3 * row_block[:, None, None] + np.arange(3)[None, :, None]).repeat(3, 2)
    c = (6 * col_block[:, None, None] + col_offset + np.arange(3)[None, None, :]).repeat(3, 1)
    return sp.csr_matrix((blocks.ravel(), (r.ravel(), c.ravel())), shape=shape)


def graph_jacobian(rest: np.ndarray, nodes: np.ndarray, links: _Links, state: GraphState) -> sp.csr_matrix:
    """d vertices / d (w_k, dt_k): (3V, 6N) sparse, for updates ``R_k <- exp([w_k]x) R_k``,
    ``t_k <- t_k + dt_k`` (``dv/dw_k = -w_vk [R_k (v - g_k)]x``, ``dv/dt_k = w_vk I``)."""
    V, N = len(rest), len(nodes)
    shape = (3 * V, 6 * N)
    rot = -links.weight[:, None, None] * _skew_blocks(_arms(rest, nodes, links, state))
    trans = links.weight[:, None, None] * np.eye(3)
    return _block_matrix(links.vertex, links.node, rot, shape) + _block_matrix(links.vertex, links.node, trans, shape, 3)


def arap_system(nodes: np.ndarray, edges: np.ndarray, state: GraphState) -> tuple[sp.csr_matrix, np.ndarray]:
    """Linearised graph ARAP residual ``A @ delta + r`` over both directions of every edge,
    each row weighted ``1/sqrt(2E)``: ``r_kl = R_k (g_l - g_k) + g_k + t_k - g_l - t_l``."""
    k = np.concatenate([edges[:, 0], edges[:, 1]])
    l = np.concatenate([edges[:, 1], edges[:, 0]])
    n, N = len(k), len(nodes)
    b = np.einsum("nij,nj->ni", state.R[k], nodes[l] - nodes[k])
    r = b + nodes[k] + state.t[k] - nodes[l] - state.t[l]
    rows = np.arange(n)
    shape = (3 * n, 6 * N)
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    A = (_block_matrix(rows, k, -_skew_blocks(b), shape) + _block_matrix(rows, k, eye, shape, 3)
         - _block_matrix(rows, l, eye, shape, 3))
    w = 1.0 / np.sqrt(max(n, 1))
    return (w * A).tocsr(), w * r.ravel()


def _apply_update(state: GraphState, delta: np.ndarray) -> GraphState:
    step = delta.reshape(-1, 6)
    return GraphState(Rotation.from_rotvec(step[:, :3]).as_matrix() @ state.R, state.t + step[:, 3:])


@dataclass(frozen=True)
class GraphFitSchedule:
    """Stiffness levels of the graph fit: per level an ARAP weight and a pair distance
    threshold (metres), each level ``steps`` Gauss-Newton steps with fresh pairs."""

    stiffness: tuple[float, ...]
    max_distance: tuple[float, ...]
    steps: int = 3
    min_normal_dot: float = 0.5
    point_weight: float = 0.1
    damping: float = 1e-6


def fit_embedded_graph(rest: np.ndarray, faces: np.ndarray, graph: EmbeddedGraph, scan: ScanTarget,
                       schedule: GraphFitSchedule, log: FitLog | None = None) -> np.ndarray:
    """Non-rigid ICP through the embedded graph (module doc, step 2).

    Args:
        rest: (V,3) template vertices already aligned to the scan (the graph's rest positions).
        faces: (F,3) template triangles.
        graph: the template's embedded graph (node vertices, edges, vertex-node weights).
        scan: the prepared scan.
        schedule: stiffness levels.
        log: optional :class:`FitLog` to fill.
    Returns:
        (V,3) deformed template, metres.
    """
    if len(schedule.stiffness) != len(schedule.max_distance):
        raise EgorelightError("graph fit: stiffness and max_distance need one entry per level")
    links = _Links.of(graph)
    nodes = rest[graph.node_vertex]
    state = GraphState.identity(graph.num_nodes)
    current = rest
    for stiffness, max_distance in zip(schedule.stiffness, schedule.max_distance):
        rules = PairRules(max_distance, schedule.min_normal_dot, schedule.point_weight)
        for _ in range(int(schedule.steps)):
            pairs = find_pairs(current, faces, scan, rules)
            A = pairs.C @ graph_jacobian(rest, nodes, links, state)
            r = pairs.C @ current.ravel() - pairs.d
            A_reg, r_reg = arap_system(nodes, graph.edges, state)
            H = (A.T @ A + stiffness * (A_reg.T @ A_reg)).tocsc()
            H = H + schedule.damping * sp.identity(H.shape[0], format="csc")
            delta = spsolve(H, -(A.T @ r + stiffness * (A_reg.T @ r_reg)))
            state = _apply_update(state, delta)
            current = deform(rest, nodes, links, state)
            if log is not None:
                log.record(pairs)
    return current


# ------------------------------------------------------------------------ per-vertex refinement
def uniform_laplacian(faces: np.ndarray, num_vertices: int) -> sp.csr_matrix:
    """(V,V) ``L = I - D^-1 A`` of the mesh edge graph (rows of isolated vertices are zero)."""
    adj = mesh_adjacency(faces, num_vertices)
    degree = np.asarray(adj.sum(axis=1)).ravel()
    inv = np.divide(1.0, degree, out=np.zeros_like(degree), where=degree > 0)
    return (sp.diags((degree > 0).astype(float)) - sp.diags(inv) @ adj).tocsr()


def refine_vertices(vertices: np.ndarray, faces: np.ndarray, scan: ScanTarget, iterations: int,
                    laplacian_weight: float, rules: PairRules, log: FitLog | None = None) -> np.ndarray:
    """Per-vertex refinement (module doc, step 3).

    Minimises the pair residuals plus ``laplacian_weight * mean_v |L (x - x0)|_v^2`` with x0 the
    input, re-pairing ``iterations`` times.

    Args:
        vertices: (V,3) template after the graph fit, metres.
        faces: (F,3).
        scan: the prepared scan.
        iterations: re-pairing rounds.
        laplacian_weight: stiffness of the displacement field.
        rules: pair rejection.
        log: optional :class:`FitLog` to fill.
    Returns:
        (V,3) refined vertices, metres.
    """
    V = len(vertices)
    L = sp.kron(uniform_laplacian(faces, V), sp.identity(3), format="csr") / np.sqrt(V)
    LtL = (L.T @ L).tocsc()
    x0 = vertices.ravel()
    x = x0
    for _ in range(int(iterations)):
        pairs = find_pairs(x.reshape(V, 3), faces, scan, rules)
        H = (pairs.C.T @ pairs.C).tocsc() + laplacian_weight * LtL + 1e-9 * sp.identity(3 * V, format="csc")
        x = spsolve(H, pairs.C.T @ pairs.d + laplacian_weight * (LtL @ x0) + 1e-9 * x0)
        if log is not None:
            log.record(pairs)
    return x.reshape(V, 3)


def surface_distances(vertices: np.ndarray, faces: np.ndarray, scan: ScanTarget) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-surface distances (metres): (template vertices -> scan surface (V,),
    scan samples -> template surface (S,))."""
    return scan.surface(vertices), SurfaceDistance(vertices, faces)(scan.samples)
