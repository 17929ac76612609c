"""Procedural HDR environment maps, disjoint sets and user map loading."""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.equirect import equirect_directions, equirect_solid_angles
from egorelight_cli.io.exr import write_exr_layers
from egorelight_cli.render.envmaps import (
    ENVMAP_KINDS,
    detailed_surroundings,
    envmap_set,
    envmap_specs,
    load_envmap,
    make_envmap,
    surface_detail,
    write_envmap,
)


def _up_irradiance(envmap: np.ndarray) -> float:
    """Mean-channel irradiance on an upward surface (cosine-weighted integral)."""
    d = equirect_directions(envmap.shape[0])
    weight = equirect_solid_angles(envmap.shape[0]) * np.clip(d[..., 1], 0.0, None)
    return float(np.einsum("hwc,hw->", envmap.astype(np.float64), weight) / 3.0)


@pytest.mark.parametrize("kind", ENVMAP_KINDS)
def test_maps_are_seeded_hdr_and_plausible(kind):
    a = make_envmap(kind, 5, height=32)
    assert a.shape == (32, 64, 3) and a.dtype == np.float32
    assert np.isfinite(a).all() and (a >= 0).all()
    np.testing.assert_array_equal(a, make_envmap(kind, 5, height=32))  # deterministic
    assert not np.allclose(a, make_envmap(kind, 6, height=32))
    # high dynamic range: small bright emitters far above the typical texel
    assert a.max() / np.median(a) > 20
    # overall brightness in the documented range
    assert 0.3 < _up_irradiance(a) < 40


def test_sky_has_a_sun_above_the_horizon_and_ground_below():
    sky = make_envmap("sky", 3, height=64)
    row, _ = np.unravel_index(np.argmax(sky.sum(-1)), sky.shape[:2])
    assert row < 32  # the sun is in the upper half (+Y)
    assert sky[:32].mean() > 0 and sky[40:].mean() > 0


def test_sun_energy_does_not_depend_on_resolution():
    levels = [_up_irradiance(make_envmap("sky", seed, height)) for seed in (0, 1) for height in (16, 64, 128)]
    for seed_levels in (levels[:3], levels[3:]):
        assert max(seed_levels) / min(seed_levels) < 1.05


def test_sets_are_disjoint_across_purposes():
    sets = {purpose: envmap_set(purpose, 12, seed=7, height=16) for purpose in ("train", "test", "wild")}
    specs = {p: envmap_specs(p, 12, seed=7) for p in sets}
    seeds = {p: {s.seed for s in specs[p]} for p in specs}
    for a, b in itertools.combinations(sets, 2):
        assert not seeds[a] & seeds[b]
        for (name_a, map_a), (name_b, map_b) in itertools.product(sets[a].items(), sets[b].items()):
            # scale-invariant distance: equal maps, or one a multiple of the other, give ~0
            x, y = map_a.ravel() / np.linalg.norm(map_a), map_b.ravel() / np.linalg.norm(map_b)
            assert np.linalg.norm(x - y) > 0.05, (name_a, name_b)
    assert all(name.startswith("wild_") for name in sets["wild"])
    assert {spec.kind for spec in specs["wild"]} == {"sky", "indoor"}
    assert {spec.kind for spec in specs["train"]} == set(ENVMAP_KINDS)
    # the same call gives the same set
    again = envmap_set("test", 12, seed=7, height=16)
    assert list(again) == list(sets["test"])
    for name in again:
        np.testing.assert_array_equal(again[name], sets["test"][name])
    with pytest.raises(EgorelightError):
        envmap_set("validation", 2)


def test_load_user_maps(tmp_path):
    envmap = make_envmap("indoor", 1, height=32)
    exr = tmp_path / "room.exr"
    write_envmap(exr, envmap)
    np.testing.assert_allclose(load_envmap(exr), envmap, rtol=1e-6)
    half = load_envmap(exr, height=16)
    assert half.shape == (16, 32, 3)
    assert _up_irradiance(half) == pytest.approx(_up_irradiance(envmap), rel=0.05)

    hdr = tmp_path / "room.hdr"
    assert cv2.imwrite(str(hdr), cv2.cvtColor(envmap, cv2.COLOR_RGB2BGR))
    loaded = load_envmap(hdr)
    np.testing.assert_allclose(loaded, envmap, rtol=0.02, atol=1e-3)  # RGBE is ~1% accurate

    for bad, message in [(tmp_path / "missing.exr", "not found"), (tmp_path / "room.png", "unsupported")]:
        if bad.suffix == ".png":
            bad.write_bytes(b"")
        with pytest.raises(EgorelightError, match=message) as info:
            load_envmap(bad)
        assert bad.name in str(info.value)
    square = tmp_path / "square.exr"
    write_exr_layers(square, {"": np.ones((8, 8, 3), np.float32)})
    with pytest.raises(EgorelightError, match="square.exr"):
        load_envmap(square)
    broken = tmp_path / "broken.hdr"
    broken.write_bytes(b"not an image")
    with pytest.raises(EgorelightError, match="broken.hdr"):
        load_envmap(broken)
    negated = tmp_path / "negated.exr"  # a sign flipped: no light left after clipping
    write_exr_layers(negated, {"": -np.ones((8, 16, 3), np.float32)})
    with pytest.raises(EgorelightError, match="holds no light") as info:
        load_envmap(negated)
    assert "negated.exr" in str(info.value)
    ringing = np.ones((8, 16, 3), np.float32)
    ringing[0, 0] = -0.01
    write_exr_layers(tmp_path / "ringing.exr", {"": ringing})
    assert load_envmap(tmp_path / "ringing.exr").min() == 0.0  # a few negative texels are clipped


def test_unknown_kind_and_bad_height():
    with pytest.raises(EgorelightError):
        make_envmap("beach", 0)
    with pytest.raises(EgorelightError):
        make_envmap("sky", 0, height=2)
    assert math.isfinite(_up_irradiance(make_envmap("studio", 0, height=8)))


def test_surface_detail_is_seeded_positive_and_keeps_irradiance():
    a, b = surface_detail(128, seed=3), surface_detail(128, seed=3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, surface_detail(128, seed=4))
    assert a.shape == (128, 256) and a.dtype == np.float32 and (a > 0).all()
    weights = equirect_solid_angles(128)
    assert abs(float((a * weights).sum() / weights.sum()) - 1.0) < 1e-5
    # real fine structure: neighbouring texels differ by tens of percent somewhere
    assert np.percentile(np.abs(np.diff(np.log(a), axis=1)), 99) > 0.2
    # a uniform place keeps its mean radiance; a map keeps its layout at the new resolution
    flat = detailed_surroundings(np.full((32, 64, 3), 0.7, np.float32), 128, seed=3)
    np.testing.assert_allclose(np.einsum("hwc,hw->c", flat, weights) / weights.sum(), 0.7, rtol=1e-5)
    envmap = make_envmap("sky", 5, height=32)
    detailed = detailed_surroundings(envmap, 128, seed=3)
    assert detailed.shape == (128, 256, 3)
    sky, ground = detailed[:32].mean(), detailed[-32:].mean()
    assert (sky > ground) == (envmap[:8].mean() > envmap[-8:].mean())
