"""The ``egorelight animate`` and ``egorelight train animate`` commands: load inputs, call
:mod:`egorelight_cli.stages.animate`, write artifacts.

``train animate`` reads a capture sequence's multi-view reconstructions (``recon/<frame>.ply``,
the training target), one or more motion artifacts of that sequence and, unless ``--no-depth``,
its pointcloud artifact; it writes a model artifact (``model.pt``, ``curve.json``, ``curve.png``).
Each ``--motion`` adds one training sample per frame (same reconstruction, same point cloud).
The demo trains on the motion the headset pipeline estimated for the training frames: under it
the depth encoding shows the network corrections like the ones it must make at run time (under
the studio's mocap there is almost nothing to correct, and the network learned to ignore the
depth). Several motions, e.g. draws of a motion error, train on all of them.
``--init MODEL`` starts from a trained model (the paper's depth-agnostic student: ``--no-depth
--init MODEL --sequence relight_train``, fine-tuned on the flat-lit frames).

``animate`` reads a motion, a point cloud (unless ``--no-depth``) and a model and writes a
meshes artifact (``meshes.npz``, see :mod:`egorelight_cli.io.mesh_sequence`), ``preview.png``
and, with ``--export ply|obj``, one mesh file per frame under ``export/``. With ``--capture``
(and the capture has ``groundtruth/``), the manifest's metrics hold point-to-surface distances
(cm) between the meshes and the true surface, whatever its topology, both ways
(``pred_to_true``: accuracy; ``true_to_pred``: completeness), over the full body and over the
surface the down-facing ego cameras see, for (a) skinning only, (b) the network without depth
and (c) with depth (keys in :func:`~egorelight_cli.stages.animate_eval.score_meshes`; the
un-prefixed ``p2s_*`` keys repeat the stage's own mesh).
``--calibration`` adds the meshes drawn over the ego images to the preview.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from typing import TYPE_CHECKING, Sequence

import numpy as np

from egorelight_cli import console
from egorelight_cli.artifacts import Artifact, ArtifactWriter, check_sequence, open_artifact, resolve_payload
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.capture import Capture, open_capture, read_reconstructions
from egorelight_cli.io.mesh_sequence import export_sequence, save_meshes
from egorelight_cli.structures.mesh_sequence import MeshSequence
from egorelight_cli.io.motion import MOTION_PAYLOAD, load_motion
from egorelight_cli.structures.motion import Motion
from egorelight_cli.io.pointcloud import POINTCLOUD_PAYLOAD
from egorelight_cli.pipeline import StageRun
from egorelight_cli.sharding import split_frames
from egorelight_cli.stages.character_commands import (CHARACTER_FINGERPRINT, character_sources,
                                                      check_same_character, load_character)
from egorelight_cli.structures.character import Character

# torch and the stage module load only past the cache check (importing torch alone takes seconds;
# an up-to-date `animate` returns in about one)
if TYPE_CHECKING:
    import torch

    from egorelight_cli.stages.animate import AnimationModel

PREVIEW_PNG = "preview.png"
EXPORT_DIR = "export"


# ---------------------------------------------------------------------------------- inputs
def _load_motion(path: Path, character: Character) -> tuple[Motion, Artifact | None]:
    motion, artifact = load_motion(path)
    motion.check_dofs(character.skeleton.dof_names, path)
    check_same_character(artifact, character, "motion")
    if motion.num_frames == 0:
        raise EgorelightError("motion holds no frames", path)
    return motion, artifact


def _load_clouds(path: Path | None, motions: Sequence[Motion],
                 no_depth: bool) -> tuple[list | None, Artifact | None, int]:
    """Per motion, per motion frame ``(points, normals)`` (None where the cloud lacks the frame),
    the artifact, and the number of motion frames with a cloud (all motions); ``(None, None, 0)``
    without depth."""
    from egorelight_cli.io.pointcloud import load_pointcloud

    if no_depth:
        return None, None, 0
    if path is None:
        raise EgorelightError("a point cloud is required (--pointcloud), or run with --no-depth")
    cloud, artifact = load_pointcloud(path)
    if len(cloud.frame_ids) == 0:
        raise EgorelightError("the point cloud holds no frame", path)
    have = set(int(f) for f in cloud.frame_ids)
    clouds = []
    for motion in motions:
        clouds.append([cloud.frame(int(f)) if int(f) in have else None for f in motion.frame_ids])
        if not any(c is not None for c in clouds[-1]):
            raise EgorelightError(f"point cloud frames {cloud.frame_ids.min()}..{cloud.frame_ids.max()} share no frame "
                                  f"with the motion ({motion.frame_ids.min()}..{motion.frame_ids.max()})", path)
    return clouds, artifact, sum(c is not None for per_motion in clouds for c in per_motion)


def _motion_and_cloud_artifacts(motion_paths: Sequence[Path], pointcloud_path: Path | None,
                                no_depth: bool) -> tuple[list[Artifact | None], Artifact | None, list[Path]]:
    """(each motion's artifact, the point cloud's artifact, the lone npz files among them), read
    from the manifests only (the arrays load past the cache check); no cloud with ``--no-depth``."""
    motion_artifacts = [resolve_payload(path, "motion", MOTION_PAYLOAD, "motion")[1] for path in motion_paths]
    lone = [Path(path) for path, artifact in zip(motion_paths, motion_artifacts) if artifact is None]
    cloud_artifact = None
    if pointcloud_path is not None and no_depth:
        raise EgorelightError("--no-depth reads no point cloud: leave out --pointcloud", pointcloud_path)
    if pointcloud_path is not None:
        cloud_artifact = resolve_payload(pointcloud_path, "pointcloud", POINTCLOUD_PAYLOAD, "pointcloud")[1]
        lone += [] if cloud_artifact is not None else [Path(pointcloud_path)]
    return motion_artifacts, cloud_artifact, lone


def load_animate_model(path: Path, character: Character, device) -> tuple[AnimationModel, Artifact, dict]:
    """Read a model artifact written by ``train animate`` and bind it to ``character``."""
    from egorelight_cli.io.model import read_model
    from egorelight_cli.stages.animate import ANIMATE_MODEL_TYPE, AnimationModel, DepthSettings, NetSettings

    artifact = open_artifact(path, kind="model")
    if artifact.single_file:
        raise EgorelightError("an animate model is a directory artifact", path)
    payload = read_model(artifact.root, stage=ANIMATE_MODEL_TYPE)
    check_same_character(artifact, character, "animate model")
    extra = payload.extra
    if int(extra.get("num_vertices", -1)) != character.num_vertices or int(extra.get("num_nodes", -1)) != character.graph.num_nodes:
        raise EgorelightError(f"model was trained for a character with {extra.get('num_vertices')} vertices and "
                              f"{extra.get('num_nodes')} graph nodes, this one has {character.num_vertices} and "
                              f"{character.graph.num_nodes}", path)
    try:
        net_settings = NetSettings.from_architecture(payload.architecture)
    except TypeError as exc:
        raise EgorelightError(f"animate model architecture is not understood ({exc})", path) from None
    depth = DepthSettings(float(extra["eps_d"]), float(extra["eps_n"]))
    net = net_settings.build_net()
    try:
        net.load_state_dict(payload.state_dict)
    except RuntimeError as exc:
        raise EgorelightError(f"animate model weights do not fit its architecture ({str(exc).splitlines()[0]})", path) from None
    return AnimationModel(character, net_settings, depth, net, device), artifact, extra


@dataclass(frozen=True)
class AnimateCommands:
    """``animate`` and ``train animate`` over one :class:`StageRun` (the global options)."""

    run: StageRun

    def _device(self):
        return self.run.compute_device()

    # ------------------------------------------------------------------------------ train
    def train(self, capture_path: Path, sequence: str, motion_paths: Sequence[Path], pointcloud_path: Path | None,
              character_spec: str, init_path: Path | None, no_depth: bool, out: Path, resume: bool = False) -> Path:
        import torch

        from egorelight_cli.nn.training import Checkpoint, checkpoint_beside
        from egorelight_cli.stages.animate import (ANIMATE_MODEL_TYPE, AnimationModel, DepthSettings, NetSettings,
                                                   TrainSettings, TrainingData, build_training_data, evaluate_chamfer,
                                                   train_animation_model)

        character, character_artifact = load_character(character_spec)
        capture, capture_artifact = open_capture(capture_path)
        seq = capture.sequence(sequence)
        seq.require_stream("recon")
        if not motion_paths:
            raise EgorelightError("train animate needs at least one --motion")
        motions = [_load_motion(path, character)[0] for path in motion_paths]
        clouds, _, cloud_frames = _load_clouds(pointcloud_path, motions, no_depth)
        clouds = clouds or [None] * len(motions)
        cfg = self.run.config()
        frames = np.intersect1d(np.concatenate([m.frame_ids for m in motions]), seq.content_frame_ids)
        if bool(cfg["train"]["flat_lit_only"]):
            frames = seq.flat_lit(frames)
        recon = read_reconstructions(seq, frames)
        if not recon:
            span = ", ".join(f"{m.frame_ids.min()}..{m.frame_ids.max()}" for m in motions)
            raise EgorelightError(f"no frame of the motion ({span}) has a flat-lit multi-view reconstruction in "
                                  f"sequence {sequence!r}", seq.root / "recon")
        motion_artifacts, cloud_artifact, lone = _motion_and_cloud_artifacts(motion_paths, pointcloud_path, no_depth)
        inputs = [capture_artifact, character_artifact, *motion_artifacts, cloud_artifact]
        # a motion given twice counts once; a copy of it at another path is an input of its own
        inputs = list({(a.digest, str(a.path)): a for a in inputs if a is not None}.values())
        sources = character_sources(character_spec, character_artifact) + lone
        sources = list(dict.fromkeys(sources + [seq.recon_path(f) for f in sorted(recon)]))
        init = None
        if init_path is not None:
            init, init_artifact, _ = load_animate_model(init_path, character, self._device())
            inputs.append(init_artifact)
        device = self._device()
        checkpoint = checkpoint_beside(out)

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            from egorelight_cli.io.model import ModelPayload, write_model

            if writer.single_file:
                raise EgorelightError("an animate model is a directory artifact: give --out a directory name", out)
            settings = TrainSettings.from_config(cfg)
            if init is not None:
                settings = settings.starting_from_a_model()
            torch.manual_seed(settings.seed)
            model = init or AnimationModel(character, NetSettings.from_config(cfg), DepthSettings.from_config(cfg),
                                           device=device)
            training_ids, validation_ids = split_frames(sorted(recon), 0, settings.validation_frames)
            if settings.validation_frames > 0 and not validation_ids:
                console.info(f"train animate: {len(recon)} frames are too few to set "
                             f"{settings.validation_frames} aside for validation; training keeps the last weights")

            def samples(frame_ids: list[int]) -> TrainingData:
                part = {f: recon[f] for f in frame_ids}
                return TrainingData.concatenate([
                    build_training_data(model, motion.theta, motion.frame_ids, per_frame, part, settings)
                    for motion, per_frame in zip(motions, clouds)])

            data = samples(training_ids)
            validation = samples(validation_ids) if validation_ids else None
            before = evaluate_chamfer(model, data, settings, no_depth=no_depth)
            curve, selected = train_animation_model(model, data, settings, no_depth=no_depth,
                                                    checkpoint=Checkpoint(checkpoint, writer.cache_key, resume),
                                                    validation=validation)
            after = evaluate_chamfer(model, data, settings, no_depth=no_depth)
            extra = {"eps_d": model.depth.eps_d, "eps_n": model.depth.eps_n, "num_vertices": character.num_vertices,
                     "num_nodes": character.graph.num_nodes, "no_depth": bool(no_depth), "sequence": sequence,
                     "frames": [int(f) for f in data.frame_ids], "validation_frames": validation_ids,
                     "motions": [str(p) for p in motion_paths],
                     "init": str(init_path) if init_path else None}
            write_model(writer.workdir, ModelPayload(ANIMATE_MODEL_TYPE, model.settings.to_dict(),
                                                     model.net.state_dict(), extra, curve),
                        curve_title="train animate: loss terms")
            writer.extra[CHARACTER_FINGERPRINT] = character.fingerprint()
            writer.metrics.update({"training_frames": int(len(data.frame_ids)), "training_motions": len(motions),
                                   "steps": settings.steps,
                                   "no_depth": bool(no_depth), "frames_with_cloud": cloud_frames,
                                   "train_chamfer_cm_before": before, "train_chamfer_cm_after": after,
                                   "final_loss": curve[-1]["loss"] if curve else None,
                                   "validation_frames": len(validation_ids), **selected})
            writer.units.update({"train_chamfer_cm": "cm (normal-filtered two-sided Chamfer, full mesh)",
                                 "validation_chamfer_cm": "cm (the same, on the frames set aside, every motion)"})

        produced = self.run.produce(out, "model", write, inputs=inputs, source_files=sources)
        checkpoint.unlink(missing_ok=True)
        return produced

    # ----------------------------------------------------------------------------- animate
    def animate(self, motion_path: Path, pointcloud_path: Path | None, model_path: Path, character_spec: str,
                capture_path: Path | None, sequence: str, calibration_path: Path | None, no_depth: bool,
                export: str | None, out: Path, fit: str | None = None) -> Path:
        """``fit``: None, ``"recon"`` (``--fit-recon``) or ``"truth"`` (``--fit-truth``): each frame then
        deformed onto the capture's reconstruction or true surface (:mod:`~egorelight_cli.stages.animate_fit`)."""
        character, character_artifact = load_character(character_spec)
        (motion_artifact,), cloud_artifact, lone = _motion_and_cloud_artifacts([motion_path], pointcloud_path, no_depth)
        model_artifact = open_artifact(model_path, kind="model")
        capture, capture_artifact = open_capture(capture_path, [sequence]) if capture_path is not None else (None, None)
        if capture is not None:  # scored against --seq's truth: the cloud must be of that sequence
            check_sequence(cloud_artifact, sequence)
        calibration = calibration_artifact = None
        if calibration_path is not None:
            from egorelight_cli.io.calibration import open_calibration

            calibration, calibration_artifact = open_calibration(calibration_path)
        inputs = [a for a in (character_artifact, motion_artifact, cloud_artifact, model_artifact, capture_artifact,
                              calibration_artifact) if a is not None]
        sources = character_sources(character_spec, character_artifact) + lone
        if fit is not None:
            sources += _fit_sources(fit, capture, capture_path, sequence)
        if self.run.up_to_date(out, "meshes", inputs, sources):
            return Path(out)
        from egorelight_cli.stages.animate import previous_rows

        motion, _ = _load_motion(motion_path, character)
        clouds, _, cloud_frames = _load_clouds(pointcloud_path, [motion], no_depth)
        clouds = None if clouds is None else clouds[0]
        model, _, _ = load_animate_model(model_path, character, self._device())

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            import time

            started = time.perf_counter()
            uv_inputs, xi_mask, template = model.uv_inputs(motion.theta, previous_rows(motion.frame_ids), clouds)
            meshes = model.mesh_sequence(uv_inputs, motion.theta, motion.frame_ids, motion.fps)
            if fit is not None:
                meshes = _fit_surface(writer, fit, capture, sequence, model, meshes, calibration, cfg)
            elapsed = time.perf_counter() - started
            save_meshes(writer, meshes, name=None, source=f"animate --fit-{fit}" if fit else "animate",
                        no_depth=bool(no_depth))
            writer.timing["frames_per_s"] = round(motion.num_frames / max(elapsed, 1e-9), 2)
            writer.metrics.update({"frames": motion.num_frames, "no_depth": bool(no_depth),
                                   "frames_with_cloud": cloud_frames,
                                   "xi_vertices_per_frame": float(xi_mask.sum(1).mean())})
            distances = None
            if capture is not None:
                distances = _score(writer, capture, sequence, model, meshes, template, uv_inputs, no_depth,
                                   int(cfg["preview"]["frames"]), calibration)
            fmt = export if export is not None else str(cfg["export"])
            if fmt != "none":
                if writer.single_file:
                    raise EgorelightError("--export needs a directory output", out)
                export_sequence(writer.path(EXPORT_DIR), meshes, fmt, character.face_uvs)
            if not writer.single_file:
                _write_preview(writer, character, meshes, distances, capture, calibration, sequence, cfg)

        return self.run.produce(out, "meshes", write, inputs=inputs, source_files=sources)


