"""Front-to-back alpha compositing of (splat, pixel) pairs, with a closed-form backward.

The pairs come from ``render/gaussian_pairs.py``: grouped by pixel, each pixel's splats front
to back. This is the differentiable core of ``render/gaussians.py``; one autograd node for all
pairs keeps the CPU cost to a few passes over them (autograd on the element-wise graph was
measured 2-3x slower). ``tests/test_gaussians.py`` holds its gradients to autograd through the
dense reference and to finite differences.

Forward, per pair ``i`` of a pixel ``x`` (splat parameters ``(u, v, a, b, c, o)``):

* ``d = x - (u, v)``, ``q = a du^2 + 2 b du dv + c dv^2``, ``alpha_i = min(ALPHA_MAX, o exp(-q/2))``;
* ``T_i = prod_{j<i} (1 - alpha_j)`` (a segmented cumulative sum of ``log(1 - alpha)`` in float64);
* ``w_i = alpha_i T_i``; outputs ``sum_i w_i f_i`` and ``sum_i w_i``.

Backward, with ``g`` the output gradient at the pixel and ``r_i = g . (f_i, 1)``:

* ``dL/df_i = w_i g``;
* ``dL/dalpha_i = T_i r_i - (sum_{j>i} w_j r_j) / (1 - alpha_i)`` (3DGS's backward pass, as a
  segmented suffix sum);
* ``dalpha/dq = -alpha/2`` and ``dalpha/do = alpha/o`` below the clamp, 0 above it.

Per-pixel and per-splat sums use ``index_add_`` (deterministic on the CPU).
"""

from __future__ import annotations

import torch

from egorelight_cli.render.gaussian_projection import ALPHA_MAX, ProjectedGaussians, splat_falloff


def exclusive_segment_cumsum(values: torch.Tensor, segment_start: torch.Tensor) -> torch.Tensor:
    """Per element, the float64 sum of the earlier elements of its (contiguous) segment.

    Args:
        values: (P,) grouped so that each segment is contiguous.
        segment_start: (P,) int64 index of the first element of each element's segment.
    """
    inclusive = torch.cumsum(values.to(torch.float64), 0)
    exclusive = inclusive - values.to(torch.float64)
    return exclusive - exclusive.index_select(0, segment_start)


def splat_parameters(proj: ProjectedGaussians) -> torch.Tensor:
    """(M,6) ``(u, v, a, b, c, opacity)`` per splat: everything a pair needs, gathered at once."""
    return torch.cat([proj.means2d, proj.conics, proj.opacities[:, None]], dim=1)


def pixel_centres(pix: torch.Tensor, width: int, dtype: torch.dtype) -> torch.Tensor:
    """(P,2) pixel centres ``(u, v)`` of flat pixel indices ``v * width + u``."""
    return torch.stack([pix % width, torch.div(pix, width, rounding_mode="floor")], dim=1).to(dtype)


def raw_alpha(du: torch.Tensor, dv: torch.Tensor, pair: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``o exp(-q/2)`` (P,) before the clamp, and ``exp(-q/2)``; pair (P,6) splat parameters."""
    falloff = splat_falloff(du, dv, pair[:, 2], pair[:, 3], pair[:, 4])
    return pair[:, 5] * falloff, falloff


class CompositeSplats(torch.autograd.Function):
    """``apply(params (M,6), features (M,D), gid, pixel_uv, pix, seg_start, seg_last, num_pixels)``.

    ``params`` rows are ``(u, v, a, b, c, opacity)``; ``pixel_uv`` (P,2) are the pairs' pixel
    centres; returns (num_pixels, D+1): per pixel the composited features and, last, the alpha.
    Pairs must each reach ``ALPHA_MIN`` (as ``find_pairs`` guarantees): no threshold is
    applied here.
    """

    @staticmethod
    def forward(ctx, params, features, gid, pixel_uv, pix, seg_start, seg_last, num_pixels):
        pair = params.index_select(0, gid)
        du, dv = pixel_uv[:, 0] - pair[:, 0], pixel_uv[:, 1] - pair[:, 1]
        raw, falloff = raw_alpha(du, dv, pair)
        alpha = raw.clamp_max(ALPHA_MAX)
        log1m = torch.log1p(-alpha.to(torch.float64))
        transmittance = torch.exp(exclusive_segment_cumsum(log1m, seg_start)).to(alpha.dtype)
        weight = alpha * transmittance
        # features with a column of ones, so one gather and one scatter give colour and alpha
        pair_features = torch.cat([features, features.new_ones(features.shape[0], 1)], 1).index_select(0, gid)
        out = features.new_zeros(num_pixels, pair_features.shape[1]).index_add_(0, pix, weight[:, None] * pair_features)
        ctx.save_for_backward(params, pair_features, gid, pix, seg_last, du, dv, raw, falloff, transmittance, weight)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        params, pair_features, gid, pix, seg_last, du, dv, raw, falloff, transmittance, weight = ctx.saved_tensors
        grad_pair = grad_out.contiguous().index_select(0, pix)  # (P,D+1)
        grad_weight = (grad_pair * pair_features).sum(1)
        alpha = raw.clamp_max(ALPHA_MAX)
        inclusive = torch.cumsum((weight * grad_weight).to(torch.float64), 0)
        behind = (inclusive.index_select(0, seg_last) - inclusive).to(alpha.dtype)
        grad_alpha = transmittance * grad_weight - behind / (1.0 - alpha)
        grad_alpha = torch.where(raw < ALPHA_MAX, grad_alpha, torch.zeros_like(grad_alpha))
        grad_q = -0.5 * grad_alpha * alpha
        # Per pair, the moments whose per-splat sums give every gradient: the splat's (a, b, c)
        # are constant over its pairs, so they multiply in after the sum (cheap, per splat).
        D = pair_features.shape[1] - 1
        per_pair = du.new_empty(du.shape[0], 6 + D)
        torch.mul(grad_q, du, out=per_pair[:, 0])
        torch.mul(grad_q, dv, out=per_pair[:, 1])
        torch.mul(per_pair[:, 0], du, out=per_pair[:, 2])
        torch.mul(per_pair[:, 0], dv, out=per_pair[:, 3])
        torch.mul(per_pair[:, 1], dv, out=per_pair[:, 4])
        torch.mul(grad_alpha, falloff, out=per_pair[:, 5])
        torch.mul(weight[:, None], grad_pair[:, :D], out=per_pair[:, 6:])
        sums = per_pair.new_zeros(params.shape[0], 6 + D).index_add_(0, gid, per_pair)
        q_du, q_dv, q_du2, q_dudv, q_dv2, grad_opacity = sums[:, :6].unbind(1)
        a, b, c = params[:, 2], params[:, 3], params[:, 4]
        grad_params = torch.stack([
            -2.0 * (a * q_du + b * q_dv),  # du = x - u, so d/du_mean = -dq/d(du)
            -2.0 * (b * q_du + c * q_dv),
            q_du2,
            2.0 * q_dudv,
            q_dv2,
            grad_opacity,
        ], dim=1)
        return grad_params, sums[:, 6:], None, None, None, None, None, None
