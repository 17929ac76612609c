"""LDR camera responses and front-facing views of environment maps."""

from __future__ import annotations

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, camera_rays_world, look_at
from egorelight_cli.geometry.equirect import (
    equirect_directions,
    rotate_envmap,
    sample_equirect,
)
from egorelight_cli.render.camera_response import (
    CameraResponse,
    exposure_for,
    random_ego_response,
    render_envmap_view,
)
from egorelight_cli.render.envmaps import make_envmap


def _grey_ramp(n: int = 4096, top: float = 1.2) -> np.ndarray:
    return np.repeat(np.linspace(0.0, top, n)[None, :, None], 3, axis=2).astype(np.float32)


def test_identity_response_is_the_srgb_curve():
    response = CameraResponse()
    image = response.apply(np.array([[[0.0, 0.2159, 1.0], [0.5, 2.0, 0.0031308]]], np.float32))
    assert image.dtype == np.uint8
    # IEC 61966-2-1: 0.2159 -> 0.5021, 0.5 -> 0.7354, 0.0031308 -> 0.04045
    np.testing.assert_array_equal(image, [[[0, 128, 255], [188, 255, 10]]])


@pytest.mark.parametrize("seed", range(4))
def test_random_responses_are_monotone_and_invertible(seed):
    rng = np.random.default_rng(seed)
    response = random_ego_response(rng, exposure=0.8)
    assert response.colour_matrix.shape == (3, 3)
    assert not np.allclose(response.colour_matrix, np.eye(3))
    assert np.abs(response.colour_matrix - np.eye(3)).max() < 0.35
    ramp = _grey_ramp(top=4.0)
    codes = response.apply(ramp).astype(int)
    assert (np.diff(codes, axis=1) >= 0).all()  # monotone in radiance, every channel
    assert codes.max() == 255 and codes.min() == 0
    # without noise, linearize inverts apply up to quantisation, where nothing clipped
    colours = rng.uniform(0.0, 0.8, size=(64, 64, 3)).astype(np.float32)
    sensor = response.sensor(colours)
    ok = (sensor > 0.02).all(-1) & (sensor < 0.98).all(-1)
    assert ok.mean() > 0.5
    back = response.linearize(response.apply(colours))
    rel = np.abs(back[ok] - colours[ok]) / np.maximum(colours[ok], 0.05)
    assert np.median(rel) < 0.01 and rel.max() < 0.08
    # round trip through a JSON-able dict
    again = CameraResponse.from_dict(response.to_dict())
    np.testing.assert_array_equal(again.apply(colours), response.apply(colours))


def test_noise_level_and_determinism():
    response = CameraResponse(exposure=1.0, noise_std=0.01)
    flat = np.full((200, 200, 3), 0.2, np.float32)
    a = response.apply(flat, np.random.default_rng(1))
    b = response.apply(flat, np.random.default_rng(1))
    np.testing.assert_array_equal(a, b)
    assert response.apply(flat).std() == 0  # no rng: no noise
    linear = response.linearize(a)
    assert 0.008 < linear.std() < 0.012
    assert abs(linear.mean() - 0.2) < 0.002


def test_exposure_and_bit_depth():
    linear = np.random.default_rng(0).uniform(0, 10.0, size=(32, 32, 3)).astype(np.float32)
    exposure = exposure_for(linear, percentile=99.0, target=0.9)
    response = CameraResponse(exposure=exposure, bits=12)
    image = response.apply(linear)
    assert image.dtype == np.uint16
    # the 99th percentile of the brightest channel lands at linear 0.9 = sRGB 0.955
    assert np.percentile(image.max(-1), 99) == pytest.approx(0.9546 * 4095, abs=3)
    assert (image == 4095).mean() < 0.01
    with pytest.raises(EgorelightError):
        CameraResponse(colour_matrix=np.zeros((3, 3)))
    with pytest.raises(EgorelightError):
        CameraResponse(gamma="log")


def _pinhole(T: np.ndarray, size: int = 65, focal: float = 40.0) -> Camera:
    return Camera("pinhole", [[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]], np.zeros(5),
                  size, size, T)