# ---------------------------------------------------------------------------------- scoring
def _fit_sources(fit: str, capture: Capture | None, capture_path: Path | None, sequence: str) -> list[Path]:
    """The files ``--fit-<fit>`` fits to (the truth's mesh file; none for the reconstructions, which
    the capture's manifest covers); a one-line error when the capture has none."""
    if capture is None:
        raise EgorelightError(f"--fit-{fit} needs --capture (a capture with "
                              + ("ground truth)" if fit == "truth" else "multi-view reconstructions)"))
    if fit == "recon":
        from egorelight_cli.stages.animate_fit import require_reconstructions

        require_reconstructions(capture.sequence(sequence), capture_path)
        return []
    path = capture.groundtruth_file(sequence, "meshes.npz")
    if path is None:
        raise EgorelightError(f"--fit-truth needs the ground-truth surface of sequence {sequence!r} "
                              "(groundtruth/<seq>/meshes.npz), which this capture does not have", capture_path)
    return [Path(path)]


def _fit_surface(writer: ArtifactWriter, fit: str, capture: Capture, sequence: str, model: AnimationModel,
                 meshes: MeshSequence, calibration, cfg: Config) -> MeshSequence:
    """``meshes`` deformed towards the reconstruction (``fit="recon"``, in the studio world like the
    motion) or the true surface (``"truth"``, in the frame of ``calibration``'s head poses when given,
    as :func:`_score` takes it); :mod:`egorelight_cli.stages.animate_fit`."""
    from egorelight_cli.stages.animate import TrainSettings
    from egorelight_cli.stages.animate_fit import (FitSettings, fit_to_surface, recon_targets, require_targets,
                                                   true_targets)

    settings = FitSettings.from_config(cfg)
    if fit == "recon":
        targets = recon_targets(capture.sequence(sequence), meshes.frame_ids, settings.target_points)
        settings = dataclasses.replace(settings, steps=settings.recon_steps)
        surface = "the multi-view reconstruction (--fit-recon)"
    else:
        from egorelight_cli.stages.animate_eval import groundtruth_meshes
        from egorelight_cli.synth.groundtruth import T_pose_frame_from_truth_world

        T = (np.eye(4) if calibration is None
             else T_pose_frame_from_truth_world(capture.groundtruth_root(), calibration, sequence))
        targets = true_targets(groundtruth_meshes(capture, sequence), meshes.frame_ids, settings.target_points, T)
        surface = "the true outer surface (--fit-truth)"
    require_targets(targets, meshes.frame_ids, f"--fit-{fit}", sequence, surface)
    fitted, summary = fit_to_surface(model, meshes, targets, TrainSettings.from_config(cfg), settings)
    writer.metrics.update({**summary, "fitted_to_groundtruth": fit == "truth", "fitted_to": fit})
    writer.units.update({"fit_chamfer_cm": f"cm, normal-filtered Chamfer to {surface}"})
    return fitted


