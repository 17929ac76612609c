"""Scoring GeoLift against a simulated capture's ground truth (evaluation only).

Per frame of a sequence with true meshes (``groundtruth/<seq>/meshes.npz``):

* **normals**: angle (degrees) between the predicted UV normal and the true surface's normal at
  each covered texel, next to the baseline of the tracked mesh's coarse normals;
* **texture**: L1 (linear radiance) between the predicted flat-lit texture and the true flat-lit
  *diffuse* texture ``albedo / pi * E_flat * exposure`` (true albedo from
  ``groundtruth/appearance.exr``, irradiance of the training's flat lighting on the true surface
  with its shadows, the capture's studio exposure), next to the mean-texture baseline. The
  specular sheen of the flat-lit images is not part of the truth; it biases the network and
  the baseline alike.

The truth needs the character's UV layout: when the true meshes have another topology the
scores are ``null`` with the reason (an out-of-model subject brings its own UV truth).
"""

from __future__ import annotations

import cv2
import numpy as np

from egorelight_cli.io.capture import Capture
from egorelight_cli.io.exr import read_exr
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import UVRaster
from egorelight_cli.render.uv_features import irradiance_map, texel_lighting, texel_surface
from egorelight_cli.stages.animate_eval import groundtruth_meshes
from egorelight_cli.stages.geolift import angle_deg


class GeoLiftTruth:
    """The true UV normals and flat-lit texture of one sequence, frame by frame."""

    def __init__(self, capture: Capture, sequence: str, raster: UVRaster, faces: np.ndarray, num_vertices: int,
                 flat_scale: float, exposure: float = 1.0):
        self.raster, self.faces = raster, faces
        self.meshes = groundtruth_meshes(capture, sequence)
        self.reason = None
        if self.meshes is None:
            self.reason = "the capture has no ground truth"
        elif self.meshes.vertices.shape[1] != num_vertices:
            self.reason = (f"the true meshes have {self.meshes.vertices.shape[1]} vertices, the character "
                           f"{num_vertices}: no UV truth in this layout")
        self.albedo = None
        appearance = capture.root / "groundtruth" / "appearance.exr"
        if self.reason is None and appearance.is_file():
            albedo = read_exr(appearance).layer("albedo")
            height, width = raster.resolution
            self.albedo = cv2.resize(albedo, (width, height), interpolation=cv2.INTER_AREA)[raster.coverage]
        self.lightstage = LightStage.from_json(capture.lights_path())
        self.flat = self.lightstage.flat(flat_scale)
        self.exposure = float(exposure)

    @property
    def available(self) -> bool:
        return self.reason is None

    def has(self, frame_id: int) -> bool:
        return self.available and int(frame_id) in set(self.meshes.frame_ids.tolist())

    def frame(self, frame_id: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(true normals (N,3), true flat-lit diffuse texture (N,3) or None) at the covered texels."""
        vertices = self.meshes.vertices[self.meshes.index_of(int(frame_id))]
        if self.albedo is None:
            return texel_surface(self.raster, vertices, self.faces).normals, None
        lit = texel_lighting(self.raster, vertices, self.faces, self.lightstage)
        irradiance = irradiance_map(lit.transfer, self.lightstage, self.flat).numpy()
        return lit.surface.normals, self.albedo / np.pi * irradiance * self.exposure


class GeoLiftScores:
    """Accumulates per-frame errors of the prediction and of the baselines."""

    def __init__(self):
        self.rows: dict[str, list[float]] = {"normal_deg": [], "normal_deg_coarse": [], "texture_l1": [],
                                             "texture_l1_mean_texture": []}

    def add(self, coverage: np.ndarray, normals: np.ndarray, coarse: np.ndarray, texture: np.ndarray,
            mean_texture: np.ndarray, truth_normals: np.ndarray, truth_texture: np.ndarray | None) -> None:
        """Maps are (3,H,W); the truth is per covered texel (N,3)."""
        def texels(maps):
            return np.moveaxis(maps, 0, -1)[coverage]

        self.rows["normal_deg"].append(float(angle_deg(texels(normals), truth_normals).mean()))
        self.rows["normal_deg_coarse"].append(float(angle_deg(texels(coarse), truth_normals).mean()))
        if truth_texture is not None:
            self.rows["texture_l1"].append(float(np.abs(texels(texture) - truth_texture).mean()))
            self.rows["texture_l1_mean_texture"].append(float(np.abs(texels(mean_texture) - truth_texture).mean()))

    def metrics(self) -> dict:
        return {key: float(np.mean(values)) if values else None for key, values in self.rows.items()}
