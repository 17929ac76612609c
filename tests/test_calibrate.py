"""The ``calibrate`` stage: sync, head tracking, hand-eye and wild alignment on the tiny capture,
plus analytic cases and bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from egorelight_cli.cli import main
from egorelight_cli.config import resolve_config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.markers import refine_marker_edges
from egorelight_cli.geometry.rigid import kabsch, mean_frame_change, rigid_from_vector, rotation_angle_deg
from egorelight_cli.io.calibration import read_calibration
from egorelight_cli.io.capture import Capture, SequenceInfo
from egorelight_cli.stages.calibrate import calibrate
from egorelight_cli.stages.calibrate_handeye import calibrate_hand_eye, detect_boards
from egorelight_cli.stages.calibrate_head import MarkerObservation, solve_head_pose
from egorelight_cli.stages.calibrate_sync import find_stream_offset
from egorelight_cli.geometry.rigid import interpolate_poses
from egorelight_cli.io.tracker import read_tracker
from egorelight_cli.stages.calibrate_wild import align_trajectories, align_wild


@pytest.fixture(scope="module")
def cfg():
    return resolve_config("calibrate", "tiny", (), None)


@pytest.fixture(scope="module")
def calibrated(tiny_capture, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("calibrate") / "calibration"
    with pytest.raises(SystemExit) as exit_info:
        main(["calibrate", "--preset", "tiny", "--capture", str(tiny_capture), "--out", str(out), "-q"])
    assert exit_info.value.code == 0
    return out


@pytest.fixture(scope="module")
def metrics(calibrated) -> dict:
    return json.loads((calibrated / "manifest.json").read_text())["metrics"]


# ------------------------------------------------------------------------------ the whole stage
def test_artifact_is_complete_and_previews_exist(calibrated, tiny_capture):
    cal = read_calibration(calibrated)
    for seq in ("handeye", "ego_train", "test", "wild"):
        assert seq in cal.head_poses and seq in cal.stream_offsets
    for name in ("markers", "board", "trajectories"):
        image = cv2.imread(str(calibrated / "previews" / f"{name}.png"))
        assert image is not None and image.shape[0] > 32 and image.std() > 1
    # a world camera pose for a valid frame of the test sequence
    poses = cal.head_poses["test"]
    frame = int(poses.frame_ids[np.flatnonzero(poses.valid)[0]])
    T = cal.T_world_from_cam("front_left", "test", frame)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)


def test_stream_offsets_are_exact(calibrated, metrics, tiny_capture):
    truth = json.loads((tiny_capture / "groundtruth/streams.json").read_text())
    cal = read_calibration(calibrated)
    for seq, doc in truth.items():
        assert cal.stream_offsets[seq] == -doc["ego_offset"]
    assert metrics["sync_all_correct"] is True
    assert cal.stream_offsets["wild"] == 0


def test_head_poses_are_accurate_and_dark_frames_flagged(calibrated, metrics, tiny_capture):
    # Tiny: two 320x240 tracking cameras, markers ~20 px wide, 2-5 markers per view. Measured:
    # median 0.1-0.4 deg and 0.06-0.4 mm; the limits leave ~2.5x margin for seeds and platforms.
    for seq in ("handeye", "ego_train", "test"):
        head = metrics["head_pose"][seq]
        assert head["rotation_error_deg_median"] < 1.0, seq
        assert head["translation_error_mm_median"] < 2.0, seq
        assert head["valid_fraction"] >= 0.75, seq
        info = json.loads((tiny_capture / f"sequences/{seq}/sequence.json").read_text())
        poses = read_calibration(calibrated).head_poses[seq]
        dark = [i for i, light in enumerate(info["lights"]) if light["pattern"] == "dark"]
        assert dark and not poses.valid[dark].any(), "a frame without light cannot have a head pose"
        assert np.isnan(poses.T_world_from_hmd[dark]).all()
        with pytest.raises(EgorelightError, match="flagged"):
            poses.pose(int(poses.frame_ids[dark[0]]))


def test_hand_eye_is_accurate_where_the_board_is_seen(calibrated, metrics):
    # Tiny: six hand-eye frames, about 13 deg of head motion: AX = XB is poorly conditioned.
    # Measured after the joint refinement: front cameras 0.3-0.5 deg and 7-8 mm; the 192 px down
    # fisheyes, which see the board small at the top of their image circle, 1.1-2.2 deg and 8-11
    # mm. Limits: ~3x the rotation, 2x the translation. The cpu preset (22 frames, 256 px down
    # cameras) reaches 0.25-0.59 deg and 3.8-4.8 mm.
    rot, trans = metrics["handeye_rotation_error_deg"], metrics["handeye_translation_error_mm"]
    limits = {"front_left": (1.5, 15.0), "front_right": (1.5, 15.0), "down_left": (6.0, 25.0), "down_right": (6.0, 25.0)}
    for role, (max_deg, max_mm) in limits.items():
        assert rot[role] < max_deg, role
        assert trans[role] < max_mm, role
        assert metrics["handeye_residual_px"][role] < 1.0
    assert metrics["uncalibrated_cameras"] == []
    assert set(read_calibration(calibrated).ego_cameras) == set(limits)


def test_a_camera_that_never_sees_the_board_is_reported_not_invented(tiny_capture, tmp_path, monkeypatch):
    import egorelight_cli.stages.calibrate_handeye as handeye

    seen = handeye.detect_boards
    monkeypatch.setattr(handeye, "detect_boards",
                        lambda *args: [o for o in seen(*args) if not o.role.startswith("down")])
    out = tmp_path / "calibration"
    with pytest.raises(SystemExit) as exit_info:
        main(["calibrate", "--preset", "tiny", "--capture", str(tiny_capture), "--out", str(out), "-q"])
    assert exit_info.value.code == 0
    metrics = json.loads((out / "manifest.json").read_text())["metrics"]
    cal = read_calibration(out)
    for role in ("down_left", "down_right"):
        assert role not in cal.ego_cameras
        assert role in metrics["uncalibrated_cameras"]
    with pytest.raises(SystemExit) as exit_info:  # handeye.on_missing=error: a one-line error, nothing written
        main(["calibrate", "--preset", "tiny", "--capture", str(tiny_capture), "--out", str(tmp_path / "strict"),
              "--set", "handeye.on_missing=error", "-q"])
    assert exit_info.value.code == 2 and not (tmp_path / "strict").exists()


def test_wild_alignment_corrects_the_tracker(metrics, calibrated):
    # Tiny wild: 8 frames of a ~130 deg/s turn, front cameras from the tiny hand-eye. The
    # tracker (50 ms late, drifting) is off by 2.2 deg on average after the best rigid fit; the
    # stereo odometry's poses by 0.56 deg and 0.75 cm RMS, latency found to the 2 ms grid step
    # (measured). The limits ask for a clear improvement and centimetre positions. Since the rig
    # carries a calibration error (0.2 px ego intrinsics, 0.3 px studio) and the subject is out of
    # model, tiny measures 1.0-1.1 deg and 2.4-3.6 cm RMS (it was 0.56 deg and 0.75 cm with an exact
    # rig), latency to 12 ms; 8 frames make them sensitive to sub-percent image changes (the cpu
    # demo's 40 frames: 0.13 deg, 2.2 cm, latency to 2 ms). With the tiny preset's larger hand-eye
    # board (so that its down cameras calibrate) the front cameras' hand-eye moved by a few mm and
    # tiny measures 0.56 deg and 5.3 cm RMS: the 8-frame odometry's scale rests on those mm.
    wild = metrics["wild"]
    assert wild["rotation_error_deg_mean"] < 0.5 * wild["raw_tracker_rotation_error_deg_mean"]
    assert wild["rotation_error_deg_mean"] < 1.6
    assert wild["position_error_cm_rms"] < 7.0
    assert wild["latency_error_s"] < 0.02
    poses = read_calibration(calibrated).head_poses["wild"]
    R = poses.T_world_from_hmd[:, :3, :3]
    assert poses.valid.all() and np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-9)


def test_rerun_is_a_noop(calibrated, tiny_capture):
    before = (calibrated / "manifest.json").read_text()
    with pytest.raises(SystemExit) as exit_info:
        main(["calibrate", "--preset", "tiny", "--capture", str(tiny_capture), "--out", str(calibrated), "-q"])
    assert exit_info.value.code == 0
    assert (calibrated / "manifest.json").read_text() == before


# ------------------------------------------------------------------------------ analytic cases
def _write_sequence(root: Path, lights: list[dict], ego_levels: list[int], sync: dict) -> SequenceInfo:
    root.mkdir(parents=True)
    for e, level in enumerate(ego_levels):
        path = root / "ego" / "front_left" / f"{e:06d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), np.full((8, 8, 3), level, np.uint8))
    doc = {"name": "s", "purpose": "test", "fps": 10.0, "frame_ids": list(range(len(lights))),
           "ego_frame_ids": list(range(len(ego_levels))), "lights": lights, "sync": sync,
           "streams": {"studio": ["cam00"], "ego": ["front_left"]}}
    (root / "sequence.json").write_text(json.dumps(doc))
    return SequenceInfo("s", root, doc)


@pytest.mark.parametrize("ego_offset", [1, 2, 3])
def test_sync_recovers_a_known_offset(tmp_path, cfg, ego_offset):
    """Ego frame e sees studio frame e + ego_offset; brightness is a clipped, nonlinear response."""
    code = [1, 1, 0, 1, 0]
    scales = [0.25] * 4 + [3.0 if b else 0.0 for b in code] + [1.0] * 4
    lights = [{"pattern": "flat" if s in (0.25, 1.0) else ("flash" if s else "dark"), "scale": s} for s in scales]
    response = lambda s: int(min(255, 255 * (s / 2.0) ** 0.45))  # noqa: E731
    ego = [response(scales[e + ego_offset]) for e in range(len(scales) - ego_offset)]
    seq = _write_sequence(tmp_path / "seq", lights, ego, {"code": code, "code_start_frame": 4, "standby_frames": 4})
    assert find_stream_offset(seq, cfg.sync).stream_offset == -ego_offset


def test_sync_without_a_visible_code_is_an_error(tmp_path, cfg):
    code = [1, 0, 1]
    scales = [0.25] * 3 + [3.0, 0.0, 3.0] + [1.0] * 3
    lights = [{"pattern": "flat" if s in (0.25, 1.0) else ("flash" if s else "dark"), "scale": s} for s in scales]
    seq = _write_sequence(tmp_path / "seq", lights, [100] * 8, {"code": code, "code_start_frame": 3})
    with pytest.raises(EgorelightError, match="flash code is not found"):
        find_stream_offset(seq, cfg.sync)


def test_marker_edges_remove_the_half_pixel_shrink():
    """A dark quadrilateral rendered with exact (area) antialiasing: corners moved 0.5 px inwards
    (like OpenCV's contour corners) come back to within 0.25 px (measured: <= 0.09 px for
    axis-aligned edges, <= 0.2 px for slanted ones, where bilinear profiles bias the crossing)."""
    scale, size = 16, 48
    truth = np.array([[12.3, 10.7], [35.6, 12.1], [34.2, 35.4], [11.1, 33.9]])
    big = np.full((size * scale, size * scale), 0.9, np.float32)
    cv2.fillPoly(big, [np.round((truth + 0.5) * scale - 0.5).astype(np.int32)], 0.05)
    image = cv2.resize(big, (size, size), interpolation=cv2.INTER_AREA)
    start = truth + np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])  # shrunk, like OpenCV's
    refined = refine_marker_edges(image, start)
    assert np.abs(refined - truth).max() < 0.25
    assert np.linalg.norm(refined - truth, axis=1).mean() < 0.5 * np.linalg.norm(start - truth, axis=1).mean()


def test_rigid_helpers_round_trip():
    rng = np.random.default_rng(3)
    T = rigid_from_vector(np.concatenate([rng.normal(size=3), rng.normal(size=3)]))
    P = rng.normal(size=(10, 3))
    Q = P @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(kabsch(P, Q), T, atol=1e-9)
    assert rotation_angle_deg(T[:3, :3], T[:3, :3]) < 1e-6


def test_mean_frame_change_recovers_one_rigid_change_of_world():
    rng = np.random.default_rng(4)
    T_a_from_b = rigid_from_vector(np.concatenate([rng.normal(size=3), rng.normal(size=3)]))
    T_b = np.stack([rigid_from_vector(np.concatenate([rng.normal(size=3), rng.normal(size=3)])) for _ in range(7)])
    assert np.allclose(mean_frame_change(T_a_from_b @ T_b, T_b), T_a_from_b, atol=1e-9)
    # per-pose noise of 1 cm / ~0.6 deg averages out to well under a centimetre and a degree
    noisy = np.stack([rigid_from_vector(np.concatenate([rng.normal(0, 0.01, 3), rng.normal(0, 0.01, 3)])) @ T
                      for T in T_a_from_b @ T_b])
    estimate = mean_frame_change(noisy, T_b)
    assert rotation_angle_deg(estimate[:3, :3], T_a_from_b[:3, :3]) < 1.0
    assert np.abs(estimate - T_a_from_b)[:3, 3].max() < 0.05


# ---------------------------------------------------------------------------------- bad input
def test_too_few_marker_detections_flag_the_frame(tiny_capture, cfg):
    capture = Capture(tiny_capture)
    cams = capture.studio_cameras
    name = next(iter(cams))
    obs = [MarkerObservation(name, 0, np.array([[10.0, 10.0], [20, 10], [20, 20], [10, 20]]), np.zeros((4, 3)))]
    T, valid, residual = solve_head_pose(obs, cams, cfg.head)
    assert not valid and np.isnan(T).all() and np.isnan(residual)


def test_hand_eye_without_head_poses_is_an_error(tiny_capture, cfg):
    capture = Capture(tiny_capture)
    seq = capture.sequence("handeye")
    with pytest.raises(EgorelightError, match="too few board detections"):
        calibrate_hand_eye(capture, seq, -2, {}, {}, cfg.handeye)


@pytest.mark.parametrize("change, says", [
    ({"dictionary": "DICT_9X9_7"}, "unknown ArUco dictionary"),
    ({"squares_x": None}, "lacks 'squares_x'"),
    ({"squares_x": 0}, "at least 2x2 squares"),
    ({"marker_length_m": -0.1}, "0 < marker_length_m"),
    ({"dictionary": "DICT_4X4_50", "squares_x": 20, "squares_y": 20}, "too few"),
])
def test_a_bad_board_description_is_an_error_naming_board_json(tiny_capture, tmp_path, cfg, change, says):
    """A hand-written rig/board.json (OpenCV raised AttributeError / SystemError: internal errors)."""
    fake = tmp_path / "capture"
    shutil.copytree(tiny_capture / "rig", fake / "rig")
    board = json.loads((fake / "rig" / "board.json").read_text())
    board.update(change)
    board = {k: v for k, v in board.items() if v is not None}
    (fake / "rig" / "board.json").write_text(json.dumps(board))
    (fake / "sequences").mkdir()
    (fake / "sequences" / "handeye").symlink_to(tiny_capture / "sequences" / "handeye")
    with pytest.raises(EgorelightError, match=says) as raised:
        calibrate_hand_eye(Capture(fake), Capture(fake).sequence("handeye"), -2, {}, {}, cfg.handeye)
    assert "board.json" in str(raised.value)


def test_sequence_without_the_needed_stream_is_an_error(tiny_capture, cfg):
    seq = Capture(tiny_capture).sequence("relight_train")
    with pytest.raises(EgorelightError, match="has no ego stream"):
        find_stream_offset(seq, cfg.sync)


def test_missing_handeye_sequence_is_an_error(tiny_capture, tmp_path, cfg):
    fake = tmp_path / "capture"
    (fake / "sequences").mkdir(parents=True)
    (fake / "rig").symlink_to(tiny_capture / "rig")
    (fake / "sequences" / "test").symlink_to(tiny_capture / "sequences" / "test")
    with pytest.raises(EgorelightError, match="no hand-eye sequence"):
        calibrate(Capture(fake), cfg)


def test_inconsistent_ego_image_size_is_an_error(tiny_capture, tmp_path, cfg):
    capture = Capture(tiny_capture)
    src = capture.sequence("handeye")
    root = tmp_path / "handeye"
    shutil.copytree(src.root / "ego", root / "ego")
    shutil.copy(src.root / "sequence.json", root / "sequence.json")
    path = root / "ego" / "front_left" / "000000.png"
    cv2.imwrite(str(path), cv2.resize(cv2.imread(str(path)), (200, 150)))
    seq = SequenceInfo("handeye", root, src.doc)
    from egorelight_cli.geometry.markers import charuco_board

    with pytest.raises(EgorelightError, match="rig/hmd.json says"):
        detect_boards(seq, capture.ego_cameras, charuco_board(capture.board), -2, cfg.handeye)


def _turning_head(times: np.ndarray) -> np.ndarray:
    """A head turning at a varying rate and nodding, 20 cm from the turn's axis: (T,4,4)."""
    yaw = 1.2 * times + 0.3 * np.sin(2 * np.pi * 0.9 * times)
    pitch = 0.15 * np.sin(2 * np.pi * 0.6 * times)
    vectors = np.stack([pitch, yaw, np.zeros_like(times), 0.2 * np.sin(yaw), 1.6 + 0.02 * np.sin(3 * times),
                        0.2 * np.cos(yaw)], axis=1)
    return rigid_from_vector(vectors)


