"""The equirectangular mapping (DESIGN.md Sec. 4): directions, coordinates, solid angles, sampling, yaw."""

from __future__ import annotations

import math

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.equirect import (
    directions_to_equirect,
    equirect_directions,
    equirect_solid_angles,
    rotate_envmap,
    sample_equirect,
    yaw_rotation,
)


def _smooth_map(height: int) -> np.ndarray:
    """A smooth, asymmetric RGB function of direction, tabulated as an equirect map."""
    d = equirect_directions(height)
    return np.stack([1.0 + d[..., 0], 1.5 + 0.5 * d[..., 1] * d[..., 2], 2.0 + d[..., 2] + 0.3 * d[..., 0] ** 2],
                    axis=-1).astype(np.float32)


def test_directions_follow_the_design_convention():
    H = 8
    d = equirect_directions(H)
    assert d.shape == (H, 2 * H, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    assert (d[0, :, 1] > 0.98).all() and (d[-1, :, 1] < -0.98).all()  # row 0 is up
    # phi = 2 pi (u + 0.5) / W - pi; theta of row i = pi (i + 0.5) / H
    theta = math.pi * 2.5 / H
    for u, phi in [(3, 2 * math.pi * 3.5 / 16 - math.pi), (12, 2 * math.pi * 12.5 / 16 - math.pi)]:
        expected = [math.sin(theta) * math.sin(phi), math.cos(theta), -math.sin(theta) * math.cos(phi)]
        np.testing.assert_allclose(d[2, u], expected, atol=1e-12)
    # continuous coordinates: the middle of the map is -Z, three quarters across is +X, a quarter -X
    coords = directions_to_equirect(np.array([[0, 0, -1.0], [1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0]]), H)
    np.testing.assert_allclose(coords[:3], [[H, H / 2], [1.5 * H, H / 2], [0.5 * H, H / 2]], atol=1e-12)
    assert coords[3, 1] == pytest.approx(0.0)


def test_round_trip_pixel_centres():
    H, W = 16, 32
    coords = directions_to_equirect(equirect_directions(H, W), H, W)
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    np.testing.assert_allclose(coords[..., 0], cols + 0.5, atol=1e-9)
    np.testing.assert_allclose(coords[..., 1], rows + 0.5, atol=1e-9)
    # the default size gives resolution-free coordinates (units of the map height)
    np.testing.assert_allclose(directions_to_equirect(equirect_directions(H, W)), coords / H, atol=1e-12)


def test_solid_angles_sum_to_four_pi_and_follow_sin_theta():
    for H in (1, 4, 37, 128):
        omega = equirect_solid_angles(H)
        assert omega.shape == (H, 2 * H)
        assert omega.sum() == pytest.approx(4 * math.pi, rel=1e-12)
    H = 64
    theta = math.pi * (np.arange(H) + 0.5) / H
    approx = (math.pi / H) * (2 * math.pi / (2 * H)) * np.sin(theta)
    np.testing.assert_allclose(equirect_solid_angles(H)[:, 0], approx, rtol=1e-3)


def test_sample_at_pixel_centres_is_exact_and_wraps_in_azimuth():
    rng = np.random.default_rng(0)
    envmap = rng.uniform(0, 5, size=(8, 16, 3)).astype(np.float32)
    dirs = equirect_directions(8)
    np.testing.assert_allclose(sample_equirect(envmap, dirs), envmap, rtol=1e-5, atol=1e-5)
    # halfway between the last and the first column (azimuth +-pi, i.e. +Z) averages them
    theta = math.pi * 3.5 / 8
    seam = np.array([0.0, math.cos(theta), math.sin(theta)])  # phi = pi
    np.testing.assert_allclose(sample_equirect(envmap, seam), 0.5 * (envmap[3, 0] + envmap[3, -1]), rtol=1e-5)
    # a smooth function is reproduced between texels
    fine = equirect_directions(64)
    coarse = _smooth_map(32)
    np.testing.assert_allclose(sample_equirect(coarse, fine)[4:-4], _smooth_map(64)[4:-4], atol=0.01)


def test_rotate_envmap_moves_content_by_the_documented_sign():
    H = 16
    envmap = np.zeros((H, 2 * H, 3), np.float32)
    centre_col = H  # column whose centre is at phi = 2 pi (H + 0.5) / (2H) - pi, just past -Z
    envmap[H // 2, centre_col] = 1.0
    d = equirect_directions(H)[H // 2, centre_col]
    rotated = rotate_envmap(envmap, 90.0)
    moved = yaw_rotation(90.0) @ d  # content at d is now at R_y(yaw) d
    assert sample_equirect(rotated, moved)[0] == pytest.approx(1.0, abs=1e-5)
    assert moved[0] < -0.99  # -Z turns towards -X for positive yaw
    np.testing.assert_allclose(rotate_envmap(envmap, 360.0), envmap)
    np.testing.assert_allclose(rotate_envmap(rotate_envmap(envmap, 45.0), 67.5), rotate_envmap(envmap, 112.5), atol=1e-6)


def test_rotate_envmap_fractional_matches_resampling():
    H = 64
    envmap = _smooth_map(H)
    yaw = 33.3
    rotated = rotate_envmap(envmap, yaw)
    expected = sample_equirect(envmap, equirect_directions(H) @ yaw_rotation(yaw))  # E(R^T d)
    np.testing.assert_allclose(rotated, expected, atol=2e-3)


def test_bad_maps_are_rejected():
    with pytest.raises(EgorelightError):
        sample_equirect(np.zeros((8, 8, 3)), np.array([0.0, 1.0, 0.0]))
    with pytest.raises(EgorelightError):
        directions_to_equirect(np.zeros((2, 3)))
    with pytest.raises(EgorelightError):
        equirect_solid_angles(0)
