"""The lightstage: dome layout, solid-angle cells, lights.json, S(E) and the irradiance convention."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.equirect import (
    equirect_directions,
    equirect_solid_angles,
    rotate_envmap,
)
from egorelight_cli.render.envmaps import make_envmap
from egorelight_cli.render.lightstage import LightStage, dome_positions


@pytest.fixture(scope="module")
def stage() -> LightStage:
    return LightStage.dome()


def _envmap_irradiance(envmap: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N,3) cosine-weighted integral of an equirect map for unit normals (N,3)."""
    d = equirect_directions(envmap.shape[0])
    cos = np.clip(np.einsum("hwk,nk->nhw", d, normals), 0.0, None)
    return np.einsum("hwc,hw,nhw->nc", envmap.astype(np.float64), equirect_solid_angles(envmap.shape[0]), cos)


def _upper_normals(count: int, min_elevation_deg: float = 0.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(4 * count, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n[n[:, 1] >= math.sin(math.radians(min_elevation_deg))][:count]


def test_dome_layout(stage):
    assert stage.num_lights == 331
    np.testing.assert_allclose(stage.centre, [0.0, 1.0, 0.0])
    np.testing.assert_allclose(stage.distances, 1.8, rtol=1e-12)
    elevation = np.degrees(np.arcsin(stage.directions[:, 1]))
    assert elevation.min() >= -30.0 and elevation.max() > 85.0
    # near-uniform: nearest-neighbour angular spacing varies little
    cos = stage.directions @ stage.directions.T
    np.fill_diagonal(cos, -1.0)
    spacing = np.degrees(np.arccos(cos.max(axis=1)))
    assert spacing.max() / spacing.min() < 1.6
    positions = dome_positions(50, radius=2.0, min_elevation_deg=0.0, centre=(1.0, 2.0, 3.0))
    np.testing.assert_allclose(np.linalg.norm(positions - [1.0, 2.0, 3.0], axis=1), 2.0)
    assert (positions[:, 1] >= 2.0).all()


def test_cell_solid_angles_partition_the_sphere(stage):
    omega = stage.cell_solid_angles()
    assert omega.shape == (331,) and (omega > 0).all()
    assert omega.sum() == pytest.approx(4 * math.pi, rel=1e-9)
    # agree with counting fine equirect texels by nearest light
    H = 256
    texels = equirect_directions(H).reshape(-1, 3)
    nearest = np.argmax(texels @ stage.directions.T, axis=1)
    counted = np.bincount(nearest, weights=equirect_solid_angles(H).reshape(-1), minlength=331)
    np.testing.assert_allclose(counted, omega, rtol=0.05, atol=2e-3)
    # dome cells are ~4 pi / 331 * (fraction of the sphere covered); the lowest ring also holds the floor
    assert np.median(omega) == pytest.approx(2 * math.pi * 1.5 / 331, rel=0.05)


def test_lights_json_round_trip(stage, tmp_path):
    gain = np.random.default_rng(0).uniform(0.8, 1.2, size=(331, 3))
    custom = LightStage(positions=stage.positions, rgb_gain=gain, radius=1.8, centre=stage.centre)
    path = tmp_path / "lights.json"
    custom.write_json(path)
    loaded = LightStage.from_json(path)
    np.testing.assert_allclose(loaded.positions, custom.positions)
    np.testing.assert_allclose(loaded.rgb_gain, gain)
    np.testing.assert_allclose(loaded.centre, custom.centre)
    assert loaded.radius == pytest.approx(1.8)
    # a real capture's file may hold positions and gains only: centre and radius are fitted
    bare = LightStage.from_json({"positions": stage.positions.tolist(), "rgb_gain": gain.tolist()})
    np.testing.assert_allclose(bare.centre, stage.centre, atol=1e-9)
    assert bare.radius == pytest.approx(1.8)
    json.dumps(custom.to_json())
    with pytest.raises(EgorelightError, match="lights.json"):
        LightStage.from_json(tmp_path / "missing" / "lights.json")
    with pytest.raises(EgorelightError):
        LightStage.from_json({"positions": [[0, 0, 0]] * 3, "rgb_gain": [[1, 1]] * 3})


def test_lighting_conditions(stage):
    olat = stage.olat(7, (1.0, 2.0, 3.0))
    assert olat.shape == (331, 3) and np.count_nonzero(olat.any(axis=1)) == 1
    np.testing.assert_allclose(olat[7], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(stage.flat(0.5), 0.5)
    with pytest.raises(EgorelightError):
        stage.olat(331)
    with pytest.raises(EgorelightError):
        stage.flat(-1.0)


def test_point_light_irradiance_convention(stage):
    """E = I gain Omega (R / d)^2 max(0, n.w) at a point below one light."""
    index = 0  # nearest the zenith
    gain = np.ones((331, 3))
    gain[index] = [1.0, 0.5, 2.0]
    custom = LightStage(positions=stage.positions, rgb_gain=gain, radius=1.8, centre=stage.centre)
    light = custom.positions[index]
    x = light - np.array([0.3, 1.2, 0.0])
    n = np.array([0.0, 1.0, 0.0])
    to_light = light - x
    d = np.linalg.norm(to_light)
    expected = 2.0 * gain[index] * custom.cell_solid_angles()[index] * (1.8 / d) ** 2 * (to_light @ n) / d
    got = custom.irradiance(x[None], n[None], custom.olat(index, 2.0))[0]
    np.testing.assert_allclose(got, expected, rtol=1e-12)


def test_flat_lighting_is_a_furnace_at_the_centre(stage):
    """A uniform environment of radiance 1 gives irradiance ~pi on an upward surface at the centre."""
    up = stage.irradiance(stage.centre[None], np.array([[0.0, 1.0, 0.0]]), stage.flat(1.0))[0]
    np.testing.assert_allclose(up, math.pi, rtol=0.02)


def test_constant_envmap_gives_that_constant(stage):
    for H in (8, 32, 64):  # 8 rows: most cells hold no texel centre and are sampled instead
        envmap = np.broadcast_to(np.array([0.2, 1.5, 3.0], np.float32), (H, 2 * H, 3))
        np.testing.assert_allclose(stage.envmap_to_intensities(envmap), np.tile([0.2, 1.5, 3.0], (331, 1)), rtol=1e-6)


def test_envmap_to_intensities_is_linear_and_yaw_consistent(stage):
    a, b = make_envmap("sky", 1, 32), make_envmap("indoor", 2, 32)
    np.testing.assert_allclose(stage.envmap_to_intensities(2 * a + b),
                               2 * stage.envmap_to_intensities(a) + stage.envmap_to_intensities(b), rtol=1e-6)
    yaw = 360.0 / 64 * 5  # whole columns: the rotated map is an exact roll
    np.testing.assert_allclose(stage.envmap_to_intensities(a, yaw_deg=yaw),
                               stage.envmap_to_intensities(rotate_envmap(a, yaw)), rtol=1e-6, atol=1e-9)


def test_irradiance_at_the_centre_matches_the_envmap(stage):
    """S(E) lights reproduce the envmap's cosine-weighted integral at the dome centre."""
    H = 128
    d = equirect_directions(H)
    smooth = (1.0 + 0.5 * d[..., 0:1] + 0.3 * d[..., 1:2] * np.array([1.0, 2.0, 3.0]) + 0.2 * d[..., 2:3] ** 2)
    intensities = stage.envmap_to_intensities(smooth)
    normals = _upper_normals(100, min_elevation_deg=60.0)  # their hemisphere stays above the floor cut
    got = stage.irradiance(np.tile(stage.centre, (len(normals), 1)), normals, intensities)
    np.testing.assert_allclose(got, _envmap_irradiance(smooth, normals), rtol=0.03)
    # lower normals also see the floor region, lumped into the lowest ring of lights (at -30 deg)
    normals = _upper_normals(100)
    got = stage.irradiance(np.tile(stage.centre, (len(normals), 1)), normals, intensities)
    np.testing.assert_allclose(got, _envmap_irradiance(smooth, normals), rtol=0.10)
    # procedural maps with small bright sources: a few % typical error (the sun is moved to the
    # nearest light's direction, up to half a cell spacing away)
    normals = _upper_normals(200)
    errors = []
    for kind, seed in [("sky", 0), ("indoor", 0), ("studio", 0), ("indoor", 1)]:
        envmap = make_envmap(kind, seed, H)
        got = stage.irradiance(np.tile(stage.centre, (len(normals), 1)), normals, stage.envmap_to_intensities(envmap))
        ref = _envmap_irradiance(envmap, normals)
        errors.append(np.abs(got.sum(1) / ref.sum(1) - 1.0))
        up = np.array([[0.0, 1.0, 0.0]])
        got_up = stage.irradiance(stage.centre[None], up, stage.envmap_to_intensities(envmap))
        np.testing.assert_allclose(got_up, _envmap_irradiance(envmap, up), rtol=0.05)
    median = float(np.median(np.concatenate(errors)))
    print(f"S(E) irradiance at the dome centre, median relative error over normals: {median:.4f}")
    assert median < 0.04
