"""PSNR and SSIM against scikit-image; the metric tone mapping."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorelight_cli.render.image_metrics import SSIM_RADIUS, psnr, ssim, ssim_box, tonemap_for_metrics

skimage_metrics = pytest.importorskip("skimage.metrics")


def _pair(seed: int = 0):
    rng = np.random.default_rng(seed)
    a = np.clip(rng.uniform(0, 1, (40, 36, 3)) * 0.5 + np.linspace(0, 0.5, 36)[None, :, None], 0, 1)
    b = np.clip(a + rng.normal(scale=0.05, size=a.shape), 0, 1)
    return a, b


@pytest.mark.parametrize("seed", [0, 1])
def test_ssim_and_psnr_match_scikit_image(seed):
    a, b = _pair(seed)
    expected_ssim = skimage_metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                                                          use_sample_covariance=False, data_range=1.0,
                                                          channel_axis=-1)
    expected_psnr = skimage_metrics.peak_signal_noise_ratio(a, b, data_range=1.0)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    assert float(ssim(ta, tb)) == pytest.approx(expected_ssim, abs=1e-10)
    assert float(psnr(ta, tb)) == pytest.approx(expected_psnr, abs=1e-9)
    assert float(ssim(ta, ta)) == pytest.approx(1.0, abs=1e-12)


def test_masked_metrics_only_see_the_mask():
    a, b = _pair(2)
    mask = np.zeros(a.shape[:2], bool)
    mask[10:30, 8:28] = True
    b_outside = b.copy()
    b_outside[~mask] = 0.0  # changing pixels far outside the mask (beyond the window) changes nothing
    ta, tb, tc, tm = (torch.from_numpy(x) for x in (a, b, b_outside, mask))
    assert float(psnr(ta, tb, tm)) == pytest.approx(float(psnr(ta, tc, tm)), abs=1e-12)
    inner = np.zeros_like(mask)
    inner[16:24, 14:22] = True  # at least a window radius inside the changed region's border
    assert float(ssim(ta, tb, torch.from_numpy(inner))) == pytest.approx(float(ssim(ta, tc, torch.from_numpy(inner))))


def test_ssim_is_differentiable():
    a, b = (torch.from_numpy(x).requires_grad_(True) for x in _pair(3))
    (1 - ssim(a, b)).backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


def test_tonemap_is_srgb_of_the_clipped_exposure():
    x = torch.tensor([0.0, 0.002, 0.18, 1.0, 5.0])
    out = tonemap_for_metrics(x)
    np.testing.assert_allclose(out.numpy(), [0.0, 12.92 * 0.002, 1.055 * 0.18 ** (1 / 2.4) - 0.055, 1.0, 1.0], rtol=1e-6)


def test_ssim_box_is_the_grown_bounding_box_and_always_fits_the_window():
    side = 2 * SSIM_RADIUS + 1
    mask = torch.zeros(40, 60, dtype=torch.bool)
    mask[12:30, 20:41] = True
    assert ssim_box(mask, margin=3) == (slice(9, 33), slice(17, 44))  # the bounding box, 3 px on each side
    for r, c in ((0, 0), (0, 59), (39, 30), (20, 30)):
        mask = torch.zeros(40, 60, dtype=torch.bool)
        mask[r, c] = True
        rows, cols = ssim_box(mask, margin=2)
        assert rows.stop - rows.start >= side and cols.stop - cols.start >= side
        assert 0 <= rows.start <= r < rows.stop <= 40 and 0 <= cols.start <= c < cols.stop <= 60
    assert ssim_box(torch.zeros(40, 60, dtype=torch.bool)) == (slice(0, 40), slice(0, 60))
