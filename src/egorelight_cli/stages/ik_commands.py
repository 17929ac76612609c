"""The ``egorelight ik`` and ``egorelight train ik`` commands: load inputs, call
:mod:`egorelight_cli.stages.ik`, write artifacts.

``ik --in`` accepts

* a keypoints artifact (directory with ``keypoints.npz``, a single ``.npz`` with its sidecar, or a
  lone self-describing ``keypoints.npz``, e.g. ``capture/groundtruth/<seq>/keypoints.npz``);
* a BVH clip (``.bvh``): its joints are mapped to the keypoint layout
  (:mod:`egorelight_cli.io.bvh`), scaled to the character (``bvh.scale: 0`` fits one global scale
  to the character's bone lengths) and fitted, i.e. retargeted onto the character;
* a DDC motion (``.motion``): taken as theta directly when its DoF count matches the character.

``--gt`` accepts a keypoints or motion artifact (or lone npz), or a directory holding
``keypoints.npz`` and/or ``motion.npz`` (the simulator's ``capture/groundtruth/<seq>/``). With
such a folder, ``--calibration`` names the calibration whose head poses placed the input
keypoints: where those live in a world of their own (a headset tracker's), the truth's keypoints
are taken into it (:func:`~egorelight_cli.synth.groundtruth.T_pose_frame_from_truth_world`) and
only keypoint errors are scored (DoF errors need one world).

``--fit-recon CAPTURE --seq S`` then moves each frame's root and body DoFs so that the skinned
character lies on the capture's multi-view reconstruction of that frame
(:mod:`egorelight_cli.stages.ik_surface`; ``train animate``'s third motion source in the demo).

``--hmd-reference MOTION --calibration CAL --seq S`` places the head by the tracked headset: its
mounting on the head is calibrated on MOTION's frames, and the keypoints are solved again with the
headset's pose as three weighted markers on the head joint (:mod:`egorelight_cli.stages.ik_head`),
before any ``--fit-recon``.

The motion artifact holds ``motion.npz`` (see :mod:`egorelight_cli.io.motion`) and, for a
directory output, ``preview.png`` (fitted skeleton over the target keypoints for a few frames).
The ik model artifact (``train ik``) is a model directory in the shared layout of
:mod:`egorelight_cli.io.model` (``model.pt``: ``theta_bar`` and the hand PCAs as tensors, DoF
names and provenance in ``extra``; ``curve.json``/``curve.png``: cumulative explained variance of
each hand's PCA per component).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from egorelight_cli import console
from egorelight_cli.artifacts import MANIFEST_NAME, Artifact, ArtifactWriter, check_sequence
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.keypoints import load_keypoints
from egorelight_cli.structures.keypoints import Keypoints
from egorelight_cli.io.motion import load_motion, save_motion
from egorelight_cli.structures.motion import Motion
from egorelight_cli.pipeline import StageRun
from egorelight_cli.stages.character_commands import (CHARACTER_FINGERPRINT, character_sources,
                                                      check_same_character)
from egorelight_cli.stages.ik import (IK_MODEL_TYPE, IKModel, IKResult, IKSettings, default_ik_model,
                                      fit_global_scale, fit_metrics, fitted_keypoints, gt_metrics, scale_keypoints,
                                      solve_ik, solve_timing, train_ik_model)
from egorelight_cli.structures.character import Character

if TYPE_CHECKING:
    from egorelight_cli.stages.ik_head import HeadChain, HMDSettings
    from egorelight_cli.stages.ik_surface import SurfaceFitSettings
    from egorelight_cli.structures.calibration import HeadPoses

PREVIEW_PNG = "preview.png"


# ---------------------------------------------------------------------------------- inputs
@dataclass
class IKInput:
    """What ``--in`` resolved to: keypoints to fit, or theta to take as is (DDC motion)."""

    keypoints: Keypoints | None = None
    theta: np.ndarray | None = None
    frame_ids: np.ndarray | None = None
    artifact: Artifact | None = None
    sources: list[Path] = field(default_factory=list)
    info: dict = field(default_factory=dict)


def load_ik_input(path: Path, character: Character, cfg: Config) -> IKInput:
    """Resolve ``--in`` (see the module docstring)."""
    path = Path(path)
    if not path.exists():
        raise EgorelightError("input not found", path)
    suffix = path.suffix.lower()
    if suffix == ".bvh":
        return _bvh_input(path, character, cfg)
    if suffix == ".motion":
        from egorelight_cli.io.ddc import read_motion

        motion = read_motion(path, num_dofs=character.skeleton.num_dofs)
        if len(motion.frame_ids) == 0:
            raise EgorelightError("DDC motion holds no frames", path)
        return IKInput(theta=motion.values, frame_ids=motion.frame_ids, sources=[path], info={"source": "ddc motion"})
    keypoints, artifact = load_keypoints(path)
    return IKInput(keypoints=keypoints, artifact=artifact, sources=[] if artifact else [path],
                   info={"source": "keypoints"})


def _bvh_input(path: Path, character: Character, cfg: Config) -> IKInput:
    from egorelight_cli.io.bvh import bvh_keypoints, read_bvh

    bvh = cfg["bvh"]
    stride = int(bvh["stride"])  # bvh.* values are checked by stages/ik.yaml's checks
    clip = read_bvh(path)
    keypoints, mapping = bvh_keypoints(clip, unit_scale=float(bvh["unit_scale"]), up_axis=str(bvh["up_axis"]),
                                       keypoint_names=character.keypoint_names)
    keypoints = keypoints.select(slice(None, None, stride))
    keypoints = Keypoints(keypoints.xyz, keypoints.confidence, keypoints.frame_ids, keypoints.names, clip.fps / stride)
    scale = float(bvh["scale"]) or fit_global_scale(character, keypoints)
    keypoints = scale_keypoints(keypoints, scale)
    info = {"source": "bvh", "bvh_joints_mapped": len(mapping), "bvh_scale": scale, "bvh_fps": clip.fps,
            "bvh_mapping": mapping}
    return IKInput(keypoints=keypoints, sources=[path], info=info)


def truth_folder_sequence(gt_path: Path | None) -> str | None:
    """The sequence of a capture's ``groundtruth/<seq>`` folder given as ``--gt``; None for anything else."""
    return Path(gt_path).name if gt_path is not None and Path(gt_path).is_dir() \
        and Path(gt_path).parent.name == "groundtruth" else None


