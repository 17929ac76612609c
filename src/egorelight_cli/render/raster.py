"""Mesh rasterisation: into a camera image by ray casting, and into UV (texture) space.

Camera rasterisation casts one ray per pixel centre (OpenCV pixel centres: pixel ``(row i,
column j)`` is at ``(u, v) = (j, i)``) through :func:`~egorelight_cli.geometry.cameras.unproject_to_rays`,
so pinhole and fisheye cameras (including > 180 degree lenses) are handled alike, and finds the
first surface with Embree (:class:`~egorelight_cli.geometry.raycast.RayCaster`).

UV-space convention (used by every function here and by the ``uvmaps`` artifacts):

* a UV map of resolution (H, W) is an *image of the UV square*: row 0 is the top, ``v = 1``;
  column 0 is the left, ``u = 0``;
* texel ``(row i, column j)`` covers ``u in [j/W, (j+1)/W]``, ``v in [1-(i+1)/H, 1-i/H]`` and is
  sampled at its centre ``u = (j + 0.5) / W``, ``v = 1 - (i + 0.5) / H``;
* continuous *texel coordinates* ``(x, y) = (u W - 0.5, (1 - v) H - 0.5)`` put texel centres
  at integers, like OpenCV pixel coordinates (so ``cv2.remap`` samples a UV map with them).

Barycentrics everywhere are the weights of a face's three vertices in ``faces`` order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, camera_rays_world
from egorelight_cli.geometry.normals import face_normals, vertex_normals
from egorelight_cli.geometry.raycast import RayCaster

# Most candidate texels tested in one broadcast block of UV rasterisation (bounds memory).
_UV_CHUNK_TEXELS = 1 << 22
# Texel centres this far outside a face (in barycentric units) still count as inside, so
# centres exactly on shared edges are never dropped by rounding.
_INSIDE_TOLERANCE = 1e-9
# How far (texels) the conservative pass searches for a free texel for a face that has none.
_CONSERVATIVE_SEARCH_RADIUS = 8


# --------------------------------------------------------------------------------------------
# Mesh attributes
# --------------------------------------------------------------------------------------------


def _normalize(vectors: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis; zero vectors stay zero."""
    norms = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return np.divide(vectors, norms, out=np.zeros_like(vectors), where=norms > 0)


def _interpolate(corner_values: np.ndarray, barycentrics: np.ndarray) -> np.ndarray:
    """Barycentric interpolation: corner values (...,3,C) and weights (...,3) -> (...,C)."""
    return np.einsum("...kc,...k->...c", corner_values, barycentrics)


# --------------------------------------------------------------------------------------------
# Camera rasterisation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RasterResult:
    """A mesh rasterised into one camera; (H,W) is the camera's image size.

    Background pixels (``mask`` False) hold face_id -1 and zeros everywhere else.

    Attributes:
        face_id: (H,W) int32 visible face, -1 for background.
        barycentrics: (H,W,3) float32 weights of the visible face's vertices.
        depth: (H,W) float32 z of the visible point in the camera frame, metres (may be
            negative for fisheye rays more than 90 degrees off-axis).
        distance: (H,W) float32 distance from the camera centre along the pixel ray, metres.
        points: (H,W,3) float32 visible surface points, world frame, metres.
        normal: (H,W,3) float32 unit interpolated vertex normals, world frame.
        face_normal: (H,W,3) float32 unit geometric face normals, world frame.
        uv: (H,W,2) float32 interpolated UVs, or None when no face UVs were given.
        mask: (H,W) bool, True where the mesh is visible.
    """

    face_id: np.ndarray
    barycentrics: np.ndarray
    depth: np.ndarray
    distance: np.ndarray
    points: np.ndarray
    normal: np.ndarray
    face_normal: np.ndarray
    uv: np.ndarray | None
    mask: np.ndarray


