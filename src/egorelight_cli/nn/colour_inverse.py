"""The inverse of the envmap colour model: ``E_l`` from ``E_h = A . phi(E_l ** gamma)`` per pixel.

``composite`` maps the avatar's HDR (radiance in the units of the avatar's light, ``E_h``) back
into the LDR space of the camera the environment was scanned with (linearised front-camera
sRGB, ``E_l``), so that the avatar sits in the background image with the same colour response.
:class:`~egorelight_cli.nn.colour_model.RootPolynomialColour` has no closed-form inverse; with
``u = E_l ** gamma`` the forward model ``f(u) = A phi(u)`` is positively homogeneous of degree 1
(``f(t u) = t f(u)``), and with ``s = sqrt(u)`` it is a quadratic form,
``phi(s ** 2) = [r^2, g^2, b^2, rg, gb, rb]`` (smooth also where a channel is 0, where the root
terms' derivatives in ``u`` blow up). Per pixel, 3 equations in 3 unknowns:

1. **Start**: the exact solution for grey inputs. At ``u = (t, t, t)`` every root term equals its
   linearisation ``sqrt(a b) ~ (a + b) / 2``, so ``f(u) ~ A M u`` with ``M`` (6,3)
   (:data:`GREY_LINEARISATION`); ``u0 = (A M)^+ y`` (one 3x3 pseudo-inverse for all pixels),
   floored at 1e-4 of its largest channel, ``s0 = sqrt(u0)``; the target is scaled to unit max
   first (homogeneity) and the solution scaled back.
2. **Gauss-Newton / Levenberg-Marquardt in log s** (``s = exp(v)`` stays positive, no boundary):
   ``v <- v - (J^T J + mu diag(J^T J))^-1 J^T (f - y)`` with the analytic Jacobian
   ``J = A dphi(s^2)/ds diag(s)``, the step clipped to +-3 (a factor e^3 in ``s``), accepted when
   the misfit ``|f - y|`` falls (``mu / 4``) and refused otherwise (``mu x 5``), ``iterations``
   times (default 20). Newton on ``u`` or ``s`` with a projection onto ``s >= 0`` stalls at the
   boundary for saturated colours (the quadratic form has mixed-sign roots); in logs a channel
   that is truly 0 goes to ``exp(-large)`` instead. Near-zero channels are ill-conditioned
   (``E_l = s^(2/gamma)`` with a vanishing misfit): their error is bounded by the residual, not
   by the channel's value.
3. ``E_l = u ** (1 / gamma)``.

Targets outside the model's range (a colour no non-negative ``E_l`` maps to, e.g. a negative
channel) end at the nearest point Newton reaches from the start; :func:`invert_colour` reports
the relative residual ``|f(u) - y| / |y|`` per pixel so callers can record it.

**Mapping an avatar back** (:class:`CameraMapping`, ``composite``). The exact inverse is right for
the light (each direction of ``E_h`` came from a panorama texel). For the avatar's colours it is
right only if the fitted model were the camera's colour response; fitted by inverse rendering, its
cross terms also absorb the avatar's and the synchronisation's errors, and on colours unlike the
panorama's (an albedo times the light) their inverse extrapolates: on the cpu demo it saturated
the avatar towards magenta. :func:`diagonal_inverse` is the robust alternative: one gain per
channel, the least-squares fit of ``E_l ~ g E_h`` over the map's texels (``E_l`` the exact
inverse of each texel). It is exact when the model is a gain per channel, and it commutes with
an albedo, so an avatar relit by ``E_h`` and mapped back is the avatar relit by ``g E_h ~ E_l``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.equirect import equirect_solid_angles
from egorelight_cli.nn.colour_model import RootPolynomialColour, channel_gains

#: (6,3) ``phi(u) ~ M u`` near grey (exact for grey): the root terms' arithmetic-mean linearisation.
GREY_LINEARISATION = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5]])


def quadratic_terms(s: np.ndarray) -> np.ndarray:
    """(N,6) ``phi(s ** 2)`` = ``[r^2, g^2, b^2, rg, gb, rb]`` of ``s`` (N,3): the root-polynomial
    expansion is a quadratic form in ``s = sqrt(u)``."""
    r, g, b = s[:, 0], s[:, 1], s[:, 2]
    return np.stack([r * r, g * g, b * b, r * g, g * b, r * b], axis=1)


def _jacobian(s: np.ndarray) -> np.ndarray:
    """(N,6,3) ``d phi(s ** 2) / ds``: smooth everywhere, also where a channel is 0."""
    r, g, b = s[:, 0], s[:, 1], s[:, 2]
    J = np.zeros((len(s), 6, 3))
    J[:, 0, 0], J[:, 1, 1], J[:, 2, 2] = 2 * r, 2 * g, 2 * b
    J[:, 3, 0], J[:, 3, 1] = g, r
    J[:, 4, 1], J[:, 4, 2] = b, g
    J[:, 5, 0], J[:, 5, 2] = b, r
    return J


def misfit_rows(s: np.ndarray, y: np.ndarray, A: np.ndarray) -> np.ndarray:
    """(N,) ``|A phi(s ** 2) - y|`` per row of ``s``, ``y`` (N,3)."""
    return np.linalg.norm(quadratic_terms(s) @ A.T - y, axis=1)


def _solve_matrices(J: np.ndarray) -> np.ndarray:
    """(N,3,3) inverses of ``J``, pseudo-inverses where a matrix is (near) singular."""
    det = np.linalg.det(J)
    norm = np.abs(J).reshape(len(J), -1).max(axis=1)
    regular = np.abs(det) > 1e-9 * np.maximum(norm, 1e-300) ** 3
    out = np.empty_like(J)
    out[regular] = np.linalg.inv(J[regular])
    if not regular.all():
        out[~regular] = np.linalg.pinv(J[~regular])
    return out


def invert_colour(model: RootPolynomialColour | tuple[np.ndarray, float], target: np.ndarray,
                  iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``target = A phi(x ** gamma)`` for ``x >= 0`` per pixel (module docstring).

    Args:
        model: the colour model, or ``(A (3,6), gamma)``.
        target: (...,3) ``E_h`` values (any leading shape, e.g. (H,W,3)).
        iterations: Newton steps.

    Returns:
        (``E_l`` (...,3) float32 non-negative, relative residual (...,) float32); pixels whose
        target is 0 map to 0 with residual 0.
    """
    if isinstance(model, RootPolynomialColour):
        A, gamma = model.A.detach().numpy().astype(np.float64), float(model.gamma.detach())
    else:
        A, gamma = np.asarray(model[0], np.float64), float(model[1])
    if A.shape != (3, 6) or not np.isfinite(A).all() or not (np.isfinite(gamma) and gamma > 0):
        raise EgorelightError(f"colour model must be a finite 3x6 A and a positive gamma, got {A.shape}, {gamma}")
    target = np.asarray(target, np.float64)
    if target.shape[-1:] != (3,) or not np.isfinite(target).all():
        raise EgorelightError(f"colours to invert must be finite (...,3), got {target.shape}")
    y = target.reshape(-1, 3)
    scale = np.abs(y).max(axis=1)
    live = scale > 0
    u_out = np.zeros_like(y)
    residual = np.zeros(len(y))
    if live.any():
        yl = y[live] / scale[live, None]  # homogeneity: solve at unit scale, scale back
        u0 = yl @ np.linalg.pinv(A @ GREY_LINEARISATION).T
        v = np.log(np.sqrt(np.maximum(u0, 1e-3 * np.maximum(u0.max(axis=1, keepdims=True), 1e-3))))
        current = misfit_rows(np.exp(v), yl, A)
        damping = np.full(len(v), 1e-4)
        eye = np.eye(3)
        for _ in range(int(iterations)):
            s = np.exp(v)
            error = quadratic_terms(s) @ A.T - yl
            J = (A @ _jacobian(s)) * s[:, None, :]  # d f / d log s
            JtJ = np.einsum("nki,nkj->nij", J, J)
            diagonal = np.maximum(np.einsum("nii->ni", JtJ), 1e-12)
            step = np.linalg.solve(JtJ + damping[:, None, None] * eye * diagonal[:, :, None],
                                   np.einsum("nki,nk->ni", J, error)[..., None])[..., 0]
            candidate = v - np.clip(step, -3.0, 3.0)
            value = misfit_rows(np.exp(candidate), yl, A)
            better = value < current
            v[better], current[better] = candidate[better], value[better]
            damping = np.where(better, np.maximum(damping / 4.0, 1e-12), damping * 5.0)
        s = np.exp(v)
        residual[live] = current / np.maximum(np.linalg.norm(yl, axis=1), 1e-12)
        u_out[live] = s * s * scale[live, None]
    x = np.power(np.maximum(u_out, 0.0), 1.0 / gamma)
    return x.reshape(target.shape).astype(np.float32), residual.reshape(target.shape[:-1]).astype(np.float32)