def test_envmap_view_looks_at_infinity():
    envmap = make_envmap("indoor", 3, height=64)
    # a camera anywhere looking along -Z sees the middle of the map at its image centre
    for eye in [(0.0, 0.0, 0.0), (5.0, -2.0, 3.0)]:
        camera = _pinhole(look_at(eye, np.add(eye, (0.0, 0.0, -1.0))))
        view = render_envmap_view(envmap, camera, supersample=1)
        np.testing.assert_allclose(view[32, 32], sample_equirect(envmap, np.array([0.0, 0.0, -1.0])), rtol=1e-5)
    # every pixel samples the map along its ray; the image's up is +Y
    camera = _pinhole(look_at((0, 0, 0), (1.0, 0.2, 0.0)))
    view = render_envmap_view(envmap, camera, supersample=1)
    _, dirs, _ = camera_rays_world(camera)
    np.testing.assert_allclose(view, sample_equirect(envmap, dirs), rtol=1e-5, atol=1e-6)
    assert dirs[0, 32, 1] > dirs[-1, 32, 1]


def test_envmap_view_yaw_matches_the_rotated_map():
    envmap = make_envmap("sky", 2, height=32)
    camera = _pinhole(look_at((0, 0, 0), (0.3, 0.1, -1.0)))
    yaw = 360.0 / 64 * 7
    np.testing.assert_allclose(render_envmap_view(envmap, camera, yaw_deg=yaw),
                               render_envmap_view(rotate_envmap(envmap, yaw), camera), rtol=1e-4, atol=1e-5)


def test_envmap_view_through_a_fisheye():
    H = 32
    d = equirect_directions(H)
    smooth = (1.0 + 0.5 * d).astype(np.float32)
    K = [[20.0, 0, 63.5], [0, 20.0, 63.5], [0, 0, 1]]  # equidistant: the 180-degree circle has radius 31 px
    camera = Camera("fisheye", K, [0.0, 0.0, 0.0, 0.0], 128, 128, look_at((0, 0, 0), (0, 0, -1.0)))
    view = render_envmap_view(smooth, camera, supersample=3)
    assert (view[0, 0] == 0).all()  # corner beyond theta = pi: no ray
    np.testing.assert_allclose(view[63:65, 63:65].mean((0, 1)), [1.0, 1.0, 0.5], atol=0.02)  # -Z
    # 90 degrees off-axis to the image right (+x_cam = +X world here) sees +X
    np.testing.assert_allclose(view[63:65, 94:96].mean((0, 1)), [1.5, 1.0, 1.0], atol=0.03)
    np.testing.assert_allclose(render_envmap_view(smooth, camera, supersample=1)[20:108, 20:108],
                               view[20:108, 20:108], atol=0.02)


def _direction_map(height: int = 256) -> np.ndarray:
    """A map whose radiance is its own direction (+1.5): lookups read back where they looked."""
    return (1.5 + equirect_directions(height)).astype(np.float32)


def test_envmap_on_a_sphere_shows_parallax():
    envmap, centre, radius = _direction_map(), np.array([0.0, 1.6, 0.0]), 4.0
    looking = (0.0, 0.0, -1.0)
    # from the centre the sphere looks like the map at infinity
    at_centre = _pinhole(look_at(centre, centre + looking))
    np.testing.assert_allclose(render_envmap_view(envmap, at_centre, supersample=1, radius_m=radius, centre=centre),
                               render_envmap_view(envmap, at_centre, supersample=1), atol=1e-6)
    # 1 m to the side, the image centre sees the sphere's point (1, 0, -sqrt(15)) from the centre
    eye = centre + (1.0, 0.0, 0.0)
    view = render_envmap_view(envmap, _pinhole(look_at(eye, eye + looking)), supersample=1, radius_m=radius,
                              centre=centre)
    expected = np.array([1.0, 0.0, -np.sqrt(15.0)]) / radius
    np.testing.assert_allclose(view[32, 32] - 1.5, expected, atol=0.01)
    with pytest.raises(EgorelightError, match="outside the surroundings"):
        far = centre + (5.0, 0.0, 0.0)
        render_envmap_view(envmap, _pinhole(look_at(far, far + looking)), radius_m=radius, centre=centre)


def test_envmap_floor_is_hit_before_the_sphere():
    envmap, centre = _direction_map(), np.array([0.0, 1.6, 0.0])
    eye = centre + (0.5, 0.0, 0.0)
    camera = _pinhole(look_at(eye, eye + (0.0, -1.0, 0.0), up=(0.0, 0.0, -1.0)))
    view = render_envmap_view(envmap, camera, supersample=1, radius_m=4.0, centre=centre, floor_y=0.0)
    # straight down onto the floor at (0.5, 0, 0): seen from the centre along (0.5, -1.6, 0)
    expected = np.array([0.5, -1.6, 0.0]) / np.hypot(0.5, 1.6)
    np.testing.assert_allclose(view[32, 32] - 1.5, expected, atol=0.01)
    with pytest.raises(EgorelightError, match="below the floor"):
        render_envmap_view(envmap, camera, radius_m=4.0, centre=centre, floor_y=2.0)
