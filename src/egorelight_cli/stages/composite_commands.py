"""The ``egorelight composite`` command: load User 1's avatar (meshes, uvmaps, relight model,
character) and User 2's environment (``envmap`` artifact) and view (calibrated front camera of the
sequence, or a virtual camera JSON), call :mod:`egorelight_cli.stages.composite`, score against the
simulator's truth (:mod:`egorelight_cli.stages.composite_eval`), write the artifact.

A ``composite`` artifact directory holds

* ``frames/<frame>.png``: (H,W,3) uint8 sRGB composites, one per User 2 frame id (a virtual
  camera: per avatar frame);
* ``composite.mp4``: the frames at ``video.fps`` when imageio-ffmpeg is installed (else the
  manifest says it was skipped);
* ``preview.png``: contact sheet (composites; with ground truth the truth composite, the
  baseline rows and the ``true_light`` oracle row under them);
* ``placement.json``: the placement (``T_user2_from_studio``, yaw, spot, floor and how it was
  chosen), the camera, the colour mapping used (the envmap's ``A``, ``gamma``, the avatar's
  mapping), the frame pairs.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from egorelight_cli import console
from egorelight_cli.artifacts import ArtifactWriter, check_sequence, open_artifact
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.io.camera_json import read_camera_json
from egorelight_cli.io.calibration import open_calibration, posed_ego_camera
from egorelight_cli.io.capture import frame_file, open_capture
from egorelight_cli.pipeline import StageRun
from egorelight_cli.stages import composite as cp

FRAMES_DIR = "frames"
PREVIEW_PNG = "preview.png"
PLACEMENT_JSON = "placement.json"
VIDEO_MP4 = "composite.mp4"


@dataclass(frozen=True)
class AvatarInputs:
    """User 1's avatar as given on the command line."""

    meshes: Path
    uvmaps: Path
    model: Path
    character: str
    sequence: str


@dataclass
class View:
    """One composite frame: User 2's frame id (None for a virtual camera), the avatar's frame id,
    the camera in User 2's frame and in the studio frame, the sRGB background (H,W,3) uint8."""

    user2_frame: int | None
    avatar_frame: int
    camera: Camera
    studio_camera: Camera
    background: np.ndarray


def _background_sequence_frames(calibration, sequence, role: str, count: int) -> list[int]:
    """The first ``count`` frames of ``sequence`` with a valid head pose and a ``role`` image."""
    poses = calibration.head_poses.get(sequence.name)
    if poses is None:
        raise EgorelightError(f"calibration has no head poses for sequence {sequence.name!r}", calibration.source)
    frames = [int(f) for f, ok in zip(poses.frame_ids, poses.valid) if ok
              and sequence.ego_image_path(role, calibration.ego_frame_id(sequence.name, int(f))).is_file()]
    if not frames:
        raise EgorelightError(f"no frame of {sequence.name} has a head pose and a {role} image", calibration.source)
    return frames[:count]


