"""The capture reader (on the session's tiny synth capture) and the pointcloud payload."""

from __future__ import annotations

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.capture import Capture
from egorelight_cli.io.pointcloud import PointCloudSequence, read_pointcloud_npz, write_pointcloud_npz


def test_capture_reader_sees_every_sequence_and_camera(tiny_capture):
    capture = Capture(tiny_capture)
    assert {"handeye", "ego_train", "relight_train", "test", "wild"} <= set(capture.sequence_names())
    assert set(capture.ego_cameras) == {"down_left", "down_right", "front_left", "front_right"}
    assert capture.ego_camera("down_left").model == "fisheye"
    test = capture.sequence("test")
    assert test.purpose == "test"
    assert set(test.content_frame_ids) <= set(test.frame_ids)
    assert capture.groundtruth_file("test", "meshes.npz") is not None  # simulated: ground truth exists
    assert capture.groundtruth_file("test", "nope.npz") is None
    wild = capture.sequence("wild")  # no studio stream: content frames are its ego frames
    assert len(wild.content_frame_ids) > 0 and set(wild.content_frame_ids) <= set(wild.ego_frame_ids)
    image = test.read_ego_image("down_left", int(test.ego_frame_ids[0]))
    cam = capture.ego_camera("down_left")
    assert image.shape == (cam.height, cam.width, 3) and image.dtype == np.uint8
    for name, camera in capture.studio_cameras.items():
        assert capture.studio_camera_roles[name] in ("studio", "tracking")
        assert np.allclose(camera.T_cam_from_world[3], [0, 0, 0, 1])


def test_capture_reader_errors_name_the_file(tiny_capture, tmp_path):
    with pytest.raises(EgorelightError, match="not a capture"):
        Capture(tmp_path)
    capture = Capture(tiny_capture)
    with pytest.raises(EgorelightError, match="no sequence 'nope'"):
        capture.sequence("nope")
    with pytest.raises(EgorelightError, match="no studio stream"):
        capture.sequence("wild").require_stream("studio")
    test = capture.sequence("test")
    with pytest.raises(EgorelightError, match="frame 9999 is out of range"):
        test.check_frames([9999], test.frame_ids, "requested")
    with pytest.raises(EgorelightError, match="not found"):
        test.read_ego_image("down_left", 9999)
    # a hand-edited rig or sequence description: the error names the file
    import json
    import shutil

    fake = tmp_path / "capture"
    shutil.copytree(tiny_capture / "rig", fake / "rig")
    shutil.copy(tiny_capture / "manifest.json", fake / "manifest.json")
    (fake / "sequences" / "test").mkdir(parents=True)
    (fake / "sequences" / "test" / "sequence.json").write_text("[1, 2]")
    hmd = json.loads((fake / "rig" / "hmd.json").read_text())
    del hmd["cameras"][0]["K"]
    (fake / "rig" / "hmd.json").write_text(json.dumps(hmd))
    broken = Capture(fake)
    with pytest.raises(EgorelightError, match="lacks K") as info:
        broken.ego_cameras
    assert str(fake / "rig" / "hmd.json") in str(info.value)
    with pytest.raises(EgorelightError, match="must be a JSON object") as info:
        broken.sequence("test")
    assert "sequence.json" in str(info.value)


def test_pointcloud_round_trip_and_validation(tmp_path):
    rng = np.random.default_rng(0)
    points = rng.normal(size=(2, 50, 3)).astype(np.float32)
    normals = points / np.linalg.norm(points, axis=2, keepdims=True)
    valid = rng.random((2, 50)) > 0.2
    cloud = PointCloudSequence(points, normals, valid, np.array([4, 7]), fps=10.0)
    write_pointcloud_npz(tmp_path / "pc.npz", cloud)
    back = read_pointcloud_npz(tmp_path / "pc.npz")
    assert np.array_equal(back.points, cloud.points) and np.array_equal(back.valid, valid)
    assert back.fps == 10.0 and list(back.frame_ids) == [4, 7]
    pts, nrm = back.frame(7)
    assert len(pts) == valid[1].sum() and np.allclose(np.linalg.norm(nrm, axis=1), 1, atol=1e-5)
    with pytest.raises(EgorelightError, match="no frame 5"):
        back.frame(5)
    with pytest.raises(EgorelightError, match="expected"):
        PointCloudSequence(points, normals[:, :10], valid, np.array([4, 7]))
    bad = points.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(EgorelightError, match="NaN"):
        PointCloudSequence(bad, normals, valid, np.array([4, 7]))
