"""Writing a simulated capture: the on-disk data contract of DESIGN.md Sec. 5.

A capture (artifact kind ``egorelight/capture``) is laid out as::

    capture/
      manifest.json                             every file below with its sha256 digest
      rig/studio_cameras.json                   {"cameras": [Camera.to_dict() + {"role": "studio"|"tracking"}]}
      rig/lights.json                           LightStage.to_json(): positions (L,3) m, rgb_gain (L,3), centre, radius
      rig/hmd.json                              {"frame": ..., "cameras": [{name, role, model, K, dist, width, height}],
                                                 "markers": {"dictionary": "DICT_4X4_50", "marker_length_m",
                                                             "markers": [{"id", "corners_hmd": (4,3)}]}}
      rig/board.json                            ChArUco board: squares_x/y, square_length_m, marker_length_m,
                                                dictionary, legacy_pattern
      scan/scan.ply                             a rest-pose 3D scan of the clothed subject (no HMD; own
                                                tessellation, noise, holes): ``character fit-scan`` input
      envmaps/<name>.exr                        HDR maps (RGB float32 equirect) named by the light patterns
      sequences/<seq>/sequence.json             see below
      sequences/<seq>/studio/<cam>/<frame>.exr  linear HDR radiance (R,G,B; half float by default)
      sequences/<seq>/masks/<cam>/<frame>.png   subject (body + worn HMD) mask, 0/255
      sequences/<seq>/normals/<cam>/<frame>.exr estimated normals, camera frame (OpenCV), layer ``normal``
                                                (normal.X/Y/Z), 0 on background; content frames only
      sequences/<seq>/recon/<frame>.ply         multi-view reconstruction (outer surface, own topology)
      sequences/<seq>/mocap.npz                 keypoints payload (xyz, confidence, frame_ids = studio ids, names)
      sequences/<seq>/ego/<role>/<frame>.png    8-bit sRGB HMD images, frame = ego frame id
      sequences/<seq>/head_pose.npz             wild only: the headset tracker's T_world_from_hmd (T,4,4)
                                                in its own world frame, sampled ``wild.tracker.samples_per_frame``
                                                times per ego frame: timestamps_s, frame_ids (the ego id of
                                                samples taken with an ego frame, -1 between them)
      previews/<seq>.png                        contact sheets
      groundtruth/...                           see :mod:`egorelight_cli.synth.groundtruth`

Frame files are named by zero-padded frame id (``000012.exr``). ``sequence.json``::

    {"name", "purpose": handeye|ego_train|relight_train|test|wild, "fps",
     "frame_ids": studio frame ids ([] without studio), "ego_frame_ids": ego frame ids ([] without ego),
     "content_frame_ids": studio frames after the standby/sync prefix,
     "lights": per studio frame {"pattern": flat|envmap|olat|group|flash|dark, "envmap": name|null,
                                 "yaw_deg", "olat_index": int|null, "scale"
                                 (+ "light_ids": [int] for group)},
     "streams": {"studio": [camera names], "masks", "normals", "recon", "mocap": bool,
                 "ego": [roles], "head_pose": bool},
     (a headset-only sequence such as ``ego_bulk``, purpose ego_train, lists only the head-tracking
     studio cameras, the down-facing ego roles, and no masks, normals or recon)
     "held_out_cameras": [names] (test), "hmd_worn": bool, "board": bool,
     "sync": {"code": [1 flash / 0 dark], "standby_frames", "code_start_frame"}}

A light entry's lighting condition (L,3) is ``scale * lights.flat(1)`` for ``flat``/``flash``, zero for
``dark``, ``scale * LightStage.envmap_to_intensities(envmaps/<envmap>.exr, yaw_deg)`` for ``envmap``
(the paper's S(E)), ``lights.olat(olat_index, scale)`` for ``olat`` and ``scale * lights.flat(1)`` on the
lights ``light_ids`` only for ``group`` (the last frames of ``test`` are such an OLAT/group tail). Studio radiance is in the
lights' units times ``studio.exposure`` (1: a flat-lit white Lambertian surface facing up reads ~1).

Ego frame ``e`` of a sequence was exposed together with studio frame ``e + ego_offset``; the offset
is ground truth only (recover it from the flash code). The ego cameras' extrinsics
``T_cam_from_hmd`` and colour responses, head poses and board pose are ground truth only. The studio
cameras and HMD intrinsics in ``rig/`` carry a seeded calibration error; the true ones are ground truth
(:mod:`egorelight_cli.synth.calibration_error`).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from egorelight_cli import console
from egorelight_cli.artifacts import ArtifactWriter
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.geometry.markers import detect_board, detect_hmd_markers
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.geometry.skeleton import keypoint_positions
from egorelight_cli.io.exr import write_exr_layers
from egorelight_cli.io.images import tonemap, write_image
from egorelight_cli.io.keypoints import write_keypoints_npz
from egorelight_cli.io.meshes import write_ply
from egorelight_cli.io.npz import write_npz
from egorelight_cli.render.camera_response import CameraResponse, random_ego_response
from egorelight_cli.render.envmaps import detailed_surroundings, envmap_set, write_envmap
from egorelight_cli.render.lighting import light_intensities
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import rasterize_uv
from egorelight_cli.render.sheets import contact_sheet
from egorelight_cli.structures.character import Character
from egorelight_cli.synth import derived, groundtruth
from egorelight_cli.synth.appearance import make_appearance
from egorelight_cli.synth.calibration_error import write_calibrations
from egorelight_cli.synth.detail import detail_normal_map
from egorelight_cli.synth.hmd import (
    DOWN_ROLES,
    EGO_ROLES,
    FRONT_ROLES,
    Hmd,
    make_hmd,
)
from egorelight_cli.synth.scan import scan_subject
from egorelight_cli.synth.rig import (
    TRACKING_ROLE,
    board_json,
    board_mesh,
    board_pose,
    held_out_cameras,
    make_lightstage,
    studio_cameras,
)
from egorelight_cli.synth.scene import (
    BOARD,
    BODY,
    HMD,
    joint_transforms,
    place,
    scene_layout,
    subject_mesh,
)
from egorelight_cli.synth.subject import Subject, make_subject
from egorelight_cli.synth.sensors import (
    DomeBackdrop,
    FrameRenderer,
    Timer,
)
from egorelight_cli.synth.sequences import SEQUENCES, SequencePlan, plan_sequence
from egorelight_cli.synth.tracker import simulate_tracker
from egorelight_cli.synth.uv_truth import UV_TRUTH, UVTruth

SEQ = "sequences"
#: Height in pixels of a tile in a sequence's preview sheet.
PREVIEW_TILE_HEIGHT = 160


def frame_name(frame_id: int, suffix: str) -> str:
    return f"{int(frame_id):06d}{suffix}"


@dataclass
class Rig:
    """Everything fixed for a whole capture."""

    subject: Subject
    cfg: Config
    appearance: object
    hmd: Hmd
    cameras: list[tuple[Camera, str]]
    held_out: list[str]
    lightstage: LightStage
    envmaps: dict[str, np.ndarray]
    train_envmaps: list[str]
    test_envmaps: list[str]
    wild_envmaps: list[str]
    wild_surroundings: dict[str, np.ndarray]
    responses: dict[str, CameraResponse]
    board_pose: np.ndarray
    timer: Timer = field(default_factory=Timer)
    _uv_truth: UVTruth | None = None

    def uv_truth(self) -> UVTruth:
        """The UV ground-truth builder of the subject (made on first use)."""
        if self._uv_truth is None:
            self._uv_truth = UVTruth(self.subject, self.appearance, self.lightstage, float(self.cfg.lights.flat_intensity),
                                     float(self.cfg.studio.exposure), int(self.cfg.groundtruth.uv_resolution))
        return self._uv_truth


@dataclass
class SequenceStats:
    """Metric accumulators of one sequence."""

    aruco_images: int = 0
    aruco_detected: int = 0
    aruco_markers: int = 0
    aruco_frames: int = 0
    aruco_frames_tracked: int = 0
    board_images: int = 0
    board_detected: int = 0
    ego_body_fraction: list = field(default_factory=list)
    ego_mean_level: list = field(default_factory=list)
    ego_clipped: list = field(default_factory=list)

    def metrics(self) -> dict:
        out: dict = {}
        if self.aruco_images:
            out["aruco_detection_rate"] = self.aruco_detected / self.aruco_images
            out["aruco_markers_per_image"] = self.aruco_markers / self.aruco_images
            out["aruco_frames_tracked_rate"] = self.aruco_frames_tracked / max(self.aruco_frames, 1)
        if self.board_images:
            out["board_detection_rate"] = self.board_detected / self.board_images
        if self.ego_body_fraction:
            out["ego_body_pixel_fraction"] = float(np.mean(self.ego_body_fraction))
        if self.ego_mean_level:
            out["ego_mean_level"] = float(np.mean(self.ego_mean_level))
            out["ego_clipped_fraction"] = float(np.mean(self.ego_clipped))
        return out


# ------------------------------------------------------------------------------------ the rig
def build_rig(cfg: Config, character: Character, user_envmaps: dict[str, np.ndarray]) -> Rig:
    seed = int(cfg.seed)
    console.info("synth: building the subject, rig and environment maps")
    subject = make_subject(character, cfg, seed)
    body = subject.body
    raster = rasterize_uv(body.face_uvs, int(cfg.appearance.texture_resolution))
    appearance = make_appearance(body, int(cfg.appearance.texture_resolution), seed, uv=raster)
    appearance = replace(appearance, normal_map=detail_normal_map(raster, body.vertices, body.faces, body.face_uvs,
                                                                  appearance.material, seed))
    hmd = make_hmd(body, cfg.hmd, seed)
    cameras = studio_cameras(cfg.studio, seed)
    held_out = held_out_cameras(cameras, int(cfg.studio.held_out))
    lightstage = make_lightstage(cfg.lights, seed)
    e = cfg.envmaps
    train = envmap_set("train", int(e.train_count), seed, int(e.height))
    test = envmap_set("test", int(e.test_count), seed, int(e.height))
    wild = envmap_set("wild", 1, seed, int(e.height))
    test.update(user_envmaps)
    envmaps = {**train, **test, **wild}
    surroundings = cfg.wild.surroundings
    wild_views = {name: detailed_surroundings(env, int(surroundings.height), seed + i, float(surroundings.detail))
                  for i, (name, env) in enumerate(wild.items())}
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xE60]))
    h = cfg.hmd
    responses = {role: random_ego_response(rng, exposure=float(h.ego_exposure if role in DOWN_ROLES else h.front_exposure),
                                           exposure_stops=float(h.exposure_stops))
                 for role in EGO_ROLES}
    rest_hmd = hmd.world_from_hmd(joint_transforms(body, body.rest_theta[None]))[0]
    head, forward = rest_hmd[:3, 3], -rest_hmd[:3, 2]
    return Rig(subject=subject, cfg=cfg, appearance=appearance, hmd=hmd, cameras=cameras,
               held_out=held_out, lightstage=lightstage, envmaps=envmaps, train_envmaps=list(train),
               test_envmaps=list(user_envmaps) + [n for n in test if n not in user_envmaps],
               wild_envmaps=list(wild), wild_surroundings=wild_views, responses=responses,
               board_pose=board_pose(cfg.board, head, forward, seed))


def write_rig(writer: ArtifactWriter, rig: Rig) -> None:
    writer.metrics.update(write_calibrations(writer, rig.cameras, rig.hmd, rig.cfg.calibration_error, int(rig.cfg.seed)))
    writer.save_json("rig/lights.json", rig.lightstage.to_json())
    writer.save_json("rig/board.json", board_json(rig.cfg.board))
    for name in rig.train_envmaps + rig.test_envmaps:
        write_envmap(writer.path(f"envmaps/{name}.exr"), rig.envmaps[name])
    for name in rig.wild_envmaps:
        write_envmap(writer.path(f"{groundtruth.GT}/envmaps/{name}.exr"), rig.envmaps[name])


def write_global_truth(writer: ArtifactWriter, rig: Rig, offsets: dict[str, int]) -> None:
    root = writer.workdir
    hmd = rig.hmd
    groundtruth.write_json(root / groundtruth.GT / "hand_eye.json", {
        role: {"T_cam_from_hmd": cam.T_cam_from_hmd.tolist(), "T_cam_from_hmd_nominal": cam.T_cam_from_hmd_nominal.tolist()}
        for role, cam in hmd.cameras.items()})
    groundtruth.write_json(root / groundtruth.GT / "streams.json", {
        seq: {"ego_offset": k, "meaning": "ego frame e was exposed with studio frame e + ego_offset"}
        for seq, k in offsets.items()})
    groundtruth.write_json(root / groundtruth.GT / "ego_response.json",
                           {role: r.to_dict() for role, r in rig.responses.items()})
    groundtruth.write_json(root / groundtruth.GT / "hmd_mount.json", {
        "head_joint": rig.subject.body.skeleton.joint_names[hmd.head_joint], "T_joint_from_hmd": hmd.T_joint_from_hmd.tolist()})
    groundtruth.write_json(root / groundtruth.GT / "board_pose.json", {"T_world_from_board": rig.board_pose.tolist()})
    groundtruth.write_appearance(root, rig.appearance)
    groundtruth.write_json(root / groundtruth.GT / "subject.json", rig.subject.description)
    write_ply(root / groundtruth.GT / "subject_rest.ply", rig.subject.rest_vertices().astype(np.float32),
              rig.subject.faces)


# ---------------------------------------------------------------------------------- sequences
def _studio_cameras_of(rig: Rig, plan: SequencePlan) -> list[tuple[Camera, str]]:
    if not plan.has_studio:
        return []
    out = []
    for cam, role in rig.cameras:
        if role == TRACKING_ROLE and not plan.hmd_on:
            continue
        if role != TRACKING_ROLE and plan.headset_only:
            continue
        if cam.name in rig.held_out and plan.name != "test":
            continue
        out.append((cam, role))
    return out


def _streams_of(cfg, plan: SequencePlan, cams: list[tuple[Camera, str]]) -> dict:
    """``sequence.json``'s ``streams``: what records in ``plan`` (headset-only sequences: the
    head-tracking cameras without masks or normals, and the down-facing ego cameras)."""
    studio_images = plan.has_studio and not plan.headset_only
    return {"studio": [cam.name for cam, _ in cams], "masks": studio_images,
            "normals": studio_images and bool(cfg.derived.normals),
            "recon": plan.has_studio and plan.name in list(cfg.derived.recon_sequences),
            "mocap": plan.has_studio,
            "ego": (list(DOWN_ROLES) if plan.headset_only else list(EGO_ROLES)) if plan.has_ego else [],
            "head_pose": not plan.has_studio}


def virtual_dome(cfg) -> LightStage:
    """Distant lights standing in for the in-the-wild environment (its S(E))."""
    return LightStage.dome(num_lights=int(cfg.wild.render_lights), radius=float(cfg.wild.dome_radius_m),
                           min_elevation_deg=-89.0, centre=(0.0, 1.0, 0.0))


def wild_place(cfg, head: np.ndarray) -> dict:
    """Where the in-the-wild surroundings are: ``{"radius_m", "centre", "floor_y"}``, a sphere
    around the wearer's head at the first frame (``head``: (N,4,4) ``T_world_from_hmd``) above
    the ground the wearer stands on (y = 0)."""
    return {"radius_m": float(cfg.wild.surroundings.radius_m), "centre": head[0, :3, 3].tolist(), "floor_y": 0.0}


def simulate_sequence(writer: ArtifactWriter, rig: Rig, plan: SequencePlan) -> dict:
    """Render and write one sequence; returns its metrics."""
    cfg, subject, hmd = rig.cfg, rig.subject, rig.hmd
    body = subject.body
    seq = plan.name
    base = f"{SEQ}/{seq}"
    seed = int(np.random.SeedSequence([int(cfg.seed), SEQUENCES.index(seq) + 11]).generate_state(1)[0])
    rng = np.random.default_rng(seed)
    console.info(f"synth: {seq}: {plan.num_frames} frames")
    beta_pose, beta_random = subject.clothing.deform(plan.theta, plan.fps, seed)
    G = joint_transforms(body, plan.theta)
    bodies = subject.pose(plan.theta, beta_pose + beta_random, G)
    keypoints = keypoint_positions(torch.as_tensor(plan.theta), body, torch.as_tensor(G)).numpy()
    head = hmd.world_from_hmd(G) if plan.hmd_on else None
    with_board = seq == "handeye"
    board = board_mesh(cfg.board) if with_board else None
    layout = scene_layout(subject_mesh(subject, rig.appearance), hmd if plan.hmd_on else None, board)
    lightstage = rig.lightstage if plan.has_studio else virtual_dome(cfg)
    renderer = FrameRenderer(layout, lightstage, int(cfg.render.exact_lights), rig.timer)
    backdrop = DomeBackdrop(rig.lightstage) if plan.has_studio else None
    cams = _studio_cameras_of(rig, plan)
    ego_ids = plan.ego_frame_ids()
    content = plan.content_mask()
    stats = SequenceStats()
    d = cfg.derived
    streams = _streams_of(cfg, plan, cams)
    viewpoints = np.array([cam.centre_world for cam, _ in cams]) if cams else np.zeros((0, 3))
    directions = derived.sphere_directions(int(d.recon_directions))
    content_ids = np.flatnonzero(content)
    preview_at = set(content_ids[np.linspace(0, len(content_ids) - 1, min(int(cfg.previews.frames), len(content_ids)))
                                 .astype(int)].tolist()) if len(content_ids) else set()
    preview_rows = []
    board_T = rig.board_pose
    for i in range(plan.num_frames):
        entry = plan.lights[i]
        intensities = light_intensities(lightstage, entry, rig.envmaps)
        parts = {BODY: bodies[i]}
        if plan.hmd_on:
            parts[HMD] = place(hmd.mesh, head[i])
        if with_board:
            parts[BOARD] = place(board, board_T)
        vertices = layout.vertices(parts)
        frame = renderer.prepare(vertices, intensities)
        tiles = []
        fid = int(plan.frame_ids[i])
        tracked = False
        for cam, role in cams:
            result = frame.render(cam, role)
            hdr = result.radiance * float(cfg.studio.exposure)
            write_exr_layers(writer.path(f"{base}/studio/{cam.name}/{frame_name(fid, '.exr')}"), {"": hdr},
                             half=bool(cfg.studio.half_float))
            subject = layout.subject_mask(result.face_id)
            if streams["masks"]:
                write_image(writer.path(f"{base}/masks/{cam.name}/{frame_name(fid, '.png')}"),
                            derived.mask_image(subject))
            if streams["normals"] and content[i]:
                n = derived.normal_estimate(result.normal, subject, cam, rng, d.normal_noise_smooth, d.normal_noise_pixel)
                write_exr_layers(writer.path(f"{base}/normals/{cam.name}/{frame_name(fid, '.exr')}"), {"normal": n},
                                 half=True)
            if plan.hmd_on and content[i] and role == TRACKING_ROLE:
                ids = detect_hmd_markers(tonemap(hdr, result.mask))
                stats.aruco_images += 1
                stats.aruco_detected += int(len(ids) > 0)
                stats.aruco_markers += len(ids)
                tracked |= len(ids) > 0
            if i in preview_at and (role == TRACKING_ROLE or len(tiles) < 4):
                tiles.append((cam.name, tonemap(hdr, result.mask)))
        if plan.hmd_on and content[i] and any(r == TRACKING_ROLE for _, r in cams):
            stats.aruco_frames += 1
            stats.aruco_frames_tracked += int(tracked)
        if plan.has_ego and ego_ids[i] >= 0:
            if plan.has_studio:
                surroundings, yaw, place_at = backdrop.envmap(intensities), 0.0, {}
            else:  # a detailed place around the scan's start, lit (low-frequency) like its map
                surroundings, yaw = rig.wild_surroundings[plan.wild_envmap], plan.wild_yaw_deg
                place_at = wild_place(cfg, head)
            for role in streams["ego"]:
                camera = hmd.cameras[role].camera(head[i])
                image, result = frame.render_ego(camera, rig.responses[role], surroundings, yaw, rng, **place_at)
                write_image(writer.path(f"{base}/ego/{role}/{frame_name(ego_ids[i], '.png')}"), image)
                if role in DOWN_ROLES and content[i]:
                    circle = np.any(result.radiance > 0, axis=-1) | result.mask
                    stats.ego_body_fraction.append(float(layout.part_mask(result.face_id, BODY)[circle].mean()))
                    stats.ego_mean_level.append(float(image.mean() / 255.0))
                    stats.ego_clipped.append(float((image.max(axis=-1) >= 255)[circle].mean()))
                if with_board and role in FRONT_ROLES and content[i]:
                    stats.board_images += 1
                    stats.board_detected += int(detect_board(image, cfg.board) >= 4)
                if i in preview_at:
                    tiles.append((f"ego {role}", image))
        if streams["recon"] and content[i]:
            n_subject = layout.subject_vertex_count()
            subject_faces = layout.subject_faces()
            sv = vertices[:n_subject]
            keep = derived.outer_faces(sv, subject_faces, RayCaster(sv, subject_faces), viewpoints, directions)
            v, f = derived.reconstruct(sv, subject_faces, keep, rng, d)
            write_ply(writer.path(f"{base}/recon/{frame_name(fid, '.ply')}"), v.astype(np.float32), f)
        if tiles:
            preview_rows.append(tiles)
    _write_sequence_files(writer, rig, plan, keypoints, bodies, beta_pose, beta_random, head, cams, rng)
    if plan.has_studio and seq in list(cfg.groundtruth.uv_sequences):
        started = time.perf_counter()
        scored = np.flatnonzero(content)[::max(int(cfg.groundtruth.uv_frame_stride), 1)]
        rig.uv_truth().write(writer.workdir / groundtruth.GT / seq / UV_TRUTH, bodies[scored], plan.frame_ids[scored])
        rig.timer.add("uv_truth", time.perf_counter() - started)
    _write_preview(writer, rig, plan, preview_rows)
    return stats.metrics()


def _write_sequence_files(writer, rig: Rig, plan: SequencePlan, keypoints, bodies, beta_pose, beta_random, head,
                          cams, rng) -> None:
    cfg, seq = rig.cfg, plan.name
    base = f"{SEQ}/{seq}"
    ego_ids = plan.ego_frame_ids()
    content = plan.content_mask()
    ids = plan.frame_ids
    if plan.has_studio:
        mocap = derived.mocap_keypoints(keypoints, ids, plan.fps, rng, cfg.derived.mocap)
        write_keypoints_npz(writer.path(f"{base}/mocap.npz"), mocap, source="synth markerless mocap")
    if not plan.has_studio:  # in the wild: the headset's own tracker, k samples per ego frame
        k = len(plan.tracker_theta) // plan.num_frames
        head_fine = rig.hmd.world_from_hmd(joint_transforms(rig.subject.body, plan.tracker_theta))
        tracked, truth = simulate_tracker(head_fine, k * plan.fps, cfg.wild.tracker, rng)
        sample_ids = np.full(len(tracked), -1, dtype=np.int64)
        sample_ids[::k] = ego_ids
        write_npz(writer.path(f"{base}/head_pose.npz"), {
            "T_world_from_hmd": tracked, "frame_ids": sample_ids, "timestamps_s": np.arange(len(tracked)) / (k * plan.fps)},
            {"kind": "egorelight/head_pose", "version": 1, "units": {"T_world_from_hmd": "m", "timestamps_s": "s"},
             "frame_ids": "ego frame id of the samples taken with an ego frame, -1 between them",
             "fps": plan.fps, "rate_hz": k * plan.fps,
             "source": "HMD built-in tracker (own world frame, latency, drift)"})
        groundtruth.write_json(writer.path(f"{groundtruth.GT}/{seq}/tracker.json"), truth)
        groundtruth.write_json(writer.path(f"{groundtruth.GT}/{seq}/surroundings.json"), {
            "envmap": plan.wild_envmap, "yaw_deg": plan.wild_yaw_deg, **wild_place(cfg, head),
            "detail_height": int(cfg.wild.surroundings.height), "detail_strength": float(cfg.wild.surroundings.detail)})
    gt_ids = ids if plan.has_studio else ego_ids
    groundtruth.write_sequence_truth(writer.workdir, seq, rig.subject, gt_ids, ego_ids, plan.fps, plan.theta,
                                     keypoints, bodies, beta_pose, beta_random, head)
    lights = [{k: v for k, v in entry.items() if k != "content"} for entry in plan.lights]
    has_ego = plan.has_ego
    writer.save_json(f"{base}/sequence.json", {
        "name": seq, "purpose": plan.purpose, "fps": plan.fps,
        "frame_ids": ids.tolist() if plan.has_studio else [],
        "ego_frame_ids": [int(e) for e in ego_ids if e >= 0] if has_ego else [],
        "content_frame_ids": ids[content].tolist() if plan.has_studio else [],
        "lights": lights if plan.has_studio else [],
        "streams": _streams_of(cfg, plan, cams),
        "held_out_cameras": plan.held_out, "hmd_worn": plan.hmd_on, "board": seq == "handeye", "sync": plan.sync,
    })


def _write_preview(writer, rig: Rig, plan: SequencePlan, rows: list) -> None:
    names = sorted({e["envmap"] for e in plan.lights if e.get("envmap")})
    env_row = [(name, tonemap(rig.envmaps[name])) for name in names[:6]]
    image = contact_sheet(rows + [env_row], title=f"{plan.name}: {plan.num_frames} frames at {plan.fps:g} fps",
                          tile_height=PREVIEW_TILE_HEIGHT)
    write_image(writer.path(f"previews/{plan.name}.png"), image)


def simulate_sequences(writer: ArtifactWriter, rig: Rig, plans: list[SequencePlan], workers: int) -> dict:
    """Simulate every plan (sequence name -> metrics, in the order of ``plans``); ``workers`` > 1
    runs that many sequences at a time in worker processes (each sequence has its own seeded
    random state, so the capture does not depend on ``workers``), longest first. Their render
    timings are added to ``rig.timer``."""
    if workers <= 1:
        return {plan.name: simulate_sequence(writer, rig, plan) for plan in plans}
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    threads = max(1, torch.get_num_threads() // workers)
    order = sorted(plans, key=lambda plan: -plan.num_frames)
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_init_worker,
                               initargs=(threads, console.verbosity()))
    try:  # a worker that dies (out of memory) fails the run with BrokenProcessPool rather than hanging it
        futures = {plan.name: pool.submit(_simulate_in_worker, writer, rig, plan) for plan in order}
        results = {name: future.result() for name, future in futures.items()}
    except BaseException:  # a failure, Ctrl-C or SIGTERM: the workers stop now, not after their sequences
        _terminate_workers(pool)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    for _, timer in results.values():
        rig.timer.merge(timer)
    return {plan.name: results[plan.name][0] for plan in plans}


def _terminate_workers(pool) -> None:
    """Stop a ProcessPoolExecutor's workers at once (``shutdown`` waits for their running tasks);
    Python 3.14's ``terminate_workers`` does this, 3.11 keeps them in ``_processes``."""
    if hasattr(pool, "terminate_workers"):
        pool.terminate_workers()
        return
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        process.terminate()


