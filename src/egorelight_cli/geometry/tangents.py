"""Tangent frames from UVs and tangent-space normal maps.

A face's UV tangent ``dP/du`` is the direction in which its surface moves as ``u`` grows (the
standard per-triangle solution of ``e1 = du1 T + dv1 B``, ``e2 = du2 T + dv2 B``). At a surface
point with (interpolated) unit normal ``n`` the orthonormal tangent frame is

    t = normalize(T - (T . n) n),   b = s * (n x t),   s = sign(du1 dv2 - du2 dv1)

(``s`` = -1 on mirrored UV islands). A tangent-space normal ``m = (m_t, m_b, m_n)`` means the
world normal ``m_t t + m_b b + m_n n``; ``(0, 0, 1)`` is the unperturbed surface. Because the
frame is built from the posed triangle itself, a normal map authored in the rest pose follows the
surface under any deformation.
"""

from __future__ import annotations

import numpy as np


def face_uv_tangents(vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-face ``dP/du`` and UV orientation sign.

    Args:
        vertices: (...,V,3) positions (any leading batch shape).
        faces: (F,3) triangles.
        face_uvs: (F,3,2) per-corner UVs.
    Returns:
        tangent (...,F,3) ``dP/du`` (metres per UV unit; zero for degenerate UV triangles),
        sign (F,) +1 or -1.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    uv = np.asarray(face_uvs, dtype=np.float64)
    p = vertices[..., faces, :]  # (...,F,3,3)
    e1, e2 = p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    safe = np.where(np.abs(det) > 1e-20, det, np.inf)
    tangent = (e1 * d2[:, 1, None] - e2 * d1[:, 1, None]) / safe[:, None]
    return tangent, np.where(det < 0, -1.0, 1.0)


def tangent_frames(normals: np.ndarray, tangents: np.ndarray, signs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal (t, b) (N,3) each from unit normals (N,3), UV tangents (N,3) and signs (N,).

    Where the tangent is parallel to the normal (or zero) an arbitrary perpendicular is used.
    """
    n = np.asarray(normals, dtype=np.float64)
    t = np.asarray(tangents, dtype=np.float64)
    t = t - np.sum(t * n, axis=-1, keepdims=True) * n
    length = np.linalg.norm(t, axis=-1, keepdims=True)
    fallback = np.cross(n, np.where(np.abs(n[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]))
    t = np.where(length > 1e-12, t / np.maximum(length, 1e-12), fallback / np.linalg.norm(fallback, axis=-1, keepdims=True))
    b = np.asarray(signs, dtype=np.float64)[..., None] * np.cross(n, t)
    return t, b


def world_from_tangent_space(tangent_normals: np.ndarray, normals: np.ndarray, tangents: np.ndarray,
                             signs: np.ndarray) -> np.ndarray:
    """(N,3) unit world normals of tangent-space normals (N,3) at points with unit normals (N,3),
    UV tangents (N,3) and signs (N,)."""
    t, b = tangent_frames(normals, tangents, signs)
    m = np.asarray(tangent_normals, dtype=np.float64)
    out = m[..., :1] * t + m[..., 1:2] * b + m[..., 2:3] * np.asarray(normals, dtype=np.float64)
    return out / np.maximum(np.linalg.norm(out, axis=-1, keepdims=True), 1e-12)


def tangent_space_from_world(world_normals: np.ndarray, normals: np.ndarray, tangents: np.ndarray,
                             signs: np.ndarray) -> np.ndarray:
    """Inverse of :func:`world_from_tangent_space`: (N,3) tangent-space unit normals."""
    t, b = tangent_frames(normals, tangents, signs)
    w = np.asarray(world_normals, dtype=np.float64)
    out = np.stack([np.sum(w * t, -1), np.sum(w * b, -1), np.sum(w * np.asarray(normals, np.float64), -1)], -1)
    return out / np.maximum(np.linalg.norm(out, axis=-1, keepdims=True), 1e-12)
