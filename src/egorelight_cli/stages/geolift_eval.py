"""Scoring GeoLift against a simulated capture's ground truth (evaluation only).

The truth is ``groundtruth/<seq>/uv_truth.npz`` (:mod:`egorelight_cli.synth.uv_truth`): per studio
content frame, in the template's UV layout (which every character fitted from the template
shares), the true normals *with the subject's sub-mesh detail* and the true flat-lit *diffuse*
texture ``albedo / pi * E_flat * exposure``. Its maps are resampled to the GeoLift resolution
(area averaging; normals renormalised) and scored at the texels both cover:

* **normals**: angle (degrees) between the predicted UV normal and the true one, next to the
  baseline of the tracked mesh's coarse normals;
* **texture**: L1 (linear radiance) between the predicted flat-lit texture and the true one, next
  to the mean-texture baseline. The specular sheen of the flat-lit images is not part of the truth;
  it biases the network and the baseline alike.

Without ``uv_truth.npz`` (a real capture, or a sequence the simulator gave none) the scores are
``null`` with the reason.
"""

from __future__ import annotations

import cv2
import numpy as np

from egorelight_cli.io.capture import Capture
from egorelight_cli.io.npz import read_npz
from egorelight_cli.render.raster import UVRaster
from egorelight_cli.stages.geolift import angle_deg

UV_TRUTH = "uv_truth.npz"


def _resample(values: np.ndarray, coverage: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H,W,C) map of per-texel values (N,C) at ``coverage``, area-resampled to ``shape``."""
    full = np.zeros(coverage.shape + (values.shape[-1],), np.float32)
    full[coverage] = values
    if full.shape[:2] == tuple(shape):
        return full
    return cv2.resize(full, (shape[1], shape[0]), interpolation=cv2.INTER_AREA).reshape(tuple(shape) + (-1,))


class GeoLiftTruth:
    """The true UV normals and flat-lit texture of one sequence at a GeoLift raster's texels."""

    def __init__(self, capture: Capture, sequence: str, raster: UVRaster):
        self.raster = raster
        path = capture.groundtruth_file(sequence, UV_TRUTH)
        self.reason = None if path is not None else (
            "the capture has no UV ground truth for this sequence" if capture.groundtruth_root() is not None
            else "the capture has no ground truth")
        self.frame_ids = np.zeros(0, np.int64)
        if path is not None:
            arrays, _ = read_npz(path)
            self.normals, self.texture = arrays["normals"], arrays["flat_texture"]
            self.coverage = arrays["coverage"].astype(bool)
            self.frame_ids = np.asarray(arrays["frame_ids"], np.int64)
            both = _resample(np.ones((int(self.coverage.sum()), 1), np.float32), self.coverage, raster.resolution)
            # texels the truth covers entirely (area resampling blends island borders with empty texels)
            self.valid = (both[..., 0] > 0.999)[raster.coverage]

    @property
    def available(self) -> bool:
        return self.reason is None

    def has(self, frame_id: int) -> bool:
        return self.available and int(frame_id) in set(self.frame_ids.tolist())

    def frame(self, frame_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(true normals (N,3), true flat-lit diffuse texture (N,3), valid (N,) bool) at the
        raster's covered texels."""
        row = int(np.flatnonzero(self.frame_ids == int(frame_id))[0])
        shape, covered = self.raster.resolution, self.raster.coverage
        normals = _resample(self.normals[row].astype(np.float32), self.coverage, shape)[covered]
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.maximum(length, 1e-12)
        texture = _resample(self.texture[row].astype(np.float32), self.coverage, shape)[covered]
        return normals, texture, self.valid & (length[:, 0] > 0.5)


class GeoLiftScores:
    """Accumulates per-frame errors of the prediction and of the baselines."""

    def __init__(self):
        self.rows: dict[str, list[float]] = {"normal_deg": [], "normal_deg_coarse": [], "texture_l1": [],
                                             "texture_l1_mean_texture": []}

    def add(self, coverage: np.ndarray, normals: np.ndarray, coarse: np.ndarray, texture: np.ndarray,
            mean_texture: np.ndarray, truth_normals: np.ndarray, truth_texture: np.ndarray | None,
            valid: np.ndarray | None = None) -> None:
        """Maps are (3,H,W); the truth is per covered texel (N,3), scored where ``valid`` (N,)."""
        keep = np.ones(int(coverage.sum()), bool) if valid is None else np.asarray(valid, bool)
        truth_normals = truth_normals[keep]
        truth_texture = None if truth_texture is None else truth_texture[keep]

        def texels(maps):
            return np.moveaxis(maps, 0, -1)[coverage][keep]

        self.rows["normal_deg"].append(float(angle_deg(texels(normals), truth_normals).mean()))
        self.rows["normal_deg_coarse"].append(float(angle_deg(texels(coarse), truth_normals).mean()))
        if truth_texture is not None:
            self.rows["texture_l1"].append(float(np.abs(texels(texture) - truth_texture).mean()))
            self.rows["texture_l1_mean_texture"].append(float(np.abs(texels(mean_texture) - truth_texture).mean()))

    def metrics(self) -> dict:
        return {key: float(np.mean(values)) if values else None for key, values in self.rows.items()}
