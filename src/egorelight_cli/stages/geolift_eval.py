"""Scoring GeoLift against a simulated capture's ground truth (evaluation only).

The truth is ``groundtruth/<seq>/uv_truth.npz`` (:mod:`egorelight_cli.synth.uv_truth`): per studio
content frame, in the template's UV layout (which every character fitted from the template
shares), the true normals *with the subject's sub-mesh detail* and the true flat-lit *diffuse*
texture ``albedo / pi * E_flat * exposure``. It is compared with a predicted texel in two ways:

* **at the surface the mesh shows** (the headline ``normal_deg``, ``texture_l1``): the truth at
  the point of the true surface (``groundtruth/<seq>/meshes.npz``) closest to the texel's point
  on the tracked mesh, looked up in the truth maps at that point's UV. This is what a render
  through the tracked mesh shows at the texel, so it scores the maps for what they are used
  for; the tracking error is in the distance (``surface_distance_median_mm``) and in the
  geometry stages' P2S.
* **at the texel's material point** (``normal_deg_uv``, ``texture_l1_uv``): the truth at the
  texel's own UV. A tracked mesh that is within millimetres of the true surface still slides
  along it by centimetres (a bone twist, the mocap's bias), so this also charges the maps for the
  tracking's sliding, which no appearance model can undo: networks trained on images learn the
  detail *where the mesh shows it*.

Truth maps are looked up at the nearest texel the truth covers. Both comparisons score the texels
that sample their own UV: the raster's conservative pass (:func:`~egorelight_cli.render.raster.rasterize_uv`)
moves texels to faces smaller than a texel nearby (40 % of the character's texels at 64x64),
and what the maps hold there was learned through the UV lookups of the pixels of *other* faces,
so neither truth is the right one for them. The material comparison also needs the truth to
cover the texel entirely after area resampling. Next to every score is its baseline: the tracked
mesh's coarse normals and the mean texture. The specular sheen of the flat-lit images is not
part of the truth; it biases the network and the baseline alike.

Without ``uv_truth.npz`` (a real capture, or a sequence the simulator gave none) the scores are
``null`` with the reason; without the true meshes' ``face_uvs`` only the material comparison is made.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage
from trimesh.triangles import points_to_barycentric

from egorelight_cli.geometry.pointcloud_ops import SurfaceDistance
from egorelight_cli.io.capture import Capture
from egorelight_cli.io.npz import read_npz
from egorelight_cli.render.raster import UVRaster, uv_to_texel_coords
from egorelight_cli.stages.geolift import angle_deg

UV_TRUTH = "uv_truth.npz"
TRUE_MESHES = "meshes.npz"


def _resample(values: np.ndarray, coverage: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H,W,C) map of per-texel values (N,C) at ``coverage``, area-resampled to ``shape``."""
    full = np.zeros(coverage.shape + (values.shape[-1],), np.float32)
    full[coverage] = values
    if full.shape[:2] == tuple(shape):
        return full
    return cv2.resize(full, (shape[1], shape[0]), interpolation=cv2.INTER_AREA).reshape(tuple(shape) + (-1,))


