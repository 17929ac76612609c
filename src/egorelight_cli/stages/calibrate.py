"""The ``calibrate`` stage: everything that puts ego-camera observations into the world.

``egorelight calibrate --capture CAPTURE --out DIR`` writes a ``calibration`` artifact
(:mod:`egorelight_cli.io.calibration`) from a capture (DESIGN.md Sec. 5), following the paper's
Sec. "Data Acquisition" and the supplement's capture details:

1. **Stream sync** (:mod:`.calibrate_sync`): per sequence with studio and ego streams, the ego
   stream's frame offset from the lightstage's flash code.
2. **Head tracking** (:mod:`.calibrate_head`): per sequence with a worn HMD and studio cameras,
   ``T_world_from_hmd`` per studio frame from the HMD's ArUco markers (flagged where evidence is
   too thin).
3. **Hand-eye** (:mod:`.calibrate_handeye`): ``T_cam_from_hmd`` of every ego camera from the
   ``handeye`` sequence's static ChArUco board (AX = XB, then a joint refinement that also
   improves that sequence's head poses).
4. **In the wild** (:mod:`.calibrate_wild`): the front cameras' stereo visual odometry, the
   headset tracker's latency and the 6-DoF offset aligning its trajectory to the odometry; the
   head poses are the odometry's, mapped into the tracker's gravity-aligned frame.

When the capture carries ``groundtruth/`` the stage scores itself (:func:`evaluate`): hand-eye
rotation/translation error per camera, head-pose error per sequence, whether each stream offset
is exact, the wild alignment error. Previews: ``previews/markers.png`` (detected markers and the
fitted layout), ``previews/board.png`` (detected vs. reprojected board corners on ego images),
``previews/trajectories.png`` (head trajectories and the wild orientations).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from egorelight_cli import console
from egorelight_cli.artifacts import ArtifactWriter
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import invert_rigid
from egorelight_cli.geometry.rigid import mean_rotation, rotation_angle_deg
from egorelight_cli.geometry.rotations import camera_centre
from egorelight_cli.io.calibration import write_calibration
from egorelight_cli.structures.calibration import STUDIO_HEAD_POSE_SOURCE, Calibration, EgoCameraCalibration, HeadPoses
from egorelight_cli.io.capture import Capture, SequenceInfo, open_capture
from egorelight_cli.pipeline import StageRun
from egorelight_cli.render.sheets import stack_rows, tile_row
from egorelight_cli.stages.calibrate_handeye import HandEyeResult, calibrate_hand_eye
from egorelight_cli.stages.calibrate_head import HeadTrack, project_points, studio_image, track_head
from egorelight_cli.stages.calibrate_sync import SyncResult, find_stream_offset
from egorelight_cli.io.tracker import tracker_head_poses
from egorelight_cli.stages.calibrate_wild import WildResult, align_wild

STAGE = "calibrate"
#: Height in pixels of an image tile in the marker and board previews.
PREVIEW_TILE_HEIGHT = 200


@dataclass
class CalibrationRun:
    """The calibration and what made it (for metrics and previews)."""

    calibration: Calibration
    syncs: dict[str, SyncResult] = field(default_factory=dict)
    tracks: dict[str, HeadTrack] = field(default_factory=dict)
    handeye: HandEyeResult | None = None
    wild: WildResult | None = None
    warnings: list[str] = field(default_factory=list)


def _has(seq: SequenceInfo, stream: str) -> bool:
    return bool(seq.streams.get(stream))


def calibrate(capture: Capture, cfg: Config) -> CalibrationRun:
    """Run the whole stage on ``capture`` with the resolved ``calibrate`` config."""
    sequences = {name: capture.sequence(name) for name in capture.sequence_names()}
    handeye_name = str(cfg.handeye_sequence)
    if handeye_name not in sequences:
        raise EgorelightError(f"the capture has no hand-eye sequence {handeye_name!r} (has "
                              f"{', '.join(sequences) or 'none'}); calibrate needs one", capture.root / "sequences")
    handeye_seq = sequences[handeye_name]
    for stream in ("studio", "ego"):
        handeye_seq.require_stream(stream)
    warnings: list[str] = []
    syncs: dict[str, SyncResult] = {}
    for name, seq in sequences.items():
        if _has(seq, "studio") and _has(seq, "ego"):
            syncs[name] = find_stream_offset(seq, cfg.sync)
            console.debug(f"calibrate: {name}: stream offset {syncs[name].stream_offset}")
    tracks: dict[str, HeadTrack] = {}
    for name, seq in sequences.items():
        if _has(seq, "studio") and bool(seq.doc.get("hmd_worn", _has(seq, "ego"))):
            tracks[name] = track_head(capture, seq, cfg.head)
            poses = tracks[name].poses
            console.info(f"calibrate: {name}: head poses for {int(poses.valid.sum())}/{len(poses.valid)} frames")
    track = tracks[handeye_name]
    heads = track.poses.valid_poses()
    handeye = calibrate_hand_eye(capture, handeye_seq, syncs[handeye_name].stream_offset, heads, track.observations,
                                 cfg.handeye)
    for role, why in handeye.missing.items():
        message = f"ego camera {role} is not calibrated: {why}"
        if str(cfg.handeye.on_missing) == "error":
            raise EgorelightError(message, handeye_seq.root)
        warnings.append(message)
        console.info(f"calibrate: warning: {message}")
    if handeye.refined_head:  # the joint refinement's head poses are better: keep them
        poses = track.poses
        T = poses.T_world_from_hmd.copy()
        for i, f in enumerate(poses.frame_ids):
            if int(f) in handeye.refined_head:
                T[i] = handeye.refined_head[int(f)]
        track.poses = HeadPoses(T, poses.frame_ids, poses.valid, poses.num_markers, poses.residual_px)
    names = {entry.get("role"): entry.get("name", entry.get("role")) for entry in capture.hmd.get("cameras", [])}
    cameras = {role: EgoCameraCalibration(role, names.get(role, role), Pi, handeye.residual_px[role],
                                          handeye.residual_mm[role])
               for role, Pi in sorted(handeye.T_cam_from_hmd.items())}
    head_poses = {name: t.poses for name, t in tracks.items()}
    offsets = {name: s.stream_offset for name, s in syncs.items()}
    wild = None
    wild_name = str(cfg.wild.sequence)
    if wild_name in sequences and _has(sequences[wild_name], "head_pose") and not _has(sequences[wild_name], "studio"):
        try:
            wild = align_wild(sequences[wild_name], capture.ego_cameras, handeye.T_cam_from_hmd, cfg.wild)
            head_poses[wild_name] = wild.poses
        except EgorelightError as error:  # keep the tracker's poses as they are, and say so
            head_poses[wild_name] = tracker_head_poses(sequences[wild_name])
            message = f"wild alignment failed ({error.message}); the tracker's poses are used without latency correction"
            warnings.append(message)
            console.info(f"calibrate: warning: {message}")
        offsets[wild_name] = 0
    extras = {
        "T_world_from_board": handeye.T_world_from_board.tolist(),
        "handeye": {k: v for k, v in handeye.info.items()},
        "uncalibrated_cameras": dict(handeye.missing),
        "sync": {name: {"stream_offset": s.stream_offset, "correlation": s.correlation, "runner_up": s.runner_up}
                 for name, s in syncs.items()},
        "head_pose_sources": {**{name: STUDIO_HEAD_POSE_SOURCE for name in tracks},
                              **({wild_name: f"headset tracker aligned to visual odometry ({cfg.wild.pose_source})"
                                  if wild else
                                  "headset tracker, uncorrected (alignment failed)"} if wild_name in head_poses else {})},
    }
    if wild is not None:
        extras["wild"] = {**wild.info, "T_vo_from_tracker": wild.T_vo_from_tracker.tolist()}
    return CalibrationRun(Calibration(cameras, offsets, head_poses, extras), syncs, tracks, handeye, wild, warnings)


# ---------------------------------------------------------------------------------- evaluation
def evaluate(capture: Capture, run: CalibrationRun) -> dict:
    """Metrics against ``groundtruth/`` (empty without one). Hand-eye translation error is the
    camera centre's distance in the HMD frame (mm); head-pose errors compare valid frames."""
    from egorelight_cli.synth.groundtruth import read_head_poses, read_json

    root = capture.groundtruth_root()
    if root is None:
        return {}
    cal = run.calibration
    metrics: dict = {}
    truth = read_json(root, "hand_eye.json")
    rot, trans = {}, {}
    for role, cam in cal.ego_cameras.items():
        G = np.asarray(truth[role]["T_cam_from_hmd"])
        rot[role] = float(rotation_angle_deg(cam.T_cam_from_hmd[:3, :3], G[:3, :3]))
        trans[role] = float(1000 * np.linalg.norm(camera_centre(cam.T_cam_from_hmd) - camera_centre(G)))
    metrics["handeye_rotation_error_deg"] = rot
    metrics["handeye_translation_error_mm"] = trans
    if rot:
        metrics["handeye_rotation_error_deg_max"] = max(rot.values())
        metrics["handeye_translation_error_mm_max"] = max(trans.values())
    metrics["handeye_calibrated_cameras"] = len(cal.ego_cameras)
    streams = read_json(root, "streams.json")
    correct = {seq: bool(cal.stream_offsets.get(seq) == -int(doc["ego_offset"])) for seq, doc in streams.items()
               if seq in run.syncs}
    metrics["sync_offset_correct"] = correct
    metrics["sync_all_correct"] = bool(correct) and all(correct.values())
    head = {}
    for seq, track in run.tracks.items():
        gt = read_head_poses(root, seq)
        index = {int(f): i for i, f in enumerate(gt["frame_ids"])}
        poses = track.poses
        rows = [i for i, f in enumerate(poses.frame_ids) if poses.valid[i] and int(f) in index]
        est = poses.T_world_from_hmd[rows]
        ref = gt["T_world_from_hmd"][[index[int(poses.frame_ids[i])] for i in rows]]
        r = rotation_angle_deg(est[:, :3, :3], ref[:, :3, :3]) if rows else np.zeros(0)
        t = 1000 * np.linalg.norm(est[:, :3, 3] - ref[:, :3, 3], axis=1) if rows else np.zeros(0)
        head[seq] = {"valid_fraction": float(poses.valid.mean()) if len(poses.valid) else 0.0,
                     "rotation_error_deg_median": float(np.median(r)) if r.size else None,
                     "rotation_error_deg_max": float(r.max()) if r.size else None,
                     "translation_error_mm_median": float(np.median(t)) if t.size else None,
                     "translation_error_mm_max": float(t.max()) if t.size else None}
    metrics["head_pose"] = head
    if run.wild is not None:
        metrics["wild"] = _wild_metrics(root, run.wild)
    return metrics