def _check_truth_frame_given(keypoints: Artifact | None, gt_path: Path) -> None:
    """Error when keypoints placed by a calibration's head poses in a world of their own (a
    headset tracker's: ``wild``) are to be scored against a truth folder without ``--calibration``:
    the two then sit in different worlds and every error is the gap between them (131 cm body
    MPJPE on the tiny capture's wild, 23 cm with it). Head poses in the studio's world need none."""
    from egorelight_cli.io.calibration import open_calibration

    sequence = truth_folder_sequence(gt_path)
    if keypoints is None or sequence is None or not (Path(gt_path) / "head_pose.npz").is_file():
        return
    placed_by = keypoints.made_from(kind="calibration")
    if not placed_by or not placed_by[0].exists():  # not placed by a calibration, or it cannot be told
        return
    calibration, _ = open_calibration(placed_by[0])
    if sequence in calibration.head_poses and not calibration.head_poses_in_studio_world(sequence):
        raise EgorelightError(f"the keypoints were placed by head poses of {placed_by[0]} in a world of their own "
                              f"(not the studio's): give --calibration {placed_by[0]} with --gt to score them in one "
                              "frame", gt_path)


def _gt_in_pose_frame(calibration, calibration_path: Path, gt_path: Path, character: Character,
                      gt_keypoints: Keypoints | None, gt_motion: Motion | None):
    """(keypoints, motion, manifest note): the ground truth of a ``capture/groundtruth/<seq>``
    folder in the frame of the calibration's head poses of ``seq`` (keypoints only, FK of the
    motion if need be, where that frame is not the truth's)."""
    import dataclasses

    from egorelight_cli.geometry.cameras import transform_points
    from egorelight_cli.synth.groundtruth import T_pose_frame_from_truth_world, truth_frame_note

    if truth_folder_sequence(gt_path) is None or not (Path(gt_path) / "head_pose.npz").is_file():
        raise EgorelightError("--calibration with --gt needs --gt to be a capture/groundtruth/<seq> folder with "
                              "head_pose.npz", gt_path or calibration_path)
    gt_path = Path(gt_path)
    sequence, root = gt_path.name, gt_path.parent.parent
    T = T_pose_frame_from_truth_world(root, calibration, sequence)
    if not np.array_equal(T, np.eye(4)):
        if gt_keypoints is None:
            from egorelight_cli.stages.ik_eval import motion_keypoints

            gt_keypoints = motion_keypoints(character, gt_motion)
        gt_keypoints = dataclasses.replace(gt_keypoints, xyz=transform_points(T, gt_keypoints.xyz))
        gt_motion = None
    return gt_keypoints, gt_motion, truth_frame_note(calibration, sequence)