def _init_worker(threads: int, verbosity: int) -> None:
    """A worker: its threads and verbosity; Ctrl-C is the parent's to handle (it terminates the
    pool), and on Linux the worker dies with the parent, whatever kills it."""
    import signal

    from egorelight_cli.runtime import apply_threads

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        import ctypes

        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    apply_threads(threads)
    console.set_verbosity(verbosity)


def _simulate_in_worker(writer: ArtifactWriter, rig: Rig, plan: SequencePlan) -> tuple[dict, Timer]:
    rig = replace(rig, timer=Timer())
    return simulate_sequence(writer, rig, plan), rig.timer


# ------------------------------------------------------------------------------------ top level
def write_capture(writer: ArtifactWriter, cfg: Config, character: Character,
                  user_envmaps: dict[str, np.ndarray] | None = None, motion_theta: np.ndarray | None = None) -> None:
    """Simulate and write a whole capture into ``writer`` (kind ``capture``)."""
    started = time.perf_counter()
    rig = build_rig(cfg, character, user_envmaps or {})
    write_rig(writer, rig)
    scan_vertices, scan_faces = scan_subject(rig.subject, cfg.scan, int(cfg.seed))
    write_ply(writer.path("scan/scan.ply"), scan_vertices.astype(np.float32), scan_faces)
    offsets: dict[str, int] = {}
    plans: list[SequencePlan] = []
    for seq in cfg.sequences_enabled:
        if seq not in SEQUENCES:
            raise EgorelightError(f"unknown sequence {seq!r} in sequences_enabled; known: {', '.join(SEQUENCES)}")
        plan = plan_sequence(seq, cfg, rig.subject.body, int(cfg.seed), rig.train_envmaps, rig.test_envmaps,
                             rig.wild_envmaps, rig.held_out, motion_theta)
        if plan.ego_offset is not None and plan.has_studio:
            offsets[seq] = int(plan.ego_offset)
        plans.append(plan)
    metrics = simulate_sequences(writer, rig, plans, min(torch.get_num_threads(), len(plans)))
    frames = sum(plan.num_frames for plan in plans)
    write_global_truth(writer, rig, offsets)
    writer.metrics.update(_summary(metrics, frames))
    per = rig.timer.per_camera_frame()  # timing, not metrics: a re-run must reproduce the manifest's digest
    writer.timing["render_s_per_frame_per_camera"] = {k: round(v, 4) for k, v in per.items()}
    writer.units.update({"length": "m", "angle": "rad", "studio": "linear radiance (lights' units x exposure)",
                         "ego": "8-bit sRGB"})
    writer.timing["simulate_s"] = round(time.perf_counter() - started, 3)


def _summary(per_seq: dict, frames: int) -> dict:
    out: dict = {"sequences": per_seq, "frames": frames}
    for key in ("aruco_detection_rate", "aruco_frames_tracked_rate", "board_detection_rate", "ego_body_pixel_fraction",
                "ego_mean_level", "ego_clipped_fraction"):
        values = [m[key] for m in per_seq.values() if key in m]
        if values:
            out[key] = float(np.mean(values))
    return out
