"""Per-frame scores of an ``egodepth`` run and the metrics computed from them.

The pointcloud artifact keeps ``scores.npz``: per output frame and depth method (the run's method,
prefix ``""``; SGBM compared on the same frames, ``sgbm_``), the sums the depth metrics need
(pixels inside the true body mask, pixels the method covers, their summed AbsRel and squared
error, the constant-depth baseline's summed AbsRel, and the pixels both methods cover with the
method's summed AbsRel there: the like-for-like comparison, since each method's own AbsRel is
taken over the pixels it chose to cover) and the point-to-surface distance of every
valid point (NaN-padded to the points per frame); plus the frames' ``posed`` flags. The manifest's
metrics are :func:`depth_metrics` of those rows, so a whole run and merged frame shards
(:mod:`egorelight_cli.sharding`) compute them the same way.
"""

from __future__ import annotations

import numpy as np

SCORES_NPZ = "scores.npz"
SUMS = ("total", "covered", "abs_rel_sum", "sq_err_sum", "constant_abs_rel_sum", "common_covered",
        "common_abs_rel_sum")
OPTIONAL_SUMS = {"constant_abs_rel_sum": "has_constant", "common_covered": "has_common",
                 "common_abs_rel_sum": "has_common"}


class DepthScores:
    """Per-frame error sums of one depth method over ``frames`` output frames of ``points`` points."""

    def __init__(self, frames: int, points: int):
        self.sums = {name: np.zeros(frames, np.float64) for name in SUMS}
        self.surface = np.full((frames, points), np.nan, np.float32)
        self.has_constant = False
        self.has_common = False

    def add_frame(self, t: int, ranges: dict, truth_maps: dict, distance: np.ndarray,
                  constant: float | None = None, other: dict | None = None) -> None:
        """Score frame ``t``: range maps (H,W) per role against ``truth_maps`` (role -> (true range,
        mask)) inside the mask, ``distance`` (N,) of the valid points from the true surface,
        ``constant``: the baseline that predicts that range everywhere on the same pixels, and
        ``other``: the other method's range maps, whose covered pixels define the common ones."""
        for role, (truth, mask) in truth_maps.items():
            pred = ranges[role]
            have = mask & (pred > 0)
            true_range = truth[have]
            error = (pred[have] - true_range).astype(np.float64)
            abs_rel = np.abs(error) / true_range
            self.sums["total"][t] += int(mask.sum())
            self.sums["covered"][t] += int(have.sum())
            self.sums["abs_rel_sum"][t] += float(abs_rel.sum())
            self.sums["sq_err_sum"][t] += float((error ** 2).sum())
            if other is not None:
                self.has_common = True
                both = other[role][have] > 0  # of the covered pixels, those the other method covers too
                self.sums["common_covered"][t] += int(both.sum())
                self.sums["common_abs_rel_sum"][t] += float(abs_rel[both].sum())
            if constant is not None:
                self.has_constant = True
                self.sums["constant_abs_rel_sum"][t] += float((np.abs(constant - true_range) / true_range)
                                                              .astype(np.float64).sum())
        self.surface[t, :len(distance)] = distance

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The rows of :data:`SCORES_NPZ` for this method (names prefixed with ``prefix``)."""
        out = {f"{prefix}{name}": v for name, v in self.sums.items()
               if name not in OPTIONAL_SUMS or getattr(self, OPTIONAL_SUMS[name])}
        out[f"{prefix}surface_distance_m"] = self.surface
        return out


def depth_metrics(rows: dict[str, np.ndarray], prefix: str) -> dict:
    """Coverage, AbsRel, RMSE (cm) and the constant baseline's AbsRel over all scored pixels, and
    the mean and median point-to-surface distance (cm), of the method ``prefix`` in ``rows``."""
    total, covered = float(rows[f"{prefix}total"].sum()), float(rows[f"{prefix}covered"].sum())
    out = {f"{prefix}depth_coverage": covered / max(total, 1.0)}
    if covered:
        out[f"{prefix}depth_absrel"] = float(rows[f"{prefix}abs_rel_sum"].sum() / covered)
        out[f"{prefix}depth_rmse_cm"] = float(np.sqrt(rows[f"{prefix}sq_err_sum"].sum() / covered) * 100)
        if f"{prefix}constant_abs_rel_sum" in rows:
            out[f"{prefix}depth_absrel_constant_baseline"] = float(rows[f"{prefix}constant_abs_rel_sum"].sum() / covered)
    if f"{prefix}common_covered" in rows:
        common = float(rows[f"{prefix}common_covered"].sum())
        out[f"{prefix}depth_common_coverage"] = common / max(total, 1.0)
        if common:
            out[f"{prefix}depth_absrel_common"] = float(rows[f"{prefix}common_abs_rel_sum"].sum() / common)
    distance = rows[f"{prefix}surface_distance_m"]
    distance = distance[np.isfinite(distance)].astype(np.float64)
    if distance.size:
        out[f"{prefix}point_to_surface_cm"] = float(distance.mean() * 100)
        out[f"{prefix}point_to_surface_median_cm"] = float(np.median(distance) * 100)
    return out


def run_metrics(rows: dict[str, np.ndarray], valid: np.ndarray, method: str, sequence: str) -> dict:
    """Everything the manifest reports: frame and point counts from ``posed`` and the points'
    ``valid`` (T,P), and :func:`depth_metrics` of each method with error rows."""
    posed = rows["posed"].astype(bool)
    T, P = valid.shape
    metrics = {"method": method, "sequence": sequence, "frames": int(T), "frames_without_pose": int(T - posed.sum()),
               "points_per_frame": int(P),
               "mean_valid_points": float(valid.sum(axis=1)[posed].mean()) if posed.any() else 0.0}
    for prefix in ("", "sgbm_"):
        if f"{prefix}total" in rows:
            metrics.update(depth_metrics(rows, prefix))
    return metrics


def merged_metrics(root, manifests: list[dict]) -> dict:
    """The metrics of merged frame shards (:func:`egorelight_cli.sharding.merge_parts`) from the
    merged ``scores.npz`` and ``pointcloud.npz``, as a single run computes them."""
    from pathlib import Path

    from egorelight_cli.io.npz import read_npz
    from egorelight_cli.io.pointcloud import POINTCLOUD_PAYLOAD, read_pointcloud_npz

    rows, _ = read_npz(Path(root) / SCORES_NPZ, check_finite=False)
    cloud = read_pointcloud_npz(Path(root) / POINTCLOUD_PAYLOAD)
    first = manifests[0]["metrics"]
    metrics = run_metrics(rows, cloud.valid, first["method"], first["sequence"])
    for key in ("mask_threshold", "mask_threshold_source", "groundtruth_frame"):  # the same in every shard
        if key in first:
            metrics[key] = first[key]
    return metrics
