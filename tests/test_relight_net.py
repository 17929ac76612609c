"""DiffuseNet / SpecularNet and texel Gaussians: shapes, baselines at zero, ray-order invariance,
and a tiny relighting fit through the Gaussian renderer that lowers its loss."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.nn.relight_net import DiffuseNet, SpecularNet
from egorelight_cli.nn.unet import UNet
from egorelight_cli.render.gaussians import render_gaussians
from egorelight_cli.render.image_metrics import ssim
from egorelight_cli.render.uv_gaussians import diffuse_colour, gaussian_regulariser, texel_footprint, texel_gaussians


def _grid_points(n: int = 16, spacing: float = 0.01) -> torch.Tensor:
    v, u = torch.meshgrid(torch.arange(n, dtype=torch.float64), torch.arange(n, dtype=torch.float64), indexing="ij")
    return torch.stack([(u - n / 2) * spacing, (v - n / 2) * spacing, torch.full_like(u, 0.5)], -1)


def test_unet_hooks_run_at_their_level():
    torch.manual_seed(0)
    net = UNet(3, 2, base_channels=4, levels=2).double()
    x = torch.randn(1, 3, 16, 16, dtype=torch.float64)
    seen = []

    def hook(f):
        seen.append(tuple(f.shape))
        return f

    torch.testing.assert_close(net.decoder_features(x, {1: hook})[-1], net.decoder_features(x)[-1])
    assert seen == [(1, 8, 8, 8), (1, 8, 8, 8)]  # encoder (before downsampling), decoder (after its block)
    changed = net.decoder_features(x, {1: lambda f: f + 1.0})[-1]
    assert not torch.allclose(changed, net.decoder_features(x)[-1])


def test_specular_net_is_non_negative_and_ignores_ray_order():
    torch.manual_seed(1)
    net = SpecularNet(base_channels=8, levels=2, attention_level=1, heads=2).double()
    features = torch.randn(2, 7, 16, 16, dtype=torch.float64)
    rays = torch.randn(2, 8, 8, 5, 6, dtype=torch.float64)
    valid = torch.rand(2, 8, 8, 5) > 0.2
    out = net(features, rays, valid)
    assert out.shape == (2, 3, 16, 16) and (out >= 0).all()
    order = torch.randperm(5)
    torch.testing.assert_close(net(features, rays[..., order, :], valid[..., order]), out)
    other = rays.clone()
    other[..., 3:] *= 2.0  # brighter lights change the specular colour
    assert not torch.allclose(net(features, other, valid), out)
    plain = SpecularNet(base_channels=8, levels=2, attention=False).double()
    assert plain(features).shape == (2, 3, 16, 16)


def test_texel_footprint_and_the_zero_output_gaussians():
    points = _grid_points(8, 0.01)
    coverage = torch.ones(8, 8, dtype=torch.bool)
    coverage[0, 0] = False
    # one square of 0.08 m laid out over the whole UV square (two triangles): 8x8 texels of 1 cm
    square = np.array([[0, 0, 0], [0.08, 0, 0], [0.08, 0.08, 0], [0, 0.08, 0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    face_uvs = square[faces][..., :2] / 0.08
    np.testing.assert_allclose(texel_footprint(np.array([0, 1]), square, faces, face_uvs, (8, 8)).numpy(), 0.01,
                               rtol=1e-9)
    np.testing.assert_allclose(texel_footprint(np.array([0]), square, faces, face_uvs, (16, 16)).numpy(), 0.005,
                               rtol=1e-9)
    footprint = torch.full((8, 8), 0.01, dtype=torch.float64)
    raw = torch.zeros(63, 14, dtype=torch.float64)
    gaussians, offsets = texel_gaussians(points[coverage], footprint[coverage], raw, diffuse_colour(raw))
    torch.testing.assert_close(gaussians.means, points[coverage])
    torch.testing.assert_close(gaussians.scales, 0.5 * footprint[coverage][:, None].expand(63, 3))
    assert torch.all(gaussians.quats == torch.tensor([1.0, 0, 0, 0], dtype=torch.float64))
    assert float(gaussians.opacities[0]) == pytest.approx(torch.sigmoid(torch.tensor(2.0)).item())
    assert float(gaussian_regulariser(offsets, gaussians.scales, footprint[coverage])) == 0.0
    big = gaussian_regulariser(torch.full((63, 3), 0.02, dtype=torch.float64), gaussians.scales * 6,
                               footprint[coverage])
    assert float(big) > 1.0


def test_a_tiny_relighting_fit_lowers_its_loss_and_renders():
    torch.manual_seed(0)
    n = 16
    points = _grid_points(n, 0.008).reshape(-1, 3)
    footprint = torch.full((n * n,), 0.008, dtype=torch.float64)
    camera = Camera("pinhole", [[60.0, 0, 15.5], [0, 60.0, 15.5], [0, 0, 1]], np.zeros(5), 32, 32, np.eye(4))
    v, u = torch.meshgrid(torch.linspace(0, 1, n), torch.linspace(0, 1, n), indexing="ij")
    albedo = torch.stack([u, v, 0.5 * torch.ones_like(u)]).double()
    inputs = torch.cat([albedo, torch.ones(1, n, n), torch.tensor([0, 0, -1.0]).view(3, 1, 1).expand(3, n, n),
                        2.0 * torch.ones(3, n, n)]).double()[None]
    target_gaussians, _ = texel_gaussians(points, footprint, torch.zeros(n * n, 14, dtype=torch.float64),
                                          (albedo * 2.0 / np.pi).reshape(3, -1).T)
    target = render_gaussians(target_gaussians, camera).colour.detach()
    diffuse = DiffuseNet(base_channels=8, levels=2).double()
    optimizer = torch.optim.Adam(diffuse.parameters(), lr=1e-2)
    losses = []
    for _ in range(30):
        raw = diffuse(inputs)[0].reshape(14, -1).T
        gaussians, offsets = texel_gaussians(points, footprint, raw, diffuse_colour(raw))
        image = render_gaussians(gaussians, camera).colour
        loss = (image - target).abs().mean() + 10 * (1 - ssim(image, target)) \
            + gaussian_regulariser(offsets, gaussians.scales, footprint)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]
    assert float(image.detach().max()) > 0.1


def test_ray_irradiance_sums_the_valid_rays_and_upsamples():
    from egorelight_cli.stages.relight import ray_irradiance

    rays = torch.zeros(2, 2, 3, 6)
    rays[..., 3:6] = torch.arange(1.0, 4.0).view(1, 1, 3, 1)  # rays carrying 1, 2 and 3
    valid = torch.ones(2, 2, 3, dtype=torch.bool)
    valid[0, 0, 2] = False  # the third ray of one texel is not valid
    low = ray_irradiance(rays, valid, (2, 2))
    assert low.shape == (3, 2, 2)
    np.testing.assert_allclose(low[:, 0, 0].numpy(), 3.0)
    np.testing.assert_allclose(low[:, 1, 1].numpy(), 6.0)
    high = ray_irradiance(rays, torch.ones_like(valid), (8, 8))
    np.testing.assert_allclose(high.numpy(), 6.0, rtol=1e-6)  # a constant map upsamples to itself


def test_irradiance_scaled_specular_is_dark_without_light():
    from egorelight_cli.stages.relight import RelightFrame, RelightModel, relit_avatar

    n = 8
    frame = RelightFrame(torch.rand(10, n, n), _grid_points(n).reshape(-1, 3).float(), torch.full((n * n,), 0.01),
                         np.ones((1, 3)), np.zeros((3, 3)), np.zeros(n * n, bool), torch.rand(n * n, 3))
    coverage = torch.ones(n, n, dtype=torch.bool)
    rays, valid = torch.rand(4, 4, 3, 6), torch.ones(4, 4, 3, dtype=torch.bool)
    dark = rays.clone()
    dark[..., 3:6] = 0.0  # the rays' directions, but no light along them
    for scale, dark_specular in (("none", True), ("irradiance", False)):
        torch.manual_seed(0)
        model = RelightModel(base_channels=4, levels=2, attention_level=1, rays=3, heads=1, specular_scale=scale)
        with torch.no_grad():
            assert float(relit_avatar(model, frame, coverage, rays, valid).specular.min()) > 0
            unlit = relit_avatar(model, frame, coverage, dark, valid).specular
        assert (float(unlit.max()) > 0) == dark_specular, scale  # the paper's head glows in the dark
    with pytest.raises(Exception, match="specular_scale"):
        RelightModel(4, 2, 1, 3, 1, specular_scale="bogus")


def _flat_lit_frame(n: int = 8, seed: int = 0):
    """A frame of n x n covered texels whose flat-lit texture, shadow map and irradiance are random."""
    from egorelight_cli.stages.relight import RelightFrame

    generator = torch.Generator().manual_seed(seed)
    maps = torch.rand(10, n, n, generator=generator) + 0.1
    texels = maps.permute(1, 2, 0).reshape(-1, 10)
    flat = np.pi * texels[:, 3:4]  # the flat light's irradiance pi rho s_flat (s_flat 1)
    lambert = texels[:, 0:3] * texels[:, 7:10] / flat
    return RelightFrame(maps, _grid_points(n).reshape(-1, 3).float(), torch.full((n * n,), 0.01), np.ones((1, 3)),
                        np.zeros((3, 3)), np.zeros(n * n, bool), lambert, flat)


@pytest.mark.parametrize("albedo", ["lambert", "gain", "texture"])
def test_learned_albedo_starts_at_the_lambert_relighting_and_stays_linear_in_the_light(albedo):
    from egorelight_cli.stages.relight import RelightModel, median_albedo, relit_avatar, relit_frame

    n = 8
    frame, coverage = _flat_lit_frame(n), torch.ones(n, n, dtype=torch.bool)
    rays, valid = torch.rand(4, 4, 3, 6), torch.ones(4, 4, 3, dtype=torch.bool)
    torch.manual_seed(0)
    model = RelightModel(4, 2, 1, 3, 1, albedo=albedo, uv_resolution=n)
    model.start_albedo(median_albedo([frame], coverage), coverage)  # one frame: its own albedo
    with torch.no_grad():
        torch.testing.assert_close(relit_avatar(model, frame, coverage, rays, valid).diffuse, frame.lambert)
        if model.albedo_map is not None:  # as if trained: the learned map moves away from the start
            model.albedo_map.add_(0.3 * torch.randn(3, n, n))
        chi = frame.maps[7:10].permute(1, 2, 0).reshape(-1, 3)
        once = relit_avatar(model, relit_frame(frame, coverage, chi), coverage, rays, valid).diffuse
        twice = relit_avatar(model, relit_frame(frame, coverage, 2.0 * chi), coverage, rays, valid).diffuse
    torch.testing.assert_close(twice, 2.0 * once)  # the learned maps do not depend on the light
    assert torch.allclose(once, frame.lambert) == (albedo == "lambert")


def test_median_albedo_is_the_median_over_frames():
    from egorelight_cli.stages.relight import median_albedo

    coverage = torch.ones(8, 8, dtype=torch.bool)
    frames = [_flat_lit_frame(seed=s) for s in range(3)]
    albedos = torch.stack([f.maps[0:3].permute(1, 2, 0).reshape(-1, 3) / f.flat_irradiance for f in frames])
    torch.testing.assert_close(median_albedo(frames, coverage), albedos.median(dim=0).values)
    chi = frames[0].maps[7:10].permute(1, 2, 0).reshape(-1, 3)
    torch.testing.assert_close(median_albedo(frames[:1], coverage) * chi, frames[0].lambert)


def test_learned_albedo_round_trips_through_the_architecture_and_checks_its_settings():
    from egorelight_cli.stages.relight import RelightModel

    model = RelightModel(4, 2, 1, 3, 1, albedo="gain", uv_resolution=8)
    with torch.no_grad():
        model.albedo_map.normal_()
    loaded = RelightModel.from_architecture(model.architecture())
    loaded.load_state_dict(model.state_dict())
    torch.testing.assert_close(loaded.albedo_map, model.albedo_map)
    old = {k: v for k, v in model.architecture().items() if k not in ("albedo", "uv_resolution")}
    assert RelightModel.from_architecture(old).albedo_map is None  # a model saved before the option: Lambert
    with pytest.raises(Exception, match="net.albedo must be one of"):
        RelightModel(4, 2, 1, 3, 1, albedo="bogus", uv_resolution=8)
    with pytest.raises(Exception, match="needs net.uv_resolution"):
        RelightModel(4, 2, 1, 3, 1, albedo="texture")
