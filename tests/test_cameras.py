"""Camera models agree with OpenCV, invert exactly, and differentiate correctly."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import (
    Camera,
    camera_rays_world,
    fisheye_max_theta,
    pixel_grid,
    project,
    project_world,
    transform_points,
    unproject_to_rays,
    world_to_camera,
)

K_PINHOLE = np.array([[812.0, 0.0, 640.3], [0.0, 805.5, 359.7], [0.0, 0.0, 1.0]])
DIST_PINHOLE = np.array([-0.28, 0.09, 0.0012, -0.0008, -0.012])
K_FISHEYE = np.array([[285.0, 0.0, 639.2], [0.0, 284.1, 640.8], [0.0, 0.0, 1.0]])
DIST_FISHEYE = np.array([0.021, -0.004, 0.0011, -0.0002])


def _points_in_front(n: int, seed: int = 0) -> np.ndarray:
    """Random camera-frame points inside a ~100 degree cone, 0.3-5 m away."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.8, 0.8, size=(n, 2))
    z = rng.uniform(0.3, 5.0, size=(n, 1))
    return np.concatenate([xy * z, z], axis=1)


def _unit_directions(n: int, max_theta_deg: float, seed: int = 0) -> np.ndarray:
    """Random unit directions up to ``max_theta_deg`` off the +z axis."""
    rng = np.random.default_rng(seed)
    theta = np.deg2rad(max_theta_deg) * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def _cv2_pinhole(points: np.ndarray) -> np.ndarray:
    return cv2.projectPoints(points, np.zeros(3), np.zeros(3), K_PINHOLE, DIST_PINHOLE)[0][:, 0]


def _cv2_fisheye(points: np.ndarray) -> np.ndarray:
    return cv2.fisheye.projectPoints(points[:, None], np.zeros(3), np.zeros(3), K_FISHEYE, DIST_FISHEYE)[0][:, 0]


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_project_matches_opencv_numpy_and_torch(model):
    points = _points_in_front(2000)
    K, dist, reference = (
        (K_PINHOLE, DIST_PINHOLE, _cv2_pinhole(points)) if model == "pinhole"
        else (K_FISHEYE, DIST_FISHEYE, _cv2_fisheye(points))
    )
    pixels, valid = project(points, K, dist, model, return_valid=True)
    assert isinstance(pixels, np.ndarray) and pixels.shape == (2000, 2)
    assert valid.all()
    assert np.abs(pixels - reference).max() < 1e-4

    for dtype, tol in [(torch.float64, 1e-4), (torch.float32, 2e-3)]:
        pixels_t = project(torch.tensor(points, dtype=dtype), torch.tensor(K), torch.tensor(dist), model)
        assert isinstance(pixels_t, torch.Tensor) and pixels_t.dtype == dtype
        assert (pixels_t.double().numpy() - reference).__abs__().max() < tol


@pytest.mark.parametrize("model,max_theta", [("pinhole", 50.0), ("fisheye", 100.0)])
def test_unproject_inverts_project(model, max_theta):
    K, dist = (K_PINHOLE, DIST_PINHOLE) if model == "pinhole" else (K_FISHEYE, DIST_FISHEYE)
    if model == "fisheye":
        assert fisheye_max_theta(dist) > np.deg2rad(100.0)
    directions = _unit_directions(5000, max_theta)
    pixels = project(directions * 2.5, K, dist, model)
    rays, valid = unproject_to_rays(pixels, K, dist, model, return_valid=True)
    assert valid.all()
    assert np.abs(np.linalg.norm(rays, axis=-1) - 1).max() < 1e-12
    assert np.abs(rays - directions).max() < 1e-6
    if model == "fisheye":  # really beyond a hemisphere
        assert (rays[:, 2] < -0.1).any()

    rays_t = unproject_to_rays(torch.tensor(pixels, dtype=torch.float32), torch.tensor(K), torch.tensor(dist), model)
    assert rays_t.dtype == torch.float32
    assert (rays_t.double().numpy() - directions).__abs__().max() < 1e-4


def test_unproject_agrees_with_opencv_undistort():
    pixels = project(_points_in_front(500, seed=3), K_PINHOLE, DIST_PINHOLE, "pinhole")
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    normalised = cv2.undistortPointsIter(pixels[:, None], K_PINHOLE, DIST_PINHOLE, None, None, criteria)[:, 0]
    rays = unproject_to_rays(pixels, K_PINHOLE, DIST_PINHOLE, "pinhole")
    assert np.abs(rays[:, :2] / rays[:, 2:] - normalised).max() < 1e-6


