"""Camera and UV-space rasterisation against analytic geometry."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, pixel_grid, unproject_to_rays
from egorelight_cli.render.raster import (
    rasterize,
    rasterize_uv,
    surface_to_texels,
    texel_centres_uv,
    texels_to_surface,
    uv_to_texel_coords,
)

RADIUS = 0.5
DISTANCE = 2.0


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)


def _camera_looking_at_origin(model: str, size: int, focal: float, dist=()) -> Camera:
    """Camera at z = -DISTANCE looking along +z (world axes = camera axes)."""
    T = np.eye(4)
    T[2, 3] = DISTANCE
    K = [[focal, 0.0, (size - 1) / 2], [0.0, focal, (size - 1) / 2], [0.0, 0.0, 1.0]]
    return Camera(model, K, list(dist), size, size, T, model)


def _sphere_entry(dirs: np.ndarray, centre_cam: np.ndarray, radius: float) -> np.ndarray:
    """Analytic distance from the camera centre to a sphere along unit rays (inf on misses)."""
    along = dirs @ centre_cam
    miss2 = centre_cam @ centre_cam - along**2
    return np.where(miss2 < radius**2, along - np.sqrt(np.clip(radius**2 - miss2, 0, None)), np.inf)


@pytest.mark.parametrize("model,focal,dist", [("pinhole", 300.0, (-0.05, 0.01, 0.0, 0.0, 0.0)),
                                              ("fisheye", 120.0, (0.01, -0.002, 0.0, 0.0))])
def test_sphere_depth_and_mask_match_analytic(sphere, model, focal, dist):
    camera = _camera_looking_at_origin(model, 160, focal, dist)
    result = rasterize(sphere.vertices, sphere.faces, camera)
    dirs = unproject_to_rays(pixel_grid(160, 160), camera.K, camera.dist, model)
    t_true = _sphere_entry(dirs.reshape(-1, 3), np.array([0.0, 0.0, DISTANCE]), RADIUS).reshape(160, 160)

    hit_true = np.isfinite(t_true)
    # Mask: identical away from the silhouette; area within the tessellation's shrinkage.
    impact = np.sqrt(np.clip(DISTANCE**2 - (dirs[..., 2] * DISTANCE) ** 2, 0, None))
    assert result.mask[impact < RADIUS * 0.98].all()
    assert not result.mask[impact > RADIUS * 1.0001].any()
    assert 0.97 < result.mask.sum() / hit_true.sum() <= 1.0

    gap = RADIUS - np.linalg.norm(sphere.triangles_center, axis=1).min()
    cos_incidence = np.abs(dirs[..., 2] * DISTANCE - t_true) / RADIUS  # |(p - c) . d| / r
    steep = result.mask & hit_true & (cos_incidence > 0.3)
    err = result.distance[steep] - t_true[steep]
    assert (err > -1e-5).all() and (err < gap / cos_incidence[steep] + 1e-5).all()
    assert np.allclose(result.depth[steep], result.distance[steep] * dirs[steep][:, 2], atol=1e-5)

    # Normals point back at the camera and match the sphere normal; background is empty.
    n_true = (result.points[steep] / np.linalg.norm(result.points[steep], axis=1, keepdims=True))
    assert (np.einsum("nc,nc->n", result.normal[steep], n_true) > 0.999).all()
    assert (np.einsum("nc,nc->n", result.face_normal[steep], n_true) > 0.99).all()
    assert (result.face_id[~result.mask] == -1).all() and (result.depth[~result.mask] == 0).all()
    assert result.uv is None


def test_pinhole_mask_area_matches_projected_disc(sphere):
    camera = _camera_looking_at_origin("pinhole", 200, 250.0)
    result = rasterize(sphere.vertices, sphere.faces, camera)
    disc_radius_px = 250.0 * np.tan(np.arcsin(RADIUS / DISTANCE))
    assert 0.97 < result.mask.sum() / (np.pi * disc_radius_px**2) < 1.01


def test_plane_depth_exact_and_uv_interpolation():
    # A 4 m square at z = 1.5 in front of a pinhole camera; UV = (x, y) rescaled to [0, 1].
    vertices = np.array([[-2.0, -2.0, 1.5], [2.0, -2.0, 1.5], [2.0, 2.0, 1.5], [-2.0, 2.0, 1.5]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    face_uvs = (vertices[faces][..., :2] + 2.0) / 4.0
    camera = Camera("pinhole", [[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]], [], 128, 96, np.eye(4), "p")
    result = rasterize(vertices, faces, camera, face_uvs=face_uvs)
    assert result.mask.all()
    assert np.allclose(result.depth, 1.5, atol=1e-5)
    expected_uv = (result.points[..., :2] + 2.0) / 4.0
    assert np.allclose(result.uv, expected_uv, atol=1e-5)
    # Points are where the pixel rays meet the plane.
    u, v = np.meshgrid(np.arange(128), np.arange(96))
    assert np.allclose(result.points[..., 0], (u - 63.5) / 100.0 * 1.5, atol=1e-5)
    assert np.allclose(result.points[..., 1], (v - 47.5) / 100.0 * 1.5, atol=1e-5)


def test_wide_fisheye_sees_behind_the_image_plane():
    # 200 degree fisheye: a sphere 100 degrees off-axis is visible, at negative camera z.
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    direction = np.array([np.sin(np.deg2rad(100.0)), 0.0, np.cos(np.deg2rad(100.0))])
    sphere.apply_translation(2.0 * direction)
    size, focal = 240, 240 / 2 / np.deg2rad(110.0)
    camera = Camera("fisheye", [[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]], [],
                    size, size, np.eye(4), "wide")
    result = rasterize(sphere.vertices, sphere.faces, camera)
    assert result.mask.sum() > 50
    assert (result.depth[result.mask] < 0).all()
    dirs = unproject_to_rays(pixel_grid(size, size)[result.mask], camera.K, camera.dist, "fisheye")
    t_true = _sphere_entry(dirs, 2.0 * direction, 0.3)
    gap = 0.3 - np.linalg.norm(sphere.triangles_center - 2.0 * direction, axis=1).min()
    central = np.isfinite(t_true) & (np.abs(dirs @ direction) > np.cos(np.arcsin(0.3 / 2.0) * 0.7))
    assert central.sum() > 10
    assert np.all(np.abs(result.distance[result.mask][central] - t_true[central]) < 3 * gap)


def _mesh_with_tiny_uv_faces(seed: int = 0):
    """Plane grid whose UV layout squeezes some faces far below one texel.

    Returns vertices (V,3), faces (F,3), face UVs (F,3,2).
    """
    rng = np.random.default_rng(seed)
    grid = trimesh.creation.box().subdivide().subdivide()  # 3D mesh, just for topology
    vertices = np.asarray(grid.vertices)
    faces = np.asarray(grid.faces)
    # Big faces: a regular grid of triangles tiled over the unit square.
    n = len(faces)
    cells = int(np.ceil(np.sqrt(n / 2)))
    k = np.arange(n)
    cell, upper = k // 2, k % 2
    cx, cy = (cell % cells) / cells, (cell // cells) / cells
    s = 1.0 / cells
    lower_tri = np.array([[0, 0], [1, 0], [1, 1]])
    upper_tri = np.array([[0, 0], [1, 1], [0, 1]])
    face_uvs = np.where(upper[:, None, None] == 1, upper_tri, lower_tri) * s + np.stack([cx, cy], -1)[:, None, :]
    # Tiny faces: 120 faces shrunk to ~1e-3 texel, many crowded into the same texel.
    tiny = rng.choice(n, size=120, replace=False)
    anchors = rng.uniform(0.2, 0.8, size=(120, 1, 2))
    anchors[:40] = anchors[0]  # 40 tiny faces inside one texel
    face_uvs[tiny] = anchors + rng.uniform(-1, 1, size=(120, 3, 2)) * 2e-6
    return vertices, faces, face_uvs, tiny


def test_uv_raster_covers_every_face_with_area():
    vertices, faces, face_uvs, tiny = _mesh_with_tiny_uv_faces()
    resolution = (64, 80)
    raster = rasterize_uv(face_uvs, resolution)
    assert raster.face_id.shape == (64, 80) and raster.barycentrics.shape == (64, 80, 3)
    assert np.array_equal(raster.coverage, raster.face_id >= 0)
    counts = np.bincount(raster.face_id[raster.coverage], minlength=len(faces))
    assert (counts >= 1).all(), f"{(counts == 0).sum()} faces got no texel"
    assert (counts[tiny] >= 1).all()
    bary = raster.barycentrics[raster.coverage]
    assert (bary >= -1e-6).all() and np.allclose(bary.sum(-1), 1.0, atol=1e-5)

    # Regular texels sample their own centre; conservative ones a point of the face near it.
    coords = surface_to_texels(raster.face_id, raster.barycentrics, face_uvs, resolution)
    rows, cols = np.nonzero(raster.coverage)
    offset = np.abs(coords[rows, cols] - np.stack([cols, rows], -1)).max(axis=1)
    is_tiny = np.isin(raster.face_id[rows, cols], tiny)
    assert offset[~is_tiny].max() < 1e-4
    assert offset[is_tiny].max() < 10.0
    assert np.isnan(surface_to_texels(np.array([-1]), np.zeros((1, 3)), face_uvs, resolution)).all()


def test_uv_raster_marks_reassigned_texels_and_can_stay_faithful_to_uv():
    vertices, faces, face_uvs, tiny = _mesh_with_tiny_uv_faces()
    resolution = (64, 80)
    conservative = rasterize_uv(face_uvs, resolution)
    faithful = rasterize_uv(face_uvs, resolution, conservative=False)
    assert not faithful.reassigned.any()
    assert not np.isin(faithful.face_id, tiny).any()  # no texel centre lies in a tiny face
    # every faithful texel samples its own centre
    coords = surface_to_texels(faithful.face_id, faithful.barycentrics, face_uvs, resolution)
    rows, cols = np.nonzero(faithful.coverage)
    assert np.abs(coords[rows, cols] - np.stack([cols, rows], -1)).max() < 1e-4
    # the conservative pass changes exactly the texels it marks, and only to give tiny faces one
    moved = conservative.face_id != faithful.face_id
    np.testing.assert_array_equal(moved, conservative.reassigned)
    assert moved.any() and np.isin(conservative.face_id[moved], tiny).all()


def test_settling_faces_without_texels_reaches_its_fixed_point_in_one_pass():
    """Where faces outnumber texels most faces find none: after the one pass, a second changes
    nothing, and no face left without a texel has an available one within its search radius."""
    from egorelight_cli.render.raster import _free_texel_near, _settle_faces_without_texels, uv_to_texel_coords

    _, faces, face_uvs, _ = _mesh_with_tiny_uv_faces()
    resolution = (12, 14)
    raster = rasterize_uv(face_uvs, resolution)
    tri = uv_to_texel_coords(face_uvs, resolution)
    edge1, edge2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    has_area = edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0] != 0
    counts = np.bincount(raster.face_id[raster.coverage], minlength=len(faces))
    left = np.flatnonzero(has_area & (counts == 0))
    assert len(faces) > 12 * 14 and left.size > 0 and (counts[has_area] > 0).any()
    face_id, barycentrics = raster.face_id.copy(), raster.barycentrics.copy()
    _settle_faces_without_texels(tri, has_area, tri.mean(axis=1), face_id, barycentrics, counts.copy())
    np.testing.assert_array_equal(face_id, raster.face_id)
    np.testing.assert_array_equal(barycentrics, raster.barycentrics)
    for face in left:
        assert _free_texel_near(tri[face].mean(axis=0), *resolution, raster.face_id, counts) is None


def test_uv_raster_convention_row_zero_is_v_one():
    face_uvs = np.array([[[0.0, 1.0], [0.5, 1.0], [0.0, 0.5]]])  # top-left corner triangle
    raster = rasterize_uv(face_uvs, 8)
    rows, cols = np.nonzero(raster.coverage)
    assert rows.max() < 4 and cols.max() < 4 and raster.coverage[0, 0]
    # Coverage equals the texel centres inside the triangle: u + (1 - v) <= 0.5.
    centres = texel_centres_uv(8)
    inside = centres[..., 0] + (1.0 - centres[..., 1]) <= 0.5 + 1e-12
    assert np.array_equal(raster.coverage, inside)
    assert np.allclose(uv_to_texel_coords(centres, 8)[3, 5], [5.0, 3.0])


def test_uv_raster_area_of_a_large_triangle():
    face_uvs = np.array([[[0.1, 0.1], [0.9, 0.2], [0.3, 0.95]]])
    raster = rasterize_uv(face_uvs, 512)
    (ax, ay), (bx, by) = face_uvs[0, 1] - face_uvs[0, 0], face_uvs[0, 2] - face_uvs[0, 0]
    area_uv = 0.5 * abs(ax * by - ay * bx)
    assert abs(raster.coverage.sum() / (area_uv * 512**2) - 1.0) < 0.01


def test_texels_to_surface_lands_on_the_mesh():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS)
    corners = sphere.vertices[sphere.faces]
    # Equirectangular UVs per face corner (seam faces become large; overlap is fine).
    u = 0.5 + np.arctan2(corners[..., 0], corners[..., 2]) / (2 * np.pi)
    v = 0.5 + np.arcsin(np.clip(corners[..., 1] / RADIUS, -1, 1)) / np.pi
    face_uvs = np.stack([u, v], -1)
    raster = rasterize_uv(face_uvs, 128)
    counts = np.bincount(raster.face_id[raster.coverage], minlength=len(sphere.faces))
    assert (counts >= 1).all()
    points = texels_to_surface(raster, sphere.vertices, sphere.faces)
    assert points.shape == (128, 128, 3) and (points[~raster.coverage] == 0).all()

    # Each texel point lies inside its face's triangle (on its plane, within its edges).
    p = points[raster.coverage].astype(np.float64)
    fid = raster.face_id[raster.coverage]
    normals = sphere.face_normals[fid]
    plane_dist = np.einsum("nc,nc->n", p - sphere.vertices[sphere.faces[fid, 0]], normals)
    assert np.abs(plane_dist).max() < 1e-6
    radius = np.linalg.norm(p, axis=1)
    gap = RADIUS - np.linalg.norm(sphere.triangles_center, axis=1).min()
    assert radius.min() > RADIUS - gap - 1e-6 and radius.max() < RADIUS + 1e-6

    # A mesh sequence (T,V,3) gives (T,H,W,3).
    sequence = np.stack([sphere.vertices, sphere.vertices * 2.0])
    both = texels_to_surface(raster, sequence, sphere.faces)
    assert both.shape == (2, 128, 128, 3) and np.allclose(both[1], 2.0 * points, atol=1e-6)


def test_uv_raster_rejects_bad_input():
    with pytest.raises(EgorelightError):
        rasterize_uv(np.zeros((4, 3)), 16)
    with pytest.raises(EgorelightError):
        rasterize_uv(np.full((1, 3, 2), np.nan), 16)
    with pytest.raises(EgorelightError):
        rasterize_uv(np.zeros((1, 3, 2)), 0)
