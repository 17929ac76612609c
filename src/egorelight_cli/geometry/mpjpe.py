"""Mean per-joint position error (MPJPE), the keypoint error of egopose and ik."""

from __future__ import annotations

import numpy as np


def mean_distance_cm(distance_m: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean of the finite (and ``mask``) entries of ``distance_m`` (metres), in cm; NaN when none."""
    distance_m = np.asarray(distance_m)
    ok = np.isfinite(distance_m) if mask is None else np.isfinite(distance_m) & mask
    return float(distance_m[ok].mean() * 100) if ok.any() else float("nan")


def mpjpe_cm(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean per-joint position error in cm over finite (and ``mask``) entries; NaN when none."""
    err = np.linalg.norm(np.asarray(pred, np.float64) - np.asarray(truth, np.float64), axis=-1)
    return mean_distance_cm(err, mask)