def load_gt(path: Path, character: Character) -> tuple[Keypoints | None, Motion | None, list[Artifact], list[Path]]:
    """Ground truth from a keypoints/motion artifact or lone npz, or a folder with
    ``keypoints.npz``/``motion.npz`` (see the module docstring)."""
    from egorelight_cli.io.npz import read_npz_meta

    path = Path(path)
    if not path.exists():
        raise EgorelightError("ground truth not found", path)
    candidates = [path]
    if path.is_dir() and not (path / MANIFEST_NAME).is_file():
        candidates = [p for p in (path / "keypoints.npz", path / "motion.npz") if p.is_file()]
        if not candidates:
            raise EgorelightError("ground-truth folder holds neither keypoints.npz nor motion.npz", path)
    keypoints = motion = None
    artifacts: list[Artifact] = []
    sources: list[Path] = []
    for candidate in candidates:
        kind = _artifact_kind(candidate) or str(read_npz_meta(candidate).get("kind", "")).removeprefix("egorelight/")
        if kind == "keypoints":
            keypoints, artifact = load_keypoints(candidate)
        elif kind == "motion":
            motion, artifact = load_motion(candidate)
            motion.check_dofs(character.skeleton.dof_names, candidate)
        else:
            raise EgorelightError(f"ground truth must be keypoints or motion, found {kind or 'no kind'}", candidate)
        if artifact is not None:
            artifacts.append(artifact)
        else:
            sources.append(candidate)
    return keypoints, motion, artifacts, sources


def _artifact_kind(path: Path) -> str | None:
    from egorelight_cli.artifacts import manifest_path_for, open_artifact

    manifest_path, _ = manifest_path_for(path)
    if not manifest_path.is_file():
        if path.is_dir():
            raise EgorelightError("not a finished egorelight artifact (directory has no manifest.json)", path)
        return None
    return open_artifact(path).kind


# ----------------------------------------------------------------------------------- models
def write_ik_model(writer: ArtifactWriter, model: IKModel) -> None:
    """Fill a model artifact with ``model`` (layout of :mod:`egorelight_cli.io.model`)."""
    from egorelight_cli.io.model import ModelPayload, write_model

    arrays = model.arrays()
    state = {k: torch.as_tensor(v) for k, v in arrays.items() if k not in ("dof_names", "hand_sides")}
    curve = []
    for component in range(max((h.num_components for h in model.hands), default=0)):
        row = {"step": component + 1}
        for h in model.hands:
            total = h.total_variance or 1.0
            row[f"{h.side.lower()}_hand_explained"] = float(h.variance[:component + 1].sum() / total)
        curve.append(row)
    extra = {"dof_names": list(model.dof_names), "hand_sides": [h.side for h in model.hands], **model.meta()}
    write_model(writer.workdir, ModelPayload(IK_MODEL_TYPE, {"type": "theta_bar + hand PCA"}, state, extra, curve),
                curve_title="ik hand PCA: cumulative explained variance")
    writer.units.update({"theta_bar": "rad | m"})
    writer.metrics.update({"source": model.source, "training_frames": model.num_training_frames})
    for h in model.hands:
        side = h.side.lower()
        writer.metrics.update({f"{side}_hand_dofs": int(len(h.dof_index)), f"{side}_hand_components": h.num_components,
                               f"{side}_hand_explained_variance": curve[h.num_components - 1][f"{side}_hand_explained"]})


