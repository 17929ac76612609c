"""The depth network's body-mask threshold, chosen on validation frames (ours; the paper gives none).

Inference keeps a pixel's depth where the network's body probability is above a threshold
(:func:`~egorelight_cli.stages.egodepth.kept_range`). A background pixel that passes it lands
metres off the body, so a handful of them dominate the point cloud's error: on the cpu capture a
model trained on 64 frames kept 91 % body pixels at 0.5 and its `test` point-to-surface was
3.67 cm, 0.71 cm at 0.9, while the 32-frame model was 99.7 % precise at 0.5 already. So
``train egodepth`` sets frames aside (:func:`~egorelight_cli.sharding.split_frames`),
measures on them, with every other inference filter applied, which share of the kept pixels the
reconstruction shows as body (precision) and which share of the body pixels is kept (recall) at
each of :data:`THRESHOLDS`, and stores the lowest threshold whose precision reaches
``train.mask_precision`` (:func:`choose_threshold`) in the model; ``egodepth`` uses it unless
``predict.mask_threshold`` is set.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

#: the thresholds tried, lowest first (0.5 is the plain classifier's)
THRESHOLDS = tuple(round(0.5 + 0.05 * i, 2) for i in range(10))


@torch.no_grad()
def precision_recall(model, views: Sequence, ray_maps: dict, self_masks: dict, settings, device: torch.device,
                     thresholds: Sequence[float] = THRESHOLDS, prior_fn=None) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall (T,) of the pixels inference keeps at each of ``thresholds`` (T,) over
    ``views`` (:class:`~egorelight_cli.stages.egodepth.TrainingView` with their stereo ranges when
    the network takes them), against the views' ``supervised`` pixels (the reconstruction's body)
    inside the lens and outside the self-occlusion masks. ``settings``: the
    :class:`~egorelight_cli.stages.egodepth.PredictSettings` of the other filters."""
    from egorelight_cli.stages.egodepth import kept_range, network_maps

    kept = np.zeros(len(thresholds))
    kept_body = np.zeros(len(thresholds))
    body = 0
    for start in range(0, len(views), 4):
        chunk = views[start:start + 4]
        stereo = np.stack([v.stereo for v in chunk]) if chunk[0].stereo is not None else None
        ranges, probability, scale = network_maps(model, np.stack([v.image for v in chunk]),
                                                  np.stack([ray_maps[v.role][0] for v in chunk]), device, prior_fn,
                                                  stereo)
        for i, view in enumerate(chunk):
            inside = ray_maps[view.role][1] & ~self_masks.get(view.role, False)
            truth = view.supervised & inside
            body += int(truth.sum())
            for k, threshold in enumerate(thresholds):
                keep = kept_range(ranges[i], probability[i], scale[i] if scale is not None else None, inside,
                                  settings, float(threshold)) > 0
                kept[k] += int(keep.sum())
                kept_body[k] += int((keep & truth).sum())
    precision = np.divide(kept_body, kept, out=np.ones_like(kept), where=kept > 0)
    recall = kept_body / body if body else np.zeros_like(kept)
    return precision, recall


def choose_threshold(precision: np.ndarray, thresholds: Sequence[float], target: float) -> float:
    """The lowest of ``thresholds`` (ascending) whose ``precision`` reaches ``target``; the most
    precise one when none does."""
    reached = np.nonzero(np.asarray(precision) >= target)[0]
    index = int(reached[0]) if reached.size else int(np.argmax(precision))
    return float(thresholds[index])


def validation_report(model, views: Sequence, ray_maps: dict, self_masks: dict, settings, target: float,
                      device: torch.device, prior_fn=None) -> dict:
    """The model's body-mask threshold and the manifest metrics that justify it: precision and
    recall on the validation ``views`` at the plain 0.5 and at the chosen threshold. No views: the
    plain 0.5, with ``mask_threshold_source`` saying why."""
    if not views:
        return {"mask_threshold": THRESHOLDS[0], "mask_threshold_source": "default (no validation frames)",
                "validation_views": 0}
    precision, recall = precision_recall(model, views, ray_maps, self_masks, settings, device, THRESHOLDS, prior_fn)
    chosen = choose_threshold(precision, THRESHOLDS, target)
    k = THRESHOLDS.index(chosen)
    return {"mask_threshold": chosen,
            "mask_threshold_source": f"lowest threshold with validation precision >= {target}",
            "validation_views": len(views),
            "validation_mask_precision_at_0.5": float(precision[0]),
            "validation_mask_recall_at_0.5": float(recall[0]),
            "validation_mask_precision": float(precision[k]),
            "validation_mask_recall": float(recall[k]),
            "validation_mask_curve": {f"{t:.2f}": [round(float(p), 5), round(float(r), 5)]
                                      for t, p, r in zip(THRESHOLDS, precision, recall)}}
