"""Image quality for relit renders: a fixed tone mapping, PSNR and SSIM (differentiable, torch).

The paper scores relit images with PSNR, SSIM x100, LPIPS x100 and FID without saying how the
HDR renders were mapped to display values (``../shared/notes/appearance.md`` Sec. 1.6). This tool
fixes one documented mapping, :func:`tonemap_for_metrics`: a constant exposure, the sRGB curve,
clipped to [0, 1]. SSIM is Wang et al. 2004 with an 11x11 Gaussian window (sigma 1.5),
``K1 = 0.01``, ``K2 = 0.03`` and population statistics -- the settings of scikit-image's
``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``, which
the tests use as the oracle; like it, the window's border is cropped before averaging. With a
mask, the SSIM map is averaged over the masked pixels instead.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

SSIM_SIGMA = 1.5
SSIM_RADIUS = 5  # int(3.5 sigma + 0.5): scipy's gaussian_filter truncation, as scikit-image uses
K1, K2 = 0.01, 0.03


def tonemap_for_metrics(linear: torch.Tensor, exposure: float = 1.0) -> torch.Tensor:
    """Linear radiance (...) -> display values in [0,1]: ``srgb(clip(exposure x, 0, 1))``."""
    x = (linear * exposure).clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None, data_range: float = 1.0) -> torch.Tensor:
    """PSNR in dB of images (H,W,C) in [0, data_range], over ``mask`` (H,W) pixels when given."""
    squared = (a - b) ** 2
    mse = squared.mean() if mask is None else squared[mask].mean()
    return 10.0 * torch.log10(data_range ** 2 / mse.clamp_min(1e-20))


def ssim_box(mask: torch.Tensor, margin: int = 8) -> tuple[slice, slice]:
    """(rows, cols) slices of the bounding box of ``mask`` (H,W) bool grown by ``margin`` pixels and,
    where it is smaller, to the SSIM window (``2 * SSIM_RADIUS + 1`` pixels a side), clipped to the
    image: a box :func:`ssim` can always be computed in. An empty mask gives the whole image."""
    rows, cols = torch.nonzero(mask, as_tuple=True)
    if len(rows) == 0:
        return slice(0, mask.shape[0]), slice(0, mask.shape[1])
    side = 2 * SSIM_RADIUS + 1

    def span(lo: int, hi: int, size: int) -> slice:  # [lo, hi) grown to `side`, shifted inside [0, size)
        lo, hi = max(lo - margin, 0), min(hi + margin, size)
        missing = max(side - (hi - lo), 0)
        lo = max(lo - (missing + 1) // 2, 0)
        hi = min(max(hi + missing // 2, lo + side), size)
        return slice(max(min(lo, hi - side), 0), hi)

    return span(int(rows.min()), int(rows.max()) + 1, mask.shape[0]), span(int(cols.min()), int(cols.max()) + 1,
                                                                             mask.shape[1])


def _gaussian_window(dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=dtype)
    w = torch.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return w / w.sum()


def _blur(x: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of (C,H,W), 'valid' (no padding: the border is cropped anyway)."""
    w = _gaussian_window(x.dtype)
    x = F.conv2d(x[:, None], w.view(1, 1, 1, -1))
    return F.conv2d(x, w.view(1, 1, -1, 1))[:, 0]


def ssim_map(a: torch.Tensor, b: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """(H - 10, W - 10) SSIM of images (H,W,C), averaged over channels (border of 5 cropped)."""
    x, y = a.permute(2, 0, 1), b.permute(2, 0, 1)
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    mu_x, mu_y = _blur(x), _blur(y)
    var_x = _blur(x * x) - mu_x ** 2
    var_y = _blur(y * y) - mu_y ** 2
    cov = _blur(x * y) - mu_x * mu_y
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2))
    return s.mean(dim=0)


def masked_ssim_sum(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor,
                    data_range: float = 1.0) -> tuple[torch.Tensor, int]:
    """(sum of the SSIM map over the ``mask`` (H,W) pixels inside the cropped border, their count) of
    images (H,W,C): what :func:`ssim` averages, for pooling over several images."""
    inner = mask[SSIM_RADIUS:-SSIM_RADIUS, SSIM_RADIUS:-SSIM_RADIUS]
    return ssim_map(a, b, data_range)[inner].sum(), int(inner.sum())


def ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None, data_range: float = 1.0) -> torch.Tensor:
    """Mean SSIM of images (H,W,C); with ``mask`` (H,W) the mean over masked pixels (inside the crop)."""
    if mask is None:
        return ssim_map(a, b, data_range).mean()
    total, count = masked_ssim_sum(a, b, mask, data_range)
    return total / count if count else torch.tensor(math.nan, dtype=total.dtype)