def rasterize(
    vertices: np.ndarray,
    faces: np.ndarray,
    camera: Camera,
    face_uvs: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    caster: RayCaster | None = None,
) -> RasterResult:
    """Rasterise a triangle mesh into ``camera`` by casting one ray per pixel centre.

    Args:
        vertices: (V,3) world positions, metres.
        faces: (F,3) vertex indices.
        camera: pinhole or fisheye :class:`Camera`.
        face_uvs: optional (F,3,2) face-corner UVs to interpolate.
        normals: optional (V,3) vertex normals; default area-weighted :func:`vertex_normals`.
        caster: a :class:`RayCaster` already built for this mesh (reuse across cameras).

    Returns:
        :class:`RasterResult` of shape (camera.height, camera.width).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if face_uvs is not None:
        face_uvs = np.asarray(face_uvs, dtype=np.float64)
        if face_uvs.shape != (len(faces), 3, 2):
            raise EgorelightError(f"face UVs must be (F,3,2) = ({len(faces)},3,2), got {face_uvs.shape}")
    if caster is None:
        caster = RayCaster(vertices, faces)
    origins, dirs_world, ray_valid = camera_rays_world(camera)
    hits = caster.first_hit(origins, dirs_world)
    mask = hits.hit & ray_valid
    return _shade_hits(vertices, faces, camera, hits, mask, dirs_world, face_uvs, normals)


def _shade_hits(vertices, faces, camera, hits, mask, dirs_world, face_uvs, normals) -> RasterResult:
    """Per-pixel attributes of the visible surface from ray hits (all (H,W,...))."""
    shape = mask.shape
    face_id = np.where(mask, hits.face_id, -1).astype(np.int32)
    fid = face_id[mask]
    bary = hits.barycentrics[mask].astype(np.float64)
    distance = hits.distance[mask].astype(np.float64)

    dirs_cam_z = dirs_world[mask] @ camera.T_cam_from_world[:3, :3][2]
    points = camera.centre_world + distance[:, None] * dirs_world[mask]
    if normals is None:
        normals = vertex_normals(vertices, faces)
    smooth = _normalize(_interpolate(np.asarray(normals, dtype=np.float64)[faces[fid]], bary))
    flat = face_normals(vertices, faces)[fid]

    def image(values: np.ndarray, channels: int | None) -> np.ndarray:
        out = np.zeros(shape if channels is None else shape + (channels,), dtype=np.float32)
        out[mask] = values
        return out

    return RasterResult(
        face_id=face_id,
        barycentrics=image(bary, 3),
        depth=image(distance * dirs_cam_z, None),
        distance=image(distance, None),
        points=image(points, 3),
        normal=image(smooth, 3),
        face_normal=image(flat, 3),
        uv=None if face_uvs is None else image(_interpolate(face_uvs[fid], bary), 2),
        mask=mask,
    )


# --------------------------------------------------------------------------------------------
# UV-space rasterisation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class UVRaster:
    """Which face (and where on it) each texel of a UV map samples; row 0 is v = 1.

    Attributes:
        face_id: (H,W) int32 face sampled by each texel, -1 for empty texels.
        barycentrics: (H,W,3) float32 weights of that face's vertices (0 where empty).
        coverage: (H,W) bool, True where face_id >= 0.
        reassigned: (H,W) bool, texels the conservative pass gave to a face that their centre is
            not in (they sample a point up to a few texels away, possibly on another island).
    """

    face_id: np.ndarray
    barycentrics: np.ndarray
    coverage: np.ndarray
    reassigned: np.ndarray | None = None

    @property
    def resolution(self) -> tuple[int, int]:
        """(H, W) in texels."""
        return self.face_id.shape


def _resolution(resolution) -> tuple[int, int]:
    """(H, W) from an int (square) or an (H, W) pair; positive."""
    if np.isscalar(resolution):
        height = width = int(resolution)
    else:
        height, width = (int(r) for r in resolution)
    if height <= 0 or width <= 0:
        raise EgorelightError(f"UV resolution must be positive, got {resolution}")
    return height, width


def uv_to_texel_coords(uv: np.ndarray, resolution) -> np.ndarray:
    """UVs (...,2) -> continuous texel coordinates (...,2) ``(x, y) = (u W - 0.5, (1 - v) H - 0.5)``."""
    height, width = _resolution(resolution)
    uv = np.asarray(uv, dtype=np.float64)
    return np.stack([uv[..., 0] * width - 0.5, (1.0 - uv[..., 1]) * height - 0.5], axis=-1)


def texel_centres_uv(resolution) -> np.ndarray:
    """(H,W,2) UV coordinates of texel centres (row 0 at the top, v = 1 - (i + 0.5) / H)."""
    height, width = _resolution(resolution)
    v = 1.0 - (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    return np.stack(np.broadcast_arrays(u[None, :], v[:, None]), axis=-1)


def _edge_planes(tri: np.ndarray, area2: np.ndarray) -> np.ndarray:
    """Barycentric weights of vertices 0 and 1 as affine functions of the 2D point (x, y).

    ``w_k(x, y) = A_k x + B_k y + C_k`` (edge functions divided by the doubled signed area),
    and ``w_2 = 1 - w_0 - w_1``. tri: (F,3,2); area2: (F,) non-zero. Returns (F,2,3) ``[A, B, C]``.
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    w0 = np.stack([b[:, 1] - c[:, 1], c[:, 0] - b[:, 0], b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]], -1)
    w1 = np.stack([c[:, 1] - a[:, 1], a[:, 0] - c[:, 0], c[:, 0] * a[:, 1] - c[:, 1] * a[:, 0]], -1)
    return np.stack([w0, w1], axis=1) / area2[:, None, None]