def load_ik_model(path: Path) -> tuple[IKModel, Artifact]:
    """Read an ik model artifact (kind model, trained by ``train ik``)."""
    from egorelight_cli.artifacts import open_artifact
    from egorelight_cli.io.model import read_model

    artifact = open_artifact(path, kind="model")
    if artifact.single_file:
        raise EgorelightError("an ik model is a directory artifact", path)
    payload = read_model(artifact.root, stage=IK_MODEL_TYPE)
    arrays = {k: v.numpy() for k, v in payload.state_dict.items()}
    arrays["dof_names"] = np.array(payload.extra.get("dof_names", []))
    arrays["hand_sides"] = np.array(payload.extra.get("hand_sides", []))
    try:
        return IKModel.from_arrays(arrays, payload.extra), artifact
    except KeyError as exc:
        raise EgorelightError(f"ik model lacks {exc.args[0]!r}", path) from None


# ---------------------------------------------------------------------------------- results
def passthrough_result(character: Character, theta: np.ndarray, frame_ids: np.ndarray, fps: float) -> IKResult:
    """An :class:`IKResult` for theta taken as is (no fit)."""
    fitted = fitted_keypoints(character, theta)
    return IKResult(np.asarray(theta, np.float64), np.asarray(frame_ids, np.int64), fps, fitted,
                    np.full(fitted.shape[:2], np.nan), (), "none", 0.0)


def preview_frames(num_frames: int, count: int) -> np.ndarray:
    """Up to ``count`` frame positions spread over the sequence."""
    return np.unique(np.linspace(0, num_frames - 1, max(min(count, num_frames), 1)).round().astype(int))


