"""Jacobian of the camera projection with respect to the camera-frame point.

EWA splatting (Zwicker et al. 2002; 3DGS Eq. 5) approximates a camera's projection near a
Gaussian's mean by its first-order Taylor expansion, so the 2D footprint covariance is
``J W Sigma W^T J^T`` with ``J = d pixel / d point_cam`` (2,3). This module gives ``J`` for the
*actual* projection of :func:`egorelight_cli.geometry.cameras.project`, including the pinhole
radial-tangential and the OpenCV fisheye distortion, in closed form (differentiable, batched).

Pixels are OpenCV's ``(u, v)``; points are metres in the OpenCV camera frame (z forward).
"""

from __future__ import annotations

import torch

from egorelight_cli.geometry.cameras import (
    _fisheye_dtheta_d,
    _fisheye_theta_d,
    _pad_dist,
    _pinhole_radial,
    _pinhole_radial_slope,
    check_model,
)


def _intrinsics_jacobian(K: torch.Tensor, D: torch.Tensor) -> torch.Tensor:
    """``d(u,v)/d(xd,yd) @ D``: K's 2x2 linear part (fx, skew, fy) applied to D (N,2,3)."""
    fx, skew, fy = K[0, 0], K[0, 1], K[1, 1]
    row_u = fx * D[:, 0] + skew * D[:, 1]
    row_v = fy * D[:, 1]
    return torch.stack([row_u, row_v], dim=1)


def _pinhole_normalised_jacobian(points: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """``d(xd, yd)/d(X, Y, Z)`` (N,2,3) of the radial-tangential model; d = (k1 k2 p1 p2 k3)."""
    X, Y, Z = points.unbind(-1)
    Z_safe = torch.where(Z.abs() > 0, Z, torch.ones_like(Z))
    x, y = X / Z_safe, Y / Z_safe
    r2 = x * x + y * y
    radial = _pinhole_radial(r2, d)
    slope = _pinhole_radial_slope(r2, d)
    p1, p2 = d[..., 2], d[..., 3]
    dxd_dx = radial + 2 * x * x * slope + 2 * p1 * y + 6 * p2 * x
    dxd_dy = 2 * x * y * slope + 2 * p1 * x + 2 * p2 * y
    dyd_dx = 2 * x * y * slope + 2 * p1 * x + 2 * p2 * y
    dyd_dy = radial + 2 * y * y * slope + 6 * p1 * y + 2 * p2 * x
    inv_z = 1.0 / Z_safe
    zero = torch.zeros_like(X)
    # d(x, y)/d(X, Y, Z)
    dx = torch.stack([inv_z, zero, -x * inv_z], dim=-1)
    dy = torch.stack([zero, inv_z, -y * inv_z], dim=-1)
    row_x = dxd_dx[:, None] * dx + dxd_dy[:, None] * dy
    row_y = dyd_dx[:, None] * dx + dyd_dy[:, None] * dy
    return torch.stack([row_x, row_y], dim=1)


def _fisheye_normalised_jacobian(points: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """``d(xd, yd)/d(X, Y, Z)`` (N,2,3) of the fisheye model, valid past 90 degrees off-axis.

    ``xd = s X, yd = s Y`` with ``s = theta_d(theta) / rho``, ``rho = |(X, Y)|`` and
    ``theta = atan2(rho, Z)``. On the optical axis the limit ``s = 1/Z`` (pinhole-like) is used.
    """
    X, Y, Z = points.unbind(-1)
    rho2 = X * X + Y * Y
    eps2 = torch.finfo(points.dtype).eps ** 2
    off_axis = rho2 > eps2 * (Z * Z)
    rho = torch.sqrt(torch.where(off_axis, rho2, torch.ones_like(rho2)))
    range2 = rho * rho + Z * Z
    theta = torch.atan2(rho, Z)
    theta_d = _fisheye_theta_d(theta, d)
    dtheta_d = _fisheye_dtheta_d(theta, d)
    s = theta_d / rho
    # ds/dq = theta_d'(theta) dtheta/dq / rho - theta_d / rho^2 drho/dq
    dtheta = torch.stack([Z * X / (rho * range2), Z * Y / (rho * range2), -rho / range2], dim=-1)
    drho = torch.stack([X / rho, Y / rho, torch.zeros_like(X)], dim=-1)
    ds = (dtheta_d / rho)[:, None] * dtheta - (theta_d / (rho * rho))[:, None] * drho
    eye_x = torch.stack([s, torch.zeros_like(s), torch.zeros_like(s)], dim=-1)
    eye_y = torch.stack([torch.zeros_like(s), s, torch.zeros_like(s)], dim=-1)
    general = torch.stack([eye_x + X[:, None] * ds, eye_y + Y[:, None] * ds], dim=1)
    # on the axis: the pinhole limit (theta ~ rho/Z, theta_d ~ theta for any k1..k4)
    Z_safe = torch.where(Z.abs() > 0, Z, torch.ones_like(Z))
    zero = torch.zeros_like(X)
    inv_z = 1.0 / Z_safe
    axis = torch.stack([
        torch.stack([inv_z, zero, -X * inv_z * inv_z], dim=-1),
        torch.stack([zero, inv_z, -Y * inv_z * inv_z], dim=-1),
    ], dim=1)
    return torch.where(off_axis[:, None, None], general, axis)


def projection_jacobian(points_cam: torch.Tensor, K: torch.Tensor, dist: torch.Tensor, model: str) -> torch.Tensor:
    """``d (u, v) / d (X, Y, Z)`` of :func:`~egorelight_cli.geometry.cameras.project`.

    Args:
        points_cam: (N,3) camera-frame points, metres (float32 or float64 tensor).
        K: (3,3) intrinsics, pixels.
        dist: (n,) distortion coefficients of ``model`` (zero-padded like ``project``).
        model: ``"pinhole"`` or ``"fisheye"``.

    Returns:
        (N,2,3) pixels per metre, same dtype and device as ``points_cam``; differentiable with
        respect to every input. Points where the projection is invalid (behind a pinhole, past
        the fisheye's monotonic range) get finite but meaningless values: mask them with
        ``project(..., return_valid=True)``.
    """
    check_model(model)
    K = torch.as_tensor(K).to(points_cam)
    d = _pad_dist(torch.as_tensor(dist).to(points_cam).reshape(-1), model)
    if model == "pinhole":
        D = _pinhole_normalised_jacobian(points_cam, d)
    else:
        D = _fisheye_normalised_jacobian(points_cam, d)
    return _intrinsics_jacobian(K, D)
