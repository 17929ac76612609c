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


def test_frames_without_ego_images_are_said_once_for_training_and_validation(tiny_capture, oracle_calibration,
                                                                             monkeypatch, capsys, tmp_path):
    """Training and validation views are two passes over the same frames; a frame without ego images
    is dropped from both and said once (it was said twice)."""
    from egorelight_cli import console

    monkeypatch.setattr(console, "_level", console.NORMAL)
    capture = Capture(tiny_capture)
    sequence = capture.sequence("test")
    missing = oracle_calibration.ego_frame_id("test", int(sequence.content_frame_ids[-1]))
    real = type(sequence).ego_image_path  # a frozen dataclass: patched on the class, for this test only
    monkeypatch.setattr(type(sequence), "ego_image_path",
                        lambda self, role, f: tmp_path / "absent.png" if f == missing else real(self, role, f))
    parts = {part: ed.supervision(capture, oracle_calibration, [sequence], ROLES, near_m=0.07, max_frames=1,
                                  validation_frames=1, part=part) for part in ("training", "validation")}
    assert all(len(views) == len(ROLES) for views in parts.values())
    assert {v.frame_id for v in parts["training"]}.isdisjoint(v.frame_id for v in parts["validation"])
    assert capsys.readouterr().err.count("are left out") == 1


def test_recon_supervision_agrees_with_the_true_body(tiny_capture, oracle_calibration):
    """The reconstruction rendered into the posed ego cameras (H inv(Pi), stream offset) lands on
    the true body: where both are hit the ranges agree to about a centimetre."""
    capture = Capture(tiny_capture)
    sequence = capture.sequence("test")
    views = ed.supervision(capture, oracle_calibration, [sequence], ROLES, near_m=0.07)
    assert len(views) == 2 * len(sequence.content_frame_ids)
    truth = ed.GroundTruth(capture, oracle_calibration, sequence, 0.05)
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


def test_a_sequence_without_a_valid_head_pose_is_an_error(tiny_capture, oracle_calibration):
    """Every pose flagged (a failed head tracking): an error naming the calibration, not a point
    cloud of no point (egodepth) or all-NaN keypoints (egopose), exit 0."""
    import dataclasses

    from egorelight_cli.errors import EgorelightError
    from egorelight_cli.stages.egopose import frame_table

    poses = oracle_calibration.head_poses["test"]
    flagged = dataclasses.replace(oracle_calibration, head_poses={
        **oracle_calibration.head_poses, "test": dataclasses.replace(poses, valid=np.zeros_like(poses.valid))})
    capture = Capture(tiny_capture)
    with pytest.raises(EgorelightError, match="has a valid head pose"):
        ed.usable_frames(flagged, capture.sequence("test"), ROLES)
    with pytest.raises(EgorelightError, match="has a valid head pose"):
        frame_table(capture, flagged, "test")


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
    # the headset-only ego_bulk (purpose ego_train, no reconstructions) supervises nothing
    assert m["training_sequences"] == ["ego_train"]


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
    for key in ("depth_absrel", "depth_rmse_cm", "point_to_surface_cm", "sgbm_depth_absrel", "sgbm_point_to_surface_cm",
                "depth_absrel_common", "sgbm_depth_absrel_common"):
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
        (base + ["--method", "sgbm", "--model", str(trained_model), "--out", str(tmp_path / "h")], "reads no model"),
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


def test_every_file_of_the_backbone_folder_enters_the_cache_key(tmp_path):
    from egorelight_cli.errors import EgorelightError
    from egorelight_cli.stages.egodepth_commands import backbone_sources

    folder = tmp_path / "depth-anything"
    folder.mkdir()
    (folder / "model.safetensors").write_bytes(b"weights")
    with pytest.raises(EgorelightError, match="config.json"):
        backbone_sources(folder)
    (folder / "config.json").write_text("{}")
    (folder / "sub").mkdir()
    (folder / "sub" / "preprocessor_config.json").write_text("{}")
    assert backbone_sources(folder) == [folder / "config.json", folder / "model.safetensors",
                                        folder / "sub" / "preprocessor_config.json"]
    assert backbone_sources(None) == []


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


class _FixedDepthNet(torch.nn.Module):
    """A stand-in network with fixed outputs (log range, body logit, log scale)."""

    stereo_input = False

    def __init__(self, log_range, logit, log_scale):
        super().__init__()
        self.outputs = (log_range, logit, log_scale)

    def forward(self, image, rays, prior=None, stereo=None):
        return self.outputs