def test_trajectory_alignment_recovers_latency_and_offset(cfg):
    fps, rate, latency = 5.0, 40.0, 0.062
    frame_times = np.arange(30) / fps
    tracker_times = np.arange(-4, 30 * 8 + 4) / rate
    T_tracker_from_world = rigid_from_vector([0.0, 2.1, 0.0, 1.5, 0.2, -0.7])
    tracker = T_tracker_from_world @ _turning_head(tracker_times - latency)  # reports the past
    truth = _turning_head(frame_times)
    T_vo_from_hmd = np.linalg.inv(truth[0]) @ truth
    found, T_vo_from_tracker, fit = align_trajectories(T_vo_from_hmd, frame_times, tracker, tracker_times, cfg.wild)
    assert abs(found - latency) <= cfg.wild.latency_step_s
    expected = np.linalg.inv(truth[0]) @ np.linalg.inv(T_tracker_from_world)
    assert rotation_angle_deg(T_vo_from_tracker[:3, :3], expected[:3, :3]) < 0.05
    assert np.linalg.norm(T_vo_from_tracker[:3, 3] - expected[:3, 3]) < 0.003
    assert fit["alignment_rms_deg"] < 0.1 and fit["alignment_rms_m"] < 0.003


def test_interpolated_poses_extrapolate_translation_only():
    times = np.array([0.0, 1.0])
    T = rigid_from_vector([[0, 0, 0, 0, 0, 0], [0, 0.5, 0, 1.0, 0, 0]])
    out = interpolate_poses(T, times, np.array([0.5, 2.0]), extrapolate=True)
    np.testing.assert_allclose(out[0], rigid_from_vector([0, 0.25, 0, 0.5, 0, 0]), atol=1e-12)
    np.testing.assert_allclose(out[1, :3, 3], [2.0, 0, 0])
    np.testing.assert_allclose(out[1, :3, :3], T[1, :3, :3])


