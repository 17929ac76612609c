"""Depth rendering, unprojection, fusion, Hoppe normals and point-to-surface distance
(geometry of the egodepth stage) on analytic scenes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, look_at
from egorelight_cli.geometry.depth import (
    camera_ray_map,
    depth_edges,
    depth_to_range,
    range_to_depth,
    render_depth,
    unproject_depth,
)
from egorelight_cli.geometry.pointcloud_ops import (
    SurfaceDistance,
    fixed_size_cloud,
    fuse_views,
    hoppe_normals,
    orient_towards,
)
from egorelight_cli.geometry.raycast import RayCaster


def fisheye(T_cam_from_world, size=64, name="fish") -> Camera:
    """A ~200 degree equidistant-ish fisheye (f = size / 3.5 px)."""
    f = size / 3.5
    K = [[f, 0, (size - 1) / 2 + 0.3], [0, f, (size - 1) / 2 - 0.2], [0, 0, 1]]
    return Camera("fisheye", K, [0.02, -0.004, 0.0007, 0.0], size, size, T_cam_from_world, name)


def plane_mesh(y: float, half: float = 3.0):
    """A horizontal square at height y (two triangles), normal +y."""
    v = np.array([[-half, y, -half], [half, y, -half], [half, y, half], [-half, y, half]], float)
    return v, np.array([[0, 2, 1], [0, 3, 2]])


def test_unprojection_of_a_rendered_plane_returns_the_plane():
    v, f = plane_mesh(-0.5)
    camera = fisheye(look_at([0.1, 0.0, 0.05], [0.3, -1.0, 0.2]))  # looking down, tilted
    rendered = render_depth(camera, RayCaster(v, f))
    assert rendered.hit.mean() > 0.3
    assert (rendered.z[rendered.hit] < 0).any(), "a >180 degree lens sees the plane past 90 degrees"
    points, valid = unproject_depth(camera, rendered.z)
    assert np.array_equal(valid, rendered.hit)
    np.testing.assert_allclose(points[valid][:, 1], -0.5, atol=2e-5)
    # range <-> z round trip through the ray map
    rays, _ = camera_ray_map(camera)
    np.testing.assert_allclose(depth_to_range(rendered.z, rays), rendered.range, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(range_to_depth(rendered.range, rays), rendered.z, rtol=1e-5, atol=1e-6)


def test_unproject_in_camera_frame_matches_axial_depth():
    camera = fisheye(np.eye(4), size=32)
    depth = np.full((32, 32), 2.0, np.float32)
    points, valid = unproject_depth(camera, depth, T_world_from_cam=np.eye(4))
    np.testing.assert_allclose(points[valid][:, 2], 2.0, rtol=1e-6)


def test_unproject_rejects_bad_depth():
    camera = fisheye(np.eye(4), size=16)
    with pytest.raises(EgorelightError, match="shape"):
        unproject_depth(camera, np.ones((8, 8)))
    bad = np.ones((16, 16))
    bad[3, 3] = np.nan
    with pytest.raises(EgorelightError, match="NaN"):
        unproject_depth(camera, bad)


def test_sphere_normals_point_outward_within_a_few_degrees():
    rng = np.random.default_rng(0)
    centre = np.array([0.2, 1.0, -0.3])
    directions = rng.normal(size=(4000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = centre + 0.15 * directions
    viewpoints = centre + 2.0 * directions  # each point seen from outside
    normals = orient_towards(hoppe_normals(points, 16), points, viewpoints)
    angle = np.degrees(np.arccos(np.clip(np.sum(normals * directions, axis=1), -1, 1)))
    assert np.percentile(angle, 99) < 4.0
    assert angle.max() < 8.0
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)


def test_two_fisheye_views_fuse_into_one_consistent_frame():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.25)
    sphere.apply_translation([0.0, -0.6, 0.1])
    caster = RayCaster(sphere.vertices, sphere.faces)
    left = fisheye(look_at([-0.06, 0.0, 0.0], [-0.02, -1.0, 0.15]), name="left")
    right = fisheye(look_at([0.06, 0.0, 0.0], [0.02, -1.0, 0.15]), name="right")
    maps, masks, centres = [], [], []
    for camera in (left, right):
        rendered = render_depth(camera, caster)
        # unproject through the camera frame + explicit pose, as the stage does with H inv(Pi)
        points, valid = unproject_depth(camera, rendered.z, T_world_from_cam=camera.T_world_from_cam)
        maps.append(points)
        masks.append(valid)
        centres.append(camera.centre_world)
    points, seen_from = fuse_views(maps, masks, centres)
    assert len(points) == sum(int(m.sum()) for m in masks) > 200
    distance = SurfaceDistance(sphere.vertices, sphere.faces)(points)
    assert distance.max() < 1e-4
    # both views contribute to the same region: each left point has a right neighbour within 2 cm
    from scipy.spatial import cKDTree

    n_left = int(masks[0].sum())
    gap, _ = cKDTree(points[n_left:]).query(points[:n_left])
    assert np.median(gap) < 0.02
    cloud, normals, valid = fixed_size_cloud(points, seen_from, 200, 12, np.random.default_rng(0))
    assert valid.all() and cloud.shape == (200, 3)
    outward = (cloud - [0.0, -0.6, 0.1]) / 0.25
    assert np.median(np.sum(normals * outward, axis=1)) > 0.99


def test_fixed_size_cloud_pads_with_invalid_points():
    points = np.random.default_rng(1).normal(size=(10, 3))
    cloud, normals, valid = fixed_size_cloud(points, np.zeros((10, 3)), 32, 8, np.random.default_rng(0))
    assert valid.sum() == 10 and not valid[10:].any()
    assert not cloud[10:].any() and not normals[10:].any()


def test_surface_distance_is_exact_on_a_plane():
    v, f = plane_mesh(0.0, half=1.0)
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.8, 0.8, 200), rng.uniform(-0.2, 0.2, 200), rng.uniform(-0.8, 0.8, 200)])
    np.testing.assert_allclose(SurfaceDistance(v, f)(points), np.abs(points[:, 1]), atol=1e-9)


def test_surface_distance_closest_face_matches_brute_force():
    from trimesh.triangles import closest_point

    rng = np.random.default_rng(2)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    v = sphere.vertices + rng.normal(scale=0.01, size=sphere.vertices.shape)
    f = np.asarray(sphere.faces)
    surface = v[f[rng.integers(len(f), size=300)]].mean(axis=1)
    points = surface * rng.uniform(0.8, 1.2, size=(300, 1))  # within ~6 cm of the surface
    point, face, distance = SurfaceDistance(v, f).closest(points)
    # every point against every face
    triangles = np.repeat(v[f][None], len(points), axis=0).reshape(-1, 3, 3)
    every = closest_point(triangles, np.repeat(points, len(f), axis=0))
    brute = np.linalg.norm(every - np.repeat(points, len(f), axis=0), axis=1).reshape(len(points), len(f))
    np.testing.assert_allclose(distance, brute.min(axis=1), atol=1e-9)
    np.testing.assert_allclose(brute[np.arange(len(points)), face], brute.min(axis=1), atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(point - points, axis=1), distance, atol=1e-9)


def test_depth_edges_mark_silhouettes_and_jumps():
    r = np.full((8, 8), 1.0)
    r[:, 4:] = 2.0
    valid = np.ones((8, 8), bool)
    edges = depth_edges(r, valid, 0.1)
    assert edges[3, 3] and edges[3, 4] and not edges[3, 1] and edges[0, 1]  # jump and image border


def test_fisheye_rectification_puts_matches_on_one_row():
    """Rectified left/right rays of one 3D point share a row, and their column difference is
    the disparity f B / z of its rectified depth (any pitch about the baseline)."""
    from egorelight_cli.geometry.cameras import project
    from egorelight_cli.geometry.fisheye_stereo import rectify_pair

    left = fisheye(look_at([-0.06, 0.0, 0.0], [-0.03, -1.0, 0.3]), size=96, name="left")
    right = fisheye(look_at([0.06, 0.0, 0.01], [0.04, -1.0, 0.35]), size=96, name="right")
    T_right_from_left = right.T_cam_from_world @ left.T_world_from_cam
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.3, 0.3, 50), rng.uniform(-1.2, -0.3, 50), rng.uniform(-0.1, 0.5, 50)])
    for pitch in (0.0, 45.0):
        pair = rectify_pair(left, right, T_right_from_left, 128, 128, 130.0, pitch)
        assert pair.baseline_m == pytest.approx(np.linalg.norm(left.centre_world - right.centre_world))
        uv = {}
        for key, camera in (("left", left), ("right", right)):
            p_cam = (camera.T_cam_from_world[:3, :3] @ points.T).T + camera.T_cam_from_world[:3, 3]
            p_rect = p_cam @ pair.R_rect_from_cam[key].T
            uv[key] = project(p_rect, pair.K, np.zeros(5), "pinhole")
            if key == "left":
                z_rect = p_rect[:, 2]
        np.testing.assert_allclose(uv["left"][:, 1], uv["right"][:, 1], atol=1e-6)
        np.testing.assert_allclose(uv["left"][:, 0] - uv["right"][:, 0], pair.K[0, 0] * pair.baseline_m / z_rect,
                                   rtol=1e-6)
        # the remap of a rectified pixel lands where the fisheye camera sees that ray
        row, col = 70, 40
        ray = np.linalg.solve(pair.K, [col, row, 1.0])
        expected = project(ray @ pair.R_rect_from_cam["left"], left.K, left.dist, "fisheye")
        np.testing.assert_allclose(pair.maps["left"][row, col], expected, atol=1e-3)
