"""The calibration payload: round trip, T_world_from_cam, flagged frames, malformed input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import look_at
from egorelight_cli.io.calibration import (Calibration, EgoCameraCalibration, HeadPoses, read_calibration,
                                           write_calibration)


def make_calibration() -> Calibration:
    Pi = look_at([0.05, -0.02, 0.08], [0.05, -1.0, 0.3])
    frames = np.array([10, 11, 12])
    H = np.stack([look_at([0, 1.6 + 0.01 * i, 0], [0, 1.6, 1.0]) for i in range(3)])
    H = np.linalg.inv(H)  # camera-style poses are fine as generic rigid transforms
    valid = np.array([True, False, True])
    H[1] = np.nan
    poses = HeadPoses(H, frames, valid, np.array([5, 1, 6]), np.array([0.3, np.nan, 0.4]))
    return Calibration(ego_cameras={"down_left": EgoCameraCalibration("down_left", "cam0", Pi, 0.4, 1.2)},
                       stream_offsets={"test": 3}, head_poses={"test": poses})


def test_round_trip_and_unprojection_transform(tmp_path):
    calib = make_calibration()
    write_calibration(tmp_path, calib)
    back = read_calibration(tmp_path)
    np.testing.assert_allclose(back.ego_cameras["down_left"].T_cam_from_hmd, calib.ego_cameras["down_left"].T_cam_from_hmd)
    assert back.ego_cameras["down_left"].residual_mm == pytest.approx(1.2)
    assert back.ego_frame_id("test", 12) == 15
    T = back.T_world_from_cam("down_left", "test", 12)
    expected = calib.head_poses["test"].T_world_from_hmd[2] @ np.linalg.inv(calib.ego_cameras["down_left"].T_cam_from_hmd)
    np.testing.assert_allclose(T, expected, atol=1e-12)
    # the camera centre is where H maps the camera's position in the HMD frame
    centre_hmd = np.linalg.inv(calib.ego_cameras["down_left"].T_cam_from_hmd)[:3, 3]
    np.testing.assert_allclose(T[:3, 3], (calib.head_poses["test"].T_world_from_hmd[2] @ np.r_[centre_hmd, 1])[:3])


def test_valid_poses_are_the_unflagged_frames():
    poses = make_calibration().head_poses["test"]
    valid = poses.valid_poses()
    assert sorted(valid) == [10, 12]
    for frame, T in valid.items():
        np.testing.assert_array_equal(T, poses.valid_pose(frame))
    assert poses.valid_pose(11) is None


def test_flagged_and_unknown_frames_are_errors(tmp_path):
    write_calibration(tmp_path, make_calibration())
    back = read_calibration(tmp_path)
    with pytest.raises(EgorelightError, match="flagged"):
        back.T_world_from_cam("down_left", "test", 11)
    with pytest.raises(EgorelightError, match="no head pose"):
        back.T_world_from_cam("down_left", "test", 99)
    with pytest.raises(EgorelightError, match="no ego camera 'front_left'") as info:
        back.T_world_from_cam("front_left", "test", 10)
    assert str(tmp_path / "calibration.json") in str(info.value)  # the error names the file
    with pytest.raises(EgorelightError, match="no head poses for sequence 'wild'"):
        back.T_world_from_cam("down_left", "wild", 10)


def test_malformed_files(tmp_path):
    write_calibration(tmp_path, make_calibration())
    doc = json.loads((tmp_path / "calibration.json").read_text())
    doc["ego_cameras"]["down_left"]["T_cam_from_hmd"][0][0] = 3.0
    (tmp_path / "calibration.json").write_text(json.dumps(doc))
    with pytest.raises(EgorelightError, match="not a rigid transform"):
        read_calibration(tmp_path)
    (tmp_path / "calibration.json").write_text("{}")
    with pytest.raises(EgorelightError, match="malformed calibration"):
        read_calibration(tmp_path)


@pytest.mark.parametrize("edit, says", [
    (lambda a: a.pop("valid"), "lack valid"),
    (lambda a: a.update(T_world_from_hmd=a["T_world_from_hmd"][:2]), r"T_world_from_hmd \(2, 4, 4\)"),
    (lambda a: a.update(valid=a["valid"].astype(np.int64)), "bool valid"),
])
def test_malformed_head_poses_are_errors_naming_the_file(tmp_path, edit, says):
    """A hand-edited head_poses/<seq>.npz (a KeyError or IndexError deep in egopose before)."""
    from egorelight_cli.io.npz import read_npz, write_npz

    write_calibration(tmp_path, make_calibration())
    npz = next((tmp_path).rglob("test.npz"))
    arrays, meta = read_npz(npz, check_finite=False)
    edit(arrays)
    write_npz(npz, arrays, meta)
    with pytest.raises(EgorelightError, match=says) as info:
        read_calibration(tmp_path)
    assert "test.npz" in str(info.value)