def _wild_copy(tiny_capture: Path, tmp_path: Path, arrays: dict | None = None) -> SequenceInfo:
    from egorelight_cli.io.npz import read_npz, write_npz

    capture = Capture(tiny_capture)
    src = capture.sequence("wild")
    root = tmp_path / "wild"
    shutil.copytree(src.root, root)
    if arrays is not None:
        old, meta = read_npz(root / "head_pose.npz")
        write_npz(root / "head_pose.npz", {**old, **arrays}, meta)
    return SequenceInfo("wild", root, src.doc)


def test_bad_tracker_files_are_errors(tiny_capture, tmp_path):
    from egorelight_cli.io.npz import read_npz

    tracker, _ = read_npz(tiny_capture / "sequences" / "wild" / "head_pose.npz")
    broken = tracker["T_world_from_hmd"].copy()
    broken[3, 0, 3] = np.nan
    cases = [({"T_world_from_hmd": broken}, "NaN"),
             ({"timestamps_s": tracker["timestamps_s"][:-1]}, "timestamps have shape"),
             ({"timestamps_s": np.zeros_like(tracker["timestamps_s"])}, "timestamps repeat")]
    for k, (arrays, message) in enumerate(cases):
        seq = _wild_copy(tiny_capture, tmp_path / str(k), arrays)
        with pytest.raises(EgorelightError, match=message) as error:
            read_tracker(seq)
        assert error.value.path == str(seq.head_pose_path())


def test_wild_alignment_needs_both_front_cameras(tiny_capture, tmp_path, cfg):
    capture = Capture(tiny_capture)
    seq = _wild_copy(tiny_capture, tmp_path)
    with pytest.raises(EgorelightError, match="both calibrated front cameras; missing front_right"):
        align_wild(seq, capture.ego_cameras, {"front_left": np.eye(4)}, cfg.wild)
    (seq.root / "head_pose.npz").unlink()
    with pytest.raises(EgorelightError, match="no headset tracker poses"):
        align_wild(seq, capture.ego_cameras, {"front_left": np.eye(4), "front_right": np.eye(4)}, cfg.wild)


def test_cli_error_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["calibrate", "--capture", str(tmp_path / "nope"), "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("egorelight: error:")
