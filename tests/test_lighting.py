"""Frame lighting from light entries, and the differentiable S(E) pooling."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.render.envmaps import make_envmap, write_envmap
from egorelight_cli.render.lighting import CaptureEnvmaps, EnvmapPooling, envmap_pooling_matrix, light_intensities
from egorelight_cli.render.lightstage import LightStage


@pytest.fixture(scope="module")
def stage() -> LightStage:
    return LightStage.dome()


@pytest.mark.parametrize("height", [8, 32])  # 8 rows: coarser than the dome, some cells hold no texel
@pytest.mark.parametrize("yaw", [0.0, 37.0])
def test_pooling_matrix_is_the_same_s_of_e(stage, height, yaw):
    envmap = make_envmap("indoor", 3, height)
    pooling = EnvmapPooling(stage, height, yaw_deg=yaw)
    pooled = pooling(torch.from_numpy(envmap).double())
    np.testing.assert_allclose(pooled.numpy(), stage.envmap_to_intensities(envmap, yaw), rtol=1e-6, atol=1e-9)
    if height == 8:
        rows = envmap_pooling_matrix(stage, height).to_dense()
        np.testing.assert_allclose(rows.sum(1).numpy(), 1.0, atol=1e-12)  # an average, also for empty cells


def test_pooling_of_a_constant_map_is_that_constant_and_it_has_gradients(stage):
    envmap = torch.full((16, 32, 3), 0.7, dtype=torch.float64, requires_grad=True)
    pooling = EnvmapPooling(stage, 16)
    lights = pooling(envmap)
    np.testing.assert_allclose(lights.detach().numpy(), 0.7, rtol=1e-12)
    weights = torch.rand(stage.num_lights, 3, dtype=torch.float64)
    grad = torch.autograd.grad((lights * weights).sum(), envmap)[0]
    dense = envmap_pooling_matrix(stage, 16).to_dense()
    np.testing.assert_allclose(grad.reshape(-1, 3).numpy(), (dense.T @ weights).numpy(), rtol=1e-12)
    with pytest.raises(EgorelightError, match="built for"):
        pooling(torch.zeros(8, 16, 3))


def test_light_entries(stage, tmp_path):
    (tmp_path / "envmaps").mkdir()
    envmap = make_envmap("sky", 1, 16)
    write_envmap(tmp_path / "envmaps" / "sky_1.exr", envmap)
    envmaps = CaptureEnvmaps(tmp_path)
    assert list(envmaps) == ["sky_1"] and "sky_1" in envmaps and "nope" not in envmaps
    np.testing.assert_allclose(light_intensities(stage, {"pattern": "flat", "scale": 2.0}, envmaps), 2.0)
    assert not light_intensities(stage, {"pattern": "dark"}, envmaps).any()
    olat = light_intensities(stage, {"pattern": "olat", "olat_index": 5, "scale": 3.0}, envmaps)
    assert olat[5].tolist() == [3.0, 3.0, 3.0] and olat.sum() == 9.0
    lit = light_intensities(stage, {"pattern": "envmap", "envmap": "sky_1", "yaw_deg": 20.0, "scale": 0.5}, envmaps)
    np.testing.assert_allclose(lit, 0.5 * stage.envmap_to_intensities(envmaps["sky_1"], 20.0))
    with pytest.raises(EgorelightError, match="does not have"):
        light_intensities(stage, {"pattern": "envmap", "envmap": "missing"}, envmaps)
    with pytest.raises(EgorelightError, match="unknown light pattern"):
        light_intensities(stage, {"pattern": "strobe"}, envmaps)
