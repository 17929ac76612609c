"""The envmap colour model: ``E_h = A . phi(E_l ** gamma)``, degree-2 root-polynomial (Finlayson 2015).

The LDR panorama ``E_l`` of the front cameras and the avatar's HDR light space do not match
(paper Eq. ``color-correct`` and supplement). Per texel, with linear ``(r, g, b) = E_l ** gamma``:

    phi(r, g, b) = [r, g, b, sqrt(r g), sqrt(g b), sqrt(r b)]      (6,)
    E_h = A @ phi                                                 A: (3, 6)

the second-order root-polynomial expansion of Finlayson, Mackiewicz and Hurlbert (2015), whose
terms scale linearly with exposure. ``gamma`` is one scalar here (the supplement's "gamma
parameters" may be per channel; one value keeps the expansion exposure-equivariant up to a
power). The identity model is ``A = [I_3 | 0]``, ``gamma = 1``.

:class:`RootPolynomialColour` is the torch module (gradients to ``A`` and ``gamma`` for the
inverse rendering); :func:`fit_colour_matrix` the closed-form least-squares ``A`` for fixed
``gamma`` (colour-science's ``matrix_colour_correction_Finlayson2015`` is its test oracle).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError

TERMS = ("r", "g", "b", "sqrt(rg)", "sqrt(gb)", "sqrt(rb)")
MODEL_NAME = "root_polynomial_degree2"
#: Inputs are clamped to this before the power and the logs (gradients stay finite at 0).
EPS = 1e-12


def root_polynomial_expansion(rgb):
    """(...,3) non-negative linear RGB -> (...,6) ``[r, g, b, sqrt(rg), sqrt(gb), sqrt(rb)]``
    (numpy in, numpy out; torch in, torch out, differentiable)."""
    if isinstance(rgb, torch.Tensor):
        x = rgb.clamp_min(0.0)
        r, g, b = x.unbind(-1)
        return torch.stack([r, g, b, torch.sqrt(r * g), torch.sqrt(g * b), torch.sqrt(r * b)], dim=-1)
    x = np.maximum(np.asarray(rgb, dtype=np.float64), 0.0)
    if x.shape[-1:] != (3,):
        raise EgorelightError(f"colours must be (...,3), got {x.shape}")
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    return np.stack([r, g, b, np.sqrt(r * g), np.sqrt(g * b), np.sqrt(r * b)], axis=-1)


def identity_matrix() -> np.ndarray:
    """(3,6) ``[I_3 | 0]``: the model that leaves a map unchanged (with gamma 1)."""
    return np.concatenate([np.eye(3), np.zeros((3, 3))], axis=1)


def fit_colour_matrix(source: np.ndarray, target: np.ndarray, gamma: float = 1.0,
                      weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares ``A`` (3,6) with ``target ~ A @ phi(source ** gamma)``.

    Args:
        source: (N,3) linear RGB inputs (e.g. panorama texels), clamped at 0.
        target: (N,3) the colours they should map to.
        gamma: the fixed exponent.
        weights: optional (N,) non-negative per-sample weights.

    Returns:
        (3,6) float64 matrix (minimum-norm solution when ``phi`` is rank deficient).
    """
    source = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    target = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    if source.shape != target.shape or source.shape[0] == 0:
        raise EgorelightError(f"colour fit needs matching non-empty (N,3) arrays, got {source.shape} and {target.shape}")
    if not (np.isfinite(source).all() and np.isfinite(target).all()):
        raise EgorelightError("colour fit inputs hold NaN or inf")
    X = root_polynomial_expansion(np.maximum(source, 0.0) ** float(gamma))
    if weights is not None:
        w = np.sqrt(np.maximum(np.asarray(weights, dtype=np.float64).reshape(-1), 0.0))[:, None]
        X, target = X * w, target * w
    A, *_ = np.linalg.lstsq(X, target, rcond=None)
    return A.T


