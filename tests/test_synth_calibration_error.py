"""Calibration as a lab has it (synth/calibration_error.py): the rig's cameras carry a seeded error
of the configured RMS reprojection size, the truth goes to groundtruth/, and 0 means exact."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from egorelight_cli.artifacts import ArtifactWriter
from egorelight_cli.config import resolve_config
from egorelight_cli.geometry.cameras import Camera, pixel_grid, unproject_to_rays
from egorelight_cli.synth.calibration_error import (
    capture_volume_points,
    perturb_ego_intrinsics,
    perturb_studio_cameras,
    read_true_ego_intrinsics,
    read_true_studio_cameras,
    reprojection_rms_px,
    write_calibrations,
)
from egorelight_cli.synth.hmd import EGO_ROLES, make_hmd
from egorelight_cli.synth.rig import studio_cameras

SEEDS = (0, 1, 2, 7)


@pytest.fixture(scope="module")
def cfg():
    return resolve_config("synth", "cpu")


@pytest.fixture(scope="module")
def exact():
    return resolve_config("synth", "cpu", overrides=["calibration_error.studio_reprojection_px=0",
                                                     "calibration_error.ego_reprojection_px=0"])


@pytest.fixture(scope="module")
def cameras(cfg):
    return studio_cameras(cfg.studio, seed=0)


@pytest.fixture(scope="module")
def hmd(character, cfg):
    return make_hmd(character, cfg.hmd, seed=0)


def _opencv_pixels(camera: Camera, points: np.ndarray) -> np.ndarray:
    rvec = cv2.Rodrigues(camera.T_cam_from_world[:3, :3])[0]
    pixels, _ = cv2.projectPoints(points, rvec, camera.T_cam_from_world[:3, 3], camera.K, camera.dist)
    return pixels.reshape(-1, 2)


def _opencv_squared_errors(true: Camera, written: Camera, points: np.ndarray) -> np.ndarray:
    """Squared pixel distances, by OpenCV's projection, of the points in front of ``true`` inside its image."""
    depth = points @ true.T_cam_from_world[2, :3] + true.T_cam_from_world[2, 3]
    a, b = _opencv_pixels(true, points), _opencv_pixels(written, points)
    inside = (depth > 0) & np.all((a >= -0.5) & (a <= [true.width - 0.5, true.height - 0.5]), axis=1)
    return np.sum((a[inside] - b[inside]) ** 2, axis=1)


def test_defaults_are_a_lab_calibration(cfg):
    assert cfg.calibration_error.studio_reprojection_px == pytest.approx(0.3)
    assert cfg.calibration_error.ego_reprojection_px == pytest.approx(0.2)