def _trajectory_error(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame (rotation error deg, position error m) of poses ``est`` (T,4,4) against ``ref``
    after the best constant rigid transform: the rotation average of ``R_ref R_est^T`` and the
    centroid offset (the trajectories' world frames differ by an arbitrary gauge)."""
    Q = mean_rotation(ref[:, :3, :3] @ np.swapaxes(est[:, :3, :3], 1, 2))
    moved = est[:, :3, 3] @ Q.T
    position = moved + np.mean(ref[:, :3, 3] - moved, axis=0)
    return rotation_angle_deg(ref[:, :3, :3], Q @ est[:, :3, :3]), np.linalg.norm(position - ref[:, :3, 3], axis=1)


def _wild_metrics(root: Path, wild: WildResult) -> dict:
    from egorelight_cli.synth.groundtruth import read_head_poses, read_json

    gt = read_head_poses(root, "wild")
    index = {int(f): i for i, f in enumerate(gt["frame_ids"])}
    ref = gt["T_world_from_hmd"][[index[int(f)] for f in wild.poses.frame_ids]]
    out = {}
    for name, est in (("", wild.poses.T_world_from_hmd), ("raw_tracker_", wild.tracker_T),
                      ("odometry_", wild.T_vo_from_hmd)):
        rotation, position = _trajectory_error(est, ref)
        out.update({f"{name}rotation_error_deg_mean": float(rotation.mean()),
                    f"{name}rotation_error_deg_max": float(rotation.max()),
                    f"{name}position_error_cm_rms": float(100 * np.sqrt(np.mean(position ** 2))),
                    f"{name}position_error_cm_max": float(100 * position.max())})
    tracker = read_json(root, "wild/tracker.json")
    return {**out, "latency_s": wild.latency_s, "latency_error_s": float(abs(wild.latency_s - float(tracker["latency_s"])))}


# ------------------------------------------------------------------------------------ previews
def marker_preview(capture: Capture, run: CalibrationRun, cfg) -> np.ndarray:
    """Studio views with detected marker corners (green) and the fitted layout reprojected (red)."""
    rows = []
    for seq_name, track in list(run.tracks.items())[:2]:
        seq = capture.sequence(seq_name)
        valid = np.flatnonzero(track.poses.valid)
        tiles = []
        picks = np.linspace(0, len(valid) - 1, min(int(cfg.preview.frames), len(valid))).astype(int) if len(valid) else []
        for i in valid[picks]:
            f = int(track.poses.frame_ids[i])
            obs = track.observations[f]
            for name in sorted({o.camera for o in obs})[:2]:
                cam = capture.studio_cameras[name]
                image, _ = studio_image(seq, name, f, float(cfg.head.tonemap_percentile))
                image = image.copy()
                T = cam.T_cam_from_world @ track.poses.T_world_from_hmd[i]
                for o in obs:
                    if o.camera != name:
                        continue
                    for uv in o.pixels:
                        cv2.circle(image, tuple(np.round(uv).astype(int)), 3, (0, 255, 0), 1)
                    for uv in project_points(T, o.corners_hmd, cam):
                        cv2.drawMarker(image, tuple(np.round(uv).astype(int)), (255, 0, 0), cv2.MARKER_CROSS, 5, 1)
                tiles.append((f"{seq_name} {name} f{f}", image))
        if tiles:
            rows.append(tile_row(tiles, height=PREVIEW_TILE_HEIGHT))
    return stack_rows(rows) if rows else np.zeros((64, 64, 3), np.uint8)


def board_preview(capture: Capture, run: CalibrationRun, cfg) -> np.ndarray:
    """Ego images of the hand-eye sequence: detected board corners (green), reprojected (red)."""
    he = run.handeye
    seq = capture.sequence(str(cfg.handeye_sequence))
    heads = run.tracks[seq.name].poses.valid_poses()
    rows = []
    frames = sorted({o.frame for o in he.observations if o.frame in heads})
    picks = [frames[i] for i in np.linspace(0, len(frames) - 1, min(int(cfg.preview.frames), len(frames))).astype(int)] \
        if frames else []
    for f in picks:
        tiles = []
        for role, cam in sorted(capture.ego_cameras.items()):
            ego = f + run.calibration.stream_offsets[seq.name]
            if not seq.ego_image_path(role, ego).exists():
                continue
            image = seq.read_ego_image(role, ego).copy()
            scale = max(1, round(300 / min(image.shape[:2])))
            image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
            for o in he.observations:
                if o.role != role or o.frame != f:
                    continue
                for uv in o.pixels:
                    cv2.circle(image, tuple(np.round((uv + 0.5) * scale - 0.5).astype(int)), 4, (0, 255, 0), 1)
                if role in he.T_cam_from_hmd:
                    T = he.T_cam_from_hmd[role] @ invert_rigid(heads[f]) @ he.T_world_from_board
                    for uv in project_points(T, o.points_board, cam):
                        if np.all(np.abs(uv) < 1e4):
                            cv2.drawMarker(image, tuple(np.round((uv + 0.5) * scale - 0.5).astype(int)), (255, 0, 0),
                                           cv2.MARKER_CROSS, 7, 1)
            tiles.append((f"{role} f{f}" + ("" if role in he.T_cam_from_hmd else " (uncalibrated)"), image))
        rows.append(tile_row(tiles, height=PREVIEW_TILE_HEIGHT))
    return stack_rows(rows) if rows else np.zeros((64, 64, 3), np.uint8)


def trajectory_preview(run: CalibrationRun) -> np.ndarray:
    """Head height and heading over frames per sequence; the wild orientations (yaw)."""
    from egorelight_cli.render.plots import line_plot

    series = {}
    for name, track in run.tracks.items():
        poses = track.poses
        forward = -poses.T_world_from_hmd[poses.valid, :3, 2]  # the HMD's z axis points backwards
        yaw = np.degrees(np.unwrap(np.arctan2(forward[:, 0], -forward[:, 2])))
        series[f"{name} yaw (deg)"] = (poses.frame_ids[poses.valid].astype(float), yaw)
    top = line_plot(series, "studio head yaw per sequence (deg; valid frames)", width=640, height=300, log_y=False,
                    x_label="frame")
    if run.wild is None:
        return top
    w = run.wild

    def yaw_of(R):
        f = -R[:, :, 2]
        return np.degrees(np.unwrap(np.arctan2(f[:, 0], -f[:, 2])))

    A = w.T_vo_from_tracker
    x = w.poses.frame_ids.astype(float)
    middle = line_plot({"tracker (raw)": (x, yaw_of((A @ w.tracker_T)[:, :3, :3])),
                        "aligned": (x, yaw_of((A @ w.poses.T_world_from_hmd)[:, :3, :3])),
                        "odometry": (x, yaw_of(w.T_vo_from_hmd[:, :3, :3]))},
                       f"wild: heading in the odometry frame (deg), latency {1000 * w.latency_s:.0f} ms",
                       width=640, height=300, log_y=False, x_label="ego frame")
    raw = (A @ w.tracker_T)[:, :3, 3] - w.T_vo_from_hmd[:, :3, 3]
    bottom = line_plot({"tracker-VO x": (x, 100 * raw[:, 0]), "tracker-VO z": (x, 100 * raw[:, 2]),
                        "VO x": (x, 100 * w.T_vo_from_hmd[:, 0, 3]), "VO z": (x, 100 * w.T_vo_from_hmd[:, 2, 3])},
                       "wild: head position in the odometry (VO) frame (cm); raw tracker minus VO",
                       width=640, height=300, log_y=False, x_label="ego frame")
    return np.concatenate([top, middle, bottom], axis=0)


# ------------------------------------------------------------------------------------- command
def write_calibration_artifact(writer: ArtifactWriter, cfg: Config, capture: Capture) -> CalibrationRun:
    """Fill a ``calibration`` artifact writer: payload, metrics, previews."""
    from egorelight_cli.io.images import write_image

    if writer.single_file:
        raise EgorelightError("a calibration is a directory artifact: give --out a directory name", writer.out)
    run = calibrate(capture, cfg)
    write_calibration(writer.workdir, run.calibration)
    he = run.handeye
    writer.metrics.update({
        "handeye_residual_px": {r: c.residual_px for r, c in run.calibration.ego_cameras.items()},
        "handeye_residual_mm": {r: c.residual_mm for r, c in run.calibration.ego_cameras.items()},
        "uncalibrated_cameras": sorted(he.missing),
        "stream_offsets": dict(run.calibration.stream_offsets),
        "head_pose_valid_frames": {n: int(p.valid.sum()) for n, p in run.calibration.head_poses.items()},
        "head_pose_frames": {n: int(len(p.valid)) for n, p in run.calibration.head_poses.items()},
    })
    if run.warnings:
        writer.metrics["warnings"] = run.warnings
    writer.metrics.update(evaluate(capture, run))
    writer.units.update({"T_cam_from_hmd": "m", "T_world_from_hmd": "m", "residual_px": "px", "residual_mm": "mm",
                         "stream_offset": "frames (ego id = studio id + offset)", "latency_s": "s"})
    write_image(writer.path("previews/markers.png"), marker_preview(capture, run, cfg))
    write_image(writer.path("previews/board.png"), board_preview(capture, run, cfg))
    write_image(writer.path("previews/trajectories.png"), trajectory_preview(run))
    return run


@dataclass(frozen=True)
class CalibrateCommand:
    """``egorelight calibrate`` over one :class:`StageRun` (the global options)."""

    run: StageRun

    def __call__(self, capture_path: Path, out: Path) -> Path:
        capture, artifact = open_capture(capture_path)
        return self.run.produce(out, "calibration", lambda w, cfg: write_calibration_artifact(w, cfg, capture),
                                inputs=[artifact])


def calibrate_command(run: StageRun, capture: Path, out: Path) -> Path:
    """``egorelight calibrate`` (declared in :mod:`egorelight_cli.declarations`)."""
    return CalibrateCommand(run)(capture, out)
