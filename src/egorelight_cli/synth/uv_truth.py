"""Per-frame UV ground truth for scoring GeoLift (``groundtruth/<seq>/uv_truth.npz``).

The subject's outer surface keeps the template's UV layout (its body is the template subdivided,
its garments are cut from the body's faces), so a UV map of the subject lines up with the maps of
any character fitted from the template (``character default`` or ``fit-scan``). For every studio
content frame (every ``groundtruth.uv_frame_stride``-th), at ``resolution`` texels:

* ``normals`` -- the true world normal at each texel *with the sub-mesh detail* (the posed
  surface's interpolated normal tilted by the detail normal map, exactly as the renderer shades);
* ``flat_texture`` -- the true flat-lit *diffuse* texture ``albedo / pi * E_flat * exposure``:
  irradiance of the flat lighting (``lights.flat_intensity``) on the true surface with its own
  shadows and the detail normals, true albedo, the studio exposure. The specular sheen of the
  flat-lit images is not part of it.

Arrays: ``normals``, ``flat_texture`` (T,N,3) float16 at the ``coverage`` (R,R) texels (row-major
order of ``coverage``), ``frame_ids`` (T,). Evaluation only.
"""

from __future__ import annotations

import numpy as np

from egorelight_cli.io.npz import write_npz
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import rasterize_uv, texel_centres_uv
from egorelight_cli.render.shading import Material
from egorelight_cli.render.uv_features import irradiance_map, texel_lighting, texel_surface
from egorelight_cli.synth.appearance import Appearance
from egorelight_cli.synth.subject import Subject

UV_TRUTH = "uv_truth.npz"


class UVTruth:
    """Computes the UV truth of posed outer surfaces of one subject (see the module docstring)."""

    def __init__(self, subject: Subject, appearance: Appearance, lightstage: LightStage, flat_intensity: float,
                 exposure: float, resolution: int):
        self.subject, self.lightstage = subject, lightstage
        # faithful to UV (no conservative pass): a texel is the surface point at its own UV, the
        # point any mesh in the same layout shows there
        self.raster = rasterize_uv(subject.face_uvs, int(resolution), conservative=False)
        covered = self.raster.coverage
        self.face_id = self.raster.face_id[covered]
        self.uv = texel_centres_uv(self.raster.resolution)[covered]
        self.material = Material(albedo=appearance.albedo, normal_map=appearance.normal_map)
        self.albedo = self.material.at(self.uv, len(self.uv))[0]
        self.flat = lightstage.flat(float(flat_intensity))
        self.exposure = float(exposure)

    def frame(self, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(normals (N,3), flat-lit diffuse texture (N,3)) of one posed outer surface (V,3)."""
        faces = self.subject.faces
        surface = texel_surface(self.raster, vertices, faces)
        normals = self.material.detail_normals(surface.normals.astype(np.float32), self.uv, self.face_id, vertices,
                                               faces, self.subject.face_uvs).astype(np.float64)
        lit = texel_lighting(self.raster, vertices, faces, self.lightstage, normals=normals, surface=surface)
        irradiance = irradiance_map(lit.transfer, self.lightstage, self.flat).numpy()
        return normals, self.albedo / np.pi * irradiance * self.exposure

    def write(self, path, surfaces: np.ndarray, frame_ids: np.ndarray) -> None:
        """Write the truth of the surfaces (T,V,3) of ``frame_ids`` (T,) to ``path``."""
        rows = [self.frame(np.asarray(v, np.float64)) for v in surfaces]
        normals = np.stack([n for n, _ in rows]) if rows else np.zeros((0, len(self.uv), 3))
        texture = np.stack([t for _, t in rows]) if rows else np.zeros((0, len(self.uv), 3))
        frame_ids = np.asarray(frame_ids, np.int64)
        write_npz(path, {"normals": normals.astype(np.float16), "flat_texture": texture.astype(np.float16),
                         "coverage": self.raster.coverage, "frame_ids": frame_ids},
                  {"kind": "egorelight/synth_uv_truth", "version": 1, "frame_ids": frame_ids.tolist(),
                   "units": {"normals": "unit vector, world frame", "flat_texture": "linear radiance (flat-lit diffuse)"},
                   "resolution": int(self.raster.resolution[0]), "layout": "the template's UV layout"})
