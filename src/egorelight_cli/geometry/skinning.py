"""Skinning: linear blend skinning (LBS), dual quaternion skinning (DQS) and their inverses.

The paper's posing function ``W(V, K(theta, B), W)`` (Sec. "Mesh-based Geometry Model") is DQS
(Kavan et al. 2008) with the DDC hemisphere rule: each influence's dual quaternion is flipped to
the hemisphere of the vertex's largest-weight influence, the signed dual quaternions are blended
with the skinning weights, and the blend is normalised by the norm of its real part.

Inputs:
    * ``bone_T``: (...,B,4,4) skinning transforms that map rest-pose positions to posed ones
      (``G_b(theta) @ inv(G_b(rest))``, see :func:`egorelight_cli.geometry.skeleton.bone_transforms`).
    * ``weights``: (V,B) skinning weights, rows summing to 1 (numpy or torch). Internally they
      are reduced to sparse influences (V,K), K = the largest number of non-zero weights of
      any vertex (6 for DDC characters), sorted by decreasing weight; this is exact, not a
      truncation.

Implementation (measured in ``bench/bench_skinning.py``): for constant weights (numpy, or a
tensor that does not require grad) the blends are sparse (V,B) matrix products with the
frames in the columns; for DQS the sign rule is folded into the sparse matrix by blending
*(main bone, bone)* pairs: every pair's signed dual quaternion is computed once per frame, and
a constant sparse (V,P) matrix blends them. Plans for numpy weights are cached per array. A
weights tensor that requires grad uses a gather of the K influences instead (differentiable
in the weights too). Both paths are differentiable in the transforms and points.

The inverse (the paper's ``W^-1``, used to unwarp posed-space residuals to the canonical space)
inverts the blended per-vertex transform returned by :func:`skinning_transforms`.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.rotations import (
    dual_quaternion_from_rigid,
    dual_quaternion_normalize,
    dual_quaternion_translation,
    make_transform,
    quaternion_rotate,
    quaternion_to_matrix,
    transform_directions,
    transform_points,
)

SKINNING_METHODS = ("dqs", "lbs")

_ARRAY_CACHE: dict[int, tuple[weakref.ref, dict]] = {}  # id(array) -> (ref, {key: value})


def _array_cache(array: np.ndarray) -> dict:
    """A per-numpy-array cache (arrays are unhashable; keyed by id, dropped when it dies)."""
    key = id(array)
    entry = _ARRAY_CACHE.get(key)
    if entry is None or entry[0]() is not array:
        entry = (weakref.ref(array, lambda _r, k=key: _ARRAY_CACHE.pop(k, None)), {})
        _ARRAY_CACHE[key] = entry
    return entry[1]


def _influences_from_dense(weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    if weights.ndim != 2:
        raise EgorelightError(f"skinning weights have shape {tuple(weights.shape)}, expected (V, B)")
    k = max(int((weights != 0).sum(-1).max().item()) if weights.numel() else 1, 1)
    weight, index = torch.topk(weights.detach(), k, dim=-1, largest=True, sorted=True)
    if weights.requires_grad:
        weight = torch.gather(weights, -1, index)
    # padding slots (weight 0) point at the vertex's main bone: harmless for the sign rule
    index = torch.where(weight != 0, index, index[:, :1])
    return index, weight


def skinning_influences(weights, dtype: torch.dtype = torch.float32,
                        device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Sparse influences of a dense (V,B) skinning weight matrix.

    Results for numpy inputs are cached per array object, dtype and device.

    Args:
        weights: (V,B) numpy array or tensor.
        dtype, device: of the returned weights.
    Returns:
        ``(index (V,K) int64, weight (V,K))``, sorted by decreasing weight per vertex; slot 0
        is the vertex's largest influence; padding has weight 0.
    """
    device = torch.device(device)
    if isinstance(weights, np.ndarray):
        per_array = _array_cache(weights)
        key = ("influences", dtype, device)
        if key not in per_array:
            per_array[key] = _influences_from_dense(torch.as_tensor(weights, dtype=dtype, device=device))
        return per_array[key]
    return _influences_from_dense(torch.as_tensor(weights).to(dtype=dtype, device=device))


