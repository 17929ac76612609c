"""geometry/headset: the headset box from markers and cameras, its pixels in a camera image."""

from __future__ import annotations

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.geometry.headset import box_surface_points, headset_box, headset_mask


def _camera(width=200, height=160, focal=100.0) -> Camera:
    """A pinhole camera at the world origin looking down +z (OpenCV axes), no distortion."""
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])
    return Camera(name="cam", model="pinhole", K=K, dist=np.zeros(5), T_cam_from_world=np.eye(4), width=width,
                  height=height)


def test_the_box_bounds_the_markers_and_cameras_with_its_margin():
    corners = np.array([[[-0.05, 0.0, -0.04], [0.05, 0.02, -0.04], [0.05, -0.02, -0.04], [-0.05, 0.01, -0.04]]])
    centres = np.array([[0.0, -0.05, 0.03]])
    box = headset_box(corners, centres, margin_m=0.01)
    np.testing.assert_allclose(box, [[-0.06, -0.06, -0.05], [0.06, 0.03, 0.04]])
    with pytest.raises(EgorelightError):
        headset_box(np.full((1, 4, 3), np.nan), np.zeros((0, 3)))


def test_box_surface_points_lie_on_its_twelve_edges():
    box = np.array([[-1.0, -2.0, -3.0], [1.0, 2.0, 3.0]])
    points = box_surface_points(box, samples=5)
    assert points.shape == (12 * 5, 3)
    on_faces = np.isclose(np.abs(points), box[1]).sum(axis=1)
    assert (on_faces >= 2).all()  # on an edge: two coordinates at a face of the box
    assert len(np.unique(points.round(9), axis=0)) == 12 * 3 + 8  # 3 inner samples per edge + the corners


def test_the_mask_is_the_projected_box_and_its_nearest_depth():
    camera = _camera()
    box = np.array([[-0.2, -0.1, -0.05], [0.2, 0.1, 0.05]])
    T_world_from_hmd = np.eye(4)
    T_world_from_hmd[:3, 3] = [0.1, 0.0, 2.0]  # 2 m in front of the camera, 0.1 m to its right
    mask, nearest = headset_mask(box, T_world_from_hmd, camera)
    assert nearest == pytest.approx(1.95)
    # the front face (z = 1.95) projects widest: x in [-0.1, 0.3] m, y in [-0.1, 0.1] m
    u = 100.0 * np.array([-0.1, 0.3]) / 1.95 + 99.5
    v = 100.0 * np.array([-0.1, 0.1]) / 1.95 + 79.5
    rows, cols = np.nonzero(mask)
    assert abs(cols.min() - u[0]) <= 1 and abs(cols.max() - u[1]) <= 1
    assert abs(rows.min() - v[0]) <= 1 and abs(rows.max() - v[1]) <= 1
    # a filled rectangle: its pixel rows and columns, boundaries included
    assert mask.sum() == (np.ptp(np.round(u)) + 1) * (np.ptp(np.round(v)) + 1)
    # behind the camera: nothing
    T_world_from_hmd[:3, 3] = [0.0, 0.0, -2.0]
    behind, nearest = headset_mask(box, T_world_from_hmd, camera)
    assert not behind.any() and nearest == np.inf
    # across the camera's plane (the front face 2 cm behind it): the depth of what projects, never negative
    T_world_from_hmd[:3, 3] = [0.0, 0.0, 0.03]
    _, nearest = headset_mask(box, T_world_from_hmd, camera)
    assert 0.0 < nearest <= 0.08
