"""Which splats cover which pixels: the (splat, pixel) pair search of ``render/gaussians.py``.

No gradients flow here; the result is index lists that ``render/gaussian_composite.py``
composites differentiably. For every visible splat, front to back, the pixels inside its exact
``ALPHA_MIN`` ellipse are listed row by row (chunked, so at most ``chunk_pairs`` are held
at once); pairs are then grouped by pixel and, per pixel, only a prefix of its front-to-back
list is kept:

* no pair behind the point where the transmittance in front of it is below ``T_MIN`` (3DGS's
  early termination);
* at most ``max_per_pixel`` pairs (the memory bound of the differentiable part: at most
  ``H W max_per_pixel`` pairs). What a cut pixel loses is at most the transmittance left in
  front of its first dropped splat; :class:`RenderStats` records the worst such value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from egorelight_cli.render.gaussian_composite import exclusive_segment_cumsum, pixel_centres, raw_alpha, splat_parameters
from egorelight_cli.render.gaussian_projection import ALPHA_MAX, ALPHA_MIN, ProjectedGaussians

T_MIN = 1e-4  # a splat whose transmittance in front is below this does not contribute (3DGS)
MAX_PER_PIXEL = 256  # default cap on contributing splats per pixel
CHUNK_PAIRS = 1 << 22  # pairs enumerated at once
_SPAN_MARGIN = 1e-4  # pixels: row spans are widened by this, so rounding never drops a pixel


@dataclass
class RenderStats:
    """What the pair search found: counts and the effect of the per-pixel cap."""

    visible_gaussians: int = 0
    pairs: int = 0
    truncated_pixels: int = 0
    max_truncated_transmittance: float = 0.0


@dataclass(frozen=True)
class SplatPairs:
    """Contributing pairs, grouped by pixel (pixel-major), each pixel's splats front to back.

    Attributes:
        gid: (P,) int64 index into the projected splats.
        pix: (P,) int64 flat pixel ``v * width + u``, non-decreasing.
        pixel_uv: (P,2) the pixel centres ``(u, v)``, in the splats' dtype.
        counts: (H*W,) int64 pairs per pixel.
        stats: :class:`RenderStats`.
    """

    gid: torch.Tensor
    pix: torch.Tensor
    pixel_uv: torch.Tensor
    counts: torch.Tensor
    stats: RenderStats

    def segment_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Per pair, the index of the first and of the last pair of its pixel, (P,) each."""
        start = segment_starts(self.counts).index_select(0, self.pix)
        return start, start + self.counts.index_select(0, self.pix) - 1


def segment_starts(counts: torch.Tensor) -> torch.Tensor:
    """Exclusive prefix sum of per-segment counts (S,) -> start offsets (S,)."""
    return torch.cumsum(counts, 0) - counts


def _enumerate_footprints(proj: ProjectedGaussians, first: int, last: int) -> tuple[torch.Tensor, torch.Tensor]:
    """All (Gaussian, flat pixel) pairs inside the ``ALPHA_MIN`` ellipses of Gaussians ``first..last-1``.

    Row by row: on row ``v`` the ellipse ``a du^2 + 2 b du dv + c dv^2 <= k^2`` (``dv = v - v_mean``,
    ``k^2 = 2 ln(o / ALPHA_MIN)``) spans ``du`` in ``(-b dv -+ sqrt(k^2 a - dv^2 (a c - b^2))) / a``;
    only those pixels are listed (a hair wider, as the box is). Gaussian-major, rows top-down.
    """
    box = proj.bbox[first:last]
    device = box.device
    rows = (box[:, 3] - box[:, 1] + 1).clamp_min(0)
    row_gid = torch.repeat_interleave(torch.arange(last - first, device=device), rows)
    row_local = torch.arange(row_gid.shape[0], device=device) - segment_starts(rows).index_select(0, row_gid)
    v = box[row_gid, 1] + row_local
    u_mean, v_mean = proj.means2d[first:last].detach().unbind(-1)
    a, b, c = proj.conics[first:last].detach().unbind(-1)
    k2 = 2.0 * torch.log((proj.opacities[first:last].detach() / ALPHA_MIN).clamp_min(1.0))
    u_row, v_row, ag, bg, cg, k2g = torch.stack([u_mean, v_mean, a, b, c, k2], 1).index_select(0, row_gid).unbind(1)
    dv = v.to(ag.dtype) - v_row
    disc = (k2g * ag - dv * dv * (ag * cg - bg * bg)).clamp_min(0.0)
    half = torch.sqrt(disc) / ag * (1 + _SPAN_MARGIN) + _SPAN_MARGIN
    centre = u_row - bg * dv / ag
    u0 = torch.ceil((centre - half).clamp(-1.0, proj.width + 1.0)).long().clamp_min(0)
    u1 = torch.floor((centre + half).clamp(-1.0, proj.width + 1.0)).long().clamp_max(proj.width - 1)
    span = (u1 - u0 + 1).clamp_min(0)
    pair_row = torch.repeat_interleave(torch.arange(span.shape[0], device=device), span)
    per_row = torch.stack([segment_starts(span), u0 + v * proj.width, row_gid + first], dim=1).index_select(0, pair_row)
    pix = per_row[:, 1] + torch.arange(pair_row.shape[0], device=device) - per_row[:, 0]
    return per_row[:, 2], pix


