"""The ``egorelight envmap`` command: load the capture and calibration, call
:mod:`egorelight_cli.stages.envmap`, score against the simulator's truth, write the artifact.

An ``envmap`` artifact directory holds

* ``envmap.exr``: ``E_h``, (H,2H) equirect RGB float32 (``geometry/equirect.py`` convention) in the
  frame of the sequence's calibrated head poses;
* ``panorama.exr``: the observed panorama ``E_o`` (RGB, 0 where unobserved) and its summed view
  weights (channel ``weight.Y``);
* ``coverage.png``: 255 where a camera saw the texel;
* ``colour_model.json``: ``A`` (3x6), ``gamma``, the terms, and which row of the method made it;
* ``light_intensities.npz``: ``intensities`` (L,3) = ``S(E_h)`` on the capture's light stage,
  ``frame_ids`` of the scan frames used;
* ``preview.png``: the panorama (unobserved texels dark red), ``E_h`` and, with ground truth,
  the true map in the same frame, each tone-mapped.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from egorelight_cli import console
from egorelight_cli.artifacts import ArtifactWriter
from egorelight_cli.config import Config
from egorelight_cli.io.calibration import open_calibration
from egorelight_cli.io.capture import open_capture
from egorelight_cli.pipeline import StageRun

ENVMAP_EXR = "envmap.exr"
PANORAMA_EXR = "panorama.exr"
COVERAGE_PNG = "coverage.png"
COLOUR_MODEL_JSON = "colour_model.json"
INTENSITIES_NPZ = "light_intensities.npz"
PREVIEW_PNG = "preview.png"
#: The method row this stage writes until the inverse rendering exists (issue 19 ablations).
ROW = "ldr_panorama_only"


@dataclass(frozen=True)
class EnvmapCommands:
    """``envmap`` over one :class:`StageRun`."""

    run: StageRun

    def predict(self, capture_path: Path, calibration_path: Path, seq: str, out: Path) -> Path:
        capture, capture_artifact = open_capture(capture_path, [seq])
        calibration, calibration_artifact = open_calibration(calibration_path)
        sequence = capture.sequence(seq)
        inputs = [capture_artifact, calibration_artifact]
        options = {"sequence": sequence.name}
        if self.run.up_to_date(out, "envmap", inputs, options=options):
            return Path(out)
        from egorelight_cli.stages import envmap as em

        settings = em.PanoramaSettings.from_config(self.run.config())
        sequence.require_stream("ego")
        em.scan_frames(calibration, sequence, settings.frames, settings.scan_s)  # fail before the output is touched

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            from egorelight_cli.errors import EgorelightError

            if writer.single_file:
                raise EgorelightError("an envmap artifact is a directory (it holds EXRs and PNGs): give --out a "
                                      "directory", out)
            _write_envmap(writer, cfg, capture, calibration, sequence, settings)

        return self.run.produce(out, "envmap", write, inputs=inputs, options=options)


def _write_envmap(writer: ArtifactWriter, cfg: Config, capture, calibration, sequence, settings) -> None:
    import time

    from egorelight_cli.io.exr import write_exr_layers
    from egorelight_cli.io.images import write_image
    from egorelight_cli.render.envmaps import write_envmap
    from egorelight_cli.render.lightstage import LightStage
    from egorelight_cli.stages import envmap as em
    from egorelight_cli.stages import envmap_eval as ev

    started = time.perf_counter()
    lightstage = LightStage.from_json(capture.lights_path())
    result = em.build_envmap(capture, calibration, sequence, settings, lightstage)
    writer.timing["envmap_s"] = round(time.perf_counter() - started, 3)
    console.info(f"envmap {sequence.name}: {len(result.frame_ids)} scan frames, "
                 f"{100 * result.panorama.coverage_fraction:.0f}% of the sphere observed")
    write_envmap(writer.path(ENVMAP_EXR), result.envmap)
    write_exr_layers(writer.path(PANORAMA_EXR), {"": np.ascontiguousarray(result.panorama.radiance),
                                                  "weight": np.ascontiguousarray(result.panorama.weight)})
    write_image(writer.path(COVERAGE_PNG), (result.panorama.coverage * 255).astype(np.uint8))
    writer.save_json(COLOUR_MODEL_JSON, result.colour_model.to_json(
        row=ROW, fitted=False, input="E_l: the inpainted panorama, linearised front-camera sRGB (camera response "
                                     "unknown)", output="E_h: the map in envmap.exr"))
    writer.save_npz(INTENSITIES_NPZ, {"intensities": result.intensities.astype(np.float32)},
                    frame_ids=result.frame_ids, units={"intensities": "linear RGB radiance per light (S(E_h))"},
                    sequence=sequence.name, num_lights=lightstage.num_lights)
    truth = ev.wild_truth(capture, calibration, sequence.name, result.frame_ids)
    write_image(writer.path(PREVIEW_PNG), preview(result, truth.envmap if truth else None, int(cfg.preview.width)))
    writer.metrics.update({
        "row": ROW, "sequence": sequence.name, "scan_frames": len(result.frame_ids),
        "views": len(result.frame_ids) * len(settings.roles), "roles": list(settings.roles),
        "coverage_fraction": result.panorama.coverage_fraction, "clipped_pixel_fraction": result.clipped_fraction,
        "map_height": settings.height, "num_lights": lightstage.num_lights,
    })
    if truth is not None:
        writer.metrics.update(ev.envmap_metrics(result.envmap, result.panorama.coverage, truth.envmap, lightstage,
                                                float(cfg.eval.log_eps)))
        writer.metrics.update({"truth_envmap": truth.name, "truth_frame_yaw_deg": truth.frame_yaw_deg,
                               "truth_frame_tilt_deg": truth.frame_tilt_deg})
    writer.extra["frame"] = f"the calibrated head poses of sequence {sequence.name}"
    writer.extra["camera_response"] = ("unknown: front images linearised by the inverse sRGB curve only; the colour "
                                       "model is the identity (A = [I | 0], gamma = 1) until the inverse rendering")
    writer.units.update({"envmap": "linear RGB radiance (front-camera units)", "centre_m": "m"})
    writer.extra["centre_m"] = [float(c) for c in result.centre]


def preview(result, truth: np.ndarray | None, width: int) -> np.ndarray:
    """(h,w,3) uint8: rows panorama (unobserved texels dark red), E_h, and the truth when given."""
    from egorelight_cli.io.images import tonemap

    height = max(width // 2, 1)

    def row(envmap: np.ndarray, label: str, mask: np.ndarray | None = None) -> np.ndarray:
        image = tonemap(envmap, mask)
        if mask is not None:
            image = np.where(mask[..., None], image, np.array([90, 0, 0], np.uint8))
        image = cv2.resize(np.ascontiguousarray(image), (width, height), interpolation=cv2.INTER_NEAREST)
        cv2.putText(image, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
        return image

    rows = [row(result.panorama.radiance, "panorama E_o (observed)", result.panorama.coverage),
            row(result.envmap, "E_h (inpainted, colour model)")]
    if truth is not None:
        rows.append(row(truth, "truth (same frame)"))
    return np.concatenate(rows, axis=0)