class GeoLiftTruth:
    """The true UV normals and flat-lit texture of one sequence, for a GeoLift raster's texels."""

    def __init__(self, capture: Capture, sequence: str, raster: UVRaster):
        self.raster = raster
        path = capture.groundtruth_file(sequence, UV_TRUTH)
        self.reason = None if path is not None else (
            "the capture has no UV ground truth for this sequence" if capture.groundtruth_root() is not None
            else "the capture has no ground truth")
        self.frame_ids = np.zeros(0, np.int64)
        self.surfaces = None
        if path is None:
            return
        arrays, _ = read_npz(path)
        self.normals, self.texture = arrays["normals"], arrays["flat_texture"]
        self.coverage = arrays["coverage"].astype(bool)
        self.frame_ids = np.asarray(arrays["frame_ids"], np.int64)
        both = _resample(np.ones((int(self.coverage.sum()), 1), np.float32), self.coverage, raster.resolution)
        faithful = ~raster.reassigned if raster.reassigned is not None else np.ones(raster.resolution, bool)
        self.faithful = faithful[raster.coverage]
        self.valid = (both[..., 0] > 0.999)[raster.coverage] & self.faithful
        # each texel of the truth's grid -> the row of its nearest covered texel
        _, (rows, cols) = ndimage.distance_transform_edt(~self.coverage, return_indices=True)
        order = np.full(self.coverage.shape, -1, np.int64)
        order[self.coverage] = np.arange(int(self.coverage.sum()))
        self.nearest = order[rows, cols]
        meshes_path = capture.groundtruth_file(sequence, TRUE_MESHES)
        if meshes_path is not None:
            meshes, _ = read_npz(meshes_path, check_finite=False)
            if "face_uvs" in meshes:
                self.surfaces = meshes

    @property
    def available(self) -> bool:
        return self.reason is None

    def has(self, frame_id: int) -> bool:
        return self.available and int(frame_id) in set(self.frame_ids.tolist())

    def _row(self, frame_id: int) -> int:
        return int(np.flatnonzero(self.frame_ids == int(frame_id))[0])

    def frame(self, frame_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """At the texels' own UVs: (true normals (N,3), true flat-lit diffuse texture (N,3),
        valid (N,) bool) at the raster's covered texels."""
        row = self._row(frame_id)
        shape, covered = self.raster.resolution, self.raster.coverage
        normals = _resample(self.normals[row].astype(np.float32), self.coverage, shape)[covered]
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.maximum(length, 1e-12)
        texture = _resample(self.texture[row].astype(np.float32), self.coverage, shape)[covered]
        return normals, texture, self.valid & (length[:, 0] > 0.5)

    def at_surface(self, frame_id: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """At the closest points of the true surface to ``points`` (N,3) (the covered texels'
        points on the tracked mesh): (true normals (N,3), true texture (N,3), distance (N,) m),
        or None without true meshes with UVs for this frame."""
        if self.surfaces is None or not np.any(self.surfaces["frame_ids"] == int(frame_id)):
            return None
        k = int(np.flatnonzero(self.surfaces["frame_ids"] == int(frame_id))[0])
        vertices = np.asarray(self.surfaces["vertices"][k], np.float64)
        faces = np.asarray(self.surfaces["faces"], np.int64)
        closest, face, distance = SurfaceDistance(vertices, faces).closest(points)
        weights = points_to_barycentric(vertices[faces[face]], closest)
        uv = np.einsum("nk,nkd->nd", weights, np.asarray(self.surfaces["face_uvs"], np.float64)[face])
        height, width = self.coverage.shape
        xy = np.rint(uv_to_texel_coords(uv, (height, width))).astype(np.int64)
        texel = self.nearest[np.clip(xy[:, 1], 0, height - 1), np.clip(xy[:, 0], 0, width - 1)]
        row = self._row(frame_id)
        normals = self.normals[row][texel].astype(np.float64)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        return normals, self.texture[row][texel].astype(np.float64), distance


SCORES_NPZ = "scores.npz"
SCORE_KEYS = ("normal_deg", "normal_deg_coarse", "texture_l1", "texture_l1_mean_texture", "surface_distance_median_mm",
              "normal_deg_uv", "normal_deg_uv_coarse", "texture_l1_uv", "texture_l1_uv_mean_texture")


class GeoLiftScores:
    """Per-frame errors of the prediction and of the baselines (see the module docstring), one row
    per scored frame; :meth:`arrays` are the rows of ``scores.npz`` (NaN: not scored)."""

    def __init__(self):
        self.frame_ids: list[int] = []
        self.rows: dict[str, list[float]] = {key: [] for key in SCORE_KEYS}

    def _add(self, values: dict, suffix: str, keep: np.ndarray, texels, truth_normals, truth_texture,
             maps: dict) -> None:
        if not keep.any():
            return
        values[f"normal_deg{suffix}"] = float(angle_deg(texels(maps["normals"])[keep], truth_normals[keep]).mean())
        values[f"normal_deg{suffix}_coarse"] = float(angle_deg(texels(maps["coarse"])[keep], truth_normals[keep]).mean())
        if truth_texture is not None:
            for key, name in (("texture", ""), ("mean_texture", "_mean_texture")):
                values[f"texture_l1{suffix}{name}"] = float(np.abs(texels(maps[key])[keep] - truth_texture[keep]).mean())

    def add(self, truth: GeoLiftTruth, frame_id: int, points: np.ndarray, normals: np.ndarray, coarse: np.ndarray,
            texture: np.ndarray, mean_texture: np.ndarray) -> None:
        """Score one frame: maps (3,H,W) on ``truth.raster``; ``points`` (N,3) the covered texels'
        points on the tracked mesh."""
        maps = {"normals": normals, "coarse": coarse, "texture": texture, "mean_texture": mean_texture}
        coverage = truth.raster.coverage

        def texels(m):
            return np.moveaxis(m, 0, -1)[coverage]

        values: dict[str, float] = {}
        truth_normals, truth_texture, valid = truth.frame(frame_id)
        self._add(values, "_uv", valid, texels, truth_normals, truth_texture, maps)
        surface = truth.at_surface(frame_id, points)
        if surface is not None:
            truth_normals, truth_texture, distance = surface
            self._add(values, "", truth.faithful, texels, truth_normals, truth_texture, maps)
            values["surface_distance_median_mm"] = float(np.median(distance[truth.faithful]) * 1000)
        self.frame_ids.append(int(frame_id))
        for key in SCORE_KEYS:
            self.rows[key].append(values.get(key, np.nan))

    def arrays(self) -> dict[str, np.ndarray]:
        return {"frame_ids": np.array(self.frame_ids, np.int64),
                **{key: np.array(values, np.float64) for key, values in self.rows.items()}}

    def metrics(self) -> dict:
        return geolift_metrics(self.arrays())


def geolift_metrics(rows: dict[str, np.ndarray]) -> dict:
    """Each score's mean over the frames that have it (None where none has), from the rows of
    ``scores.npz`` (a whole run's or merged frame shards')."""
    out = {}
    for key in SCORE_KEYS:
        values = rows[key][np.isfinite(rows[key])]
        out[key] = float(values.mean()) if values.size else None
    return out


def merged_metrics(root, manifests: list[dict]) -> dict:
    """The metrics of merged frame shards (:func:`egorelight_cli.sharding.merge_parts`): counts
    summed over the parts, the scores from the merged ``scores.npz``, as a single run computes them."""
    from pathlib import Path

    from egorelight_cli.io.npz import read_npz

    first = manifests[0]["metrics"]
    metrics = {k: v for k, v in first.items() if k not in SCORE_KEYS}
    for key in ("frames", "frames_with_lighting_features"):
        metrics[key] = sum(int(m["metrics"][key]) for m in manifests)
    if all(key in first for key in SCORE_KEYS):
        rows, _ = read_npz(Path(root) / SCORES_NPZ, check_finite=False)
        metrics.update(geolift_metrics(rows))
    return metrics