def _score(writer: ArtifactWriter, capture: Capture, sequence: str, model: AnimationModel, meshes: MeshSequence,
           template, uv_inputs: torch.Tensor, no_depth: bool, preview_count: int,
           pose_calibration=None) -> dict[int, np.ndarray] | None:
    """Ground-truth metrics (a) skinning, (b) no depth, (c) full, against a truth of any
    topology (:func:`~egorelight_cli.stages.animate_eval.score_meshes`); per-vertex pred->true
    distances (cm) of the preview frames. With ``pose_calibration`` (the one the motion's head
    poses came from) the meshes are first taken from its frame to the truth's
    (:func:`~egorelight_cli.synth.groundtruth.T_pose_frame_from_truth_world`); without, the two
    are taken to be the same."""
    from egorelight_cli.stages.animate import XI_CHANNELS
    from egorelight_cli.stages.animate_eval import SCORED, groundtruth_meshes, score_meshes, true_surfaces
    from egorelight_cli.geometry.cameras import invert_rigid, transform_points
    from egorelight_cli.synth.groundtruth import T_pose_frame_from_truth_world, oracle_calibration, truth_frame_note

    truth = groundtruth_meshes(capture, sequence)
    if truth is None:
        return None
    calibration = oracle_calibration(capture.root)
    surfaces = true_surfaces(capture, calibration, sequence, truth, meshes.frame_ids)
    predictions = {"skinning": template.vertices.astype(np.float32)}
    if no_depth:
        predictions["no_depth"] = meshes.vertices
    else:
        blind = uv_inputs.clone()
        blind[:, XI_CHANNELS] = 0.0
        predictions["no_depth"] = model.predict(blind, meshes.theta)["vertices"]
        predictions["full"] = meshes.vertices
    if pose_calibration is not None:  # the meshes live in the frame of the head poses: take them to the truth's
        T = T_pose_frame_from_truth_world(capture.groundtruth_root(), pose_calibration, sequence)
        if not np.array_equal(T, np.eye(4)):
            predictions = {k: transform_points(invert_rigid(T), np.asarray(v)).astype(np.float32)
                           for k, v in predictions.items()}
        writer.metrics["groundtruth_frame"] = truth_frame_note(pose_calibration, sequence)
    scores = score_meshes(predictions, meshes.faces, meshes.frame_ids, surfaces)
    mine = "no_depth" if no_depth else "full"
    for key in [f"p2s_{measure}_cm" for measure in SCORED] + ["p2s_cm", "p2s_ego_visible_cm"]:
        scores[key] = scores[f"{mine}_{key}"]
    scores["ego_visible_true_area_fraction"] = (float(np.mean([s.visible_area_fraction for s in surfaces.values()]))
                                                if surfaces else 0.0)
    writer.metrics.update(scores)
    writer.units.update({
        "p2s_pred_to_true_cm": "cm, mean distance of the predicted (outer) vertices to the true (outer) surface",
        "p2s_true_to_pred_cm": "cm, area-weighted mean distance of the true (outer) surface to the predicted (outer) "
                               "surface",
        "p2s_ego_visible_pred_to_true_cm": "cm, pred->true over the predicted vertices whose closest true point "
                                           "the down-facing ego cameras see",
        "p2s_ego_visible_true_to_pred_cm": "cm, true->pred over the true surface the down-facing ego cameras see",
        "p2s_cm": "cm, = p2s_pred_to_true_cm (earlier name)",
        "p2s_ego_visible_cm": "cm, = p2s_ego_visible_pred_to_true_cm (earlier name)",
        "ego_visible_true_area_fraction": "fraction of the true outer surface's area the down cameras see"})
    from egorelight_cli.stages.ik_commands import preview_frames

    distances = {}
    for row in preview_frames(meshes.num_frames, int(preview_count)):
        fid = int(meshes.frame_ids[row])
        if fid in surfaces:
            distances[fid] = surfaces[fid].distance_cm(meshes.vertices[row])[0]
    return distances


