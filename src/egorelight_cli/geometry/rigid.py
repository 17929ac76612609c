"""Small numpy helpers for rigid transforms (4,4) and rotations (3,3), float64, metres.

Parameter vectors are ``(rx, ry, rz, tx, ty, tz)``: a rotation vector (radians) and a translation.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def rigid_from_vector(v) -> np.ndarray:
    """(4,4) rigid transform from a 6-vector (rotation vector, translation); (...,6) -> (...,4,4)."""
    v = np.asarray(v, dtype=np.float64)
    T = np.zeros(v.shape[:-1] + (4, 4))
    T[..., :3, :3] = Rotation.from_rotvec(v[..., :3].reshape(-1, 3)).as_matrix().reshape(v.shape[:-1] + (3, 3))
    T[..., :3, 3] = v[..., 3:]
    T[..., 3, 3] = 1.0
    return T


def vector_from_rigid(T) -> np.ndarray:
    """6-vector (rotation vector, translation) of rigid transforms (...,4,4) -> (...,6)."""
    T = np.asarray(T, dtype=np.float64)
    rot = Rotation.from_matrix(T[..., :3, :3].reshape(-1, 3, 3)).as_rotvec().reshape(T.shape[:-2] + (3,))
    return np.concatenate([rot, T[..., :3, 3]], axis=-1)


def rigid(R, t) -> np.ndarray:
    """(4,4) from a rotation (3,3) and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, np.float64)
    T[:3, 3] = np.asarray(t, np.float64).reshape(3)
    return T


def rotation_angle_deg(R_a, R_b) -> np.ndarray:
    """Angle (degrees) of ``R_a^T R_b`` for rotations (...,3,3)."""
    R = np.swapaxes(np.asarray(R_a, np.float64), -1, -2) @ np.asarray(R_b, np.float64)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def project_to_rotation(M) -> np.ndarray:
    """The closest rotations (...,3,3) to 3x3 matrices (...,3,3): the rotation of the polar
    decomposition (SVD, determinant +1)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, np.float64))
    U[..., :, 2] *= np.sign(np.linalg.det(U @ Vt))[..., None]
    return U @ Vt


def mean_rotation(Rs) -> np.ndarray:
    """Chordal L2 mean of rotations (N,3,3)."""
    return project_to_rotation(np.sum(np.asarray(Rs, np.float64), axis=0))


def mean_frame_change(T_a_from_x, T_b_from_x) -> np.ndarray:
    """(4,4) rigid ``T_a_from_b`` with ``T_a_from_x[i] ~ T_a_from_b @ T_b_from_x[i]`` for poses
    (N,4,4) of one moving body in two world frames a and b: rotation the chordal mean of the
    per-pose ``R_a R_b^T``, translation the least-squares one for that rotation (same units)."""
    Ta, Tb = np.asarray(T_a_from_x, np.float64), np.asarray(T_b_from_x, np.float64)
    R = mean_rotation(Ta[:, :3, :3] @ np.swapaxes(Tb[:, :3, :3], 1, 2))
    return rigid(R, np.mean(Ta[:, :3, 3] - Tb[:, :3, 3] @ R.T, axis=0))


def kabsch_rotations(P: np.ndarray, Q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted rotations R (T,3,3) with ``R P + t ~ Q``; P (K,3), Q (T,K,3), w (T,K)."""
    wsum = w.sum(axis=1, keepdims=True)[..., None]
    pc = (w[..., None] * P).sum(axis=1, keepdims=True) / wsum
    qc = (w[..., None] * Q).sum(axis=1, keepdims=True) / wsum
    H = np.einsum("tk,tki,tkj->tij", w, P - pc, Q - qc)
    return project_to_rotation(np.swapaxes(H, 1, 2))


def kabsch(source, target, weights=None) -> np.ndarray:
    """(4,4) rigid ``T`` minimising ``sum w |T source_i - target_i|^2`` for points (N,3), N >= 3."""
    P, Q = np.asarray(source, np.float64), np.asarray(target, np.float64)
    w = np.ones(len(P)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    mp, mq = w @ P, w @ Q
    R = kabsch_rotations(P, Q[None], w[None])[0]
    return rigid(R, mq - R @ mp)


def interpolate_poses(T, times, query, extrapolate: bool = False) -> np.ndarray:
    """Poses (M,4,4) at increasing ``times`` (M,) evaluated at ``query`` (N,) -> (N,4,4): slerp
    rotations, linear translations. Outside ``times`` poses are held at the ends, or with
    ``extrapolate`` their translations continue at the end velocities (rotations still held)."""
    T, times, query = np.asarray(T, np.float64), np.asarray(times, np.float64), np.asarray(query, np.float64)
    q = np.clip(query, times[0], times[-1])
    out = np.tile(np.eye(4), (len(query), 1, 1))
    out[:, :3, :3] = Slerp(times, Rotation.from_matrix(T[:, :3, :3]))(q).as_matrix() if len(T) > 1 else T[0, :3, :3]
    for c in range(3):
        out[:, c, 3] = np.interp(q, times, T[:, c, 3])
    if extrapolate and len(T) > 1:
        lo, hi = query < times[0], query > times[-1]
        v0 = (T[1, :3, 3] - T[0, :3, 3]) / (times[1] - times[0])
        v1 = (T[-1, :3, 3] - T[-2, :3, 3]) / (times[-1] - times[-2])
        out[lo, :3, 3] += (query[lo] - times[0])[:, None] * v0
        out[hi, :3, 3] += (query[hi] - times[-1])[:, None] * v1
    return out
