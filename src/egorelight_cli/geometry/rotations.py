"""Rotations, rigid transforms, quaternions and dual quaternions (batched, differentiable).

Conventions:
    * Every function takes leading batch dimensions ``...`` and keeps them.
    * Rotation matrices act on column vectors: ``x' = R @ x``.
    * Quaternions are ``(w, x, y, z)`` (scalar first), Hamilton product.
    * A rigid transform is a 4x4 homogeneous matrix ``[[R, t], [0, 1]]``.
    * A dual quaternion is a pair ``(real, dual)`` of ``(..., 4)`` quaternions; for a rigid
      transform ``(R, t)``: ``real = q(R)`` and ``dual = 0.5 * (0, t) * real``.
    * Euler angles are ``(rx, ry, rz)`` radians composed as ``R = Rz @ Ry @ Rx`` (the DDC
      embedded-graph convention: x is applied first).

Everything works in float32 and float64 and has finite gradients everywhere it is smooth,
including at the zero rotation.
"""

from __future__ import annotations

import numpy as np
import torch

_SMALL_ANGLE_SQ = 1e-8  # below this squared angle Rodrigues uses its Taylor series


def cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product with broadcasting over leading dims; (...,3), (...,3) -> (...,3)."""
    a, b = torch.broadcast_tensors(a, b)
    return torch.linalg.cross(a, b, dim=-1)


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix ``[v]_x`` with ``[v]_x @ u == cross(v, u)``.

    Args:
        v: (...,3).
    Returns:
        (...,3,3).
    """
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(v.shape[:-1] + (3, 3))