# ---------------------------------------------------------------------------------- preview
def _colour_by_distance(distance_cm: np.ndarray, max_cm: float = 2.0) -> np.ndarray:
    """(V,3) RGB in [0,255]: blue (0) -> red (``max_cm`` and more), via OpenCV's JET map."""
    import cv2

    level = np.clip(distance_cm / max_cm, 0, 1) * 255
    bgr = cv2.applyColorMap(level.astype(np.uint8)[:, None], cv2.COLORMAP_JET)[:, 0]
    return bgr[:, ::-1].astype(np.float32)


def _side_view(character: Character, vertices: np.ndarray, distance_cm: np.ndarray | None, width: int,
               height: int) -> np.ndarray:
    """(H,W,3) uint8 side view; coloured by distance to the truth when given, else grey-shaded."""
    from egorelight_cli.render.preview import framing_camera, shade_mesh
    from egorelight_cli.render.raster import rasterize

    forward = np.array([0.0, 0.0, -1.0])
    side = np.cross(forward, [0.0, 1.0, 0.0])
    camera = framing_camera(vertices, side, width, height, "side")
    if distance_cm is None:
        return shade_mesh(character, vertices, camera)
    raster = rasterize(vertices, character.faces, camera)
    colours = _colour_by_distance(distance_cm)
    image = np.full((height, width, 3), 255.0, np.float32)
    mask = raster.mask
    corner = colours[character.faces[raster.face_id[mask]]]  # (P,3,3)
    colour = np.einsum("pkc,pk->pc", corner, raster.barycentrics[mask])
    to_cam = camera.centre_world[None] - raster.points[mask]
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    lambert = np.abs(np.sum(raster.normal[mask] * to_cam, axis=1))
    image[mask] = colour * (0.45 + 0.55 * lambert)[:, None]
    return np.clip(image, 0, 255).astype(np.uint8)


