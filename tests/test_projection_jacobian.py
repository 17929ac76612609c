"""The closed-form projection Jacobian equals autograd through ``project``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorelight_cli.geometry.cameras import project
from egorelight_cli.geometry.projection_jacobian import projection_jacobian

K = torch.tensor([[300.0, 0.4, 160.0], [0.0, 310.0, 120.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
DISTORTION = {
    "pinhole": torch.tensor([-0.21, 0.06, 0.0011, -0.0007, -0.01], dtype=torch.float64),
    "fisheye": torch.tensor([0.021, -0.004, 0.0011, -0.0002], dtype=torch.float64),
}


def _autograd_jacobian(points, model):
    jac = torch.autograd.functional.jacobian(lambda p: project(p, K, DISTORTION[model], model), points)
    index = torch.arange(points.shape[0])
    return jac[index, :, index, :]  # (N,2,3)


def _points(model: str, n: int = 300) -> torch.Tensor:
    rng = np.random.default_rng(3)
    if model == "pinhole":
        z = rng.uniform(0.3, 4.0, n)
        xy = rng.uniform(-0.7, 0.7, (n, 2)) * z[:, None]
        return torch.tensor(np.column_stack([xy, z]))
    # fisheye: directions up to 110 degrees off-axis (past the image plane), 0.2-3 m away
    theta = np.deg2rad(110.0) * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    radius = rng.uniform(0.2, 3.0, n)[:, None]
    directions = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    return torch.tensor(directions * radius)


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_jacobian_matches_autograd(model):
    points = _points(model)
    _, valid = project(points, K, DISTORTION[model], model, return_valid=True)
    assert valid.all()
    expected = _autograd_jacobian(points, model)
    actual = projection_jacobian(points, K, DISTORTION[model], model)
    assert actual.shape == (points.shape[0], 2, 3)
    np.testing.assert_allclose(actual.numpy(), expected.numpy(), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_jacobian_on_the_optical_axis_is_the_pinhole_limit(model):
    points = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
    J = projection_jacobian(points, K, DISTORTION[model], model)[0]
    fx, skew, fy = K[0, 0].item(), K[0, 1].item(), K[1, 1].item()
    expected = np.array([[fx / 2.0, skew / 2.0, 0.0], [0.0, fy / 2.0, 0.0]])
    np.testing.assert_allclose(J.numpy(), expected, atol=1e-12)
    # and the neighbourhood agrees with finite differences of the projection
    step = 1e-6
    for axis in range(3):
        offset = torch.zeros(1, 3, dtype=torch.float64)
        offset[0, axis] = step
        numeric = (project(points + offset, K, DISTORTION[model], model)
                   - project(points - offset, K, DISTORTION[model], model))[0] / (2 * step)
        np.testing.assert_allclose(numeric.numpy(), J[:, axis].numpy(), rtol=1e-5, atol=1e-5)


def test_jacobian_is_differentiable():
    points = _points("fisheye", 5).requires_grad_(True)
    J = projection_jacobian(points, K, DISTORTION["fisheye"], "fisheye")
    assert torch.autograd.gradcheck(
        lambda p: projection_jacobian(p, K, DISTORTION["fisheye"], "fisheye"), (points,), eps=1e-6, atol=1e-6)
    assert torch.isfinite(torch.autograd.grad(J.sum(), points)[0]).all()