def channel_gains(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """(3,) least-squares gains ``g`` with ``target ~ g * source`` per channel, over (N,3) pairs,
    each pair weighted by ``weights`` (N,) when given (a channel whose source is 0 everywhere gets
    its numerator over 1e-12)."""
    source = np.asarray(source, np.float64).reshape(-1, 3)
    target = np.asarray(target, np.float64).reshape(-1, 3)
    w = np.ones((len(source), 1)) if weights is None else np.asarray(weights, np.float64).reshape(-1, 1)
    return (w * source * target).sum(axis=0) / np.maximum((w * source * source).sum(axis=0), 1e-12)


class RootPolynomialColour(torch.nn.Module):
    """``E_h = A . phi(E_l ** gamma)`` with learnable ``A`` (3,6) and scalar ``gamma`` (> 0).

    ``forward`` maps (...,3) linear RGB (any leading shape, e.g. an (H,2H,3) map) to (...,3).
    ``gamma`` is stored as ``log_gamma`` so that it stays positive under gradient steps.
    """

    def __init__(self, A: np.ndarray | None = None, gamma: float = 1.0):
        super().__init__()
        A = identity_matrix() if A is None else np.asarray(A, dtype=np.float64)
        if A.shape != (3, 6) or not np.isfinite(A).all():
            raise EgorelightError(f"colour matrix A must be a finite 3x6 matrix, got shape {A.shape}")
        if not (np.isfinite(gamma) and gamma > 0):
            raise EgorelightError(f"colour model gamma must be positive, got {gamma}")
        self.A = torch.nn.Parameter(torch.tensor(A, dtype=torch.float64))
        self.log_gamma = torch.nn.Parameter(torch.tensor(float(np.log(gamma)), dtype=torch.float64))

    @property
    def gamma(self) -> torch.Tensor:
        return torch.exp(self.log_gamma)

    def expand(self, rgb: torch.Tensor) -> torch.Tensor:
        """(...,3) -> (...,6) ``phi(rgb ** gamma)``, computed in logs so that the gradient to
        gamma is finite at 0 (inputs are clamped to :data:`EPS`)."""
        logs = torch.log(rgb.to(self.A.dtype).clamp_min(EPS))
        lr, lg, lb = logs.unbind(-1)
        g = self.gamma
        return torch.exp(g * torch.stack([lr, lg, lb, 0.5 * (lr + lg), 0.5 * (lg + lb), 0.5 * (lr + lb)], dim=-1))

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        if rgb.shape[-1] != 3:
            raise EgorelightError(f"colour model input must be (...,3), got {tuple(rgb.shape)}")
        return (self.expand(rgb) @ self.A.T).to(rgb.dtype)

    def apply_numpy(self, rgb: np.ndarray) -> np.ndarray:
        """The model on a numpy (...,3) array, float32 out."""
        with torch.no_grad():
            return self(torch.from_numpy(np.asarray(rgb, dtype=np.float64))).numpy().astype(np.float32)

    def to_json(self, **extra) -> dict:
        """``colour_model.json`` content: model name, terms, A (3x6 rows), gamma, plus ``extra``."""
        return {"model": MODEL_NAME, "terms": list(TERMS), "A": self.A.detach().numpy().tolist(),
                "gamma": float(self.gamma.detach()), **extra}

    @classmethod
    def from_json(cls, data: dict | str | Path) -> RootPolynomialColour:
        """Read :meth:`to_json` output (a dict or a file path)."""
        source = None
        if isinstance(data, (str, Path)):
            source = Path(data)
            try:
                data = json.loads(source.read_text())
            except (OSError, json.JSONDecodeError) as exc:
                raise EgorelightError(f"cannot read colour model ({exc})", source) from None
        if data.get("model") != MODEL_NAME:
            raise EgorelightError(f"colour model is {data.get('model')!r}, expected {MODEL_NAME!r}", source)
        try:
            return cls(np.asarray(data["A"], dtype=np.float64), float(data["gamma"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise EgorelightError(f"malformed colour model ({type(exc).__name__}: {exc})", source) from None
        except EgorelightError as exc:
            raise EgorelightError(exc.message, source) from None