def test_laplace_depth_loss_is_minimised_at_the_mean_absolute_error():
    """With the uncertainty, the depth term adds the Laplace NLL |e|/b + log b over the supervised
    pixels: for one b shared by all pixels it is smallest at b = mean |e| (analytic), and it
    sends no gradient into the range (the error is detached)."""
    generator = torch.Generator().manual_seed(0)
    target = torch.rand(1, 1, 8, 8, generator=generator) - 1.0
    error = torch.randn(1, 1, 8, 8, generator=generator) * 0.2
    supervised = torch.rand(1, 1, 8, 8, generator=generator) < 0.6
    batch = {"image": torch.zeros(1, 3, 8, 8), "rays": torch.zeros(1, 3, 8, 8), "log_range": target,
             "supervised": supervised, "inside": torch.ones(1, 1, 8, 8, dtype=torch.bool)}
    mean_abs = float(error.abs()[supervised].mean())
    scales = np.linspace(0.3, 3.0, 271) * mean_abs
    nll = [float(ed.depth_losses(_FixedDepthNet(target + error, torch.zeros(1, 1, 8, 8),
                                                torch.full((1, 1, 8, 8), float(np.log(b)))), batch)["depth"])
           for b in scales]
    assert scales[int(np.argmin(nll))] == pytest.approx(mean_abs, rel=0.01)
    log_range = (target + error).requires_grad_()
    log_scale = torch.full((1, 1, 8, 8), -3.0, requires_grad=True)
    losses = ed.depth_losses(_FixedDepthNet(log_range, torch.zeros(1, 1, 8, 8), log_scale), batch)
    grad_nll = torch.autograd.grad(losses["scale_nll"], log_range, retain_graph=True, allow_unused=True)[0]
    (grad_depth,) = torch.autograd.grad(losses["depth"], log_range)
    assert grad_nll is None
    np.testing.assert_allclose(grad_depth.numpy(), (torch.sign(error) * supervised / supervised.sum()).numpy(), atol=1e-7)
    plain = ed.depth_losses(_FixedDepthNet(target + error, torch.zeros(1, 1, 8, 8), None), batch)
    assert float(plain["depth"]) == pytest.approx(mean_abs, rel=1e-5) == float(plain["depth_l1_log"])


def test_prediction_drops_pixels_the_network_expects_to_be_wrong(tiny_capture, oracle_calibration):
    capture = Capture(tiny_capture)
    sequence = capture.sequence("test")
    frame = int(sequence.content_frame_ids[0])
    views = [ed.load_view(capture, oracle_calibration, sequence, r, frame) for r in ROLES]
    camera = views[0].camera
    ray_maps = {r: ed.camera_ray_map(capture.ego_camera(r)) for r in ROLES}
    shape = (2, 1, camera.height, camera.width)
    log_scale = torch.full(shape, float(np.log(0.05)))
    log_scale[..., : camera.width // 2] = float(np.log(0.2))  # the left half is uncertain
    model = _FixedDepthNet(torch.full(shape, float(np.log(0.4))), torch.full(shape, 5.0), log_scale)
    settings = ed.PredictSettings(0.5, 0.07, 3.0, 0.0, 0.1)
    ranges = ed.predict_ranges_net(model, views, ray_maps, {}, settings, torch.device("cpu"))
    for role in ROLES:
        inside = ray_maps[role][1]
        assert not ranges[role][:, : camera.width // 2].any()
        np.testing.assert_allclose(ranges[role][:, camera.width // 2:][inside[:, camera.width // 2:]], 0.4, rtol=1e-6)
    off = ed.predict_ranges_net(model, views, ray_maps, {}, ed.PredictSettings(0.5, 0.07, 3.0, 0.0, 0.0),
                                torch.device("cpu"))
    assert (off[ROLES[0]] > 0).sum() == ray_maps[ROLES[0]][1].sum()


def test_network_beats_sgbm_on_held_out_frames(net_cloud):
    """On test (frames the network never saw), against SGBM on the same frames: lower AbsRel and
    point-to-surface distance over what each covers, and lower AbsRel on the pixels both cover."""
    m = json.loads((net_cloud / "manifest.json").read_text())["metrics"]
    assert m["depth_absrel"] < 0.8 * m["sgbm_depth_absrel"]
    assert m["depth_absrel_common"] < m["sgbm_depth_absrel_common"]
    assert m["point_to_surface_cm"] < 0.8 * m["sgbm_point_to_surface_cm"]
    assert m["depth_coverage"] > 0.5 * m["sgbm_depth_coverage"]


def test_common_pixel_absrel_is_taken_where_both_methods_have_depth():
    from egorelight_cli.stages.egodepth_scores import DepthScores, depth_metrics

    truth = np.full((2, 4), 0.5, np.float32)
    mask = np.ones((2, 4), bool)
    net = np.array([[0.55, 0.55, 0.6, 0.0], [0.5, 0.5, 0.0, 0.0]], np.float32)  # AbsRel 0.1 0.1 0.2 - 0 0 - -
    sgbm = np.array([[0.45, 0.0, 0.5, 1.0], [0.0, 0.6, 0.0, 0.0]], np.float32)  # AbsRel 0.1 - 0 1 - 0.2 - -
    scores = {"": DepthScores(1, 3), "sgbm_": DepthScores(1, 3)}
    scores[""].add_frame(0, {"a": net}, {"a": (truth, mask)}, np.zeros(0), other={"a": sgbm})
    scores["sgbm_"].add_frame(0, {"a": sgbm}, {"a": (truth, mask)}, np.zeros(0), other={"a": net})
    rows = {k: v for s in ("", "sgbm_") for k, v in scores[s].arrays(s).items()}
    ours, theirs = depth_metrics(rows, ""), depth_metrics(rows, "sgbm_")
    assert ours["depth_common_coverage"] == theirs["sgbm_depth_common_coverage"] == pytest.approx(3 / 8)  # (0,0) (0,2) (1,1)
    assert ours["depth_absrel_common"] == pytest.approx((0.1 + 0.2 + 0.0) / 3, rel=1e-5)
    assert theirs["sgbm_depth_absrel_common"] == pytest.approx((0.1 + 0.0 + 0.2) / 3, rel=1e-5)
    assert ours["depth_absrel"] == pytest.approx(0.4 / 5, rel=1e-5)
    assert theirs["sgbm_depth_absrel"] == pytest.approx(1.3 / 4, rel=1e-5)
