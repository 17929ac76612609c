"""Face and vertex normals of triangle meshes (batched, differentiable).

Counter-clockwise triangles (seen from outside) give outward normals:
``n = (v1 - v0) x (v2 - v0)``. Every function takes torch tensors (and keeps their dtype and
autograd graph) or numpy arrays (computed in float64, returned as numpy float64).
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from egorelight_cli.geometry.rotations import cross


def _numpy_in_numpy_out(func):
    """Let a torch function take numpy vertices: float64 in, numpy float64 out."""
    @functools.wraps(func)
    def wrapper(vertices, faces, *args, **kwargs):
        if torch.is_tensor(vertices):
            return func(vertices, faces, *args, **kwargs)
        result = func(torch.as_tensor(np.asarray(vertices, dtype=np.float64)), faces, *args, **kwargs)
        return result.numpy()
    return wrapper


def _faces_tensor(faces, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(faces) if not torch.is_tensor(faces) else faces, dtype=torch.int64, device=device).reshape(-1, 3)


def _normalize(v: torch.Tensor, eps: float) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(eps)


@_numpy_in_numpy_out
def face_area_normals(vertices: torch.Tensor, faces) -> torch.Tensor:
    """Unnormalised face normals, ``(v1 - v0) x (v2 - v0)`` (length = twice the face area).

    Args:
        vertices: (...,V,3).
        faces: (F,3) int (numpy or tensor).
    Returns:
        (...,F,3) in squared vertex units.
    """
    f = _faces_tensor(faces, vertices.device)
    v0 = vertices.index_select(-2, f[:, 0])
    v1 = vertices.index_select(-2, f[:, 1])
    v2 = vertices.index_select(-2, f[:, 2])
    return cross(v1 - v0, v2 - v0)


@_numpy_in_numpy_out
def face_normals(vertices: torch.Tensor, faces, eps: float = 1e-20) -> torch.Tensor:
    """Unit face normals; degenerate faces give zero vectors.

    Args:
        vertices: (...,V,3).
        faces: (F,3).
        eps: norm floor.
    Returns:
        (...,F,3).
    """
    return _normalize(face_area_normals.__wrapped__(vertices, faces), eps)


@_numpy_in_numpy_out
def vertex_normals(vertices: torch.Tensor, faces, eps: float = 1e-20) -> torch.Tensor:
    """Area-weighted unit vertex normals (sum of incident face area normals, normalised).

    Vertices without faces get zero vectors.

    Args:
        vertices: (...,V,3).
        faces: (F,3).
        eps: norm floor.
    Returns:
        (...,V,3).
    """
    f = _faces_tensor(faces, vertices.device)
    fn = face_area_normals.__wrapped__(vertices, f)  # (...,F,3)
    acc = torch.zeros_like(vertices)
    for corner in range(3):
        acc = acc.index_add(-2, f[:, corner], fn)
    return _normalize(acc, eps)
