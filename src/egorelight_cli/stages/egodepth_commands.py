"""The ``egorelight train egodepth`` and ``egorelight egodepth`` commands: load the capture and
calibration, call :mod:`egorelight_cli.stages.egodepth`, write artifacts.

``train egodepth`` writes a model artifact (``model.pt``: the network's state dict, its
architecture, and in ``extra`` the roles, image sizes and per-camera self-occlusion masks;
``curve.json``/``curve.png``). ``egodepth`` writes a ``pointcloud`` artifact:
``pointcloud.npz`` (:mod:`egorelight_cli.io.pointcloud`), ``depth/<role>/<frame>.exr`` (channel
``Z``, axial depth in metres, 0 = none; frame = master-clock id), ``preview.png`` (ego image,
predicted and true depth) and ``preview_pointcloud.png`` (points over the true mesh).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from egorelight_cli import console
from egorelight_cli.artifacts import Artifact, ArtifactWriter, open_artifact
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.calibration import open_calibration
from egorelight_cli.structures.calibration import Calibration
from egorelight_cli.io.capture import Capture, frame_file, open_capture
from egorelight_cli.io.folders import visible_files
from egorelight_cli.pipeline import StageRun
from egorelight_cli.sharding import FrameRange

# torch and the stage module load only past the cache check, so an up-to-date run returns in
# well under a second (importing torch alone takes seconds)
if TYPE_CHECKING:
    import torch

    from egorelight_cli.stages import egodepth as ed

PREVIEW_PNG = "preview.png"
POINTCLOUD_PREVIEW_PNG = "preview_pointcloud.png"


def load_inputs(capture_path: Path, calibration_path: Path,
                sequences: list[str] | None = None) -> tuple[Capture, Artifact, Calibration, Artifact]:
    capture, capture_artifact = open_capture(capture_path, sequences)
    calibration, calibration_artifact = open_calibration(calibration_path)
    return capture, capture_artifact, calibration, calibration_artifact


def backbone_sources(backbone: Path | None) -> list[Path]:
    """The files of a ``--backbone`` folder that enter the cache key: every file in it (``config.json``
    and the weights ``from_pretrained`` loads, whatever their format) but hidden ones (``.git/``),
    sorted; none without one."""
    if backbone is None:
        return []
    files = visible_files(backbone)  # no .git/
    if Path(backbone) / "config.json" not in files:
        raise EgorelightError("not a Depth-Anything-V2 model folder (no config.json)", backbone)
    return files


def _prior(backbone: Path | None, device: torch.device):
    if backbone is None:
        return None
    from egorelight_cli.nn.depth_net import DepthAnythingPrior

    return DepthAnythingPrior(backbone, device)


def load_depth_model(path: Path, roles) -> tuple[ed.DepthNet, dict, dict, Artifact]:
    """(network, self-occlusion masks by role, model extras, artifact) of a ``train egodepth`` model."""
    from egorelight_cli.io.model import read_model
    from egorelight_cli.stages import egodepth as ed

    artifact = open_artifact(path, kind="model")
    if artifact.single_file:
        raise EgorelightError("an egodepth model is a directory artifact", path)
    payload = read_model(artifact.root, stage=ed.MODEL_STAGE)
    try:
        model = ed.DepthNet.from_architecture(payload.architecture)
        model.load_state_dict(payload.state_dict)
    except (KeyError, RuntimeError) as exc:
        raise EgorelightError(f"egodepth model does not match the network ({type(exc).__name__}: {exc})", path) from None
    masks = {role: np.asarray(m.numpy(), bool) for role, m in payload.extra.get("self_masks", {}).items()}
    missing = [r for r in roles if r not in masks]
    if missing:
        raise EgorelightError(f"egodepth model was trained for cameras {', '.join(masks)}, not {', '.join(missing)}",
                              path)
    return model.eval(), masks, payload.extra, artifact


@dataclass(frozen=True)
class EgodepthCommands:
    """``egodepth`` and ``train egodepth`` over one :class:`StageRun`."""

    run: StageRun

    # ------------------------------------------------------------------------------- train
    def train(self, capture_path: Path, calibration_path: Path, out: Path, backbone: Path | None = None,
              resume: bool = False) -> Path:
        import torch

        from egorelight_cli.nn.training import Checkpoint, checkpoint_beside
        from egorelight_cli.stages import egodepth as ed
        from egorelight_cli.stages.egodepth_mask import validation_report

        capture, capture_artifact, calibration, calibration_artifact = load_inputs(capture_path, calibration_path)
        cfg = self.run.config()
        roles = tuple(cfg.roles)
        # the reconstructions supervise: headset-only sequences (no recon stream) are left out
        names = list(cfg.train.sequences) or [s.name for s in capture.sequences_with_purpose("ego_train")
                                               if s.streams.get("recon")]
        if not names:
            raise EgorelightError("capture has no ego_train sequence with reconstructions (set train.sequences)",
                                  capture.root)
        sequences = [capture.sequence(n) for n in names]
        device = self.run.compute_device()
        prior = _prior(backbone, device)  # checks the folder before anything runs
        sources = backbone_sources(backbone)
        checkpoint = checkpoint_beside(out)

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            from egorelight_cli.io.model import ModelPayload, write_model

            if writer.single_file:
                raise EgorelightError("an egodepth model is a directory artifact: give --out a directory name", out)
            started = time.perf_counter()
            ray_maps = {r: ed.camera_ray_map(capture.ego_camera(r)) for r in roles}
            stereo = None
            settings = ed.PredictSettings.from_config(cfg)
            if bool(cfg.net.stereo_input):
                sgbm = ed.SGBMDepth(capture, calibration, roles, cfg)
                stereo = lambda views: sgbm(views, ray_maps, settings)  # noqa: E731
            split = (capture, calibration, sequences, roles, float(cfg.train.near_m), int(cfg.train.max_frames),
                     stereo, int(cfg.train.validation_frames))
            views = ed.supervision(*split, part="training")
            validation = ed.supervision(*split, part="validation")
            masks = ed.self_occlusion_masks(views, float(cfg.train.self_occlusion_fraction))
            writer.timing["supervision_s"] = round(time.perf_counter() - started, 3)
            console.info(f"train egodepth: {len(views)} supervised views from {', '.join(names)}")
            started = time.perf_counter()
            model, curve = ed.train_depth_net(views, ray_maps, masks, ed.TrainSettings.from_config(cfg), cfg.net,
                                              device, Checkpoint(checkpoint, writer.cache_key, resume), prior)
            writer.timing["train_s"] = round(time.perf_counter() - started, 3)
            writer.metrics.update(ed.fit_report(model, views, ray_maps, masks, prior))
            mask_report = validation_report(model, validation, ray_maps, masks, settings,
                                            float(cfg.train.mask_precision), torch.device("cpu"), prior)
            writer.metrics.update(mask_report)
            extra = {"roles": list(roles), "self_masks": {r: torch.from_numpy(m) for r, m in masks.items()},
                     "mask_threshold": mask_report["mask_threshold"],
                     "validation_frames": sorted({(v.sequence, v.frame_id) for v in validation}),
                     "image_size": {r: [capture.ego_camera(r).width, capture.ego_camera(r).height] for r in roles},
                     "backbone": str(backbone) if backbone is not None else None,
                     "training_views": len(views), "training_sequences": names}
            write_model(writer.workdir, ModelPayload(ed.MODEL_STAGE, model.architecture(), model.state_dict(), extra,
                                                     curve), curve_title="egodepth training loss")
            writer.metrics.update({
                "training_sequences": names,
                "training_views": len(views), "training_frames": len({(v.sequence, v.frame_id) for v in views}),
                "supervised_fraction": float(np.mean([v.supervised.mean() for v in views])),
                "self_occlusion_fraction": {r: float(m.mean()) for r, m in masks.items()},
                "loss_first": curve[0]["loss"] if curve else None, "loss_last": curve[-1]["loss"] if curve else None,
                "backbone": "depth-anything-v2" if backbone is not None else "none (trained from scratch)",
            })
            writer.runtime["device"] = str(device)

        result = self.run.produce(out, "model", write, inputs=[capture_artifact, calibration_artifact],
                                  source_files=sources)
        checkpoint.unlink(missing_ok=True)  # only once the output check passed and the model is written
        return result

    # ------------------------------------------------------------------------------ predict
    def predict(self, capture_path: Path, calibration_path: Path, model_path: Path | None, seq: str, out: Path,
                method: str | None = None, backbone: Path | None = None,
                frame_range: FrameRange = FrameRange()) -> Path:
        capture, capture_artifact, calibration, calibration_artifact = load_inputs(capture_path, calibration_path, [seq])
        cfg = self.run.config()
        method = method or str(cfg.predict.method)
        roles = tuple(cfg.roles)
        sequence = capture.sequence(seq)
        inputs = [capture_artifact, calibration_artifact]
        sources = backbone_sources(backbone)
        if method == "net":
            if model_path is None:
                raise EgorelightError("egodepth --method net needs --model (a `train egodepth` artifact)")
            inputs.append(open_artifact(model_path, kind="model"))
        elif model_path is not None:
            raise EgorelightError(f"egodepth --method {method} reads no model: leave out --model", model_path)
        if self.run.up_to_date(out, "pointcloud", inputs, sources):
            return Path(out)
        from egorelight_cli.stages import egodepth as ed

        if method not in ed.METHODS:
            raise EgorelightError(f"unknown egodepth method {method!r}; expected one of {', '.join(ed.METHODS)}")
        ed.check_roles(capture, sequence, roles)
        model = masks = extra = None
        if method == "net":
            model, masks, extra, _ = load_depth_model(model_path, roles)
            for role in roles:
                c = capture.ego_camera(role)
                if masks[role].shape != (c.height, c.width):
                    raise EgorelightError(f"egodepth model was trained on {masks[role].shape[1]}x{masks[role].shape[0]} "
                                          f"{role} images, the capture has {c.width}x{c.height}", model_path)
            if model.prior_channels and backbone is None:
                raise EgorelightError("this egodepth model was trained with a Depth-Anything-V2 backbone: pass --backbone")
        device = self.run.compute_device()
        prior = _prior(backbone, device) if model is not None and model.prior_channels else None
        frames, posed = ed.usable_frames(calibration, sequence, roles)

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            if writer.single_file:
                raise EgorelightError("a pointcloud artifact is a directory (it holds depth EXRs): give --out a directory",
                                      out)
            _predict_sequence(writer, cfg, capture, calibration, sequence, roles, frames, posed, method, model, masks,
                              device, prior, frame_range, extra or {})
            if model is None:  # a classical method (OpenCV SGBM) runs on the CPU whatever --device says
                writer.runtime["device"] = "cpu"

        return self.run.produce(out, "pointcloud", write, inputs=inputs, source_files=sources)


def _predict_sequence(writer: ArtifactWriter, cfg: Config, capture: Capture, calibration: Calibration, sequence,
                      roles, frames: np.ndarray, posed: np.ndarray, method: str, model, masks, device, prior,
                      frame_range: FrameRange, extra: dict | None = None) -> None:
    from egorelight_cli.stages import egodepth as ed
    from egorelight_cli.stages.egodepth_preview import depth_preview_row, pointcloud_preview
    from egorelight_cli.io.exr import write_exr
    from egorelight_cli.io.images import write_image
    from egorelight_cli.io.pointcloud import save_pointcloud
    from egorelight_cli.sharding import write_preview
    from egorelight_cli.stages.egodepth_scores import SCORES_NPZ, DepthScores, run_metrics
    from egorelight_cli.structures.pointcloud import PointCloudSequence

    settings = ed.PredictSettings.from_config(cfg)
    if method == "net":
        model_threshold = extra.get("mask_threshold")
        settings = settings.for_model(model_threshold)
        writer.metrics["mask_threshold"] = settings.mask_threshold
        writer.metrics["mask_threshold_source"] = (
            "predict.mask_threshold" if cfg.predict.mask_threshold is not None else
            "the model's (chosen on its validation frames)" if model_threshold is not None else
            f"default {ed.DEFAULT_MASK_THRESHOLD} (the model has none)")
    ray_maps = {r: ed.camera_ray_map(capture.ego_camera(r)) for r in roles}
    model = model.to(device) if model is not None else None
    compare = method == "net" and bool(cfg.eval.compare_sgbm)
    uses_stereo = method == "sgbm" or (model is not None and model.stereo_input)  # SGBM on every frame
    sgbm = ed.SGBMDepth(capture, calibration, roles, cfg) if uses_stereo or compare else None
    truth = ed.GroundTruth(capture, calibration, sequence, float(cfg.eval.occluder_margin_m))
    P = int(cfg.pointcloud.points)
    k = int(cfg.pointcloud.normal_neighbours)
    preview_at = np.linspace(0, len(frames) - 1, max(min(int(cfg.preview.frames), len(frames)), 1)).round().astype(int)
    start, stop = frame_range.bounds(len(frames))
    if not frame_range.whole:
        writer.extra["shard"] = frame_range.manifest(len(frames))
    frames, posed = frames[start:stop], posed[start:stop]
    T = len(frames)
    points = np.zeros((T, P, 3), np.float32)
    normals = np.zeros((T, P, 3), np.float32)
    valid = np.zeros((T, P), bool)
    scores = {"": DepthScores(T, P)}
    if compare:
        scores["sgbm_"] = DepthScores(T, P)
    timing = {"depth_s": 0.0, "pointcloud_s": 0.0}
    preview_rows = {}
    for t in console.progress(range(T), total=T, desc=f"egodepth {sequence.name}"):
        f = int(frames[t])
        if not posed[t]:
            continue
        rng = np.random.default_rng([int(cfg.seed), f])  # per frame: a frame's points do not depend on its shard
        views = [ed.load_view(capture, calibration, sequence, r, f) for r in roles]
        started = time.perf_counter()
        stereo = sgbm(views, ray_maps, settings) if uses_stereo else None
        if method == "net":
            ranges = ed.predict_ranges_net(model, views, ray_maps, masks, settings, device, prior, stereo)
        else:
            ranges = stereo
        timing["depth_s"] += time.perf_counter() - started
        started = time.perf_counter()
        points[t], normals[t], valid[t], depths = ed.frame_pointcloud(views, ranges, ray_maps, P, k, rng)
        timing["pointcloud_s"] += time.perf_counter() - started
        for role, depth in depths.items():
            write_exr(writer.path(f"depth/{role}/{frame_file(f, '.exr')}"), {"Z": depth})
        truth_maps = distance = None
        if truth.has(f):
            surface, truth_maps = truth.frame(f, views)
            distance = surface(points[t][valid[t]])
            constant = float(np.exp(float(model.log_range_mean))) if model is not None else None
            if compare and stereo is None:  # scored only: a monocular network's frame with ground truth
                stereo = sgbm(views, ray_maps, settings)
            scores[""].add_frame(t, ranges, truth_maps, distance, constant, stereo if compare else None)
            if compare:
                other_points, _, other_valid, _ = ed.frame_pointcloud(views, stereo, ray_maps, P, k, rng)
                scores["sgbm_"].add_frame(t, stereo, truth_maps, surface(other_points[other_valid]), other=ranges)
        if start + t in preview_at:
            preview_rows[start + t] = depth_preview_row(views, ranges, truth_maps, int(cfg.preview.scale))
            if start + t == preview_at[0]:  # the point cloud of the first previewed frame
                mesh = None
                if truth.has(f):
                    i = int(np.nonzero(truth.frame_ids == f)[0][0])
                    mesh = (truth.vertices[i], truth.faces)
                write_image(writer.path(POINTCLOUD_PREVIEW_PNG), pointcloud_preview(
                    points[t][valid[t]], normals[t][valid[t]], distance, mesh, int(cfg.preview.width),
                    int(cfg.preview.height)))
    fps = sequence.fps if "fps" in sequence.doc else None
    save_pointcloud(writer, PointCloudSequence(points, normals, valid, frames, fps), method=method,
                    sequence=sequence.name, roles=list(roles))
    write_preview(writer, preview_rows, frame_range, PREVIEW_PNG)
    rows = {"posed": posed, **({n: v for prefix, s in scores.items() for n, v in s.arrays(prefix).items()}
                               if truth.available else {})}
    writer.save_npz(SCORES_NPZ, rows, frame_ids=frames, rows=sorted(rows),
                    description="per frame: the depth error sums and point-to-surface distances (m, NaN-padded) "
                                "of each method, the metrics' source")
    writer.metrics.update(run_metrics(rows, valid, method, sequence.name))
    if truth.available:
        from egorelight_cli.synth.groundtruth import truth_frame_note

        writer.metrics["groundtruth_frame"] = truth_frame_note(calibration, sequence.name)
    done = int(posed.sum())
    writer.timing.update({"depth_ms_per_frame": round(1000 * timing["depth_s"] / max(done, 1), 2),
                          "pointcloud_ms_per_frame": round(1000 * timing["pointcloud_s"] / max(done, 1), 2)})
    writer.units.update({"depth": "m (axial z, EXR channel Z)", "points": "m"})


# ------------------------------------------------------------- handlers (egorelight_cli.declarations)
def train_command(run: StageRun, capture: Path, calibration: Path, backbone: Path | None, resume: bool,
                  out: Path) -> Path:
    return EgodepthCommands(run).train(capture, calibration, out, backbone, resume)


def egodepth_command(run: StageRun, capture: Path, calibration: Path, model: Path | None, backbone: Path | None,
                     sequence: str, out: Path, frame_range: FrameRange) -> Path:
    return EgodepthCommands(run).predict(capture, calibration, model, sequence, out, None, backbone, frame_range)
