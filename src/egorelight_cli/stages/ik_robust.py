"""Robust keypoint data for :mod:`egorelight_cli.stages.ik`: a unit sanity check, gross-outlier
rejection and the Huber data term.

* **Units**: a body spans about 2 m. :func:`keypoint_span_m` measures the span of the keypoints
  robustly (per frame, twice the 90th percentile of the keypoints' distances from the frame's body
  centre, the median over frames), so a few broken keypoints do not move it, and
  :func:`check_keypoint_units` refuses keypoints spanning more than ``max_span_m`` (integer
  millimetres read as metres span ~2000 m) or less than ``min_span_m``.
* **Gross outliers before the fit** (:func:`distant_keypoints`): keypoints farther than
  ``distance_m`` from their frame's body centre (the per-axis median of the frame's body
  keypoints), e.g. a coordinate of 1e9, are dropped.
* **Outliers after a first fit** (:func:`residual_outliers`): keypoints whose residual exceeds
  both ``residual_factor`` times the median residual of the sequence and ``min_residual_m`` are
  dropped and the motion is fitted again.
* **Huber data term** (:func:`huber_factors`): a keypoint at distance ``d`` (metres) from its
  target costs ``d^2`` up to ``delta`` and ``2 delta d - delta^2`` beyond (times its confidence
  and the solver's weight and unit), so a keypoint that is off by more than ``delta`` pulls with a
  bounded force. Solved by iteratively reweighted Gauss-Newton: row weight ``min(1, delta/d)``.
"""

from __future__ import annotations

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.structures.keypoints import BODY_SLICE

ROBUST_LOSSES = ("huber", "l2")
SPAN_QUANTILE = 0.9


def body_centres(xyz: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per frame the per-axis median of the valid body keypoints (all valid keypoints when fewer
    than 3 body ones are valid); ``xyz`` (T,K,3) metres, ``valid`` (T,K) bool -> (T,3), NaN for a
    frame without any valid keypoint."""
    points = np.where(valid[..., None], xyz, np.nan)
    body = valid[:, BODY_SLICE].sum(axis=1) >= 3
    centres = np.full((xyz.shape[0], 3), np.nan)
    for frames, candidates in ((body, points[:, BODY_SLICE]), (~body & valid.any(axis=1), points)):
        if frames.any():
            centres[frames] = np.nanmedian(candidates[frames], axis=1)
    return centres


def _distances_from_centre(xyz: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(T,K) distance (m) of every valid keypoint from its frame's body centre, NaN elsewhere."""
    with np.errstate(invalid="ignore", over="ignore"):
        distance = np.linalg.norm(xyz - body_centres(xyz, valid)[:, None], axis=-1)
    return np.where(valid, distance, np.nan)


def keypoint_span_m(xyz: np.ndarray, valid: np.ndarray) -> float | None:
    """Robust extent (m) of the keypoints (see the module docstring); None when no frame has 3
    valid keypoints."""
    distance = _distances_from_centre(np.asarray(xyz, np.float64), valid)
    frames = valid.sum(axis=1) >= 3
    if not frames.any():
        return None
    return float(np.median(2.0 * np.nanquantile(distance[frames], SPAN_QUANTILE, axis=1)))


def check_keypoint_units(xyz: np.ndarray, valid: np.ndarray, min_span_m: float, max_span_m: float, path=None) -> None:
    """Raise unless the keypoints span between ``min_span_m`` and ``max_span_m`` metres."""
    span = keypoint_span_m(xyz, valid)
    if span is None or min_span_m <= span <= max_span_m:
        return
    hint = ("millimetres or centimetres read as metres?" if span > max_span_m else "not metres?")
    raise EgorelightError(f"keypoints span {span:.4g} m, a body spans about 2 m (expected {min_span_m:g} to "
                          f"{max_span_m:g} m): {hint}", path)


def distant_keypoints(xyz: np.ndarray, valid: np.ndarray, distance_m: float) -> np.ndarray:
    """(T,K) bool: valid keypoints farther than ``distance_m`` from their frame's body centre."""
    distance = _distances_from_centre(np.asarray(xyz, np.float64), valid)
    return valid & ~(distance <= distance_m)


def residual_outliers(residual_m: np.ndarray, valid: np.ndarray, factor: float, min_residual_m: float) -> np.ndarray:
    """(T,K) bool: valid keypoints whose fit residual (m) exceeds ``factor`` times the median
    residual of the valid ones and ``min_residual_m``; none when ``factor`` is 0."""
    values = residual_m[valid]
    if factor <= 0 or not values.size:
        return np.zeros(valid.shape, bool)
    threshold = max(factor * float(np.median(values)), min_residual_m)
    return valid & (np.nan_to_num(residual_m, nan=0.0) > threshold)


def huber_factors(distance: torch.Tensor, delta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """For keypoint distances (...,) in metres: the factor turning the squared residual into the
    Huber cost (1 up to ``delta``, ``2 delta/d - (delta/d)^2`` beyond; differentiable) and the
    square root of the reweighted Gauss-Newton row weight ``min(1, delta/d)``."""
    far = distance > delta
    d = distance.clamp(min=delta)
    ratio = delta / d
    energy = torch.where(far, 2.0 * ratio - ratio * ratio, torch.ones_like(d))
    return energy, torch.where(far, ratio.sqrt(), torch.ones_like(d))
