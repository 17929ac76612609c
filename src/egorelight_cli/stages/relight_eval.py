"""Scoring relit renders like the paper (Sec. "Relighting Experiments"), against the captured images.

A view is scored on the metric tone mapping (:func:`~egorelight_cli.render.image_metrics.tonemap_for_metrics`)
inside the subject mask, with the head region excluded (the avatar is trained without the HMD,
the test frames show it): pixels where the render's ``head`` pass covers more than half of its
alpha. PSNR (dB) and SSIM (x100) for the model, its diffuse part alone ("without SpecularNet"),
and the baselines: the Lambert relighting of the flat-lit texture ``a chi / (pi rho s_flat)`` and
the baked flat-lit texture, all rendered with the
model's Gaussians. LPIPS and FID need pretrained networks that cannot be downloaded: ``null``.
"""

from __future__ import annotations

import numpy as np
import torch

from egorelight_cli.render.gaussians import GaussianRender
from egorelight_cli.render.image_metrics import psnr, ssim, tonemap_for_metrics

#: metric prefix -> the tone-mapped image it scores (``render``: the model's colour, else a render pass)
ROWS = {"": "render", "diffuse_only_": "diffuse", "lambert_": "lambert", "baked_": "baked"}


SCORES_NPZ = "scores.npz"
#: light patterns of a sequence's robustness tail (one light at a time, a random group of lights:
#: synth's ``light_tail``), scored apart from its HDR-lit (``envmap``) frames as ``<pattern>_tail_*``
TAIL_PATTERNS = ("olat", "group")
SCORED_PATTERNS = ("envmap",) + TAIL_PATTERNS


class RelightScores:
    """Per-view PSNR/SSIM of the model and its baselines (one row per :meth:`start_view`)."""

    def __init__(self):
        self.views: list[dict[str, float]] = []

    def start_view(self) -> None:
        self.views.append({})

    def add(self, key: str, value: float) -> None:
        self.views[-1][key] = value

    def arrays(self) -> dict[str, np.ndarray]:
        """Per-view rows by score name (NaN where a view has no such score: an empty region)."""
        names = sorted({k for view in self.views for k in view})
        return {k: np.array([view.get(k, np.nan) for view in self.views], np.float64) for k in names}

    def metrics(self, patterns: np.ndarray | None = None) -> dict:
        return relight_metrics(self.arrays(), patterns)


def relight_metrics(rows: dict[str, np.ndarray], patterns: np.ndarray | None = None) -> dict:
    """Each score's mean over the views that have it (``rows``: :meth:`RelightScores.arrays`, or
    the merged rows of frame shards), and ``null`` LPIPS/FID with the reason.

    With the per-view light ``patterns``, the plain metrics are the HDR-lit (``envmap``) views' and
    each tail pattern present gets its own ``<pattern>_tail_<score>`` means (:data:`TAIL_PATTERNS`)."""
    def means(select: np.ndarray, prefix: str = "") -> dict:
        return {prefix + key: float(np.nanmean(v[select])) if np.isfinite(v[select]).any() else float("nan")
                for key, v in rows.items()}

    if patterns is None:
        out = means(np.ones(len(next(iter(rows.values()), [])), bool)) if rows else {}
    else:
        patterns = np.asarray(patterns).astype(str)
        out = means(patterns == "envmap")
        for pattern in TAIL_PATTERNS:
            if (patterns == pattern).any():
                out.update(means(patterns == pattern, f"{pattern}_tail_"))
                out[f"{pattern}_tail_views"] = int((patterns == pattern).sum())
    out.update({"lpips": None, "fid": None, "lpips_fid": "need pretrained AlexNet/Inception weights: not scored"})
    return out


def merged_metrics(root, manifests: list[dict]) -> dict:
    """The metrics of merged frame shards (:func:`egorelight_cli.sharding.merge_parts`) from the
    merged ``scores.npz``, as a single run computes them."""
    from pathlib import Path

    from egorelight_cli.io.npz import read_npz

    rows, _ = read_npz(Path(root) / SCORES_NPZ, check_finite=False)
    first = manifests[0]["metrics"]
    metrics = {k: first[k] for k in ("sequence", "cameras", "lighting")}
    metrics["views"] = int(len(rows["frame_ids"]))
    if "scored" in first:
        return {**metrics, "scored": first["scored"]}
    return {**metrics, **relight_metrics({k: v for k, v in rows.items() if k not in VIEW_KEYS}, rows.get("light"))}


#: per-view columns of ``scores.npz`` that are not scores: the frame, the camera, its light pattern
VIEW_KEYS = ("frame_ids", "camera", "light")


def tonemapped(render: GaussianRender, names) -> dict[str, torch.Tensor]:
    """The render's colour (``render``) or passes ``names`` on the metric tone mapping, (H,W,3) in [0,1]."""
    return {name: tonemap_for_metrics(render.colour if name == "render" else render.passes[name]) for name in names}


def _uint8(images: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
    return {k: (v.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8) for k, v in images.items()}


def display_images(render: GaussianRender) -> dict:
    """The render and its baseline passes on the metric tone mapping, uint8 (H,W,3) by name."""
    return _uint8(tonemapped(render, ("render", "lambert", "baked")))


def score_view(scores: RelightScores, render: GaussianRender, target: torch.Tensor, mask: torch.Tensor) -> dict:
    """Score one render against its captured image; returns the tone-mapped uint8 images by name."""
    head = render.passes["head"][..., 0] > 0.5 * render.alpha.clamp_min(1e-6)
    region = mask & ~head
    display = {"target": tonemap_for_metrics(target), **tonemapped(render, ROWS.values())}
    if bool(region.any()):
        for prefix, name in ROWS.items():
            scores.add(f"{prefix}psnr", float(psnr(display[name], display["target"], region)))
            scores.add(f"{prefix}ssim", 100.0 * float(ssim(display[name], display["target"], region)))
    scores.add("head_excluded_fraction", float(head[mask].float().mean()) if bool(mask.any()) else 0.0)
    return _uint8(display)