@dataclass(frozen=True)
class IKCommands:
    """``ik`` and ``train ik`` over one :class:`StageRun` (the global options)."""

    run: StageRun

    def ik(self, input_path: Path, character_spec: str, model_path: Path | None, gt_path: Path | None,
           calibration_path: Path | None, out: Path, fit_recon: Path | None = None,
           sequence: str | None = None, hmd_reference: Path | None = None) -> Path:
        from egorelight_cli.stages.character_commands import load_character
        from egorelight_cli.stages.ik_head import HMDSettings
        from egorelight_cli.stages.ik_surface import SurfaceFitSettings

        cfg = self.run.config()
        settings = IKSettings.from_config(cfg)  # a bad config value fails before anything is read
        surface_settings = SurfaceFitSettings.from_config(cfg)  # likewise ik --fit-recon's
        HMDSettings.from_config(cfg)  # and --hmd-reference's
        recon = _recon_sequence(fit_recon, sequence, hmd_reference is not None)
        character, character_artifact = load_character(character_spec)
        source = load_ik_input(input_path, character, cfg)
        inputs = [a for a in (source.artifact, character_artifact) if a is not None]
        sources = source.sources + character_sources(character_spec, character_artifact)
        if recon is not None:
            inputs.append(recon[1])
        model = None
        if model_path is not None:
            model, model_artifact = load_ik_model(model_path)
            model.check_character(character, model_path)
            inputs.append(model_artifact)
        gt_keypoints = gt_motion = None
        if gt_path is not None:
            truth_sequence = truth_folder_sequence(gt_path)
            if truth_sequence is not None:
                check_sequence(source.artifact, truth_sequence)
            gt_keypoints, gt_motion, gt_artifacts, gt_sources = load_gt(gt_path, character)
            inputs += gt_artifacts
            sources += gt_sources
        # the truth is taken into the frame of --calibration's head poses where it has some (a sequence
        # where the headset was not worn is scored as it is, when --calibration is there for --hmd-reference)
        posed_truth = calibration_path is not None and gt_path is not None and (
            hmd_reference is None or (Path(gt_path) / "head_pose.npz").is_file())
        if not posed_truth and gt_path is not None:
            _check_truth_frame_given(source.artifact, gt_path)
        gt_frame = calibration = None
        if calibration_path is not None:
            from egorelight_cli.io.calibration import open_calibration

            if gt_path is None and hmd_reference is None:
                raise EgorelightError("--calibration needs --gt (a capture/groundtruth/<seq> folder) or --hmd-reference",
                                      calibration_path)
            calibration, calibration_artifact = open_calibration(calibration_path)
            inputs.append(calibration_artifact)
            if posed_truth:
                gt_keypoints, gt_motion, gt_frame = _gt_in_pose_frame(calibration, calibration_path, gt_path, character,
                                                                      gt_keypoints, gt_motion)
                sources.append(Path(gt_path) / "head_pose.npz")  # the truth's frame is read from it
        hmd = None
        if hmd_reference is not None:
            hmd, reference_artifact = _hmd_mount(hmd_reference, calibration, calibration_path, sequence, character)
            inputs.append(reference_artifact)
            check_sequence(source.artifact, sequence)  # the head poses must be the input's
        if source.keypoints is not None:
            from egorelight_cli.stages.ik import check_keypoints_for

            check_keypoints_for(character, source.keypoints, settings, input_path)

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            settings = IKSettings.from_config(cfg)
            used = None
            if source.keypoints is not None:
                used = model or default_ik_model(character, settings)
                result = solve_ik(character, source.keypoints, used, settings)
                # which prior regularised the fit: "motions" (trained) or "default" (synthetic hands, rest pose)
                writer.metrics.update({"prior": used.source, "prior_training_frames": used.num_training_frames})
            else:
                result = passthrough_result(character, source.theta, source.frame_ids, settings.fps)
            keypoint_fit = result
            if hmd is not None:
                result = _head_from_hmd(writer, character, result, source.keypoints, hmd, used, settings,
                                        HMDSettings.from_config(cfg))
            if recon is not None:
                result = _fit_to_recon(writer, character, result, source.keypoints, recon[0], surface_settings)
            save_motion(writer, result.motion(character.skeleton.dof_names), source=source.info.get("source"))
            writer.extra[CHARACTER_FINGERPRINT] = character.fingerprint()  # the DoFs pose this character
            writer.metrics.update(fit_metrics(result))
            writer.timing.update(solve_timing(result))
            writer.metrics.update({k: v for k, v in source.info.items() if k != "source"})
            writer.metrics["input"] = source.info.get("source")
            if gt_keypoints is not None or gt_motion is not None:
                writer.metrics.update(gt_metrics(character, result, gt_keypoints, gt_motion))
                if result is not keypoint_fit:  # --fit-recon's baseline: the keypoint fit it started from
                    writer.metrics.update({f"keypoint_fit_{k}": v for k, v in
                                           gt_metrics(character, keypoint_fit, gt_keypoints, gt_motion).items()})
                if gt_frame is not None:
                    writer.metrics["groundtruth_frame"] = gt_frame
            writer.runtime["solver"] = result.solver
            if not writer.single_file:
                _write_preview(writer, character, result, source.keypoints, cfg)

        return self.run.produce(out, "motion", write, inputs=inputs, source_files=sources)

    def train(self, motion_paths: tuple[Path, ...], character_spec: str, out: Path) -> Path:
        from egorelight_cli.stages.character_commands import load_character

        IKSettings.from_config(self.run.config())  # a bad config value fails before anything is read
        character, character_artifact = load_character(character_spec)
        inputs = [a for a in (character_artifact,) if a is not None]
        sources = character_sources(character_spec, character_artifact)
        motions = []
        for path in motion_paths:
            motion, artifact = load_motion(path)
            motion.check_dofs(character.skeleton.dof_names, path)
            check_same_character(artifact, character, "motion")
            motions.append(motion.theta)
            if artifact is not None:
                inputs.append(artifact)
            else:
                sources.append(Path(path))

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            if writer.single_file:
                raise EgorelightError("an ik model is a directory artifact: give --out a directory name", out)
            write_ik_model(writer, train_ik_model(character, motions, IKSettings.from_config(cfg)))

        return self.run.produce(out, "model", write, inputs=inputs, source_files=sources)