def test_reprojection_rms_of_a_principal_point_shift_is_the_shift(cameras):
    true = cameras[0][0]
    K = true.K.copy()
    K[0, 2] += 0.3
    K[1, 2] -= 0.4
    shifted = dataclasses.replace(true, K=K)
    assert reprojection_rms_px(true, shifted, capture_volume_points()) == pytest.approx(0.5, rel=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
def test_studio_error_has_the_requested_rms_over_the_capture_volume(cameras, cfg, seed):
    written, rms = perturb_studio_cameras(cameras, cfg.calibration_error, seed)
    assert abs(rms - 0.3) < 0.2 * 0.3
    points = capture_volume_points()
    squared = np.concatenate([_opencv_squared_errors(t, w, points) for (t, _), (w, _) in zip(cameras, written)])
    assert np.sqrt(squared.mean()) == pytest.approx(rms, rel=1e-6)  # OpenCV agrees on the pooled figure
    for (true, role), (cam, written_role) in zip(cameras, written):
        assert (cam.name, cam.width, cam.height, cam.model, written_role) == \
            (true.name, true.width, true.height, true.model, role)
        # every kind of parameter is off: focal length, principal point, distortion, pose
        assert cam.K[0, 0] != true.K[0, 0] and np.all(cam.K[:2, 2] != true.K[:2, 2])
        assert np.all(cam.dist[:4] != np.pad(true.dist, (0, 5 - true.dist.size))[:4])
        assert not np.allclose(cam.T_cam_from_world[:3, :3], true.T_cam_from_world[:3, :3], rtol=0, atol=1e-9)
        assert not np.allclose(cam.centre_world, true.centre_world, rtol=0, atol=1e-9)
        # a calibration error, not a different rig: well under a percent, a degree, a centimetre
        assert abs(cam.K[0, 0] / true.K[0, 0] - 1) < 0.01
        assert np.linalg.norm(cam.centre_world - true.centre_world) < 0.01
        assert 0.02 < reprojection_rms_px(true, cam, points) < 1.5


def test_studio_error_is_seeded(cameras, cfg):
    a, _ = perturb_studio_cameras(cameras, cfg.calibration_error, 3)
    b, _ = perturb_studio_cameras(cameras, cfg.calibration_error, 3)
    c, _ = perturb_studio_cameras(cameras, cfg.calibration_error, 4)
    assert [x.to_dict() for x, _ in a] == [x.to_dict() for x, _ in b]
    assert [x.to_dict() for x, _ in a] != [x.to_dict() for x, _ in c]


def _image_rms_px(true, written) -> float:
    """RMS over every pixel of the true image: its ray, projected by the written intrinsics."""
    rays, valid = unproject_to_rays(pixel_grid(true.width, true.height).reshape(-1, 2), true.K, true.dist,
                                    true.model, return_valid=True)
    at_origin = [Camera(c.model, c.K, c.dist, c.width, c.height, np.eye(4)) for c in (true, written)]
    return reprojection_rms_px(*at_origin, rays[valid])


@pytest.mark.parametrize("seed", SEEDS)
def test_ego_intrinsics_error_has_the_requested_rms_over_the_image(hmd, cfg, seed):
    written, rms = perturb_ego_intrinsics(hmd.cameras, cfg.calibration_error, seed)
    assert abs(rms - 0.2) < 0.2 * 0.2
    assert list(written) == list(hmd.cameras)
    per_camera = []
    for role, true in hmd.cameras.items():
        cam = written[role]
        assert cam.model == true.model and (cam.width, cam.height) == (true.width, true.height)
        assert cam.T_cam_from_hmd is true.T_cam_from_hmd  # intrinsics only
        assert cam.K[0, 0] != true.K[0, 0] and np.any(cam.dist != true.dist)
        per_camera.append(_image_rms_px(true, cam))
    # every pixel of every image (not the module's grid of rays) gives the same figure within 20 %
    assert abs(np.sqrt(np.mean(np.square(per_camera))) - 0.2) < 0.2 * 0.2


def test_zero_error_reproduces_the_exact_rig(cameras, hmd, exact):
    written, rms = perturb_studio_cameras(cameras, exact.calibration_error, 5)
    assert rms == 0.0 and [c.to_dict() for c, _ in written] == [c.to_dict() for c, _ in cameras]
    ego, rms = perturb_ego_intrinsics(hmd.cameras, exact.calibration_error, 5)
    assert rms == 0.0 and all(ego[r].to_json() == hmd.cameras[r].to_json() for r in hmd.cameras)


def _write(tmp_path, cameras, hmd, cfg):
    with ArtifactWriter(tmp_path / "capture", kind="capture", stage="synth", config=cfg) as writer:
        metrics = write_calibrations(writer, cameras, hmd, cfg.calibration_error, int(cfg.seed))
        writer.save_json("sequences/none/sequence.json", {})
    return tmp_path / "capture", metrics


def test_written_rig_round_trips_and_truth_is_in_groundtruth(tmp_path, cameras, hmd, cfg):
    root, metrics = _write(tmp_path, cameras, hmd, cfg)
    assert abs(metrics["studio_calibration_rms_px"] - 0.3) < 0.06
    assert abs(metrics["ego_intrinsics_rms_px"] - 0.2) < 0.04
    expected, _ = perturb_studio_cameras(cameras, cfg.calibration_error, int(cfg.seed))
    rig = json.loads((root / "rig/studio_cameras.json").read_text())["cameras"]
    assert [c["role"] for c in rig] == [role for _, role in cameras]
    assert [Camera.from_dict(c).to_dict() for c in rig] == [c.to_dict() for c, _ in expected]
    truth = read_true_studio_cameras(root)
    assert {n: c.to_dict() for n, c in truth.items()} == {c.name: c.to_dict() for c, _ in cameras}
    doc = json.loads((root / "groundtruth/studio_cameras.json").read_text())
    assert doc["reprojection_rms_px"]["all"] == pytest.approx(metrics["studio_calibration_rms_px"])
    assert set(doc["reprojection_rms_px"]) == {c.name for c, _ in cameras} | {"all"}

    hmd_doc = json.loads((root / "rig/hmd.json").read_text())
    assert hmd_doc["markers"] == hmd.to_json()["markers"]
    assert [c["role"] for c in hmd_doc["cameras"]] == list(EGO_ROLES)
    ego_truth = read_true_ego_intrinsics(root)
    assert set(ego_truth) == set(hmd.cameras)
    for entry in hmd_doc["cameras"]:
        assert "T_cam_from_hmd" not in entry
        K, dist = ego_truth[entry["role"]]
        np.testing.assert_array_equal(K, hmd.cameras[entry["role"]].K)
        np.testing.assert_array_equal(dist, hmd.cameras[entry["role"]].dist)
        assert not np.array_equal(np.asarray(entry["K"]), K)


def test_exact_config_writes_the_truth_into_the_rig(tmp_path, cameras, hmd, exact):
    root, metrics = _write(tmp_path, cameras, hmd, exact)
    assert metrics == {"studio_calibration_rms_px": 0.0, "ego_intrinsics_rms_px": 0.0}
    rig = json.loads((root / "rig/studio_cameras.json").read_text())
    truth = json.loads((root / "groundtruth/studio_cameras.json").read_text())
    assert rig["cameras"] == truth["cameras"]
    assert json.loads((root / "rig/hmd.json").read_text()) == json.loads(json.dumps(hmd.to_json()))