#: ``composite`` colour.inverse: how the avatar's radiance goes back into the camera's space.
INVERSE_METHODS = ("diagonal", "exact")


def diagonal_inverse(model: RootPolynomialColour, envmap: np.ndarray, iterations: int = 20) -> np.ndarray:
    """(3,) per-channel gains ``g`` with ``E_l ~ g E_h``: least squares over the texels of the
    equirect ``envmap`` (H,W,3), the ``E_h`` map of ``model``, against their exact inverses (module
    docstring), each texel weighted by its solid angle (a light integrates over the sphere; unweighted,
    the rows by the poles counted ~1/sin(theta) times too much)."""
    E_h = np.asarray(envmap, np.float64)
    if E_h.ndim != 3 or E_h.shape[-1] != 3:
        raise EgorelightError(f"the environment map must be an (H,W,3) equirect map, got shape {E_h.shape}")
    solid_angles = equirect_solid_angles(*E_h.shape[:2]).reshape(-1)
    E_h = E_h.reshape(-1, 3)
    if not ((E_h * E_h).sum(axis=0) > 0).all():
        raise EgorelightError("the environment map has a channel that is 0 everywhere: no gain to fit")
    return channel_gains(E_h, invert_colour(model, E_h, iterations)[0], solid_angles)


@dataclass(frozen=True, eq=False)
class CameraMapping:
    """Avatar radiance in ``E_h`` units -> camera-linear ``E_l``, per pixel.

    Attributes:
        method: ``exact`` (the per-pixel inverse of ``model``) or ``linear`` (``E_l = matrix @ E_h``,
            negative values clipped: a gain per channel, or a known camera's 3x3 response).
        model: the colour model (``exact``).
        matrix: (3,3) float64 (``linear``).
        iterations: Newton steps of the ``exact`` inverse.
    """

    method: str
    model: RootPolynomialColour | None = None
    matrix: np.ndarray | None = None
    iterations: int = 20

    def __post_init__(self) -> None:
        if self.method not in ("exact", "linear"):
            raise EgorelightError(f"camera mapping method must be exact or linear, got {self.method!r}")
        if self.method == "exact" and not isinstance(self.model, RootPolynomialColour):
            raise EgorelightError("an exact camera mapping needs the colour model")
        if self.method == "linear" and (self.matrix is None or np.shape(self.matrix) != (3, 3)
                                        or not np.isfinite(self.matrix).all()):
            raise EgorelightError(f"a linear camera mapping needs a finite 3x3 matrix, got {np.shape(self.matrix)}")

    def apply(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(``E_l`` (N,3) float32, relative residual (N,) float32; 0 for ``linear``) of (N,3) colours."""
        if self.method == "exact":
            return invert_colour(self.model, rgb, self.iterations)
        mapped = np.maximum(np.asarray(rgb, np.float64) @ self.matrix.T, 0.0)
        return mapped.astype(np.float32), np.zeros(mapped.shape[:-1], np.float32)

    def to_json(self) -> dict:
        if self.method == "exact":
            return {"method": "exact", "inverse": "per-pixel Levenberg-Marquardt in log sqrt(E_l^gamma) from the "
                    f"grey solution ({self.iterations} steps), nn/colour_inverse.py"}
        return {"method": "linear", "matrix": self.matrix.tolist()}


def camera_mapping(model: RootPolynomialColour, envmap: np.ndarray, method: str, iterations: int = 20) -> CameraMapping:
    """The :class:`CameraMapping` of ``colour.inverse`` = ``method`` (:data:`INVERSE_METHODS`) for the
    colour ``model`` of ``envmap`` (H,2H,3) ``E_h``."""
    if method == "exact":
        return CameraMapping("exact", model=model, iterations=iterations)
    if method == "diagonal":
        return CameraMapping("linear", matrix=np.diag(diagonal_inverse(model, envmap, iterations)))
    raise EgorelightError(f"colour.inverse must be one of {', '.join(INVERSE_METHODS)}, got {method!r}")