@dataclass(frozen=True)
class CompositeCommands:
    """``composite`` over one :class:`StageRun`."""

    run: StageRun

    def predict(self, capture_path: Path, calibration_path: Path, envmap_path: Path, avatar: AvatarInputs, seq: str,
                role: str | None, camera_json: Path | None, place: str, out: Path) -> Path:
        from egorelight_cli.nn.colour_inverse import camera_mapping
        from egorelight_cli.nn.colour_model import RootPolynomialColour
        from egorelight_cli.render.envmaps import load_envmap
        from egorelight_cli.stages.character_commands import character_sources, load_character
        from egorelight_cli.stages.envmap_inverse import EgoAvatarData
        from egorelight_cli.stages.geolift_commands import load_character_meshes
        from egorelight_cli.stages.relight_commands import load_relight_model

        cfg = self.run.config()
        settings = cp.CompositeSettings.from_config(cfg)
        forward_m, right_m, yaw_deg = cp.parse_place(place)
        if camera_json is not None and role is not None:
            raise EgorelightError("give --camera or --camera-json, not both")
        role = role or (None if camera_json is not None else "front_left")
        capture, capture_artifact = open_capture(capture_path, [seq, avatar.sequence])
        calibration, calibration_artifact = open_calibration(calibration_path)
        envmap_artifact = open_artifact(envmap_path, kind="envmap")
        if envmap_artifact.single_file:
            raise EgorelightError("an envmap artifact is a directory", envmap_path)
        check_sequence(envmap_artifact, seq)  # the light of the room the avatar goes into
        colour = RootPolynomialColour.from_json(envmap_artifact.root / "colour_model.json")
        envmap = load_envmap(envmap_artifact.root / "envmap.exr")
        try:
            mapping = camera_mapping(colour, envmap, settings.colour_inverse, settings.colour_iterations)
        except EgorelightError as exc:
            raise EgorelightError(exc.message, envmap_artifact.root / "envmap.exr") from None
        sequence, avatar_sequence = capture.sequence(seq), capture.sequence(avatar.sequence)
        character, character_artifact = load_character(avatar.character)
        model, net, model_artifact = load_relight_model(avatar.model)
        meshes, meshes_artifact = load_character_meshes(avatar.meshes, character)
        uvmaps = open_artifact(avatar.uvmaps, kind="uvmaps")
        for artifact in (meshes_artifact, uvmaps):
            check_sequence(artifact, avatar.sequence)
        data = EgoAvatarData(capture, avatar_sequence, meshes, uvmaps, character, int(net["uv_resolution"]),
                             int(net["attention_level"]), int(net["rays"]))
        avatar_frames = [int(f) for f in meshes.frame_ids if data.has_maps(int(f))]
        if not avatar_frames:
            raise EgorelightError("no frame of the meshes has uvmaps", avatar.uvmaps)
        front = role or "front_left"
        for r in {front}:
            if r not in capture.ego_cameras or r not in calibration.ego_cameras:
                raise EgorelightError(f"--camera: the capture or the calibration has no HMD camera {r!r} (capture has "
                                      f"{', '.join(capture.ego_cameras) or 'none'})")
        virtual = read_camera_json(camera_json) if camera_json is not None else None
        if role is not None:
            sequence.require_stream("ego")
        user2 = _background_sequence_frames(calibration, sequence, front, settings.frames if role else 1)
        inputs = [a for a in (capture_artifact, calibration_artifact, envmap_artifact, character_artifact,
                              model_artifact, meshes_artifact, uvmaps) if a is not None]
        options = {"camera_role": role or "virtual"}  # the declared options enter the key from the declaration
        sources = [camera_json] if camera_json is not None else []
        sources += character_sources(avatar.character, character_artifact)
        sources += [] if meshes_artifact else [Path(avatar.meshes)]
        if self.run.up_to_date(out, "composite", inputs, sources, options):
            return Path(out)
        eye = settings.eye_height_m if settings.eye_height_m is not None else (
            cp.eye_height(calibration, seq) if settings.floor == "head" else None)
        self.run.compute_device()

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            if writer.single_file:
                raise EgorelightError("a composite artifact is a directory (PNG frames): give --out a directory", out)
            started = time.perf_counter()
            head = calibration.head_poses[seq].pose(user2[0])
            floor_y = float(head[1, 3]) - eye if settings.floor == "head" else 0.0
            hips = _hips(character, meshes, avatar_frames[0])
            placement = cp.place_avatar(data.vertices(avatar_frames[0]), *hips,
                                        calibration.T_world_from_cam(front, seq, user2[0]), head[:3, 3],
                                        forward_m, right_m, yaw_deg, floor_y, settings.floor)
            views = _views(capture, calibration, sequence, front, virtual, user2, avatar_frames, placement,
                           settings, envmap, colour)
            lightstage = data.lightstage
            light = torch.from_numpy(lightstage.envmap_to_intensities(envmap, -placement.yaw_deg))
            composites, residuals, masks = _render_row(model, data, views, light, mapping)
            if not any(m.any() for m in masks):
                raise EgorelightError(f"the avatar is in view in none of the {len(views)} frames: --place "
                                      f"{forward_m:g},{right_m:g},{yaw_deg:g} puts it out of the camera's sight (at "
                                      "or behind the viewer?)")
            writer.timing["composite_s"] = round(time.perf_counter() - started, 3)
            writer.timing["per_frame_s"] = round(writer.timing["composite_s"] / len(views), 3)
            for view, image in zip(views, composites):
                _write_png(writer, view, image)
            writer.extra["video"] = _write_video(writer, composites, settings.fps)
            sheet = [("composite (User 1 relit by User 2's light)", composites)]
            from egorelight_cli.stages import composite_eval as ce

            evaluation = ce.evaluate(capture, calibration, seq, front, avatar.sequence, placement, views, composites, masks,
                                     lambda light_row, mapping_row: _render_row(model, data, views, light_row,
                                                                                mapping_row)[0],
                                     envmap, colour, mapping, lightstage, light, settings.colour_iterations)
            if evaluation is not None:
                writer.metrics.update(evaluation.metrics)
                sheet += evaluation.sheet_rows
                writer.timing["eval_s"] = round(evaluation.seconds, 3)
            from egorelight_cli.io.images import write_image
            from egorelight_cli.render.sheets import labelled_rows

            shown = np.unique(np.round(np.linspace(0, len(views) - 1, min(settings.sheet_columns, len(views))))
                              .astype(int))
            write_image(writer.path(PREVIEW_PNG), labelled_rows([(label, [images[i] for i in shown])
                                                                 for label, images in sheet],
                                                                settings.sheet_tile_width))
            writer.save_json(PLACEMENT_JSON, {
                **placement.to_json(), "place": {"forward_m": forward_m, "right_m": right_m, "yaw_deg": yaw_deg},
                "eye_height_m": eye, "camera": views[0].camera.to_dict() if virtual is not None else front,
                "frames": [{"user2": v.user2_frame, "avatar": v.avatar_frame} for v in views],
                "colour_mapping": {**colour.to_json(), "avatar_to_camera": mapping.to_json(),
                                   "max_residual_p99": max(residuals)},
                "frame": f"the calibrated head poses of sequence {seq} (User 2)"})
            writer.metrics.update({
                "frames": len(views), "avatar_frames": sorted({v.avatar_frame for v in views}),
                "user2_frames": [v.user2_frame for v in views if v.user2_frame is not None],
                "avatar_coverage": [float(m.mean()) for m in masks], "frames_with_avatar": int(sum(m.any() for m in masks)),
                "colour_inverse_residual_p99": max(residuals), "placement_yaw_deg": placement.yaw_deg,
                "floor_y_m": placement.floor_y, "floor": settings.floor, "width": views[0].camera.width,
                "height": views[0].camera.height})
            writer.extra["floor"] = (f"head: floor = User 2's first head height minus the eye height {eye:.3f} m "
                                     "(auto: median HMD height of the calibration's studio sequences)"
                                     if settings.floor == "head" else "world: y = 0 of the calibration's frame")
            writer.extra["colour"] = (f"avatar HDR (E_h units) -> camera-linear by the {settings.colour_inverse} "
                                      "inverse of the envmap colour model (colour.inverse) -> alpha-composited in "
                                      "linear light over the sRGB-decoded background -> sRGB")
            writer.units.update({"psnr": "dB on 8-bit sRGB composites in the avatar mask (render or truth alpha "
                                         "> 0.5), pooled over the pixels of the scored frames", "ssim": "x100",
                                "floor_y_m": "m", "placement_yaw_deg": "deg",
                                "colour_inverse_residual_p99": "|f(E_l) - E_h| / |E_h| of the exact inverse; 0 for a "
                                                               "linear mapping (colour.inverse=diagonal)"})

        return self.run.produce(out, "composite", write, inputs=inputs, source_files=sources, options=options)