def _groups_by_box_size(box_w: np.ndarray, box_h: np.ndarray, faces: np.ndarray, budget: int):
    """Yield (face indices, box height, box width) groups of faces with equal bounding-box size.

    Each group's candidate count n * h * w stays within ``budget`` (a lone larger face is its
    own group), so a group is tested as one dense (n, h, w) block.
    """
    keys = box_h[faces] * (int(box_w.max(initial=0)) + 1) + box_w[faces]
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    ends = np.r_[starts[1:], len(order)]
    for start, end in zip(starts, ends):
        group = faces[order[start:end]]
        h, w = int(box_h[group[0]]), int(box_w[group[0]])
        per_chunk = max(budget // (h * w), 1)
        for chunk_start in range(0, len(group), per_chunk):
            yield group[chunk_start:chunk_start + per_chunk], h, w


def _scan_faces(tri: np.ndarray, area2: np.ndarray, height: int, width: int, face_id: np.ndarray,
                barycentrics: np.ndarray) -> None:
    """Write every texel whose centre lies inside a face (bounding box + edge functions).

    tri: (F,3,2) corners in texel coordinates; faces with area2 == 0 are skipped. Faces are
    processed in groups of equal bounding-box size, each as one broadcast (n, h, w) block of
    edge-function tests. Where UV islands overlap, the face written last wins.
    """
    lo = np.maximum(np.ceil(tri.min(axis=1) - 1e-9).astype(np.int64), 0)
    hi = np.minimum(np.floor(tri.max(axis=1) + 1e-9).astype(np.int64), [width - 1, height - 1])
    box_w = np.clip(hi[:, 0] - lo[:, 0] + 1, 0, None)
    box_h = np.clip(hi[:, 1] - lo[:, 1] + 1, 0, None)
    scannable = np.flatnonzero((area2 != 0) & (box_w > 0) & (box_h > 0))
    if not scannable.size:
        return
    planes = _edge_planes(tri, np.where(area2 != 0, area2, 1.0))  # (F,2,3)
    for group, h, w in _groups_by_box_size(box_w, box_h, scannable, _UV_CHUNK_TEXELS):
        col = (lo[group, 0][:, None, None] + np.arange(w)[None, None, :]).astype(np.float64)  # (n,1,w)
        row = (lo[group, 1][:, None, None] + np.arange(h)[None, :, None]).astype(np.float64)  # (n,h,1)
        p = planes[group][:, :, :, None, None]  # (n,2,3,1,1)
        w0 = p[:, 0, 0] * col + p[:, 0, 1] * row + p[:, 0, 2]  # (n,h,w)
        w1 = p[:, 1, 0] * col + p[:, 1, 1] * row + p[:, 1, 2]
        w2 = 1.0 - w0 - w1
        inside = (w0 >= -_INSIDE_TOLERANCE) & (w1 >= -_INSIDE_TOLERANCE) & (w2 >= -_INSIDE_TOLERANCE)
        k, i, j = np.nonzero(inside)
        bary = np.clip(np.stack([w0[k, i, j], w1[k, i, j], w2[k, i, j]], axis=-1), 0.0, 1.0)
        rows, cols = lo[group[k], 1] + i, lo[group[k], 0] + j
        face_id[rows, cols] = group[k]
        barycentrics[rows, cols] = bary / bary.sum(axis=-1, keepdims=True)


def _closest_barycentrics(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentrics (N,3) of the point of each triangle (N,3,2) closest to points (N,2).

    Ericson's region test (Real-Time Collision Detection, 5.1.5), vectorised; works for either
    winding and for slivers.
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac = b - a, c - a
    ap, bp, cp = points - a, points - b, points - c
    dot = lambda x, y: np.einsum("ij,ij->i", x, y)  # noqa: E731
    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2

    def ratio(num, den):
        return np.divide(num, den, out=np.zeros_like(num), where=den != 0)

    t_ab = ratio(d1, d1 - d3)
    t_ac = ratio(d2, d2 - d6)
    t_bc = ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    total = va + vb + vc
    v_in, w_in = ratio(vb, total), ratio(vc, total)
    zeros, ones = np.zeros_like(d1), np.ones_like(d1)
    regions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
    ]
    choices = [
        np.stack([ones, zeros, zeros], -1),
        np.stack([zeros, ones, zeros], -1),
        np.stack([1 - t_ab, t_ab, zeros], -1),
        np.stack([zeros, zeros, ones], -1),
        np.stack([1 - t_ac, zeros, t_ac], -1),
        np.stack([zeros, 1 - t_bc, t_bc], -1),
    ]
    inside = np.stack([1 - v_in - w_in, v_in, w_in], -1)
    conditions = [r[:, None] for r in regions]
    return np.select(conditions, choices, default=inside)


def _assign_texel(face: int, row: int, col: int, tri: np.ndarray, face_id, barycentrics, counts) -> None:
    """Give texel (row, col) to ``face`` with the barycentrics of the face point closest to its centre."""
    owner = face_id[row, col]
    if owner >= 0:
        counts[owner] -= 1
    face_id[row, col] = face
    counts[face] += 1
    centre = np.array([[col, row]], dtype=np.float64)
    barycentrics[row, col] = _closest_barycentrics(centre, tri[face][None])[0]


def _free_texel_near(centre: np.ndarray, height: int, width: int, face_id, counts) -> tuple[int, int] | None:
    """Nearest texel to ``centre`` (texel coords) that is empty or whose face keeps another texel."""
    col0, row0 = int(np.clip(np.rint(centre[0]), 0, width - 1)), int(np.clip(np.rint(centre[1]), 0, height - 1))
    r = _CONSERVATIVE_SEARCH_RADIUS
    rows = np.arange(max(row0 - r, 0), min(row0 + r, height - 1) + 1)
    cols = np.arange(max(col0 - r, 0), min(col0 + r, width - 1) + 1)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    owners = face_id[rr, cc]
    free = (owners < 0) | (counts[np.maximum(owners, 0)] >= 2)
    if not free.any():
        return None
    dist2 = (cc - centre[0]) ** 2 + (rr - centre[1]) ** 2
    best = np.argmin(np.where(free, dist2, np.inf))
    return int(rr.flat[best]), int(cc.flat[best])


def _cover_small_faces(tri: np.ndarray, has_area: np.ndarray, face_id, barycentrics) -> None:
    """Conservative pass: every face with UV area gets at least one texel.

    Faces that no texel centre fell in (smaller than a texel, or hidden under an overlapping
    UV island) take the nearest texel that is empty or whose face keeps another texel, sampled
    at the face point closest to the texel centre. A vectorised first round takes the texel
    nearest each face's centroid; the few conflicts left are settled one face at a time.
    """
    height, width = face_id.shape
    n_faces = len(tri)
    counts = np.bincount(face_id[face_id >= 0], minlength=n_faces)
    centroids = tri.mean(axis=1)

    needy = np.flatnonzero(has_area & (counts == 0))
    if needy.size:
        cols = np.clip(np.rint(centroids[needy, 0]), 0, width - 1).astype(np.int64)
        rows = np.clip(np.rint(centroids[needy, 1]), 0, height - 1).astype(np.int64)
        owners = face_id[rows, cols]
        free = (owners < 0) | (counts[np.maximum(owners, 0)] >= 2)
        texel = rows * width + cols
        _, first = np.unique(np.where(free, texel, -1 - np.arange(len(texel))), return_index=True)
        take = first[free[first]]
        np.subtract.at(counts, owners[take][owners[take] >= 0], 1)
        face_id[rows[take], cols[take]] = needy[take]
        counts[needy[take]] += 1
        centres = np.stack([cols[take], rows[take]], axis=-1).astype(np.float64)
        barycentrics[rows[take], cols[take]] = _closest_barycentrics(centres, tri[needy[take]])

    _settle_faces_without_texels(tri, has_area, centroids, face_id, barycentrics, counts)


def _settle_faces_without_texels(tri: np.ndarray, has_area: np.ndarray, centroids: np.ndarray, face_id,
                                 barycentrics, counts) -> None:
    """One pass over the faces with UV area and no texel, each taking the nearest available texel
    (:func:`_free_texel_near`). A second pass would change nothing: an assignment never makes a
    texel available (the texel's new face holds it alone; its old face keeps one texel fewer) and
    never leaves a face without one, so a face that finds no texel within its search radius finds
    none later either. Where UV faces outnumber texels (a small resolution), most searches fail,
    and repeating them was most of a layout's build time."""
    height, width = face_id.shape
    for face in np.flatnonzero(has_area & (counts == 0)):
        spot = _free_texel_near(centroids[face], height, width, face_id, counts)
        if spot is not None:
            _assign_texel(face, spot[0], spot[1], tri, face_id, barycentrics, counts)


def rasterize_uv(face_uvs: np.ndarray, resolution, conservative: bool = True) -> UVRaster:
    """Rasterise UV triangles into a texel grid (row 0 = v = 1; texel centres sampled).

    Every texel whose centre lies in a face's UV triangle samples that face (later faces win
    where UV islands overlap). Then a conservative pass gives each face with non-zero UV area
    that received no texel (smaller than a texel, or overlapped) the nearest available texel,
    sampled at the face point closest to that texel's centre. That pass moves texels away from
    the surface point at their own UV (to a face up to a few texels away, possibly on another UV
    island): ``conservative=False`` skips it, for maps that must be a faithful function of UV
    (ground truth to compare maps of another mesh in the same layout against).

    Args:
        face_uvs: (F,3,2) face-corner UVs in [0, 1] (outside parts are clipped).
        resolution: int (square) or (H, W) in texels.
        conservative: run the conservative pass (every face with UV area gets a texel).

    Returns:
        :class:`UVRaster` of shape (H, W).
    """
    face_uvs = np.asarray(face_uvs, dtype=np.float64)
    if face_uvs.ndim != 3 or face_uvs.shape[1:] != (3, 2):
        raise EgorelightError(f"face UVs must be (F,3,2), got {face_uvs.shape}")
    if not np.isfinite(face_uvs).all():
        raise EgorelightError("face UVs contain NaN or infinity")
    height, width = _resolution(resolution)
    tri = uv_to_texel_coords(face_uvs, (height, width))
    area2 = ((tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1])
             - (tri[:, 1, 1] - tri[:, 0, 1]) * (tri[:, 2, 0] - tri[:, 0, 0]))
    face_id = np.full((height, width), -1, dtype=np.int64)
    barycentrics = np.zeros((height, width, 3), dtype=np.float64)
    _scan_faces(tri, area2, height, width, face_id, barycentrics)
    centre_faces = face_id.copy()
    if conservative:
        _cover_small_faces(tri, area2 != 0, face_id, barycentrics)
    coverage = face_id >= 0
    barycentrics[~coverage] = 0.0
    return UVRaster(face_id=face_id.astype(np.int32), barycentrics=barycentrics.astype(np.float32),
                    coverage=coverage, reassigned=face_id != centre_faces)