def test_batched_leading_dims_and_batched_intrinsics():
    points = _points_in_front(24).reshape(2, 3, 4, 3)
    flat = project(points.reshape(-1, 3), K_PINHOLE, DIST_PINHOLE, "pinhole")
    assert np.allclose(project(points, K_PINHOLE, DIST_PINHOLE, "pinhole").reshape(-1, 2), flat)

    K_batch = np.stack([K_PINHOLE, K_PINHOLE * [[2.0], [2.0], [1.0]]])
    pts = points.reshape(2, 12, 3)
    out = project(pts, K_batch, np.stack([DIST_PINHOLE, DIST_PINHOLE]), "pinhole")
    assert np.allclose(out[0], flat[:12])
    assert np.allclose(out[1], project(pts[1], K_batch[1], DIST_PINHOLE, "pinhole"))
    assert np.allclose(project(pts, K_batch, DIST_PINHOLE, "pinhole"), out)  # one dist for all
    rays = unproject_to_rays(out, K_batch, DIST_PINHOLE, "pinhole")
    assert np.allclose(rays, pts / np.linalg.norm(pts, axis=-1, keepdims=True), atol=1e-9)


def test_pinhole_masks_points_behind_camera():
    points = np.array([[0.1, 0.2, 2.0], [0.1, 0.2, -2.0], [0.0, 0.0, 0.0], [0.3, -0.1, -1e-3]])
    pixels, valid = project(points, K_PINHOLE, DIST_PINHOLE, "pinhole", return_valid=True)
    assert valid.tolist() == [True, False, False, False]
    assert np.isfinite(pixels[0]).all() and np.isnan(pixels[1:]).all()

    pixels_t, valid_t = project(torch.tensor(points), torch.tensor(K_PINHOLE), torch.tensor(DIST_PINHOLE),
                                "pinhole", return_valid=True)
    assert valid_t.tolist() == [True, False, False, False]


def test_fisheye_sees_behind_the_image_plane_but_not_past_its_limit():
    theta_max = float(fisheye_max_theta(DIST_FISHEYE))
    beyond = np.deg2rad(179.0) if theta_max < np.deg2rad(179.0) else None
    dirs = np.array([[np.sin(t), 0.0, np.cos(t)] for t in (0.0, np.deg2rad(95.0), np.deg2rad(100.0))])
    _, valid = project(dirs, K_FISHEYE, DIST_FISHEYE, "fisheye", return_valid=True)
    assert valid.all()
    if beyond is not None:
        _, valid = project(np.array([[np.sin(beyond), 0.0, np.cos(beyond)]]), K_FISHEYE, DIST_FISHEYE,
                           "fisheye", return_valid=True)
        assert not valid.any()


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_project_gradients(model):
    K, dist = (K_PINHOLE, DIST_PINHOLE) if model == "pinhole" else (K_FISHEYE, DIST_FISHEYE)
    points = torch.tensor(_points_in_front(6, seed=1), requires_grad=True)
    K_t = torch.tensor(K, requires_grad=True)
    dist_t = torch.tensor(dist, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p, k, d: project(p, k, d, model), (points, K_t, dist_t))


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_unproject_gradients(model):
    K, dist = (K_PINHOLE, DIST_PINHOLE) if model == "pinhole" else (K_FISHEYE, DIST_FISHEYE)
    max_theta = 40.0 if model == "pinhole" else 95.0
    pixels = torch.tensor(project(_unit_directions(6, max_theta, seed=2), K, dist, model), requires_grad=True)
    K_t = torch.tensor(K, requires_grad=True)
    dist_t = torch.tensor(dist, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, k, d: unproject_to_rays(x, k, d, model), (pixels, K_t, dist_t))


def test_gradient_on_the_optical_axis_is_finite():
    for model, K, dist in [("pinhole", K_PINHOLE, DIST_PINHOLE), ("fisheye", K_FISHEYE, DIST_FISHEYE)]:
        points = torch.tensor([[0.0, 0.0, 2.0]], requires_grad=True)
        K32, dist32 = torch.tensor(K, dtype=torch.float32), torch.tensor(dist, dtype=torch.float32)
        project(points, K32, dist32, model).sum().backward()
        assert torch.isfinite(points.grad).all()
        pixels = torch.tensor([[K[0, 2], K[1, 2]]], requires_grad=True)
        unproject_to_rays(pixels, torch.tensor(K), torch.tensor(dist), model).sum().backward()
        assert torch.isfinite(pixels.grad).all()