def _frame_key(view: View) -> int:
    return view.user2_frame if view.user2_frame is not None else view.avatar_frame


def _write_png(writer: ArtifactWriter, view: View, image: np.ndarray) -> None:
    from egorelight_cli.io.images import write_image

    write_image(writer.path(f"{FRAMES_DIR}/{frame_file(_frame_key(view), '.png')}"), image)


def _write_video(writer: ArtifactWriter, frames: list[np.ndarray], fps: float) -> str:
    """Write ``composite.mp4`` through imageio-ffmpeg; a note when it is not installed."""
    import importlib.util

    if importlib.util.find_spec("imageio") is None or importlib.util.find_spec("imageio_ffmpeg") is None:
        return "skipped: imageio-ffmpeg is not installed (pip install imageio-ffmpeg); PNG frames only"
    import imageio.v2 as imageio

    even = [f[: f.shape[0] // 2 * 2, : f.shape[1] // 2 * 2] for f in frames]  # yuv420p needs even sizes
    imageio.mimwrite(writer.path(VIDEO_MP4), even, fps=fps, macro_block_size=1)
    return f"{VIDEO_MP4} ({len(frames)} frames at {fps:g} fps)"


def _hips(character, meshes, frame_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(left hip, right hip) (3,) of the avatar's frame from its skeleton (FK of the meshes' theta)."""
    from egorelight_cli.stages.ik_eval import fitted_keypoints

    names = list(character.keypoint_names)
    if "LeftUpLeg" not in names or "RightUpLeg" not in names:
        raise EgorelightError("the character's keypoints have no LeftUpLeg/RightUpLeg (hips) to face the avatar by")
    theta = np.asarray(meshes.theta[meshes.index_of(frame_id)], np.float64)[None]
    keypoints = fitted_keypoints(character, theta)[0]
    return keypoints[names.index("LeftUpLeg")], keypoints[names.index("RightUpLeg")]


def _views(capture, calibration, sequence, role: str, virtual: Camera | None, user2: list[int],
           avatar_frames: list[int], placement: cp.Placement, settings: cp.CompositeSettings, envmap, colour) -> list[View]:
    """The composite frames: User 2's frames paired with the avatar's frames in order (cycled), or
    the virtual camera over ``settings.frames`` avatar frames with the envmap's view as background."""
    import cv2

    views = []
    if virtual is not None:
        from egorelight_cli.io.images import linear_to_srgb
        from egorelight_cli.nn.colour_inverse import invert_colour
        from egorelight_cli.render.camera_response import render_envmap_view

        camera = cp.scaled_camera(virtual, settings.scale)
        E_l, _ = invert_colour(colour, envmap, settings.colour_iterations)
        background = np.round(linear_to_srgb(np.clip(render_envmap_view(E_l, camera), 0, 1)) * 255).astype(np.uint8)
        for k in range(settings.frames):
            f = avatar_frames[k % len(avatar_frames)]
            views.append(View(None, f, camera, placement.camera_in_studio(camera), background))
        return views
    for k, f in enumerate(user2):
        camera = cp.scaled_camera(posed_ego_camera(capture, calibration, role, sequence.name, f), settings.scale)
        image = sequence.read_ego_image(role, calibration.ego_frame_id(sequence.name, f))[..., :3]
        if image.dtype != np.uint8:
            raise EgorelightError(f"{role} images must be 8-bit sRGB, got {image.dtype}")
        if image.shape[:2] != (camera.height, camera.width):
            image = cv2.resize(np.ascontiguousarray(image), (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        views.append(View(f, avatar_frames[k % len(avatar_frames)], camera, placement.camera_in_studio(camera), image))
    return views


def _render_row(model, data, views: list[View], light: torch.Tensor, mapping):
    """(composites (H,W,3) uint8, p99 mapping residuals, avatar masks (H,W) alpha > 0.5), one per
    view, of the avatar under ``light`` (L,3) mapped into the camera by ``mapping``
    (:class:`~egorelight_cli.nn.colour_inverse.CameraMapping`; None: identity)."""
    out, residuals, masks = [], [], []
    for view in console.progress(views, total=len(views), desc="composite"):
        render, alpha = cp.render_avatar(model, data, view.avatar_frame, view.studio_camera, light)
        avatar, residual = cp.avatar_to_camera(render, alpha, mapping)
        out.append(cp.composite_image(view.background, avatar, alpha))
        residuals.append(residual)
        masks.append(alpha > 0.5)
    return out, residuals, masks


def composite_command(run: StageRun, meshes: Path, uvmaps: Path, model: Path, character: str, capture: Path,
                      calibration: Path, envmap: Path, camera_json: Path | None, avatar_sequence: str, sequence: str,
                      camera: str | None, place: str, out: Path) -> Path:
    """``egorelight composite`` (declared in :mod:`egorelight_cli.declarations`)."""
    avatar = AvatarInputs(meshes, uvmaps, model, character, avatar_sequence)
    return CompositeCommands(run).predict(capture, calibration, envmap, avatar, sequence, camera, camera_json, place,
                                          out)
