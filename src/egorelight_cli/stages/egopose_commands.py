"""The ``egorelight egopose`` and ``egorelight train egopose`` commands: load inputs, call
:mod:`egorelight_cli.stages.egopose`, write artifacts.

* ``train egopose`` writes a model artifact (:mod:`egorelight_cli.io.model` layout): ``model.pt``
  (the :class:`~egorelight_cli.nn.egopose_net.EgoPoseNet` state dict, its constructor arguments,
  the input size and the training mean pose in ``extra``), ``curve.json``/``curve.png``. Metrics:
  training frames, the fit to the mocap on them (``train_*``), the held-out validation MPJPE vs
  the mocap (``validation_*``, works on real captures), and, for a simulated capture whose
  calibration covers ``evaluate_sequence`` (``test``), MPJPE against its ground truth there
  (``test_*``, unseen lighting): the jitter ablation compares these (``--no-jitter``). Every
  MPJPE comes with the mean-pose baseline (``*_mean_pose_*``). A resumable checkpoint lives next to the output in ``.<out>.checkpoint/`` while
  training (``--resume`` continues from it when it was made with the same cache key; without it an
  old one is ignored and overwritten); it is removed once the model is written.
* ``egopose`` writes a keypoints artifact (``keypoints.npz`` + ``per_frame.npz`` with the
  estimates before the temporal module + ``preview.png``); metrics vs
  ``groundtruth/<seq>/keypoints.npz`` when the capture has it.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from egorelight_cli.artifacts import Artifact, ArtifactWriter, open_artifact
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.calibration import open_calibration
from egorelight_cli.structures.calibration import Calibration
from egorelight_cli.io.capture import Capture, open_capture
from egorelight_cli.io.keypoints import read_keypoints_npz, save_keypoints
from egorelight_cli.pipeline import StageRun
from egorelight_cli.sharding import FrameRange

# torch, the network and the stage module load only past the cache check (importing torch alone
# takes seconds; an up-to-date `egopose` returns in under one)
if TYPE_CHECKING:
    import torch

    from egorelight_cli.nn.egopose_net import EgoPoseNet
    from egorelight_cli.stages.egopose import EgoPoseSettings, TrainResult

PREVIEW_PNG = "preview.png"
PER_FRAME_NPZ = "per_frame.npz"


@dataclass
class EgoPoseModel:
    """A trained estimator read back from a model artifact."""

    net: EgoPoseNet
    input_size: int
    mean_pose_heading: np.ndarray | None
    extra: dict


def load_egopose_model(path: Path) -> tuple[EgoPoseModel, Artifact]:
    """Read an egopose model artifact (kind model, trained by ``train egopose``)."""
    from egorelight_cli.io.model import read_model
    from egorelight_cli.nn.egopose_net import EgoPoseNet
    from egorelight_cli.stages.egopose import EGOPOSE_MODEL_TYPE

    artifact = open_artifact(path, kind="model")
    if artifact.single_file:
        raise EgorelightError("an egopose model is a directory artifact", path)
    payload = read_model(artifact.root, stage=EGOPOSE_MODEL_TYPE)
    try:
        net = EgoPoseNet(**payload.architecture)
        result = net.load_state_dict(payload.state_dict, strict=False)
    except (TypeError, RuntimeError) as exc:  # unknown constructor arguments, tensor shape mismatches
        raise EgorelightError(f"egopose model does not fit this tool's network ({type(exc).__name__}: "
                              f"{' '.join(str(exc).split())[:300]}); retrain it", path) from None
    if result.missing_keys or result.unexpected_keys:
        raise EgorelightError(f"egopose model does not fit this tool's network (missing {result.missing_keys[:3]}, "
                              f"unexpected {result.unexpected_keys[:3]}); retrain it", path)
    net.eval()
    mean_pose = payload.extra.get("mean_pose_heading")
    mean_pose = None if mean_pose is None else np.asarray(mean_pose, np.float32)
    return EgoPoseModel(net, int(payload.extra["input_size"]), mean_pose, payload.extra), artifact


def read_backbone_weights(path: Path) -> dict[str, torch.Tensor]:
    """A torch state dict (or ``{"state_dict": ...}`` / an egorelight model.pt) of encoder weights."""
    import torch

    if not path.is_file():
        raise EgorelightError("backbone weights not found", path)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        first = (str(exc).strip().splitlines() or [""])[0]
        raise EgorelightError(f"cannot load backbone weights ({type(exc).__name__}: {first})", path) from None
    if isinstance(data, dict) and isinstance(data.get("state_dict"), dict):
        data = data["state_dict"]
    if not isinstance(data, dict) or not all(isinstance(v, torch.Tensor) for v in data.values()):
        raise EgorelightError("backbone weights are not a state dict of tensors", path)
    return data


# ---------------------------------------------------------------------------------- commands
def default_training_sequence(capture) -> str:
    """The sequence of purpose ``ego_train`` with ego images, mocap and the most content frames (ties: by name),
    e.g. the headset-only ``ego_bulk`` of the cpu preset over its ``ego_train``."""
    candidates = [s for s in capture.sequences_with_purpose("ego_train")
                  if s.streams.get("ego") and s.mocap_path().is_file()]
    if not candidates:
        raise EgorelightError("the capture has no sequence of purpose ego_train with ego images and mocap.npz; "
                              "give --seq", capture.root / "sequences")
    return max(sorted(candidates, key=lambda s: s.name), key=lambda s: len(s.content_frame_ids)).name  # first of ties


@dataclass(frozen=True)
class EgoPoseCommands:
    """``egopose`` and ``train egopose`` over one :class:`StageRun` (the global options)."""

    run: StageRun

    def train(self, capture_path: Path, calibration_path: Path, out: Path, sequence: str | None = None,
              backbone_weights: Path | None = None, resume: bool = False) -> Path:
        from egorelight_cli.nn.training import Checkpoint, checkpoint_beside
        from egorelight_cli.stages.egopose import (EGOPOSE_MODEL_TYPE, EgoPoseSettings, load_frames, rig_geometry,
                                                   train_egopose)

        capture, capture_artifact = open_capture(capture_path)
        calibration, calibration_artifact = open_calibration(calibration_path)
        cfg = self.run.config()
        sequence = sequence or str(cfg.train.sequence) or default_training_sequence(capture)
        info = capture.sequence(sequence)
        info.require_stream("ego")
        if not info.mocap_path().is_file():
            raise EgorelightError(f"sequence {sequence!r} has no mocap.npz to supervise training", info.mocap_path())
        mocap = read_keypoints_npz(info.mocap_path()).require_standard_layout(info.mocap_path())
        backbone = read_backbone_weights(Path(backbone_weights)) if backbone_weights is not None else None
        inputs = [a for a in (capture_artifact, calibration_artifact) if a is not None]
        sources = [info.mocap_path()] + ([Path(backbone_weights)] if backbone_weights is not None else [])
        checkpoint_dir = checkpoint_beside(out, "")

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            from egorelight_cli.io.model import ModelPayload, write_model

            if writer.single_file:
                raise EgorelightError("an egopose model is a directory artifact: give --out a directory name", out)
            settings = EgoPoseSettings(cfg)
            rig = rig_geometry(capture, calibration)
            frames = load_frames(capture, calibration, sequence, int(cfg.input_size), only_content=True)
            started = time.perf_counter()
            result = train_egopose(frames, mocap, rig, settings, Checkpoint(checkpoint_dir, writer.cache_key, resume),
                                   backbone)
            writer.timing["train_s"] = round(time.perf_counter() - started, 2)
            extra = {"input_size": int(cfg.input_size), "training_sequence": sequence,
                     "mean_pose_heading": result.mean_pose_heading.tolist(), "roles": ["down_left", "down_right"],
                     "backbone_weights": str(backbone_weights) if backbone_weights else None, **result.info}
            write_model(writer.workdir, ModelPayload(EGOPOSE_MODEL_TYPE, settings.architecture(),
                                                     result.net.state_dict(), extra, result.curve),
                        curve_title="egopose training losses")
            writer.metrics.update(result.info)
            writer.metrics["backbone"] = "pretrained (--backbone-weights)" if backbone is not None else "from scratch"
            writer.metrics.update(_training_fit(result, frames, mocap, rig, settings))
            writer.metrics.update(_held_out_metrics(capture, calibration, result, rig, settings))

        produced = self.run.produce(out, "model", write, inputs=inputs, source_files=sources)
        if checkpoint_dir.exists():
            shutil.rmtree(checkpoint_dir, ignore_errors=True)  # every torchrun rank gets here
        return produced

    def egopose(self, capture_path: Path, calibration_path: Path, model_path: Path, sequence: str, out: Path,
                frame_range: FrameRange = FrameRange()) -> Path:
        capture, capture_artifact = open_capture(capture_path, [sequence])
        calibration, calibration_artifact = open_calibration(calibration_path)
        capture.sequence(sequence).require_stream("ego")
        inputs = [a for a in (capture_artifact, calibration_artifact, open_artifact(model_path, kind="model"))
                  if a is not None]
        if self.run.up_to_date(out, "keypoints", inputs):
            return Path(out)
        model, _ = load_egopose_model(model_path)
        from egorelight_cli.sharding import write_preview
        from egorelight_cli.stages.egopose import frame_table, groundtruth_keypoints, load_frames, predict, rig_geometry
        from egorelight_cli.synth.groundtruth import truth_frame_note
        from egorelight_cli.stages.egopose_preview import preview_image, preview_rows
        from egorelight_cli.stages.egopose_scores import SCORES_NPZ, egopose_metrics, egopose_scores

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            rig = rig_geometry(capture, calibration)
            table = frame_table(capture, calibration, sequence)
            start, stop = frame_range.bounds(len(table.frame_ids))
            first = max(0, start - (model.net.window - 1))  # the temporal window's context before the range
            frames = load_frames(capture, calibration, sequence, model.input_size, rows=slice(first, stop))
            started = time.perf_counter()
            prediction = predict(model.net, frames, rig, float(cfg.confidence_sigma_m))
            elapsed = time.perf_counter() - started
            keep = np.arange(start - first, len(frames.frame_ids))
            frames, prediction = frames.select(keep), prediction.select(keep)
            writer.timing["inference_ms_per_frame"] = round(1000 * elapsed / len(frames.frame_ids), 2)
            if not frame_range.whole:
                writer.extra["shard"] = frame_range.manifest(len(table.frame_ids))
            save_keypoints(writer, prediction.keypoints, sequence=sequence, head_poses=frames.head_pose_source)
            truth = groundtruth_keypoints(capture, sequence, calibration)
            scored = truth is not None and frames.head_pose_source == "calibration"
            scores = egopose_scores(prediction, frames, truth if scored else None, model.mean_pose_heading)
            writer.metrics["head_poses"] = frames.head_pose_source
            writer.metrics.update(egopose_metrics(scores, prediction.keypoints.confidence))
            if truth is not None and not scored:
                writer.metrics["groundtruth_not_scored"] = "head poses are in the tracker's own world frame"
            if scored:
                writer.metrics["groundtruth_frame"] = truth_frame_note(calibration, sequence)
            if writer.single_file:
                return
            writer.save_npz(SCORES_NPZ, scores, frame_ids=frames.frame_ids, rows=sorted(scores),
                            units={k: "cm" for k in scores if k.endswith("_cm")},
                            description="per-frame, per-joint errors against the ground truth (NaN: not scored) "
                                        "and the frame flags the metrics are computed from")
            writer.save_npz(PER_FRAME_NPZ, {"xyz": prediction.per_frame, "pixels": prediction.pixels.astype(np.float32),
                                            "frame_ids": frames.frame_ids},
                            frame_ids=frames.frame_ids, units={"xyz": "m", "pixels": "px"}, rows=["frame_ids", "pixels", "xyz"],
                            description="fused per-frame keypoints before the temporal module; soft-argmax pixels "
                                        "per view (down_left, down_right)")
            shown = [int(p) for p in preview_rows(table.usable, int(cfg.preview.frames)) if start <= p < stop]
            images = preview_image(capture, frames, rig, prediction, truth, np.array(shown, int) - start,
                                   int(cfg.preview.tile))
            write_preview(writer, dict(zip(shown, images)), frame_range, PREVIEW_PNG)

        return self.run.produce(out, "keypoints", write, inputs=inputs)


def _training_fit(result: TrainResult, frames, mocap, rig, settings: EgoPoseSettings) -> dict:
    """MPJPE (cm) to the mocap on the frames trained on, and the mean-pose baseline there."""
    from egorelight_cli.stages.egopose import evaluate, predict

    frames = frames.select(np.nonzero(np.isin(frames.frame_ids, result.frame_ids))[0])
    prediction = predict(result.net, frames, rig, float(settings.cfg.confidence_sigma_m))
    metrics = evaluate(prediction, frames, mocap, result.mean_pose_heading, prefix="train_")
    return {k: v for k, v in metrics.items() if "per_frame" not in k}


def _held_out_metrics(capture: Capture, calibration: Calibration, result: TrainResult, rig,
                      settings: EgoPoseSettings) -> dict:
    """Scores on ``evaluate_sequence`` (unseen lighting) when the capture has its ground truth."""
    from egorelight_cli.stages.egopose import evaluate, groundtruth_keypoints, load_frames, predict

    sequence = str(settings.cfg.evaluate_sequence)
    if not sequence or sequence not in capture.sequence_names() or sequence not in calibration.head_poses:
        return {}
    truth = groundtruth_keypoints(capture, sequence, calibration)
    if truth is None:
        return {}
    frames = load_frames(capture, calibration, sequence, int(settings.cfg.input_size))
    prediction = predict(result.net, frames, rig, float(settings.cfg.confidence_sigma_m))
    return evaluate(prediction, frames, truth, result.mean_pose_heading, prefix=f"{sequence}_")


# ------------------------------------------------------------- handlers (egorelight_cli.declarations)
def train_command(run: StageRun, capture: Path, calibration: Path, backbone_weights: Path | None,
                  sequence: str | None, resume: bool, out: Path) -> Path:
    return EgoPoseCommands(run).train(capture, calibration, out, sequence, backbone_weights, resume)


def egopose_command(run: StageRun, capture: Path, calibration: Path, model: Path, sequence: str, out: Path,
                    frame_range: FrameRange) -> Path:
    return EgoPoseCommands(run).egopose(capture, calibration, model, sequence, out, frame_range)