def _ego_overlay(capture: Capture, calibration, sequence: str, character: Character, vertices: np.ndarray,
                 frame_id: int, height: int) -> np.ndarray | None:
    """The down-left ego image with the mesh's visible vertices drawn over it (None if unavailable)."""
    import cv2

    from egorelight_cli.geometry.cameras import project_world
    from egorelight_cli.io.calibration import posed_ego_camera

    try:
        seq = capture.sequence(sequence)
        role = next(r for r in seq.ego_roles if r.startswith("down"))
        camera = posed_ego_camera(capture, calibration, role, sequence, frame_id)
        image = seq.read_ego_image(role, calibration.ego_frame_id(sequence, int(frame_id)))
    except (EgorelightError, StopIteration):
        return None
    from egorelight_cli.stages.animate_eval import ego_visible_vertices

    seen = ego_visible_vertices(vertices, character.faces, [camera])
    pixels, valid = project_world(camera, vertices[seen], return_valid=True)
    image = np.ascontiguousarray(image[..., :3]).copy()
    for (u, v), ok in zip(np.asarray(pixels), np.asarray(valid)):
        if ok and np.isfinite(u) and np.isfinite(v):
            cv2.circle(image, (int(round(u)), int(round(v))), 0, (40, 255, 80), -1)
    scale = height / image.shape[0]
    return cv2.resize(image, (max(int(round(image.shape[1] * scale)), 1), height), interpolation=cv2.INTER_NEAREST)


