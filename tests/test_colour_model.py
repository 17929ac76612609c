"""nn/colour_model.py against colour-science's Finlayson 2015 root-polynomial expansion and regression."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.nn.colour_model import (
    RootPolynomialColour,
    fit_colour_matrix,
    identity_matrix,
    root_polynomial_expansion,
)

with warnings.catch_warnings():  # colour-science warns once that matplotlib is absent
    warnings.simplefilter("ignore")
    colour_characterisation = pytest.importorskip("colour.characterisation")


def _colours(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.01, 1.0, size=(n, 3))


def test_expansion_equals_colour_science():
    rgb = _colours(50)
    oracle = colour_characterisation.polynomial_expansion_Finlayson2015(rgb, degree=2, root_polynomial_expansion=True)
    np.testing.assert_allclose(root_polynomial_expansion(rgb), oracle, rtol=1e-12)
    torch_terms = root_polynomial_expansion(torch.from_numpy(rgb)).numpy()
    np.testing.assert_allclose(torch_terms, oracle, rtol=1e-12)
    with torch.no_grad():  # the module's log-space expansion at gamma = 1
        np.testing.assert_allclose(RootPolynomialColour().expand(torch.from_numpy(rgb)).numpy(), oracle, rtol=1e-10)


def test_fitted_matrix_equals_colour_science():
    source = _colours(40, 1)
    truth = np.random.default_rng(2).normal(size=(3, 6)) * 0.5 + identity_matrix()
    target = root_polynomial_expansion(source) @ truth.T + np.random.default_rng(3).normal(0, 0.01, (40, 3))
    A = fit_colour_matrix(source, target)
    oracle = colour_characterisation.matrix_colour_correction_Finlayson2015(source, target, degree=2,
                                                                          root_polynomial_expansion=True)
    np.testing.assert_allclose(A, oracle, rtol=1e-8, atol=1e-10)
    assert np.abs(A - truth).max() < 0.2  # noise is small: the fit is near the truth
    # colour-science applies its matrix with the same expansion
    applied = colour_characterisation.apply_matrix_colour_correction_Finlayson2015(source, oracle, degree=2,
                                                                                 root_polynomial_expansion=True)
    model = RootPolynomialColour(A, 1.0)
    np.testing.assert_allclose(model.apply_numpy(source), applied, rtol=1e-5, atol=1e-6)


def test_gamma_fit_and_exact_recovery():
    source = _colours(60, 4)
    truth, gamma = identity_matrix() * 1.7 + 0.05, 1.6
    target = RootPolynomialColour(truth, gamma).apply_numpy(source).astype(np.float64)
    np.testing.assert_allclose(fit_colour_matrix(source, target, gamma), truth, atol=1e-4)
    weighted = fit_colour_matrix(source, target, gamma, weights=np.linspace(0.1, 2, 60))
    np.testing.assert_allclose(weighted, truth, atol=1e-4)


def test_module_gradients_and_round_trip(tmp_path):
    model = RootPolynomialColour(gamma=1.3)
    rgb = torch.tensor([[0.0, 0.5, 1.0], [0.2, 0.0, 0.0]], dtype=torch.float64)
    out = model(rgb)
    out.sum().backward()
    assert torch.isfinite(model.A.grad).all() and torch.isfinite(model.log_gamma.grad)
    assert float(model.gamma.detach()) == pytest.approx(1.3)
    identity = RootPolynomialColour()(torch.tensor([[0.3, 0.6, 0.9]], dtype=torch.float64))
    np.testing.assert_allclose(identity.detach().numpy(), [[0.3, 0.6, 0.9]], rtol=1e-10)
    doc = model.to_json(row="test")
    path = tmp_path / "colour_model.json"
    import json

    path.write_text(json.dumps(doc))
    again = RootPolynomialColour.from_json(path)
    np.testing.assert_allclose(again.A.detach().numpy(), model.A.detach().numpy())
    assert float(again.gamma.detach()) == pytest.approx(1.3)
    with pytest.raises(EgorelightError, match="3x6"):
        RootPolynomialColour(np.eye(3))
    with pytest.raises(EgorelightError, match="gamma"):
        RootPolynomialColour(gamma=0.0)
    with pytest.raises(EgorelightError, match="expected"):
        RootPolynomialColour.from_json({"model": "linear"})
    with pytest.raises(EgorelightError, match="matching"):
        fit_colour_matrix(np.zeros((3, 3)), np.zeros((4, 3)))