def _chunks(bbox: torch.Tensor, chunk_pairs: int) -> list[tuple[int, int]]:
    """Consecutive Gaussian ranges whose boxes hold about ``chunk_pairs`` pixels each."""
    area = ((bbox[:, 2] - bbox[:, 0] + 1).clamp_min(0) * (bbox[:, 3] - bbox[:, 1] + 1).clamp_min(0))
    ends = torch.cumsum(area, 0)
    bounds, first = [], 0
    while first < bbox.shape[0]:
        start_total = int(ends[first - 1]) if first > 0 else 0
        last = int(torch.searchsorted(ends, start_total + chunk_pairs, right=True))
        last = max(last, first + 1)
        bounds.append((first, last))
        first = last
    return bounds


@torch.no_grad()
def find_pairs(proj: ProjectedGaussians, max_per_pixel: int = MAX_PER_PIXEL,
               chunk_pairs: int = CHUNK_PAIRS) -> SplatPairs:
    """The contributing (splat, pixel) pairs of ``proj`` (see the module docstring)."""
    num_pixels = proj.width * proj.height
    device = proj.means2d.device
    taken = torch.zeros(num_pixels, dtype=torch.int64, device=device)
    log_T = torch.zeros(num_pixels, dtype=torch.float64, device=device)
    truncated = torch.zeros(num_pixels, dtype=torch.bool, device=device)
    truncated_T = torch.zeros(num_pixels, dtype=torch.float64, device=device)
    log_T_min = math.log(T_MIN)
    params = splat_parameters(proj)
    empty = torch.zeros(0, dtype=torch.int64, device=device)
    kept_gid, kept_pix, kept_rank = [empty], [empty], [empty]
    chunks = _chunks(proj.bbox, chunk_pairs)
    for first, last in chunks:
        gid, pix = _enumerate_footprints(proj, first, last)
        pair, uv = params.index_select(0, gid), pixel_centres(pix, proj.width, params.dtype)
        alpha = raw_alpha(uv[:, 0] - pair[:, 0], uv[:, 1] - pair[:, 1], pair)[0].clamp_max(ALPHA_MAX)
        hit = torch.nonzero(alpha >= ALPHA_MIN).squeeze(1)
        # a stable sort keeps each pixel's splats front to back (int32 keys sort faster)
        sorted_pix, order = torch.sort(pix.index_select(0, hit).to(torch.int32), stable=True)
        hit = hit.index_select(0, order)
        gid, alpha, pix = gid.index_select(0, hit), alpha.index_select(0, hit), sorted_pix.to(torch.int64)
        seg_start = segment_starts(torch.bincount(pix, minlength=num_pixels)).index_select(0, pix)
        rank = torch.arange(pix.shape[0], device=device) - seg_start + taken.index_select(0, pix)
        log1m = torch.log1p(-alpha.to(torch.float64))
        log_T_front = exclusive_segment_cumsum(log1m, seg_start) + log_T.index_select(0, pix)
        alive = log_T_front >= log_T_min
        keep = alive & (rank < max_per_pixel)
        if not bool(keep.all()):
            cut = alive & ~keep
            truncated[pix[cut]] = True
            truncated_T.scatter_reduce_(0, pix[cut], log_T_front[cut].exp(), reduce="amax")
            keep = torch.nonzero(keep).squeeze(1)
            gid, pix, rank, log1m = (t.index_select(0, keep) for t in (gid, pix, rank, log1m))
        kept_gid.append(gid)
        kept_pix.append(pix)
        kept_rank.append(rank)
        taken += torch.bincount(pix, minlength=num_pixels)
        log_T.index_add_(0, pix, log1m)
    gid, pix = torch.cat(kept_gid), torch.cat(kept_pix)
    if len(chunks) > 1:  # counting sort: pixel-major, and within a pixel by rank (= front to back)
        position = segment_starts(taken).index_select(0, pix) + torch.cat(kept_rank)
        order = torch.empty_like(position)
        order[position] = torch.arange(position.shape[0], device=device)
        gid, pix = gid.index_select(0, order), pix.index_select(0, order)
    stats = RenderStats(visible_gaussians=int(proj.index.shape[0]), pairs=int(gid.shape[0]),
                        truncated_pixels=int(truncated.sum()),
                        max_truncated_transmittance=float(truncated_T.max()) if num_pixels else 0.0)
    return SplatPairs(gid, pix, pixel_centres(pix, proj.width, params.dtype), taken, stats)