def _write_preview(writer: ArtifactWriter, character: Character, meshes: MeshSequence,
                   distances: dict[int, np.ndarray] | None, capture: Capture | None, calibration, sequence: str,
                   cfg: Config) -> None:
    import cv2

    from egorelight_cli.io.images import write_image
    from egorelight_cli.render import sheets
    from egorelight_cli.stages.ik_commands import preview_frames

    preview = cfg["preview"]
    width, height = int(preview["width"]), int(preview["height"])
    tiles = []
    for row in preview_frames(meshes.num_frames, int(preview["frames"])):
        fid = int(meshes.frame_ids[row])
        d = None if distances is None else distances.get(fid)
        tile = _side_view(character, meshes.vertices[row], d, width, height)
        label = f"frame {fid}" + ("" if d is None else f" {d.mean():.2f} cm")
        parts = [sheets.label(tile, label, colour=(0, 0, 0))]
        if capture is not None and calibration is not None:
            ego = _ego_overlay(capture, calibration, sequence, character, meshes.vertices[row], fid, height)
            if ego is not None:
                parts.insert(0, ego)
        tiles.append(np.concatenate(parts, axis=1))
    image = sheets.stack_rows(tiles, max_width=None, fill=255)
    if distances is not None:
        image = np.pad(image, ((0, 16), (0, 0), (0, 0)), constant_values=255)
        cv2.putText(image, "colour: distance to true mesh, blue 0 -> red 2 cm", (4, image.shape[0] - 5),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    write_image(writer.path(PREVIEW_PNG), image)


# ------------------------------------------------------------- handlers (egorelight_cli.declarations)
def train_command(run: StageRun, capture: Path, motion: tuple[Path, ...], pointcloud: Path | None, character: str,
                  init: Path | None, sequence: str, no_depth: bool, resume: bool, out: Path) -> Path:
    return AnimateCommands(run).train(capture, sequence, motion, pointcloud, character, init, no_depth, out, resume)


def animate_command(run: StageRun, motion: Path, pointcloud: Path | None, model: Path, character: str,
                    capture: Path | None, calibration: Path | None, sequence: str, no_depth: bool, fit_recon: bool,
                    fit_truth: bool, out: Path) -> Path:
    if fit_recon and fit_truth:
        raise EgorelightError("--fit-recon and --fit-truth exclude each other: pick the surface to fit to")
    fit = "recon" if fit_recon else "truth" if fit_truth else None
    return AnimateCommands(run).animate(motion, pointcloud, model, character, capture, sequence, calibration, no_depth,
                                        None, out, fit)