def texels_to_surface(uv_raster: UVRaster, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Surface point sampled by each texel.

    Args:
        uv_raster: from :func:`rasterize_uv` on this mesh's face UVs.
        vertices: (V,3) or (...,V,3) (e.g. a (T,V,3) mesh sequence), metres.
        faces: (F,3) vertex indices.

    Returns:
        (...,H,W,3) float32 points; zeros on empty texels (see ``uv_raster.coverage``).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    covered = uv_raster.coverage
    fid = uv_raster.face_id[covered]
    if fid.size and fid.max() >= len(faces):
        raise EgorelightError(f"UV raster refers to face {fid.max()} but the mesh has {len(faces)} faces")
    corners = vertices[..., faces[fid], :]  # (...,P,3,3)
    points = np.einsum("...pkc,pk->...pc", corners, uv_raster.barycentrics[covered].astype(np.float64))
    lead = vertices.shape[:-2]
    out = np.zeros(lead + uv_raster.face_id.shape + (3,), dtype=np.float32)
    out[..., covered, :] = points
    return out


def surface_to_texels(face_id: np.ndarray, barycentrics: np.ndarray, face_uvs: np.ndarray, resolution) -> np.ndarray:
    """Continuous texel coordinates of surface points given as (face, barycentrics).

    Args:
        face_id: (...) int face per point; negative entries give NaN.
        barycentrics: (...,3) weights of the face's vertices.
        face_uvs: (F,3,2) face-corner UVs.
        resolution: int or (H, W) of the UV map.

    Returns:
        (...,2) ``(x, y)`` = (column, row) texel coordinates with texel centres at integers
        (see module docstring); feed to ``cv2.remap`` to sample a UV map at the points.
    """
    face_id = np.asarray(face_id)
    face_uvs = np.asarray(face_uvs, dtype=np.float64)
    valid = face_id >= 0
    uv = _interpolate(face_uvs[np.where(valid, face_id, 0)], np.asarray(barycentrics, dtype=np.float64))
    coords = uv_to_texel_coords(uv, resolution)
    coords[~valid] = np.nan
    return coords
