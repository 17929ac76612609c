"""The egodepth stage on the tiny capture: supervision rendering, a short training run, the
pointcloud artifact (net and SGBM), metrics against ground truth and one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from egorelight_cli.cli import main
from egorelight_cli.io.calibration import posed_ego_camera
from egorelight_cli.io.capture import Capture
from egorelight_cli.io.exr import read_exr
from egorelight_cli.io.pointcloud import load_pointcloud
from egorelight_cli.stages import egodepth as ed

ROLES = ("down_left", "down_right")


def run_cli(*args: str) -> int:
    with pytest.raises(SystemExit) as exit_info:
        main(["-q", *args])
    return exit_info.value.code


@pytest.fixture(scope="module")
def trained_model(tiny_capture, oracle_calibration_artifact, tmp_path_factory):
    out = tmp_path_factory.mktemp("egodepth") / "model"
    code = run_cli("train", "egodepth", "--preset", "tiny", "--capture", str(tiny_capture), "--calibration",
                   str(oracle_calibration_artifact), "--out", str(out))
    assert code == 0
    return out


@pytest.fixture(scope="module")
def net_cloud(tiny_capture, oracle_calibration_artifact, trained_model, tmp_path_factory):
    out = tmp_path_factory.mktemp("egodepth") / "pointcloud"
    code = run_cli("egodepth", "--preset", "tiny", "--capture", str(tiny_capture), "--calibration",
                   str(oracle_calibration_artifact), "--model", str(trained_model), "--seq", "test", "--out", str(out))
    assert code == 0
    return out


def test_recon_supervision_agrees_with_the_true_body(tiny_capture, oracle_calibration):
    """The reconstruction rendered into the posed ego cameras (H inv(Pi), stream offset) lands on
    the true body: where both are hit the ranges agree to about a centimetre."""
    capture = Capture(tiny_capture)
    sequence = capture.sequence("test")
    views = ed.supervision(capture, oracle_calibration, [sequence], ROLES, near_m=0.07)
    assert len(views) == 2 * len(sequence.content_frame_ids)
    truth = ed.GroundTruth(capture, sequence, 0.05)
    gaps = []
    for view in views[:2]:
        ego = ed.load_view(capture, oracle_calibration, sequence, view.role, view.frame_id)
        _, maps = truth.frame(view.frame_id, [ego])
        true_range, mask = maps[view.role]
        both = mask & view.supervised
        assert both.sum() > 0.1 * view.supervised.size
        gaps.append(np.abs(view.range[both] - true_range[both]))
    assert np.median(np.concatenate(gaps)) < 0.01
    masks = ed.self_occlusion_masks(views, 0.5)
    assert set(masks) == set(ROLES) and all(0 < m.mean() < 0.5 for m in masks.values())


def test_frames_of_a_sequence_without_studio_are_ego_ids(tiny_capture, oracle_calibration):
    sequence = Capture(tiny_capture).sequence("wild")
    frames, posed = ed.usable_frames(oracle_calibration, sequence, ROLES)
    np.testing.assert_array_equal(frames, sequence.ego_frame_ids)
    assert posed.all()


def test_training_reduces_the_loss_and_beats_a_constant_depth(trained_model):
    from egorelight_cli.stages.egodepth_commands import load_depth_model

    manifest = json.loads((trained_model / "manifest.json").read_text())
    assert manifest["kind"] == "egorelight/model"
    m = manifest["metrics"]
    assert m["loss_last"] < 0.5 * m["loss_first"]
    # on its training views the network is far better than the constant training-median range
    assert m["train_log_range_l1"] < 0.6 * m["train_log_range_l1_constant_baseline"]
    assert m["train_mask_iou"] > 0.5
    assert (trained_model / "curve.png").is_file()
    model, masks, extra, _ = load_depth_model(trained_model, ROLES)
    assert extra["roles"] == list(ROLES) and set(masks) == set(ROLES)


def test_pointcloud_artifact_and_metrics(net_cloud, tiny_capture, oracle_calibration):
    cloud, artifact = load_pointcloud(net_cloud)
    cfg_points = artifact.manifest["config"]["pointcloud"]["points"]
    capture = Capture(tiny_capture)
    sequence = capture.sequence("test")
    np.testing.assert_array_equal(cloud.frame_ids, sequence.content_frame_ids)
    assert cloud.points.shape == (len(cloud.frame_ids), cfg_points, 3)
    assert cloud.valid.mean() > 0.5
    np.testing.assert_allclose(np.linalg.norm(cloud.normals[cloud.valid], axis=1), 1.0, atol=1e-4)
    m = artifact.metrics
    for key in ("depth_absrel", "depth_rmse_cm", "point_to_surface_cm", "sgbm_depth_absrel", "sgbm_point_to_surface_cm"):
        assert np.isfinite(m[key]), key
    assert m["point_to_surface_median_cm"] < 3.0
    assert (net_cloud / "preview.png").is_file() and (net_cloud / "preview_pointcloud.png").is_file()
    # the depth EXRs unproject (z = (K Pi H)^-1 d) onto the stored points
    frame = int(cloud.frame_ids[0])
    points, _ = cloud.frame(frame)
    from scipy.spatial import cKDTree

    from egorelight_cli.geometry.depth import unproject_depth

    unprojected = []
    for role in ROLES:
        depth = read_exr(net_cloud / "depth" / role / f"{frame:06d}.exr").channels["Z"]
        camera = posed_ego_camera(capture, oracle_calibration, role, "test", frame)
        p, valid = unproject_depth(camera, depth)
        unprojected.append(p[valid])
    gap, _ = cKDTree(np.concatenate(unprojected)).query(points)
    assert gap.max() < 1e-4
    # normals face the cameras that saw the points
    centre = np.mean([posed_ego_camera(capture, oracle_calibration, r, "test", frame).centre_world for r in ROLES], 0)
    _, normals = cloud.frame(frame)
    assert np.mean(np.sum(normals * (centre - points), axis=1) > 0) > 0.95


def test_sgbm_method_needs_no_model(tiny_capture, oracle_calibration_artifact, tmp_path):
    out = tmp_path / "sgbm"
    assert run_cli("egodepth", "--preset", "tiny", "--method", "sgbm", "--capture", str(tiny_capture),
                   "--calibration", str(oracle_calibration_artifact), "--out", str(out)) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["metrics"]["method"] == "sgbm"
    assert manifest["metrics"]["depth_coverage"] > 0.05
    assert manifest["metrics"]["point_to_surface_median_cm"] < 3.0


def test_bad_inputs_give_one_line_errors(tiny_capture, oracle_calibration_artifact, trained_model, tmp_path, capsys):
    base = ["egodepth", "--preset", "tiny", "--capture", str(tiny_capture), "--calibration",
            str(oracle_calibration_artifact)]
    cases = [
        (base + ["--out", str(tmp_path / "a")], "needs --model"),
        (base + ["--model", str(trained_model), "--seq", "nope", "--out", str(tmp_path / "b")], "no sequence"),
        (base + ["--model", str(tiny_capture), "--out", str(tmp_path / "c")], "wrong artifact kind"),
        (["egodepth", "--capture", str(oracle_calibration_artifact), "--calibration", str(oracle_calibration_artifact),
          "--method", "sgbm", "--out", str(tmp_path / "d")], "wrong artifact kind"),
        (base + ["--model", str(trained_model), "--seq", "relight_train", "--out", str(tmp_path / "e")], "no ego"),
        (["train", "egodepth", "--preset", "tiny", "--capture", str(tiny_capture), "--calibration",
          str(oracle_calibration_artifact), "--set", "train.sequences=[handeye]", "--out", str(tmp_path / "f")],
         "no training frame"),
        (["train", "egodepth", "--capture", str(tiny_capture), "--calibration", str(oracle_calibration_artifact),
          "--backbone", str(tmp_path), "--out", str(tmp_path / "g")], "Depth-Anything"),
    ]
    for args, message in cases:
        capsys.readouterr()
        assert run_cli(*args) == 2, args
        err = capsys.readouterr().err.strip()
        assert err.startswith("egorelight: error:") and message in err and "\n" not in err, err


def test_random_crops_stay_inside_and_reach_the_borders():
    rows = torch.arange(32.0).view(1, 1, 32, 1).expand(1, 1, 32, 32)
    generator = torch.Generator().manual_seed(0)
    covered = torch.zeros(32)
    for _ in range(300):
        crop = ed._crop({"image": rows}, 16, generator)["image"]
        assert crop.shape[-2:] == (16, 16)
        covered[crop[0, 0, :, 0].long()] += 1
    assert covered[-1] > 0.25 * covered[16] and covered[0] > 0.25 * covered[16]


def test_egodepth_frame_shards_merge_into_the_single_run(tiny_capture, oracle_calibration_artifact, trained_model,
                                                         net_cloud, tmp_path):
    from tiny_models import assert_shards_merge_into

    args = ["egodepth", "--preset", "tiny", "--capture", str(tiny_capture), "--calibration",
            str(oracle_calibration_artifact), "--model", str(trained_model), "--seq", "test"]
    for count in (2, 4):
        parts = [tmp_path / f"part{i}of{count}" for i in range(count)]
        for i, part in enumerate(parts):
            assert run_cli(*args, "--shard", f"{i}/{count}", "--out", str(part)) == 0
        merged = assert_shards_merge_into(net_cloud, parts, tmp_path / f"merged{count}")
        assert merged["metrics"]["sgbm_depth_absrel"] > 0  # both methods' rows merged
