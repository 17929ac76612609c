"""A manifest's metrics as rows a person can read: each value next to its baselines (paired by the
stages' naming conventions), which one is better, and the paper's figure where one is known.

Pairing conventions (what the stages write):

* a baseline *prefix* before the metric, after an optional split prefix (``test_``, ``val_``, ...):
  ``mpjpe_body_cm`` / ``mean_pose_mpjpe_body_cm``, ``depth_absrel`` / ``sgbm_depth_absrel``,
  ``psnr`` / ``lambert_psnr`` / ``baked_psnr``, ``test_mpjpe_body_cm`` / ``test_mean_pose_mpjpe_body_cm``;
* a *variant* prefix on our own value: ``full_p2s_*`` / ``no_depth_p2s_*`` / ``skinning_p2s_*``;
* inside a nested group (``parts.pants.psnr`` / ``parts.pants.lambert_psnr``) the same conventions
  hold after the group's dotted prefix;
* a baseline *suffix*: ``normal_deg`` / ``normal_deg_coarse``, ``texture_l1`` / ``texture_l1_mean_texture``,
  ``depth_absrel`` / ``depth_absrel_constant_baseline``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

SPLITS = ("test_", "train_", "validation_", "val_", "olat_tail_", "group_tail_")
#: baseline prefix -> label (the order in which they are shown)
BASELINE_PREFIXES = {
    "no_depth_": "no depth", "skinning_": "skinning only", "mean_pose_": "mean pose", "per_frame_": "network alone",
    "sgbm_": "SGBM stereo", "lambert_": "Lambert", "baked_": "baked texture", "diffuse_only_": "diffuse only",
    "flat_studio_": "flat studio light", "ldr_panorama_only_": "LDR panorama only",
}
#: prefixes that mark our own value when its baselines carry another prefix of the same family
VARIANT_PREFIXES = ("full_",)
BASELINE_SUFFIXES = {"_coarse": "coarse mesh normal", "_mean_texture": "mean texture",
                     "_constant_baseline": "constant depth"}
LOWER_IS_BETTER = ("mpjpe", "p2s", "point_to_surface", "absrel", "rmse", "_deg", "l1", "error", "residual", "lpips",
                   "fid", "ms_per_frame", "loss")
HIGHER_IS_BETTER = ("psnr", "ssim", "coverage", "explained", "detection_rate", "valid_fraction", "tracked_rate")

PAPER_POSE = "paper, pose table (Ours, real data); notes/appearance.md Sec. 1.7, issue 21"
PAPER_TRACKING = ("paper, ego-tracking table, point-to-surface cm full-body / ego-visible (real data; the paper's "
                  "P2S is compared with our pred->true); notes/appearance.md Sec. 1.7")
PAPER_RELIGHT = "paper, Tab. relight-full, subject #1 (Ours; SSIM, LPIPS x100); notes/appearance.md Sec. 1.7"
#: (artifact kind, metric key) -> (the paper's figure, where it is quoted). Only numbers quoted in
#: ../shared/notes/appearance.md or the issues; they are measured on real captures, not the simulator.
PAPER_FIGURES: dict[tuple[str, str], tuple[float, str]] = {
    ("keypoints", "mpjpe_body_cm"): (4.11, PAPER_POSE),
    ("keypoints", "mpjpe_hands_cm"): (4.71, PAPER_POSE),
    ("model", "test_mpjpe_body_cm"): (4.11, PAPER_POSE),
    ("model", "test_mpjpe_hands_cm"): (4.71, PAPER_POSE),
    ("meshes", "full_p2s_pred_to_true_cm"): (1.23, PAPER_TRACKING),
    ("meshes", "full_p2s_ego_visible_pred_to_true_cm"): (1.12, PAPER_TRACKING),
    ("meshes", "no_depth_p2s_pred_to_true_cm"): (1.29, PAPER_TRACKING + " (Ours w/o depth)"),
    ("meshes", "no_depth_p2s_ego_visible_pred_to_true_cm"): (1.24, PAPER_TRACKING + " (Ours w/o depth)"),
    ("meshes", "skinning_p2s_pred_to_true_cm"): (1.27, PAPER_TRACKING + " (DDC, motion only); issue 15"),
    ("meshes", "skinning_p2s_ego_visible_pred_to_true_cm"): (1.24, PAPER_TRACKING + " (DDC, motion only)"),
    ("renders", "psnr"): (34.81, PAPER_RELIGHT),
    ("renders", "ssim"): (92.46, PAPER_RELIGHT),
    ("renders", "lpips"): (8.56, PAPER_RELIGHT),
    ("renders", "fid"): (31.90, PAPER_RELIGHT),
}
PAPER_RUNTIME = "paper, Tab. runtime-breakdown (per frame, RTX 4090); notes/appearance.md Sec. 1.7"


def _entry(manifest: dict, where: str, key: str):
    block = manifest.get(where)
    value = block.get(key) if isinstance(block, dict) else None
    return float(value) if is_number(value) and value > 0 else None


def _from_rate(manifest: dict):
    rate = _entry(manifest, "timing", "frames_per_s")
    return None if rate is None else 1000.0 / rate


def _per_view_wall(manifest: dict):
    wall, views = _entry(manifest, "timing", "wall_s"), _entry(manifest, "metrics", "views")
    return None if wall is None or views is None else 1000.0 * wall / views


#: section -> (the paper's per-frame runtime in ms, how ours is read from a manifest, what ours is)
PAPER_RUNTIME_MS = {
    "egopose": (17.62, lambda m: _entry(m, "timing", "inference_ms_per_frame"), "network inference"),
    "ik": (67.25, lambda m: _entry(m, "timing", "ms_per_frame"), "solve"),
    "egodepth": (87.71, lambda m: _entry(m, "timing", "depth_ms_per_frame"), "depth estimation"),
    "animate": (21.50, _from_rate, "animation, from frames_per_s"),
    "relight": (100.19, _per_view_wall, "whole run's wall time / rendered views, loading included"),
}


@dataclass
class Comparison:
    """A baseline (or the paper's figure) next to our value; ``better`` says whether ours wins
    (None: cannot tell)."""

    label: str
    key: str
    value: Any
    better: bool | None
    paper: tuple[float, str] | None = None


@dataclass
class MetricRow:
    key: str
    value: Any
    comparisons: list[Comparison] = field(default_factory=list)
    paper: Comparison | None = None
    unit: str | None = None


def flatten(metrics: dict, prefix: str = "") -> dict[str, Any]:
    """Nested dicts become dotted keys (``head_pose.test.valid_fraction``); lists stay values."""
    out: dict[str, Any] = {}
    for key, value in metrics.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def direction(key: str) -> int:
    """+1 when higher is better, -1 when lower is better, 0 when the name does not say."""
    name = key.rsplit(".", 1)[-1].lower()
    if any(token in name for token in HIGHER_IS_BETTER):
        return 1
    if any(token in name for token in LOWER_IS_BETTER):
        return -1
    return 0


def ours_is_better(key: str, ours: Any, other: Any) -> bool | None:
    sign = direction(key)
    if not sign or not is_number(ours) or not is_number(other) or ours == other:
        return None
    return (ours - other) * sign > 0


def _split(key: str) -> tuple[str, str]:
    """(split prefix, the rest): a nested group (``parts.pants.``) and a split (``olat_tail_``) both
    belong to the prefix, so ``parts.pants.lambert_psnr`` pairs with ``parts.pants.psnr``."""
    group, dot, key = key.rpartition(".")
    group += dot
    for split in SPLITS:
        if key.startswith(split):
            return group + split, key[len(split):]
    return group, key


def baselines_of(key: str, flat: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, baseline key) present in ``flat`` for metric ``key`` by the naming conventions."""
    split, rest = _split(key)
    if any(rest.startswith(p) for p in BASELINE_PREFIXES) or any(rest.endswith(s) for s in BASELINE_SUFFIXES):
        return []
    found = []
    core = rest
    for variant in VARIANT_PREFIXES:
        if rest.startswith(variant):
            core = rest[len(variant):]
    for prefix, label in BASELINE_PREFIXES.items():
        candidate = split + prefix + core
        if candidate in flat and candidate != key:
            found.append((label, candidate))
    for suffix, label in BASELINE_SUFFIXES.items():
        if key + suffix in flat:
            found.append((label, key + suffix))
    return found


def metric_rows(kind: str, metrics: dict, units: dict | None = None) -> list[MetricRow]:
    """Rows in manifest order; a baseline shown next to its metric gets no row of its own."""
    flat = flatten(metrics or {})
    units = units or {}
    pairs = {key: baselines_of(key, flat) for key in flat}
    consumed = {b for found in pairs.values() for _, b in found}
    rows = []
    for key, value in flat.items():
        if key in consumed and not pairs[key]:
            continue
        row = MetricRow(key, value, unit=units.get(key) if isinstance(units.get(key), str) else None)
        for label, other in pairs[key]:
            row.comparisons.append(Comparison(label, other, flat[other], ours_is_better(key, value, flat[other]),
                                              PAPER_FIGURES.get((kind, other))))
        if (kind, key) in PAPER_FIGURES:
            figure, source = PAPER_FIGURES[(kind, key)]
            row.paper = Comparison(source, key, figure, ours_is_better(key, value, figure))
        rows.append(row)
    return rows


def verdict(row: MetricRow) -> str:
    """``better`` (beats every baseline), ``worse`` (loses to every one), ``mixed`` or ``""``."""
    votes = [c.better for c in row.comparisons if c.better is not None]
    if not votes:
        return ""
    return "better" if all(votes) else "worse" if not any(votes) else "mixed"


MPJPE = re.compile(r"^(?P<series>.*?)mpjpe_(?P<mid>(?:[a-z]+_)*?)(?P<group>body|hands|all)_cm$")
GROUPS = ("body", "hands", "all")


def mpjpe_groups(kind: str, metrics: dict) -> dict[str, dict[str, dict[str, float]]]:
    """MPJPE per joint group for bar charts: ``{split: {series: {group: cm}}}`` from keys like
    ``mpjpe_body_cm``, ``mean_pose_mpjpe_hands_cm``, ``test_per_frame_mpjpe_all_cm``,
    ``gt_mpjpe_body_cm``; the paper's figures join the split they are quoted for."""
    charts: dict[str, dict[str, dict[str, float]]] = {}
    for key, value in flatten(metrics or {}).items():
        match = MPJPE.match(key)
        if not match or not is_number(value):
            continue
        split, series = _split(match["series"] + match["mid"])
        name = BASELINE_PREFIXES.get(series, series.rstrip("_") or "ours")
        charts.setdefault(split.rstrip("_") or "all frames", {}).setdefault(name, {})[match["group"]] = float(value)
        figure = PAPER_FIGURES.get((kind, key))
        if figure is not None:
            charts[split.rstrip("_") or "all frames"].setdefault("paper (real data)", {})[match["group"]] = figure[0]
    for chart in charts.values():  # the paper's bars last
        if "paper (real data)" in chart:
            chart["paper (real data)"] = chart.pop("paper (real data)")
    return charts


def runtime_row(section: str, manifest: dict) -> tuple[float, float, str] | None:
    """(ours ms/frame, the paper's ms/frame, what is compared and where the paper's is from), when
    both are known."""
    if section not in PAPER_RUNTIME_MS:
        return None
    figure, read, what = PAPER_RUNTIME_MS[section]
    ours = read(manifest)
    return None if ours is None else (ours, figure, f"{what}; {PAPER_RUNTIME}")