def _recon_sequence(capture_path: Path | None, sequence: str | None, hmd: bool = False):
    """``(SequenceInfo, capture artifact)`` of ``--fit-recon CAPTURE --seq S``, None without
    ``--fit-recon``; a one-line error when the two do not come together or the sequence has no
    reconstruction (``hmd``: ``--hmd-reference`` was given, which also needs ``--seq``)."""
    from egorelight_cli.io.capture import open_capture

    if capture_path is None:
        if sequence is not None and not hmd:
            raise EgorelightError("--seq names the input's sequence for --fit-recon or --hmd-reference; give one of them")
        return None
    if sequence is None:
        raise EgorelightError("--fit-recon needs --seq: the sequence whose reconstructions the motion is fitted to")
    from egorelight_cli.stages.animate_fit import require_reconstructions

    capture, artifact = open_capture(capture_path, [sequence])
    seq = capture.sequence(sequence)
    require_reconstructions(seq, capture_path)
    return seq, artifact


def _fit_to_recon(writer: ArtifactWriter, character: Character, result: IKResult, keypoints: Keypoints | None,
                  sequence, settings: SurfaceFitSettings) -> IKResult:
    """``result`` with its DoFs fitted to ``sequence``'s reconstructions (stages/ik_surface.py)."""
    from egorelight_cli.stages.animate_fit import recon_targets, require_targets
    from egorelight_cli.stages.ik_surface import fit_motion_to_surface, with_theta

    targets = recon_targets(sequence, result.frame_ids, settings.target_points)
    require_targets(targets, result.frame_ids, "--fit-recon", sequence.name, "the multi-view reconstruction")
    theta, summary = fit_motion_to_surface(character, result.theta, result.frame_ids, targets, settings)
    writer.metrics.update(summary)
    writer.units["surface_fit_chamfer_cm"] = "cm, normal-filtered point-to-plane Chamfer of the skinned character " \
                                             "to the reconstruction"
    return with_theta(character, result, theta, None if keypoints is None else keypoints.xyz.astype(np.float64))


@dataclass(frozen=True)
class _HMDHead:
    """What ``--hmd-reference`` gives the fit: the head chain, the mounting and the input's HMD poses
    (None: the sequence has none)."""

    chain: "HeadChain"
    T_hmd_from_head: np.ndarray
    mount: dict
    head_poses: "HeadPoses | None"


def _hmd_mount(reference_path: Path, calibration, calibration_path: Path | None, sequence: str | None,
               character: Character) -> tuple[_HMDHead, Artifact]:
    """The HMD's mounting on the head, calibrated on the ``--hmd-reference`` motion's frames with a
    valid head pose in its own sequence (:func:`~egorelight_cli.stages.ik_head.calibrate_hmd_from_head`),
    and the head poses of ``sequence`` (the input's)."""
    from egorelight_cli.stages.ik_head import calibrate_hmd_from_head, head_chain, head_transforms

    if calibration is None or sequence is None:
        raise EgorelightError("--hmd-reference needs --calibration (the head poses) and --seq (the input's sequence)",
                              reference_path)
    reference, artifact = load_motion(reference_path)
    if artifact is None:
        raise EgorelightError("--hmd-reference must be a motion artifact (its manifest names its sequence)",
                              reference_path)
    reference.check_dofs(character.skeleton.dof_names, reference_path)
    check_same_character(artifact, character, "--hmd-reference motion")
    reference_sequence = ((artifact.manifest.get("config") or {}).get("options") or {}).get("sequence")
    if reference_sequence not in calibration.head_poses:
        raise EgorelightError(f"the calibration has no head poses of sequence {reference_sequence!r} (the "
                              "--hmd-reference motion's)", calibration_path)
    if sequence not in calibration.head_poses:  # the headset was not worn (relight_train): the head stays
        console.info(f"ik: the calibration has no head poses of sequence {sequence!r}: the head is not placed "
                     "by the headset")
    posed = _valid_hmd_poses(calibration.head_poses[reference_sequence], reference.frame_ids)
    if not posed:
        raise EgorelightError(f"no frame of the motion has a valid head pose of sequence {reference_sequence!r}",
                              reference_path)
    chain = head_chain(character)
    T_hmd_from_head, mount = calibrate_hmd_from_head(
        np.stack(list(posed.values())), head_transforms(character, reference.theta[list(posed)], chain.joint))
    mount["hmd_mount_sequence"] = str(reference_sequence)
    return _HMDHead(chain, T_hmd_from_head, mount, calibration.head_poses.get(sequence)), artifact