@dataclass(frozen=True)
class _SkinPlan:
    """Sparse blending matrices for constant skinning weights."""

    lbs: torch.Tensor  # (V,B) sparse COO
    pair_main: torch.Tensor  # (P,) main bone of each (main, bone) pair
    pair_bone: torch.Tensor  # (P,) bone of each pair
    dqs: torch.Tensor  # (V,P) sparse COO


def _build_plan(weights: torch.Tensor) -> _SkinPlan:
    index, weight = _influences_from_dense(weights)
    V, K = index.shape
    B = weights.shape[1]
    rows = torch.arange(V, device=index.device).repeat_interleave(K)
    keep = weight.reshape(-1) != 0
    rows, bones, vals = rows[keep], index.reshape(-1)[keep], weight.reshape(-1)[keep]
    mains = index[:, 0].repeat_interleave(K)[keep]
    pairs, pair_col = torch.unique(mains * B + bones, return_inverse=True)

    def sparse(cols: torch.Tensor, ncols: int) -> torch.Tensor:
        return torch.sparse_coo_tensor(torch.stack([rows, cols]), vals, (V, ncols), check_invariants=True).coalesce()

    return _SkinPlan(lbs=sparse(bones, B), pair_main=pairs // B, pair_bone=pairs % B, dqs=sparse(pair_col, len(pairs)))


def _skin_plan(weights, dtype: torch.dtype, device: torch.device) -> _SkinPlan | None:
    """The sparse plan for constant weights (cached for numpy), None for weights requiring grad."""
    if isinstance(weights, np.ndarray):
        per_array = _array_cache(weights)
        key = ("plan", dtype, device)
        if key not in per_array:
            per_array[key] = _build_plan(torch.as_tensor(weights, dtype=dtype, device=device))
        return per_array[key]
    weights = torch.as_tensor(weights)
    if weights.requires_grad:
        return None
    return _build_plan(weights.to(dtype=dtype, device=device))


def sparse_blend(matrix: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Rows of a sparse (M,N) matrix applied to per-item values: ``out_m = sum_n A_mn values_n``.

    The leading batch dimensions of ``values`` go into the columns of one sparse matmul.

    Args:
        matrix: (M,N) sparse COO tensor.
        values: (...,N,C).
    Returns:
        (...,M,C).
    """
    batch, (N, C) = values.shape[:-2], values.shape[-2:]
    M = matrix.shape[0]
    X = values.reshape(-1, N, C).permute(1, 0, 2).reshape(N, -1)
    Y = torch.sparse.mm(matrix, X)
    return Y.reshape(M, -1, C).permute(1, 0, 2).reshape(batch + (M, C))


def _gather_influences(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(...,B,C) per-bone values -> (...,V,K,C) per-vertex-influence values."""
    V, K = index.shape
    return values.index_select(-2, index.reshape(-1)).unflatten(-2, (V, K))


def append_homogeneous_row(top: torch.Tensor) -> torch.Tensor:
    """(...,3,4) -> (...,4,4) with the homogeneous row (0, 0, 0, 1)."""
    bottom = torch.zeros(top.shape[:-2] + (1, 4), dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], -2)


def _blend_linear_top(bone_T: torch.Tensor, weights) -> torch.Tensor:
    """(...,B,4,4) -> (...,V,3,4): the top rows of the LBS-blended transforms."""
    top = bone_T[..., :3, :].flatten(-2)  # (...,B,12)
    plan = _skin_plan(weights, bone_T.dtype, bone_T.device)
    if plan is not None:
        blended = sparse_blend(plan.lbs, top)
    else:
        index, weight = skinning_influences(weights, bone_T.dtype, bone_T.device)
        blended = torch.einsum("...vkc,vk->...vc", _gather_influences(top, index), weight)
    return blended.unflatten(-1, (3, 4))


def blend_linear(bone_T: torch.Tensor, weights) -> torch.Tensor:
    """LBS blend of bone transforms per vertex: ``M_v = sum_b w_vb T_b``.

    Args:
        bone_T: (...,B,4,4).
        weights: (V,B) skinning weights (see module doc).
    Returns:
        (...,V,4,4) blended affine transforms (not rigid in general).
    """
    return append_homogeneous_row(_blend_linear_top(bone_T, weights))


def blend_dual_quaternions(bone_T: torch.Tensor, weights) -> tuple[torch.Tensor, torch.Tensor]:
    """DQS blend of rigid bone transforms (see :func:`dual_quaternion_blend`).

    Args:
        bone_T: (...,B,4,4) rigid bone transforms.
        weights: (V,B) skinning weights.
    Returns:
        ``(real, dual)`` (...,V,4) unit dual quaternions.
    """
    real, dual = dual_quaternion_from_rigid(bone_T)
    return dual_quaternion_blend(real, dual, weights)


def dual_quaternion_blend(real: torch.Tensor, dual: torch.Tensor, weights) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-vertex DQS blend of per-bone dual quaternions with the hemisphere sign fix.

    Each influence's dual quaternion is negated when its real part has a negative dot product
    with the real part of the vertex's largest-weight influence; the signed dual quaternions
    are summed with the weights and divided by the norm of the blended real part. The result
    is therefore the same whichever sign each bone's dual quaternion has.

    Args:
        real, dual: (...,B,4) per-bone unit dual quaternions.
        weights: (V,B) skinning weights.
    Returns:
        ``(real, dual)`` (...,V,4) unit dual quaternions.
    """
    dq = torch.cat([real, dual], -1)  # (...,B,8)
    plan = _skin_plan(weights, real.dtype, real.device)
    if plan is not None:
        bone = dq.index_select(-2, plan.pair_bone)  # (...,P,8)
        dots = (real.index_select(-2, plan.pair_main) * bone[..., :4]).sum(-1, keepdim=True)
        blended = sparse_blend(plan.dqs, torch.where(dots < 0, -bone, bone))
    else:
        index, weight = skinning_influences(weights, real.dtype, real.device)
        dq = _gather_influences(dq, index)  # (...,V,K,8)
        dots = torch.einsum("...vkc,...vc->...vk", dq[..., :4], dq[..., 0, :4])  # vs. the main influence
        blended = torch.einsum("...vk,...vkc->...vc", torch.where(dots < 0, -weight, weight), dq)
    return dual_quaternion_normalize(blended[..., :4], blended[..., 4:])


def skinning_transforms(bone_T: torch.Tensor, weights, method: str = "dqs") -> torch.Tensor:
    """Blended per-vertex transforms (rest -> posed) for ``method`` 'dqs' (rigid) or 'lbs' (affine).

    Args:
        bone_T: (...,B,4,4).
        weights: (V,B).
        method: 'dqs' or 'lbs'.
    Returns:
        (...,V,4,4).
    """
    if method == "lbs":
        return blend_linear(bone_T, weights)
    if method == "dqs":
        real, dual = blend_dual_quaternions(bone_T, weights)
        return make_transform(quaternion_to_matrix(real), dual_quaternion_translation(real, dual))
    raise EgorelightError(f"unknown skinning method {method!r}, expected one of {SKINNING_METHODS}")


def linear_blend_skinning(points: torch.Tensor, bone_T: torch.Tensor, weights) -> torch.Tensor:
    """LBS: ``p'_v = sum_b w_vb T_b p_v``.

    Args:
        points: (...,V,3) rest-pose (canonical) positions, metres.
        bone_T: (...,B,4,4) skinning transforms.
        weights: (V,B).
    Returns:
        (...,V,3) posed positions, metres.
    """
    return transform_points(_blend_linear_top(bone_T, weights), points)


def dual_quaternion_skinning(points: torch.Tensor, bone_T: torch.Tensor, weights) -> torch.Tensor:
    """DQS with the DDC hemisphere sign fix (see :func:`blend_dual_quaternions`).

    Args:
        points: (...,V,3) rest-pose positions, metres.
        bone_T: (...,B,4,4) rigid skinning transforms.
        weights: (V,B).
    Returns:
        (...,V,3) posed positions, metres.
    """
    real, dual = blend_dual_quaternions(bone_T, weights)
    return quaternion_rotate(real, points) + dual_quaternion_translation(real, dual)


def skin_points(points: torch.Tensor, bone_T: torch.Tensor, weights, method: str = "dqs") -> torch.Tensor:
    """:func:`dual_quaternion_skinning` or :func:`linear_blend_skinning` by name; shapes as there."""
    if method == "dqs":
        return dual_quaternion_skinning(points, bone_T, weights)
    if method == "lbs":
        return linear_blend_skinning(points, bone_T, weights)
    raise EgorelightError(f"unknown skinning method {method!r}, expected one of {SKINNING_METHODS}")


def _normalize(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(eps)


def skin_directions(directions: torch.Tensor, bone_T: torch.Tensor, weights, method: str = "dqs",
                    normalize: bool = True) -> torch.Tensor:
    """Skin directions (e.g. normals) with the linear part of the blended transform only.

    For DQS this is the blended rotation (exact for normals). For LBS it is the blended 3x3
    matrix (the usual approximation for normals; renormalised).

    Args:
        directions: (...,V,3) rest-pose directions.
        bone_T: (...,B,4,4).
        weights: (V,B).
        method: 'dqs' or 'lbs'.
        normalize: return unit vectors.
    Returns:
        (...,V,3).
    """
    if method == "dqs":
        real, _ = blend_dual_quaternions(bone_T, weights)
        out = quaternion_rotate(real, directions)
    else:
        out = transform_directions(skinning_transforms(bone_T, weights, method), directions)
    return _normalize(out) if normalize else out


def inverse_skinning_points(points: torch.Tensor, vertex_T: torch.Tensor, rigid: bool = False) -> torch.Tensor:
    """The paper's ``W^-1`` for points: map posed points back to the canonical (rest) space.

    ``p_canonical = A_v^-1 (p - t_v)`` with ``vertex_T = [[A_v, t_v], [0, 1]]`` the blended
    per-vertex transform of :func:`skinning_transforms` (or of graph posing).

    Args:
        points: (...,V,3) posed-space points, metres.
        vertex_T: (...,V,4,4) per-vertex rest -> posed transforms.
        rigid: ``A_v`` is a rotation (DQS): use its transpose instead of a general solve.
    Returns:
        (...,V,3) canonical-space points, metres.
    """
    A, t = vertex_T[..., :3, :3], vertex_T[..., :3, 3]
    local = (points - t)[..., None]
    if rigid:
        return (A.transpose(-1, -2) @ local)[..., 0]
    return torch.linalg.solve(A, local)[..., 0]


def inverse_skinning_directions(directions: torch.Tensor, vertex_T: torch.Tensor, rigid: bool = False,
                                normalize: bool = False) -> torch.Tensor:
    """``W^-1`` for directions (e.g. displacement vectors or normals): ``A_v^-1 d``.

    Args:
        directions: (...,V,3) posed-space vectors.
        vertex_T: (...,V,4,4) per-vertex rest -> posed transforms.
        rigid: ``A_v`` is a rotation (DQS): use its transpose.
        normalize: return unit vectors (for normals).
    Returns:
        (...,V,3) canonical-space vectors.
    """
    A = vertex_T[..., :3, :3]
    d = directions[..., None]
    out = (A.transpose(-1, -2) @ d)[..., 0] if rigid else torch.linalg.solve(A, d)[..., 0]
    return _normalize(out) if normalize else out
