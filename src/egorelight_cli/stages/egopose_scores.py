"""Per-frame scores of an ``egopose`` run and the metrics computed from them.

The keypoints artifact keeps ``scores.npz``: per output frame, the per-joint error (cm) of the
output, of the per-frame estimate (before the temporal module) and of the mean-pose baseline
against the simulator's ground truth (NaN where a frame is not scored: no truth, an invalid head
pose, or the sync prefix), and the frame's ``valid`` / ``content`` flags. The manifest's metrics
are :func:`egopose_metrics` of those rows and the keypoints' confidences, so a run over all frames
and the merge of frame shards (:mod:`egorelight_cli.sharding`) compute them the same way.
"""

from __future__ import annotations

import numpy as np

from egorelight_cli.structures.keypoints import BODY_SLICE, HANDS_SLICE, Keypoints

SCORES_NPZ = "scores.npz"
#: per-joint error arrays in scores.npz and the metric prefix each becomes
ERRORS = {"error_cm": "", "per_frame_error_cm": "per_frame_", "mean_pose_error_cm": "mean_pose_"}


def joint_errors_cm(pred: np.ndarray, frame_ids: np.ndarray, truth: Keypoints, rows_mask: np.ndarray) -> np.ndarray:
    """(T,J) float32 distance (cm) of ``pred`` (T,J,3) from the truth at the same frame ids, on
    frames ``rows_mask`` (T,) the truth holds; NaN elsewhere and where either side is missing."""
    out = np.full(pred.shape[:2], np.nan, np.float32)
    _, pred_rows, truth_rows = np.intersect1d(frame_ids, truth.frame_ids, return_indices=True)
    keep = rows_mask[pred_rows]
    p, t = pred[pred_rows[keep]], truth.xyz[truth_rows[keep]]
    out[pred_rows[keep]] = 100.0 * np.linalg.norm(np.asarray(p, np.float64) - np.asarray(t, np.float64), axis=-1)
    return out


def egopose_scores(prediction, frames, truth: Keypoints | None, mean_pose_heading: np.ndarray | None) -> dict:
    """The rows of :data:`SCORES_NPZ` for a :class:`~egorelight_cli.stages.egopose.Prediction` of
    ``frames``: flags always, error rows only with a ``truth`` (usable frames are scored)."""
    from egorelight_cli.stages.egopose import mean_pose_keypoints

    scores = {"valid": frames.valid.copy(), "content": frames.content.copy()}
    if truth is None:
        return scores
    ids, rows = frames.frame_ids, frames.usable
    scores["error_cm"] = joint_errors_cm(prediction.keypoints.xyz, ids, truth, rows)
    scores["per_frame_error_cm"] = joint_errors_cm(prediction.per_frame, ids, truth, rows)
    if mean_pose_heading is not None:
        scores["mean_pose_error_cm"] = joint_errors_cm(mean_pose_keypoints(mean_pose_heading, frames), ids, truth, rows)
    return scores


def _mean(errors: np.ndarray) -> float:
    finite = errors[np.isfinite(errors)]
    return round(float(finite.astype(np.float64).mean()), 3) if finite.size else float("nan")


def egopose_metrics(scores: dict[str, np.ndarray], confidence: np.ndarray) -> dict:
    """The manifest metrics from ``scores`` (rows of :data:`SCORES_NPZ`) and the output's
    per-joint ``confidence`` (T,J): frame counts, mean confidence and, where error rows exist,
    MPJPE (cm) of body, hands and all keypoints for the output, the per-frame estimate and the
    mean-pose baseline (``<prefix>mpjpe_<part>_cm``)."""
    valid, content = scores["valid"].astype(bool), scores["content"].astype(bool)
    metrics: dict = {"output_frames": int(len(valid)), "invalid_head_pose_frames": int((~valid).sum()),
                     "content_frames": int(content.sum()),
                     "mean_confidence": round(float(confidence[valid].mean()), 4) if valid.any() else 0.0}
    for name, prefix in ERRORS.items():
        if name not in scores:
            continue
        errors = scores[name]
        metrics.update({f"{prefix}mpjpe_body_cm": _mean(errors[:, BODY_SLICE]),
                        f"{prefix}mpjpe_hands_cm": _mean(errors[:, HANDS_SLICE]),
                        f"{prefix}mpjpe_all_cm": _mean(errors)})
        if not prefix:
            metrics["scored_frames"] = int(np.isfinite(errors).all(axis=1).sum())
    return metrics


def merged_metrics(root, manifests: list[dict]) -> dict:
    """The metrics of merged frame shards (:func:`egorelight_cli.sharding.merge_parts`): computed
    from the merged ``scores.npz`` and ``keypoints.npz`` in ``root``, as a single run does."""
    from pathlib import Path

    from egorelight_cli.io.keypoints import KEYPOINTS_PAYLOAD, read_keypoints_npz
    from egorelight_cli.io.npz import read_npz

    scores, _ = read_npz(Path(root) / SCORES_NPZ, check_finite=False)
    keypoints = read_keypoints_npz(Path(root) / KEYPOINTS_PAYLOAD)
    first = manifests[0]["metrics"]
    metrics = {"head_poses": first["head_poses"], **egopose_metrics(scores, keypoints.confidence)}
    for key in ("groundtruth_not_scored", "groundtruth_frame"):  # the same in every shard
        if key in first:
            metrics[key] = first[key]
    return metrics