def _valid_hmd_poses(poses: "HeadPoses", frame_ids: np.ndarray) -> dict[int, np.ndarray]:
    """Row of ``frame_ids`` -> ``T_world_from_hmd`` (4,4), for the frames with a valid head pose."""
    valid = poses.valid_poses()
    return {row: valid[int(f)] for row, f in enumerate(frame_ids) if int(f) in valid}


def _head_from_hmd(writer: ArtifactWriter, character: Character, result: IKResult, keypoints: Keypoints | None,
                   hmd: _HMDHead, model: IKModel | None, settings: IKSettings, marker: HMDSettings) -> IKResult:
    """The motion with its head placed by the HMD in each frame with a valid HMD pose: the keypoints
    solved again with the HMD's head markers (:func:`~egorelight_cli.stages.ik_head.with_head_markers`),
    or, for an input given as DoFs (``result`` without keypoints), the neck and head DoFs fitted to
    it (:func:`~egorelight_cli.stages.ik_head.fit_head_to_hmd`). ``result`` is the keypoint fit."""
    from dataclasses import replace

    from egorelight_cli.stages.ik_head import (fit_head_to_hmd, head_marker_keypoints, head_offset_summary,
                                               with_head_markers)
    from egorelight_cli.stages.ik_surface import with_theta

    posed = {} if hmd.head_poses is None else _valid_hmd_poses(hmd.head_poses, result.frame_ids)
    targets = {row: T_world_from_hmd @ hmd.T_hmd_from_head for row, T_world_from_hmd in posed.items()}
    if keypoints is None:
        theta, summary = fit_head_to_hmd(character, result.theta, targets, hmd.chain)
        out = with_theta(character, result, theta, None)
    else:
        marked = with_head_markers(character, hmd.chain.joint, marker.marker_spacing_m)
        weights = np.concatenate([np.ones(len(character.keypoint_names)), np.full(3, marker.weight)])
        solved = solve_ik(marked, head_marker_keypoints(keypoints, targets, marker.marker_spacing_m), model, settings,
                          weights) if targets else result
        K = len(character.keypoint_names)
        solved = replace(solved, residual_m=solved.residual_m[:, :K],
                         rejected=None if solved.rejected is None else solved.rejected[:, :K],
                         seconds=solved.seconds + (result.seconds if solved is not result else 0.0))  # both solves
        out = with_theta(character, solved, solved.theta, keypoints.xyz.astype(np.float64))
        summary = head_offset_summary(character, result.theta, out.theta, targets, hmd.chain.joint)
        summary["hmd_marker_weight"] = marker.weight
    writer.metrics.update({**hmd.mount, **summary})
    writer.units.update({"hmd_mount_spread_cm": "cm, mean distance of the reference frames' HMD-to-head transforms "
                                                "from their mean", "hmd_head_offset_cm_before": "cm, head joint off "
                                                "the HMD's in the keypoint fit (after: with the headset)"})
    return out


def _write_preview(writer: ArtifactWriter, character: Character, result: IKResult, keypoints: Keypoints | None,
                   cfg: Config) -> None:
    from egorelight_cli.io.images import write_image
    from egorelight_cli.render.preview import skeleton_fit_image

    preview = cfg["preview"]
    rows = preview_frames(len(result.theta), int(preview["frames"]))
    targets = keypoints.xyz[rows] if keypoints is not None else None
    labels = [f"frame {int(result.frame_ids[r])}" for r in rows]
    image = skeleton_fit_image(character, result.theta[rows], targets, int(preview["width"]), int(preview["height"]), labels)
    write_image(writer.path(PREVIEW_PNG), image)


# ------------------------------------------------------------- handlers (egorelight_cli.declarations)
def train_command(run: StageRun, motions: tuple[Path, ...], character: str, out: Path) -> Path:
    return IKCommands(run).train(motions, character, out)


def ik_command(run: StageRun, input: Path, character: str, model: Path | None, gt: Path | None,
               calibration: Path | None, fit_recon: Path | None, hmd_reference: Path | None, sequence: str | None,
               out: Path) -> Path:
    return IKCommands(run).ik(input, character, model, gt, calibration, out, fit_recon, sequence, hmd_reference)
