"""Gaussian splatting: the fast path against the dense reference, analytic cases, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, look_at, project
from egorelight_cli.render.gaussian_pairs import T_MIN
from egorelight_cli.render.gaussian_projection import ALPHA_MAX, image_tangent_bounds, in_field_of_view
from egorelight_cli.render.gaussians import render_gaussians
from egorelight_cli.render.gaussians_reference import render_gaussians_dense
from egorelight_cli.structures.gaussians import GaussianSet

W, H = 40, 30


def _camera(model: str, width: int = W, height: int = H, focal: float = 36.0, dist=None, pose=None) -> Camera:
    if dist is None:
        dist = [0.04, -0.01, 0.001, -0.0005, 0.0] if model == "pinhole" else [0.02, -0.01, 0.002, 0.0]
    K = [[focal, 0.0, (width - 1) / 2], [0.0, focal * 1.02, (height - 1) / 2], [0.0, 0.0, 1.0]]
    return Camera(model, K, dist, width, height, np.eye(4) if pose is None else pose, name=model)


def _scene(n: int, seed: int = 0, dtype=torch.float64, channels: int = 3, max_opacity: float = 1.0) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([0.5, 0.4, 0.3], dtype=dtype)
    means[:, 2] += 1.6
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.08 + 0.01
    opacities = torch.rand(n, generator=g, dtype=dtype) * max_opacity
    colours = torch.rand(n, channels, generator=g, dtype=dtype)
    return GaussianSet(means, quats, scales, opacities, colours)


def _single(mean, scale, opacity=0.8, colour=(1.0, 0.5, 0.25), quat=(1.0, 0.0, 0.0, 0.0)) -> GaussianSet:
    f = torch.float64
    return GaussianSet(torch.tensor([mean], dtype=f), torch.tensor([quat], dtype=f),
                       torch.tensor([[scale] * 3], dtype=f), torch.tensor([opacity], dtype=f),
                       torch.tensor([colour], dtype=f))


def _close(a: torch.Tensor, b: torch.Tensor, tol: float) -> None:
    np.testing.assert_allclose(a.detach().numpy(), b.detach().numpy(), rtol=tol, atol=tol)


# --------------------------------------------------------------------------- fast == dense


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fast_path_matches_dense_reference(model, seed):
    gaussians = _scene(250, seed)
    camera = _camera(model)
    diffuse = gaussians.colours[:, :1] * 0.5
    kwargs = dict(background=[0.1, 0.2, 0.3], passes={"diffuse": diffuse}, pass_backgrounds={"diffuse": [0.7]})
    fast = render_gaussians(gaussians, camera, **kwargs)
    dense = render_gaussians_dense(gaussians, camera, **kwargs)
    assert fast.stats.pairs > 1000 and fast.alpha.max() > 0.9  # a real scene, not an empty image
    for name in ("colour", "alpha", "depth"):
        _close(getattr(fast, name), getattr(dense, name), 1e-10)
    _close(fast.passes["diffuse"], dense.passes["diffuse"], 1e-10)
    assert fast.colour.shape == (H, W, 3) and fast.passes["diffuse"].shape == (H, W, 1)


def test_float32_fast_path_matches_float64_dense():
    gaussians = _scene(250, 5)
    camera = _camera("pinhole")
    fast = render_gaussians(gaussians.to(dtype=torch.float32), camera)
    dense = render_gaussians_dense(gaussians, camera)
    assert fast.colour.dtype == torch.float32
    _close(fast.colour.double(), dense.colour, 2e-4)
    _close(fast.expected_depth.double(), dense.expected_depth, 2e-4)


def test_chunked_pair_search_gives_the_same_image():
    gaussians = _scene(200, 7)
    camera = _camera("fisheye")
    whole = render_gaussians(gaussians, camera)
    chunked = render_gaussians(gaussians, camera, chunk_pairs=64)
    _close(whole.colour, chunked.colour, 1e-12)
    assert whole.stats.pairs == chunked.stats.pairs


def test_render_is_deterministic():
    gaussians = _scene(200, 8, dtype=torch.float32)
    for tensor in gaussians.tensors():
        tensor.requires_grad_(True)
    camera = _camera("pinhole")
    results = []
    for _ in range(2):
        out = render_gaussians(gaussians, camera)
        grads = torch.autograd.grad(out.colour.square().sum() + out.depth.sum(), gaussians.tensors())
        results.append((out.colour.detach().clone(), grads))
    assert torch.equal(results[0][0], results[1][0])
    assert all(torch.equal(a, b) for a, b in zip(results[0][1], results[1][1]))


# --------------------------------------------------------------------------- analytic cases


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
@pytest.mark.parametrize("eps2d", [0.0, 0.3])
def test_isotropic_gaussian_has_its_analytic_footprint(model, eps2d):
    focal, distance, sigma, opacity = 36.0, 2.0, 0.12, 0.8
    camera = _camera(model, focal=focal, dist=np.zeros(5 if model == "pinhole" else 4))
    out = render_gaussians(_single([0.0, 0.0, distance], sigma, opacity), camera, eps2d=eps2d)
    # on the axis the projection's Jacobian is diag(f, 1.02 f) / z for both models
    var_u = (focal * sigma / distance) ** 2 + eps2d
    var_v = (1.02 * focal * sigma / distance) ** 2 + eps2d
    v, u = np.mgrid[0:H, 0:W]
    du, dv = u - (W - 1) / 2, v - (H - 1) / 2
    expected = opacity * np.exp(-0.5 * (du ** 2 / var_u + dv ** 2 / var_v))
    expected[expected < 1 / 255] = 0.0
    np.testing.assert_allclose(out.alpha.numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(out.colour[..., 1].numpy(), 0.5 * expected, atol=1e-12)
    np.testing.assert_allclose(out.expected_depth.numpy()[expected > 0], distance, atol=1e-12)


def test_front_opaque_gaussian_hides_the_back_one_whatever_the_input_order():
    camera = _camera("pinhole", dist=np.zeros(5))
    front = _single([0.0, 0.0, 1.0], 0.2, opacity=1.0, colour=(1.0, 0.0, 0.0))
    back = _single([0.0, 0.0, 2.0], 0.4, opacity=1.0, colour=(0.0, 1.0, 0.0))
    centre = (H // 2, W // 2)
    for order in ((front, back), (back, front)):
        both = GaussianSet(*(torch.cat([a, b]) for a, b in zip(order[0].tensors(), order[1].tensors())))
        out = render_gaussians(both, camera)
        a_front = render_gaussians(front, camera).alpha[centre]
        a_back = render_gaussians(back, camera).alpha[centre]
        colour = out.colour[centre]
        assert a_front > 0.98  # clamped at ALPHA_MAX near the centre
        np.testing.assert_allclose(colour.numpy(), [a_front, (1 - a_front) * a_back, 0.0], atol=1e-12)
        assert colour[1] < 0.011  # the back Gaussian shows only through the 1% the front leaves


def test_early_termination_stops_at_T_MIN():
    """Layers of opacity 0.99: after two the transmittance is 1e-4; the third and later add nothing."""
    camera = _camera("pinhole", dist=np.zeros(5))
    layers = [_single([0.0, 0.0, 1.0 + 0.1 * i], 0.5, opacity=1.0, colour=(float(i), 0.0, 0.0)) for i in range(5)]
    stack = GaussianSet(*(torch.cat(parts) for parts in zip(*(g.tensors() for g in layers))))
    centre = (H // 2, W // 2)
    out = render_gaussians(stack, camera)
    alphas = [float(render_gaussians(g, camera).alpha[centre]) for g in layers]
    assert alphas[0] == pytest.approx(ALPHA_MAX)
    T, expected = 1.0, 0.0
    for i, a in enumerate(alphas):
        if T < T_MIN:
            break
        expected += i * a * T
        T *= 1 - a
    assert float(out.colour[centre][0]) == pytest.approx(expected, abs=1e-12)
    assert float(out.colour[centre][0]) < 0.0099 + 2 * 1e-4  # layers 2.. contribute at most T_MIN-ish


def test_per_pixel_cap_is_a_prefix_and_is_reported():
    gaussians = _scene(300, 11)
    camera = _camera("pinhole")
    capped = render_gaussians(gaussians, camera, max_per_pixel=3)
    dense_capped = render_gaussians_dense(gaussians, camera, max_per_pixel=3)
    full = render_gaussians(gaussians, camera)
    _close(capped.colour, dense_capped.colour, 1e-10)
    assert capped.stats.truncated_pixels > 0
    assert capped.stats.pairs <= 3 * W * H
    # what the cap can lose is bounded by the reported transmittance left behind the kept splats
    lost = (full.alpha - capped.alpha).max().item()
    assert 0 < lost <= capped.stats.max_truncated_transmittance + 1e-12
    assert full.stats.truncated_pixels == 0


def test_fisheye_renders_gaussians_beyond_90_degrees():
    # a wide fisheye (no distortion: theta_d = theta; 14 px per radian keeps 120 degrees in view)
    camera = _camera("fisheye", width=64, height=64, focal=14.0, dist=np.zeros(4))
    angle = math.radians(105.0)
    mean = [0.6 * math.sin(angle), 0.0, 0.6 * math.cos(angle)]  # behind the image plane (z < 0)
    gaussian = _single(mean, 0.03, opacity=0.9)
    out = render_gaussians(gaussian, camera)
    dense = render_gaussians_dense(gaussian, camera)
    u, v = project(np.array([mean]), camera.K, camera.dist, "fisheye")[0]
    assert 63 / 2 + 14.0 * math.pi / 2 < u < 63  # in the image, further out than the 90-degree circle
    peak = np.unravel_index(int(out.alpha.argmax()), out.alpha.shape)
    assert abs(peak[1] - u) <= 1 and abs(peak[0] - v) <= 1
    assert out.alpha.max() > 0.5
    _close(out.alpha, dense.alpha, 1e-12)
    np.testing.assert_allclose(out.expected_depth[peak].item(), 0.6, atol=1e-12)  # fisheye depth is range


def test_pinhole_culls_gaussians_far_outside_its_field_of_view():
    # the composite's front camera (k1 < 0, k2 > 0: the radial curve rises for ever, so x/z = 10 is
    # still "valid"): a small Gaussian 2 m away beside the camera, ~84 degrees off-axis, projected
    # through the polynomial far past the lens became a splat over the whole image (composite)
    camera = _camera("pinhole", width=80, height=60, focal=40.0, dist=[-0.0507, 0.01455, 0.0, 0.0, 0.0])
    beside = _single([2.0, 0.0, 0.2], 0.02, opacity=0.9)
    x_lo, x_hi, y_lo, y_hi = image_tangent_bounds(camera)
    assert x_hi < 2.0 / 0.2 and x_lo < 0 < x_hi and y_lo < 0 < y_hi
    out = render_gaussians(beside, camera)
    assert out.stats.visible_gaussians == 0 and float(out.alpha.max()) == 0.0
    # one just outside the image's edge (inside the margin) still reaches into it, as before
    x_edge = 0.5 * (x_hi + image_tangent_bounds(camera, margin=0.0)[1])
    edge = _single([x_edge * 1.0, 0.0, 1.0], 0.08, opacity=0.9)
    out = render_gaussians(edge, camera)
    assert out.stats.visible_gaussians == 1 and float(out.alpha[:, -1].max()) > 0.1
    _close(out.alpha, render_gaussians_dense(edge, camera).alpha, 1e-12)
    # the fisheye keeps everything up to its valid angle (test above)
    assert bool(in_field_of_view(torch.tensor([[2.0, 0.0, 0.2]]), _camera("fisheye")).all())


def test_background_and_empty_image():
    camera = _camera("pinhole")
    behind = _single([0.0, 0.0, -1.0], 0.1)
    out = render_gaussians(behind, camera, background=[0.2, 0.4, 0.6])
    assert out.stats.visible_gaussians == 0
    np.testing.assert_allclose(out.colour.numpy(), np.broadcast_to([0.2, 0.4, 0.6], (H, W, 3)))
    assert float(out.alpha.abs().max()) == 0.0


# --------------------------------------------------------------------------- gradients


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_gradients_match_autograd_through_the_dense_reference(model):
    gaussians = _scene(120, 3)
    for tensor in gaussians.tensors():
        tensor.requires_grad_(True)
    weights = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    grads = []
    for render in (render_gaussians, render_gaussians_dense):
        passes = {"diffuse": (gaussians.colours[:, :2] * 0.3)}
        out = render(gaussians, _camera(model), background=[0.3, 0.3, 0.3], passes=passes)
        loss = (out.colour * weights).sum() + 0.5 * out.depth.sum() + out.passes["diffuse"].square().sum()
        grads.append(torch.autograd.grad(loss, gaussians.tensors()))
    for name, fast, dense in zip(("means", "quats", "scales", "opacities", "colours"), *grads):
        assert dense.abs().max() > 0, name
        _close(fast, dense, 1e-9)


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_gradients_match_finite_differences(model):
    gaussians = _scene(6, 21, max_opacity=0.9)  # below ALPHA_MAX: no clamp kinks
    camera = _camera(model, width=14, height=12, focal=12.0)
    weights = torch.rand(12, 14, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def loss(means, quats, scales, opacities, colours):
        out = render_gaussians(GaussianSet(means, quats, scales, opacities, colours), camera)
        return (out.colour * weights).sum() + 0.3 * out.depth.sum() + out.alpha.sum()

    inputs = tuple(t.clone().requires_grad_(True) for t in gaussians.tensors())
    assert render_gaussians(gaussians, camera).stats.pairs > 50
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-7, atol=1e-5, rtol=1e-4)


def test_culled_gaussians_get_zero_not_nan_gradients():
    gaussians = _scene(50, 4)
    gaussians.means.data[:10, 2] = -1.0  # behind the pinhole
    for tensor in gaussians.tensors():
        tensor.requires_grad_(True)
    out = render_gaussians(gaussians, _camera("pinhole"))
    grads = torch.autograd.grad(out.colour.sum(), gaussians.tensors())
    for grad in grads:
        assert torch.isfinite(grad).all()
        assert float(grad[:10].abs().max()) == 0.0


# --------------------------------------------------------------------------- structure and errors


def test_gaussian_set_validates_shapes_and_dtypes():
    g = _scene(4, 0)
    with pytest.raises(EgorelightError, match="quats"):
        GaussianSet(g.means, g.quats[:, :3], g.scales, g.opacities, g.colours)
    with pytest.raises(EgorelightError, match="colours"):
        GaussianSet(g.means, g.quats, g.scales, g.opacities, g.colours[:3])
    with pytest.raises(EgorelightError, match="dtype"):
        GaussianSet(g.means.float(), g.quats, g.scales, g.opacities, g.colours)
    covariance = g.covariances()
    assert torch.allclose(covariance, covariance.transpose(1, 2))
    assert (torch.linalg.eigvalsh(covariance) > 0).all()
    np.testing.assert_allclose(torch.linalg.eigvalsh(covariance).numpy(),
                               torch.sort(g.scales ** 2, dim=1).values.numpy(), rtol=1e-10)


def test_render_rejects_bad_arguments():
    g = _scene(4, 0)
    camera = _camera("pinhole")
    with pytest.raises(EgorelightError, match="background"):
        render_gaussians(g, camera, background=[0.0, 0.0])
    with pytest.raises(EgorelightError, match="pass 'x'"):
        render_gaussians(g, camera, passes={"x": torch.zeros(3, 1, dtype=torch.float64)})
    with pytest.raises(EgorelightError, match="max_per_pixel"):
        render_gaussians(g, camera, max_per_pixel=0)
    with pytest.raises(EgorelightError, match="backend"):
        render_gaussians(g, camera, backend="opengl")
    with pytest.raises(EgorelightError, match="gsplat"):
        render_gaussians(g, camera, backend="gsplat")  # the Gaussians are on the CPU


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat renders on CUDA only")
@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_gsplat_agrees_with_the_torch_path(model):
    pytest.importorskip("gsplat")
    gaussians = _scene(400, 2, dtype=torch.float32).to(device="cuda")
    camera = _camera(model, width=80, height=60, focal=70.0, dist=np.zeros(5 if model == "pinhole" else 4),
                     pose=look_at((0.0, 0.0, -0.2), (0.0, 0.0, 1.6), up=(0.0, -1.0, 0.0)))
    ours = render_gaussians(gaussians, camera, backend="torch")
    theirs = render_gaussians(gaussians, camera, backend="gsplat")
    assert theirs.backend == "gsplat" and theirs.device.startswith("cuda")
    # gsplat cuts splats at 3 sigma and sorts by z: agreement to a few percent, not bit for bit
    assert (ours.colour - theirs.colour).abs().mean() < 0.01
    assert (ours.alpha - theirs.alpha).abs().mean() < 0.01
