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

With ``--meshes/--uvmaps/--model`` (tracked meshes and GeoLift uvmaps of the sequence, the relight
model) and ``--sync-meshes/--sync-uvmaps`` (the same of the studio sequence ``inverse.sync.sequence``
with ego images, for the colour synchronisation), ``A`` and ``gamma`` are fitted by inverse
rendering (:mod:`egorelight_cli.stages.envmap_inverse`) and the artifact also holds
``inverse_preview.png`` (per view: ego image, ego warped onto the render, the fitted render, the
part masks) and ``curve.json`` (the fit's loss). The manifest's ``metrics.rows`` holds every row
(``ldr_panorama_only``, ``fitted``, ``no_flow``, ``no_part_masks``) with the same metrics, plus the
relit-render PSNR; the top-level metrics are the row written as ``envmap.exr``. Without those
inputs the stage writes the LDR-panorama row and says so.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from egorelight_cli import console
from egorelight_cli.artifacts import ArtifactWriter
from egorelight_cli.config import Config
from egorelight_cli.io.calibration import open_calibration
from egorelight_cli.io.capture import open_capture
from egorelight_cli.errors import EgorelightError
from egorelight_cli.pipeline import StageRun

if TYPE_CHECKING:  # the inverse rendering's module is imported only when it runs
    from egorelight_cli.stages.envmap_inverse import EgoAvatarData, InverseSettings

ENVMAP_EXR = "envmap.exr"
PANORAMA_EXR = "panorama.exr"
COVERAGE_PNG = "coverage.png"
COLOUR_MODEL_JSON = "colour_model.json"
INTENSITIES_NPZ = "light_intensities.npz"
PREVIEW_PNG = "preview.png"
#: The method row this stage writes until the inverse rendering exists (issue 19 ablations).
ROW = "ldr_panorama_only"
INVERSE_PREVIEW_PNG = "inverse_preview.png"
CURVE_JSON = "curve.json"


@dataclass(frozen=True)
class InverseInputs:
    """What the inverse rendering reads (paths as given on the command line)."""

    meshes: Path
    uvmaps: Path
    model: Path
    sync_meshes: Path
    sync_uvmaps: Path
    character: str = "default"

    @classmethod
    def from_options(cls, meshes, uvmaps, model, sync_meshes, sync_uvmaps, character) -> InverseInputs | None:
        """None when none is given; an error naming what is missing when only some are."""
        given = {"--meshes": meshes, "--uvmaps": uvmaps, "--model": model, "--sync-meshes": sync_meshes,
                 "--sync-uvmaps": sync_uvmaps}
        if all(v is None for v in given.values()):
            return None
        missing = [k for k, v in given.items() if v is None]
        if missing:
            raise EgorelightError(f"the inverse rendering needs {', '.join(given)} together (missing "
                                  f"{', '.join(missing)}); without all of them envmap writes the LDR-panorama row")
        return cls(Path(meshes), Path(uvmaps), Path(model), Path(sync_meshes), Path(sync_uvmaps), character)

    def open(self, capture, sequence, sync_sequence):
        """(wild data, studio data, model, the model's training sequence (None if unrecorded), input
        artifacts, source files: the lone npz and character files read)
        (:class:`~egorelight_cli.stages.envmap_inverse.EgoAvatarData`)."""
        from egorelight_cli.artifacts import check_sequence, open_artifact
        from egorelight_cli.stages.character_commands import character_sources, load_character
        from egorelight_cli.stages.envmap_inverse import EgoAvatarData
        from egorelight_cli.stages.geolift_commands import load_character_meshes
        from egorelight_cli.stages.relight_commands import load_relight_model

        character, character_artifact = load_character(self.character)
        model, net, model_artifact = load_relight_model(self.model)
        data, artifacts = [], [character_artifact, model_artifact]
        sources = character_sources(self.character, character_artifact)
        for seq, meshes_path, uvmaps_path in ((sequence, self.meshes, self.uvmaps),
                                              (sync_sequence, self.sync_meshes, self.sync_uvmaps)):
            meshes, meshes_artifact = load_character_meshes(meshes_path, character)
            uvmaps = open_artifact(uvmaps_path, kind="uvmaps")
            for artifact in (meshes_artifact, uvmaps):
                check_sequence(artifact, seq.name)
            data.append(EgoAvatarData(capture, seq, meshes, uvmaps, character, int(net["uv_resolution"]),
                                      int(net["attention_level"]), int(net["rays"])))
            artifacts += [meshes_artifact, uvmaps]
            sources += [] if meshes_artifact else [meshes_path]
        return data[0], data[1], model, net["sequence"], [a for a in artifacts if a is not None], sources


@dataclass(frozen=True)
class LoadedInverse:
    """What the inverse rendering runs on, opened before the cache check: the wild and studio
    (sync) sequences' avatar data, the relight model, the sequence it was trained on and the
    settings."""

    wild: EgoAvatarData
    studio: EgoAvatarData
    model: object
    trained_on: str
    settings: InverseSettings


@dataclass(frozen=True)
class EnvmapCommands:
    """``envmap`` over one :class:`StageRun`."""

    run: StageRun

    def predict(self, capture_path: Path, calibration_path: Path, seq: str, out: Path,
                inverse: InverseInputs | None = None) -> Path:
        sync_name = str(self.run.config().inverse.sync.sequence)
        capture, capture_artifact = open_capture(capture_path, [seq] + ([sync_name] if inverse is not None else []))
        calibration, calibration_artifact = open_calibration(calibration_path)
        sequence = capture.sequence(seq)
        inputs, sources = [capture_artifact, calibration_artifact], []
        options = {}  # --seq enters the key from the declaration; the sync sequence is derived
        loaded = None
        if inverse is not None:
            from egorelight_cli.stages.envmap_inverse import InverseSettings

            sync_sequence = capture.sequence(sync_name)
            wild, studio, model, trained_on, artifacts, sources = inverse.open(capture, sequence, sync_sequence)
            inputs += artifacts
            options["sync_sequence"] = sync_sequence.name
            loaded = LoadedInverse(wild, studio, model, trained_on, InverseSettings.from_config(self.run.config()))
        if self.run.up_to_date(out, "envmap", inputs, sources, options):
            return Path(out)
        from egorelight_cli.stages import envmap as em

        settings = em.PanoramaSettings.from_config(self.run.config())
        sequence.require_stream("ego")
        em.scan_frames(calibration, sequence, settings.frames, settings.scan_s)  # fail before the output is touched
        if loaded is not None:
            from egorelight_cli.stages import envmap_inverse as ei

            roles = loaded.settings.roles
            for data in (loaded.wild, loaded.studio):
                for role in roles:
                    if role not in data.sequence.ego_roles or role not in calibration.ego_cameras:
                        raise EgorelightError(f"inverse.roles: {data.sequence.name} or the calibration has no camera "
                                              f"{role!r} (sequence has {', '.join(data.sequence.ego_roles) or 'none'})")
            ei.usable_frames(loaded.wild, calibration, roles, 1)
            ei.usable_frames(loaded.studio, calibration, roles, 1, loaded.settings.sync_patterns)

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            if writer.single_file:
                raise EgorelightError("an envmap artifact is a directory (it holds EXRs and PNGs): give --out a "
                                      "directory", out)
            _write_envmap(writer, cfg, capture, calibration, sequence, settings, loaded)

        return self.run.produce(out, "envmap", write, inputs=inputs, source_files=sources, options=options)


def _write_envmap(writer: ArtifactWriter, cfg: Config, capture, calibration, sequence, settings,
                  loaded: LoadedInverse | None) -> None:
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
    models = {ROW: result.colour_model}
    row, inverse = ROW, None
    if loaded is not None:
        inverse = _inverse(writer, cfg, capture, calibration, result, loaded)
        models.update({name: fit.colour for name, fit in inverse.fits.items()})
        row = "fitted"
    # the root-polynomial models' cross terms can take a texel below zero: radiance is clamped there
    maps = {name: np.maximum(model.apply_numpy(result.inpainted), 0.0) for name, model in models.items()}
    envmap = maps[row]
    intensities = lightstage.envmap_to_intensities(envmap)
    write_envmap(writer.path(ENVMAP_EXR), envmap)
    write_exr_layers(writer.path(PANORAMA_EXR), {"": np.ascontiguousarray(result.panorama.radiance),
                                                  "weight": np.ascontiguousarray(result.panorama.weight)})
    write_image(writer.path(COVERAGE_PNG), (result.panorama.coverage * 255).astype(np.uint8))
    doc = models[row].to_json(row=row, fitted=inverse is not None,
                              input="E_l: the inpainted panorama, linearised front-camera sRGB (camera response "
                                    "unknown)", output="E_h: the map in envmap.exr")
    if inverse is not None:
        doc.update({"colour_sync": inverse.sync, "reg_max": inverse.reg_max, "flow": inverse.flow,
                    "rows": {name: model.to_json() for name, model in models.items()}})
    writer.save_json(COLOUR_MODEL_JSON, doc)
    writer.save_npz(INTENSITIES_NPZ, {"intensities": intensities.astype(np.float32)},
                    frame_ids=result.frame_ids, units={"intensities": "linear RGB radiance per light (S(E_h))"},
                    sequence=sequence.name, num_lights=lightstage.num_lights)
    truth = ev.wild_truth(capture, calibration, sequence.name, result.frame_ids)
    shown = dataclasses.replace(result, envmap=envmap)
    write_image(writer.path(PREVIEW_PNG), preview(shown, truth.envmap if truth else None, int(cfg.preview.width)))
    writer.metrics.update({
        "row": row, "sequence": sequence.name, "scan_frames": len(result.frame_ids),
        "views": len(result.frame_ids) * len(settings.roles), "roles": list(settings.roles),
        "coverage_fraction": result.panorama.coverage_fraction, "clipped_pixel_fraction": result.clipped_fraction,
        "map_height": settings.height, "num_lights": lightstage.num_lights,
    })
    if truth is not None:
        rows = {name: ev.envmap_metrics(m, result.panorama.coverage, truth.envmap, lightstage, float(cfg.eval.log_eps))
                for name, m in maps.items()}
        if int(cfg.eval.relit_cameras) > 0:
            relit = ev.relit_psnr(capture.groundtruth_root(), {n: lightstage.envmap_to_intensities(m)
                                                                for n, m in maps.items()},
                                  lightstage.envmap_to_intensities(truth.envmap), int(cfg.eval.relit_cameras))
            for name in rows:
                rows[name]["relit_psnr"] = relit["relit_psnr"][name] if relit["relit_psnr"] else None
            writer.metrics["relit_views"] = relit["relit_views"]
        writer.metrics.update(rows[row])
        writer.metrics["rows"] = rows
        writer.metrics.update({"truth_envmap": truth.name, "truth_frame_yaw_deg": truth.frame_yaw_deg,
                               "truth_frame_tilt_deg": truth.frame_tilt_deg})
    if inverse is not None:
        sync_truth = ev.colour_sync_truth(capture, inverse.sync)
        if sync_truth is not None:
            writer.metrics["colour_sync_truth"] = sync_truth
    writer.extra["frame"] = f"the calibrated head poses of sequence {sequence.name}"
    if inverse is None:
        writer.extra["camera_response"] = ("unknown: front images linearised by the inverse sRGB curve only; the "
                                           "colour model is the identity (A = [I | 0], gamma = 1): no --meshes/"
                                           "--uvmaps/--model/--sync-* given, so no inverse rendering")
        console.info("envmap: no --meshes/--uvmaps/--model: the LDR-panorama row (A = I, gamma = 1) is written")
    writer.units.update({"envmap": "linear RGB radiance (front-camera units)" if inverse is None else
                         "linear RGB radiance (the avatar's studio light units)", "centre_m": "m",
                         "relit_psnr": "dB, oracle renders, metric tone mapping"})
    writer.extra["centre_m"] = [float(c) for c in result.centre]


def _inverse(writer: ArtifactWriter, cfg: Config, capture, calibration, result, loaded: LoadedInverse):
    """Run the inverse rendering, write its curve and preview, record its settings."""
    import json
    import time

    from egorelight_cli.io.images import write_image
    from egorelight_cli.stages import envmap_inverse as ei

    settings = loaded.settings
    reg_max = settings.reg_max if settings.reg_max is not None else ei.auto_reg_max(capture, loaded.trained_on)
    started = time.perf_counter()
    with torch.enable_grad():
        inverse = ei.inverse_render(loaded.model, loaded.wild, loaded.studio, calibration, result.inpainted, settings,
                                    int(cfg.seed), reg_max)
    writer.timing["inverse_s"] = round(time.perf_counter() - started, 3)
    if inverse.flow_note:
        console.info(inverse.flow_note)
        writer.extra["flow_fallback"] = inverse.flow_note
    (writer.workdir / CURVE_JSON).write_text(json.dumps({n: f.curve for n, f in inverse.fits.items()}))
    fit = inverse.fits["fitted"]
    writer.metrics.update({
        "inverse_frames": [int(f) for f in inverse.frames], "inverse_views": len(inverse.views),
        "inverse_steps": settings.steps, "inverse_loss_first": fit.curve[0]["image"],
        "inverse_loss_last": fit.curve[-1]["image"], "flow": inverse.flow, "reg_max": reg_max,
        "gamma": float(fit.colour.gamma.detach()),
        "flow_consistent_fraction": float(np.nanmean([v.flow_consistent_fraction for v in inverse.views])),
        "flow_warped_views": int(sum(v.flow_used for v in inverse.views)),
        "image_pass": inverse.image_pass,
        "near_excluded_fraction": float(np.nanmean([v.near_fraction for v in inverse.views])),
        "colour_sync_residual_l1": {r: s["residual_l1"] for r, s in inverse.sync.items()},
        "colour_sync_gain": {r: s["gain"] for r, s in inverse.sync.items()},
        "sync_sequence": loaded.studio.sequence.name,
    })
    writer.extra["observed_mask"] = ("render mask eroded by inverse.mask_erode_px, without pixels whose rendered depth is "
                                     "under inverse.min_depth_m, intersected with forward-backward "
                                     "consistent flow and unclipped ego pixels (no ground truth)")
    write_image(writer.path(INVERSE_PREVIEW_PNG), inverse_preview(loaded.model, loaded.wild, inverse))
    return inverse


def inverse_preview(model, wild, inverse) -> np.ndarray:
    """(h,w,3) uint8: per view, ego image | ego warped onto the render | fitted render | part masks."""
    from egorelight_cli.io.images import linear_to_srgb
    from egorelight_cli.render.lighting import EnvmapPooling
    from egorelight_cli.stages import envmap_inverse as ei

    fit = inverse.fits["fitted"]
    parts = ei.texel_parts(wild.character, wild.raster)
    rows = []
    with torch.no_grad():
        E_l = torch.from_numpy(np.asarray(inverse.panorama, np.float64))
        intensities = EnvmapPooling(wild.lightstage, *E_l.shape[:2])(fit.colour(E_l))
        for view in inverse.views:
            matrix = torch.tensor(inverse.sync[view.role]["matrix"], dtype=torch.float32)
            render = (ei.render_view(model, wild, view, intensities, parts, inverse.image_pass).colour
                      @ matrix.T).numpy()
            colours = np.array([[230, 80, 60], [60, 120, 230], [240, 200, 40], [80, 200, 90], [200, 90, 220]])
            masks = view.masks.numpy()
            labels = np.zeros(masks.shape[1:] + (3,), np.uint8)
            for k in range(len(masks)):
                labels[masks[k]] = colours[k % len(colours)]
            tiles = [np.round(linear_to_srgb(np.clip(x, 0, 1)) * 255).astype(np.uint8)
                     for x in (view.ego, view.target.numpy(), render)]
            rows.append(np.concatenate(tiles + [labels], axis=1))
    return np.concatenate(rows, axis=0)


def preview(result, truth: np.ndarray | None, width: int) -> np.ndarray:
    """(h,w,3) uint8: rows panorama (unobserved texels dark red), E_h, and the truth when given."""
    from egorelight_cli.io.images import tonemap
    from egorelight_cli.render.sheets import label as label_image

    height = max(width // 2, 1)

    def row(envmap: np.ndarray, text: str, mask: np.ndarray | None = None) -> np.ndarray:
        image = tonemap(envmap, mask)
        if mask is not None:
            image = np.where(mask[..., None], image, np.array([90, 0, 0], np.uint8))
        return label_image(cv2.resize(np.ascontiguousarray(image), (width, height), interpolation=cv2.INTER_NEAREST),
                           text)

    rows = [row(result.panorama.radiance, "panorama E_o (observed)", result.panorama.coverage),
            row(result.envmap, "E_h (inpainted, colour model)")]
    if truth is not None:
        rows.append(row(truth, "truth (same frame)"))
    return np.concatenate(rows, axis=0)


def envmap_command(run: StageRun, capture: Path, calibration: Path, meshes: Path | None, uvmaps: Path | None,
                   model: Path | None, sync_meshes: Path | None, sync_uvmaps: Path | None, character: str,
                   sequence: str, out: Path) -> Path:
    """``egorelight envmap`` (declared in :mod:`egorelight_cli.declarations`)."""
    inverse = InverseInputs.from_options(meshes, uvmaps, model, sync_meshes, sync_uvmaps, character)
    if inverse is None and character != "default":
        raise EgorelightError("--character is read only by the inverse rendering (with --meshes, --uvmaps, --model, "
                              "--sync-meshes and --sync-uvmaps)")
    return EnvmapCommands(run).predict(capture, calibration, sequence, out, inverse)