def test_camera_dict_round_trip_and_world_rays():
    rotation = cv2.Rodrigues(np.array([0.1, -0.4, 0.2]))[0]
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = [0.2, -0.1, 3.0]
    camera = Camera("fisheye", K_FISHEYE, DIST_FISHEYE, 1280, 1280, T, "down_left")
    entry = json.loads(json.dumps(camera.to_dict()))
    assert set(entry) == {"name", "model", "K", "dist", "T_cam_from_world", "width", "height"}
    again = Camera.from_dict(entry)
    assert again.name == "down_left" and again.model == "fisheye" and (again.width, again.height) == (1280, 1280)
    assert np.array_equal(again.K, camera.K) and np.array_equal(again.T_cam_from_world, T)

    # A world point projects to a pixel whose world ray passes through it.
    point_world = transform_points(camera.T_world_from_cam, np.array([0.3, -0.2, 1.7]))
    pixel = project_world(camera, point_world)
    origins, dirs, valid = camera_rays_world(camera, pixel[None])
    assert valid.all()
    to_point = point_world - origins[0]
    assert np.allclose(dirs[0], to_point / np.linalg.norm(to_point), atol=1e-9)
    assert np.allclose(world_to_camera(camera, point_world), [0.3, -0.2, 1.7])

    # hmd.json ego cameras carry no pose: it is supplied by the caller.
    ego_entry = {k: v for k, v in entry.items() if k != "T_cam_from_world"} | {"role": "down_left"}
    with pytest.raises(EgorelightError):
        Camera.from_dict(ego_entry)
    assert np.array_equal(Camera.from_dict(ego_entry, T_cam_from_world=np.eye(4)).T_cam_from_world, np.eye(4))
    # The camera keeps private read-only copies.
    K = K_PINHOLE.copy()
    pinhole = Camera("pinhole", K, DIST_PINHOLE, 1280, 720, np.eye(4))
    K[0, 0] = 1.0
    assert pinhole.K[0, 0] == K_PINHOLE[0, 0] and not pinhole.K.flags.writeable


def test_pixel_grid_uses_opencv_pixel_centres():
    grid = pixel_grid(4, 3)
    assert grid.shape == (3, 4, 2)
    assert grid[0, 0].tolist() == [0.0, 0.0] and grid[2, 3].tolist() == [3.0, 2.0]


def test_bad_inputs_raise_egorelight_error():
    with pytest.raises(EgorelightError):
        Camera("orthographic", K_PINHOLE, [], 10, 10, np.eye(4))
    with pytest.raises(EgorelightError):
        Camera.from_dict({"name": "x", "model": "pinhole", "K": np.eye(2).tolist()})
    with pytest.raises(EgorelightError):
        project(np.zeros((3, 2)), K_PINHOLE, DIST_PINHOLE, "pinhole")
    with pytest.raises(EgorelightError):
        project(np.ones((3, 3)), K_FISHEYE, np.zeros(6), "fisheye")


def test_a_virtual_camera_json_that_cannot_render_is_an_error_naming_it(tmp_path):
    from egorelight_cli.geometry.cameras import Camera, look_at
    from egorelight_cli.io.camera_json import read_camera_json

    good = Camera("pinhole", [[200, 0, 80], [0, 200, 60], [0, 0, 1]], [], 160, 120,
                  np.linalg.inv(look_at([0, 1.5, 3], [0, 1, 0])), "orbit").to_dict()
    (tmp_path / "good.json").write_text(json.dumps(good))
    assert read_camera_json(tmp_path / "good.json").width == 160
    scaled = np.asarray(good["T_cam_from_world"]) @ np.diag([2.0, 2.0, 2.0, 1.0])
    for name, change, says in (("zero_t", {"T_cam_from_world": np.zeros((4, 4)).tolist()}, "not a rigid"),
                               ("scaled", {"T_cam_from_world": scaled.tolist()}, "not a rigid"),
                               ("zero_f", {"K": [[0, 0, 80], [0, 0, 60], [0, 0, 1]]}, "focal lengths"),
                               ("huge", {"width": 100000, "height": 100000}, "outside 1..16384"),
                               ("text", {"width": "wide"}, "bad value")):
        (tmp_path / f"{name}.json").write_text(json.dumps({**good, **change}))
        with pytest.raises(EgorelightError, match=says) as info:
            read_camera_json(tmp_path / f"{name}.json")
        assert f"{name}.json" in str(info.value)


def test_k_and_dist_batches_broadcast_or_are_an_error():
    from egorelight_cli.geometry.cameras import _prepare

    _, K, dist = _prepare(torch.zeros(5, 3), torch.eye(3).expand(2, 1, 3, 3), torch.zeros(3, 4), "fisheye")
    assert K.shape == (2, 3, 3, 3) and dist.shape == (2, 3, 4)
    with pytest.raises(EgorelightError, match="batch shapes differ"):
        _prepare(torch.zeros(5, 3), torch.eye(3).expand(2, 3, 3), torch.zeros(3, 4), "fisheye")