def axis_angle_rotation(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotation about a unit ``axis`` by ``angle`` (Rodrigues), for an already-normalised axis.

    Args:
        axis: (...,3) unit vectors (broadcastable against ``angle[..., None]``).
        angle: (...) radians.
    Returns:
        (...,3,3) rotation matrices.
    """
    s = torch.sin(angle)[..., None, None]
    c = torch.cos(angle)[..., None, None]
    K = skew(axis)
    eye = torch.eye(3, dtype=K.dtype, device=K.device)
    return eye + s * K + (1.0 - c) * (K @ K)


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of an axis-angle vector ``omega`` (angle = |omega|, axis = omega/|omega|).

    ``R = I + a [w]_x + b [w]_x^2`` with ``a = sin(t)/t`` and ``b = (1 - cos t)/t^2``; near
    ``t = 0`` the Taylor series is used so values and gradients are exact there too.

    Args:
        axis_angle: (...,3) radians.
    Returns:
        (...,3,3).
    """
    theta_sq = (axis_angle * axis_angle).sum(-1)
    small = theta_sq < _SMALL_ANGLE_SQ
    safe_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    theta = torch.sqrt(safe_sq)
    a = torch.where(small, 1.0 - theta_sq / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta_sq / 24.0, (1.0 - torch.cos(theta)) / safe_sq)
    K = skew(axis_angle)
    eye = torch.eye(3, dtype=K.dtype, device=K.device)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """Axis-angle vector of a rotation matrix (angle in [0, pi]), via the quaternion.

    Args:
        R: (...,3,3).
    Returns:
        (...,3) radians.
    """
    q = matrix_to_quaternion(R)
    q = torch.where(q[..., :1] < 0, -q, q)
    vec = q[..., 1:]
    sin_half = torch.linalg.vector_norm(vec, dim=-1)
    half = torch.atan2(sin_half, q[..., 0])
    small = sin_half < 1e-6
    safe = torch.where(small, torch.ones_like(sin_half), sin_half)
    scale = torch.where(small, 2.0 / q[..., 0].clamp_min(1e-12), 2.0 * half / safe)
    return vec * scale[..., None]


def euler_to_matrix(euler: torch.Tensor) -> torch.Tensor:
    """``R = Rz(rz) @ Ry(ry) @ Rx(rx)`` from Euler angles ``(rx, ry, rz)``.

    Args:
        euler: (...,3) radians, ordered (x, y, z).
    Returns:
        (...,3,3).
    """
    rx, ry, rz = euler.unbind(-1)
    cx, sx = torch.cos(rx), torch.sin(rx)
    cy, sy = torch.cos(ry), torch.sin(ry)
    cz, sz = torch.cos(rz), torch.sin(rz)
    rows = [
        cy * cz, sx * sy * cz - cx * sz, cx * sy * cz + sx * sz,
        cy * sz, sx * sy * sz + cx * cz, cx * sy * sz - sx * cz,
        -sy, sx * cy, cx * cy,
    ]
    return torch.stack(rows, -1).reshape(euler.shape[:-1] + (3, 3))


def matrix_to_euler(R: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`euler_to_matrix`: ``(rx, ry, rz)`` with ``ry`` in [-pi/2, pi/2].

    At gimbal lock (``|ry| = pi/2``) ``rz`` is set to 0.

    Args:
        R: (...,3,3).
    Returns:
        (...,3) radians.
    """
    sy = torch.sqrt(R[..., 0, 0] ** 2 + R[..., 1, 0] ** 2)
    singular = sy < 1e-6
    ry = torch.atan2(-R[..., 2, 0], sy)
    rx = torch.where(singular, torch.atan2(-R[..., 1, 2], R[..., 1, 1]), torch.atan2(R[..., 2, 1], R[..., 2, 2]))
    rz = torch.where(singular, torch.zeros_like(ry), torch.atan2(R[..., 1, 0], R[..., 0, 0]))
    return torch.stack([rx, ry, rz], -1)


# ----------------------------------------------------------------------------------------------
# Quaternions (w, x, y, z)
# ----------------------------------------------------------------------------------------------


def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a * b``.

    Args:
        a, b: (...,4) broadcastable.
    Returns:
        (...,4).
    """
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def quaternion_conjugate(q: torch.Tensor) -> torch.Tensor:
    """``(w, -x, -y, -z)``; (...,4) -> (...,4)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a quaternion (normalised first; zero quaternions give NaN).

    Args:
        q: (...,4) (w, x, y, z).
    Returns:
        (...,3,3).
    """
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, -1).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternion of a rotation matrix (Shepperd's method, branch-free and differentiable).

    Of the four candidate formulas the best-conditioned one is selected per matrix. The sign
    is whatever that formula yields (``q`` and ``-q`` are the same rotation).

    Args:
        R: (...,3,3).
    Returns:
        (...,4) unit quaternions (w, x, y, z).
    """
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    # 4 * q_i^2 for each component
    diag = torch.stack([
        1.0 + m00 + m11 + m22,
        1.0 + m00 - m11 - m22,
        1.0 - m00 + m11 - m22,
        1.0 - m00 - m11 + m22,
    ], -1)
    # candidate quaternions scaled by 4*q_i (row i uses component i as pivot)
    cand = torch.stack([
        torch.stack([diag[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
        torch.stack([m21 - m12, diag[..., 1], m10 + m01, m02 + m20], -1),
        torch.stack([m02 - m20, m10 + m01, diag[..., 2], m12 + m21], -1),
        torch.stack([m10 - m01, m20 + m02, m21 + m12, diag[..., 3]], -1),
    ], -2)
    denom = 2.0 * torch.sqrt(diag.clamp_min(0.1))  # only the chosen pivot (diag >= 1) matters
    cand = cand / denom[..., None]
    best = diag.argmax(-1)
    q = torch.take_along_dim(cand, best[..., None, None].expand(best.shape + (1, 4)), dim=-2)[..., 0, :]
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)


def quaternion_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors by unit quaternions: ``v + 2 u x (u x v + w v)`` with ``q = (w, u)``.

    Args:
        q: (...,4) unit quaternions.
        v: (...,3).
    Returns:
        (...,3).
    """
    w, u = q[..., :1], q[..., 1:]
    return v + 2.0 * cross(u, cross(u, v) + w * v)


# ----------------------------------------------------------------------------------------------
# Rigid transforms
# ----------------------------------------------------------------------------------------------


def make_transform(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``[[R, t], [0, 1]]``.

    Args:
        R: (...,3,3).
        t: (...,3).
    Returns:
        (...,4,4).
    """
    # np.broadcast_shapes, not torch's: its first call imports torch.fx and sympy (~0.35 s a process)
    batch = tuple(np.broadcast_shapes(tuple(R.shape[:-2]), tuple(t.shape[:-1])))
    top = torch.cat([R.expand(batch + (3, 3)), t.expand(batch + (3,))[..., None]], -1)
    bottom = torch.zeros(batch + (1, 4), dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], -2)


def invert_rigid(T):
    """Inverse of rigid transforms, ``[[R^T, -R^T t], [0, 1]]`` (exact transpose form).

    Args:
        T: (...,4,4) with an orthonormal rotation block: a torch tensor (differentiable, same
            dtype and device) or anything numpy reads (float64).
    Returns:
        (...,4,4) of the same kind.
    """
    if isinstance(T, torch.Tensor):
        Rt = T[..., :3, :3].transpose(-1, -2)
        return make_transform(Rt, -(Rt @ T[..., :3, 3:])[..., 0])
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def camera_centre(T_cam_from_x: np.ndarray) -> np.ndarray:
    """(...,3) the camera's centre in frame ``x`` from ``T_cam_from_x`` (...,4,4) rigid (units of its
    translation): the translation of :func:`invert_rigid`."""
    return invert_rigid(np.asarray(T_cam_from_x, np.float64))[..., :3, 3]


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply affine 4x4 (or 3x4) transforms to points: ``T[:3,:3] @ p + T[:3,3]``.

    Args:
        T: (...,4,4) or (...,3,4).
        points: (...,3), broadcastable with ``T``'s batch.
    Returns:
        (...,3).
    """
    return (T[..., :3, :3] @ points[..., None])[..., 0] + T[..., :3, 3]


def transform_directions(T: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Apply only the linear 3x3 block: ``T[:3,:3] @ d``; (...,4,4), (...,3) -> (...,3)."""
    return (T[..., :3, :3] @ directions[..., None])[..., 0]


# ----------------------------------------------------------------------------------------------
# Dual quaternions
# ----------------------------------------------------------------------------------------------


def dual_quaternion_from_rigid(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit dual quaternion of a rigid transform.

    Args:
        T: (...,4,4) rigid transforms (rotation block orthonormal), translations in metres.
    Returns:
        ``(real, dual)``, each (...,4): ``real = q(R)``, ``dual = 0.5 * (0, t) * real``.
    """
    real = matrix_to_quaternion(T[..., :3, :3])
    t = T[..., :3, 3]
    t_quat = torch.cat([torch.zeros_like(t[..., :1]), t], -1)
    dual = 0.5 * quaternion_multiply(t_quat, real)
    return real, dual


def dual_quaternion_normalize(real: torch.Tensor, dual: torch.Tensor, eps: float = 1e-12) -> tuple[torch.Tensor, torch.Tensor]:
    """Divide a (blended) dual quaternion by the norm of its real part (Kavan et al. 2008).

    Args:
        real, dual: (...,4).
        eps: norms below this are treated as ``eps`` (no division by zero).
    Returns:
        ``(real, dual)`` (...,4) with unit real part.
    """
    norm = torch.linalg.vector_norm(real, dim=-1, keepdim=True).clamp_min(eps)
    return real / norm, dual / norm


def dual_quaternion_translation(real: torch.Tensor, dual: torch.Tensor) -> torch.Tensor:
    """Translation ``2 * vec(dual * conj(real))`` of a dual quaternion with unit real part.

    Args:
        real, dual: (...,4).
    Returns:
        (...,3).
    """
    return 2.0 * quaternion_multiply(dual, quaternion_conjugate(real))[..., 1:]


def rigid_from_dual_quaternion(real: torch.Tensor, dual: torch.Tensor) -> torch.Tensor:
    """4x4 rigid transform of a dual quaternion (normalised first).

    Args:
        real, dual: (...,4).
    Returns:
        (...,4,4).
    """
    real, dual = dual_quaternion_normalize(real, dual)
    return make_transform(quaternion_to_matrix(real), dual_quaternion_translation(real, dual))


def dual_quaternion_transform_points(real: torch.Tensor, dual: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply unit dual quaternions (real part of norm 1) to points: ``R p + t``.

    Args:
        real, dual: (...,4).
        points: (...,3).
    Returns:
        (...,3).
    """
    return quaternion_rotate(real, points) + dual_quaternion_translation(real, dual)
