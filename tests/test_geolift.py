"""GeoLift: UV inputs, the network's baseline start, losses, and train/predict through the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from egorelight_cli.io.exr import read_exr
from egorelight_cli.io.mesh_sequence import read_meshes_npz
from egorelight_cli.nn.geolift_net import GeoLiftNet
from egorelight_cli.render.lighting import CaptureEnvmaps, light_intensities
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import rasterize_uv, texel_centres_uv
from egorelight_cli.render.uv_features import irradiance_map, light_transfer, texel_surface, texel_visibility
from egorelight_cli.stages import geolift as gl


@pytest.fixture(scope="module")
def raster(character):
    return rasterize_uv(character.face_uvs, 24)


def test_coarse_maps_tangent_frames_and_the_temporal_stack(character, raster):
    rng = np.random.default_rng(0)
    frames = np.stack([character.vertices + rng.normal(scale=0.002, size=character.vertices.shape) for _ in range(3)])
    coarse = gl.coarse_maps(raster, frames, character.faces, character.face_uvs)
    maps = coarse.normals
    assert maps.shape == (3, 3, 24, 24) and coarse.frames.shape == (3, 6, 24, 24)
    length = np.linalg.norm(maps, axis=1)
    np.testing.assert_allclose(length[:, raster.coverage], 1.0, atol=1e-5)
    assert not length[:, ~raster.coverage].any()
    # (t, b, n) is orthonormal at every covered texel, t along the UV's u direction
    t, b = coarse.frames[:, :3][:, :, raster.coverage], coarse.frames[:, 3:][:, :, raster.coverage]
    n = maps[:, :, raster.coverage]
    for x, y in ((t, t), (b, b)):
        np.testing.assert_allclose((x * y).sum(axis=1), 1.0, atol=1e-4)
    for x, y in ((t, b), (t, n), (b, n)):
        np.testing.assert_allclose((x * y).sum(axis=1), 0.0, atol=1e-4)
    first = gl.stacked_input(maps, 0)
    np.testing.assert_array_equal(first, np.concatenate([maps[0]] * 3))  # clamped at the sequence start
    np.testing.assert_array_equal(gl.stacked_input(maps, 2), np.concatenate([maps[0], maps[1], maps[2]]))
    # stacked sequences: the history stops at the frame's own sequence start
    np.testing.assert_array_equal(gl.stacked_input(maps, 2, first=1), np.concatenate([maps[1], maps[1], maps[2]]))
    inputs = gl.network_inputs(maps, np.array([0, 1, 1]))
    np.testing.assert_array_equal(inputs[1].numpy(), np.concatenate([maps[1]] * 3))


def test_untrained_network_returns_the_baselines(character, raster):
    coarse = gl.coarse_maps(raster, character.vertices[None], character.faces, character.face_uvs)
    init = np.random.default_rng(1).uniform(0.1, 0.9, size=(3, 24, 24))
    model = GeoLiftNet(base_channels=8, levels=2, uv_resolution=24, texture_init=init)
    normals, texture = gl.predict_maps(model, coarse, 0)
    covered = raster.coverage
    np.testing.assert_allclose(normals[:, covered], coarse.normals[0][:, covered], atol=1e-5)
    np.testing.assert_allclose(texture, init, rtol=1e-4)  # the per-texel start, not its mean


def test_learned_detail_is_a_tangent_space_normal_map_that_follows_the_surface(character, raster):
    """A per-texel detail ``D = (a, 0, 0)`` tilts the normal towards the UV tangent by atan(a),
    and under a rigid motion of the mesh the lifted normals move with it (the U-Net part is zero)."""
    from scipy.spatial.transform import Rotation

    model = GeoLiftNet(base_channels=8, levels=2, uv_resolution=24)
    with torch.no_grad():
        model.detail[:, 0] = 0.5
    rotation = Rotation.from_euler("xyz", [0.4, -1.1, 0.7]).as_matrix()
    rest = gl.coarse_maps(raster, character.vertices[None], character.faces, character.face_uvs)
    moved = gl.coarse_maps(raster, (character.vertices @ rotation.T)[None], character.faces, character.face_uvs)
    covered = raster.coverage
    lifted_rest = gl.predict_maps(model, rest, 0)[0][:, covered]
    lifted_moved = gl.predict_maps(model, moved, 0)[0][:, covered]
    tilt = np.degrees(np.arccos(np.clip((lifted_rest * rest.normals[0][:, covered]).sum(0), -1, 1)))
    np.testing.assert_allclose(tilt, np.degrees(np.arctan(0.5)), atol=1e-3)
    assert ((lifted_rest * rest.frames[0][:3][:, covered]).sum(0) > 0).all()  # towards +t
    np.testing.assert_allclose(rotation @ lifted_rest, lifted_moved, atol=2e-5)


def test_detail_loss_asks_for_structure_not_values():
    generator = torch.Generator().manual_seed(0)
    estimate = torch.nn.functional.normalize(torch.randn(12, 3, generator=generator), dim=1)
    valid = torch.ones(12, dtype=torch.bool)
    right = torch.tensor([1, 2, 3, -1, 5, 6, 7, -1, 9, 10, 11, -1])
    down = torch.tensor([4, 5, 6, 7, 8, 9, 10, 11, -1, -1, -1, -1])
    shifted = estimate + torch.tensor([0.3, -0.2, 0.1])  # same structure, other values
    assert float(gl.detail_loss(shifted, estimate, valid, [right, down])) == pytest.approx(0.0, abs=1e-7)
    flat = estimate.mean(0, keepdim=True).expand(12, 3)  # right values on average, no structure
    assert float(gl.detail_loss(flat, estimate, valid, [right, down])) > 0.1
    invalid = valid.clone()
    invalid[:] = False
    assert float(gl.detail_loss(shifted * 5, estimate, invalid, [right, down])) == 0.0


def test_mean_texture_averages_what_each_texel_saw():
    uv = texel_centres_uv((4, 4))[1, 2][None].astype(np.float32)  # the texel (row 1, column 2)
    views = [gl.TrainView(0, uv, np.array([[c, 0.0, 1.0]], np.float32), *([np.zeros((1, 3), np.float32),
                                                                             np.zeros(1, bool)] * 2),
                          np.array([-1]), np.array([-1])) for c in (0.2, 0.6)]
    texture = gl.mean_texture(views, (4, 4))
    np.testing.assert_allclose(texture[:, 1, 2], [0.4, 0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(texture[:, 0, 0], [0.4, 0.0, 1.0], atol=1e-6)  # unseen: the overall mean


@pytest.fixture(scope="module")
def trained_geolift(tiny_capture, skinned_meshes, tmp_path_factory):
    from egorelight_cli.cli import main

    out = tmp_path_factory.mktemp("geolift") / "model"
    meshes = skinned_meshes / "relight_train.npz"
    with pytest.raises(SystemExit) as exit_info:
        main(["--preset", "tiny", "--set", "train.steps=30", "-q", "train", "geolift", "--capture", str(tiny_capture),
              "--meshes", str(meshes), "--out", str(out)])
    assert exit_info.value.code == 0
    return out


def test_train_geolift_writes_a_model_with_baselines(trained_geolift):
    manifest = json.loads((trained_geolift / "manifest.json").read_text())
    metrics = manifest["metrics"]
    assert manifest["kind"] == "egorelight/model" and metrics["training_views"] > 0 and metrics["validation_views"] > 0
    for key in ("val_rgb_l1", "val_rgb_l1_mean_texture", "val_normal_deg", "val_normal_deg_coarse"):
        assert np.isfinite(metrics[key]), key
    assert metrics["loss_last"] < metrics["loss_first"]
    assert "substitute" in metrics["detail_loss"]
    assert manifest["runtime"]["device"] == "cpu"


def test_geolift_writes_uvmaps_with_lighting_features_and_scores(tiny_capture, skinned_meshes, trained_geolift,
                                                                 tmp_path, run, character):
    meshes_path = skinned_meshes / "test.npz"
    out = tmp_path / "uvmaps"
    result = run("--preset", "tiny", "geolift", "--meshes", meshes_path, "--model", trained_geolift,
                 "--capture", tiny_capture, "--seq", "test", "--out", out)
    assert result.returncode == 0, result.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    meshes = read_meshes_npz(meshes_path)
    assert manifest["metrics"]["frames"] == meshes.num_frames
    for key in ("normal_deg", "normal_deg_coarse", "texture_l1", "texture_l1_mean_texture"):
        assert np.isfinite(manifest["metrics"][key]), key
    assert (out / "preview.png").is_file()
    # the lighting features of a frame are exactly rho/chi of its lifted normals under its lighting
    f = int(meshes.frame_ids[-1])
    exr = read_exr(out / "maps" / f"{f:06d}.exr")
    normals = exr.layer("normal")
    resolution = normals.shape[:2]
    uv_raster = rasterize_uv(character.face_uvs, resolution)
    np.testing.assert_array_equal(exr.layer("coverage")[..., 0] > 0, uv_raster.coverage)
    vertices = meshes.vertices[-1]
    surface = texel_surface(uv_raster, vertices, character.faces)
    stage = LightStage.from_json(tiny_capture / "rig" / "lights.json")
    from egorelight_cli.io.capture import Capture

    entry = Capture(tiny_capture).sequence("test").light_entry(f)
    lifted = normals[uv_raster.coverage].astype(np.float64)
    lifted /= np.linalg.norm(lifted, axis=1, keepdims=True)
    transfer = light_transfer(surface.points, lifted, stage, texel_visibility(vertices, character.faces, surface, stage))
    chi = irradiance_map(transfer, stage, light_intensities(stage, entry, CaptureEnvmaps(tiny_capture))).numpy()
    np.testing.assert_allclose(exr.layer("diffuse")[uv_raster.coverage], chi, rtol=2e-3, atol=1e-5)
    shadow = exr.layer("shadow")[..., 0]
    assert shadow.min() >= 0 and (shadow[uv_raster.coverage] > 0).mean() > 0.9
    # the same meshes with another --seq is another output, not "up to date"
    result = run("--preset", "tiny", "geolift", "--meshes", meshes_path, "--model", trained_geolift,
                 "--capture", tiny_capture, "--seq", "relight_train", "--out", out)
    assert result.returncode == 0, result.stderr
    assert json.loads((out / "manifest.json").read_text())["metrics"]["sequence"] == "relight_train"


def test_the_baseline_maps_in_the_networks_place_score_as_the_baselines(tiny_capture, skinned_meshes,
                                                                        trained_geolift, tmp_path, run):
    """``predict.normals=coarse`` / ``predict.texture=mean`` (the paper's "w/o GeoLiftingNet"): the
    uvmaps carry the baselines, so each map's error is its baseline's."""
    meshes_path = skinned_meshes / "test.npz"
    result = run("--preset", "tiny", "--set", "predict.normals=coarse", "--set", "predict.texture=mean", "geolift",
                 "--meshes", meshes_path, "--model", trained_geolift, "--capture", tiny_capture, "--seq", "test",
                 "--out", tmp_path / "baseline")
    assert result.returncode == 0, result.stderr
    metrics = json.loads((tmp_path / "baseline" / "manifest.json").read_text())["metrics"]
    assert metrics["normals_from"] == "coarse" and metrics["texture_from"] == "mean"
    for key, baseline in (("normal_deg", "normal_deg_coarse"), ("normal_deg_uv", "normal_deg_uv_coarse"),
                          ("texture_l1", "texture_l1_mean_texture"), ("texture_l1_uv", "texture_l1_uv_mean_texture")):
        assert metrics[key] == pytest.approx(metrics[baseline], rel=1e-6), key
    result = run("--preset", "tiny", "--set", "predict.normals=true", "geolift", "--meshes", meshes_path, "--model",
                 trained_geolift, "--out", tmp_path / "bad")
    assert result.returncode == 2 and "predict.normals" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "bad").exists()


def test_train_geolift_resumes_an_interrupted_run_to_the_same_model(tiny_capture, skinned_meshes, tmp_path,
                                                                   monkeypatch):
    """Ctrl-C in step 3 of 4 (checkpoints every 2 steps; two views per step: two loss calls), then
    --resume, gives the weights of one uninterrupted run."""
    from tiny_models import assert_resumes_to_the_same_model

    args = ["--preset", "tiny", "-q", "--set", "train.steps=4", "--set", "train.checkpoint_every=2", "train", "geolift",
            "--capture", tiny_capture, "--meshes", skinned_meshes / "relight_train.npz"]
    assert_resumes_to_the_same_model(args, tmp_path / "resumed", tmp_path / "whole", monkeypatch, gl, "view_losses",
                                     fail_at_call=5, resumed_from_call=4)


def test_train_geolift_pairs_meshes_with_sequences(tiny_capture, skinned_meshes, tmp_path, run):
    result = run("--preset", "tiny", "train", "geolift", "--capture", tiny_capture, "--meshes",
                 skinned_meshes / "relight_train.npz", "--meshes", skinned_meshes / "ego_train.npz", "--seq",
                 "relight_train", "--out", tmp_path / "m")
    assert result.returncode == 2 and "--seq" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    result = run("--preset", "tiny", "-q", "--set", "train.steps=2", "train", "geolift", "--capture", tiny_capture,
                 "--meshes", skinned_meshes / "relight_train.npz", "--seq", "relight_train",
                 "--meshes", skinned_meshes / "ego_train.npz", "--seq", "ego_train", "--out", tmp_path / "both")
    assert result.returncode == 0, result.stderr
    metrics = json.loads((tmp_path / "both" / "manifest.json").read_text())["metrics"]
    assert metrics["sequences"] == ["relight_train", "ego_train"] and metrics["validation_views"] > 0


def test_geolift_errors_are_one_line(tiny_capture, skinned_meshes, trained_geolift, tmp_path, run):
    meshes_path = skinned_meshes / "test.npz"
    other = tmp_path / "other.npz"
    meshes = read_meshes_npz(meshes_path)
    from egorelight_cli.io.mesh_sequence import MeshSequence, write_meshes_npz

    write_meshes_npz(other, MeshSequence(meshes.vertices[:, :100], np.zeros((1, 3), np.int32), meshes.theta,
                                         meshes.eg_rotation, meshes.eg_translation, meshes.offsets[:, :100],
                                         meshes.frame_ids))
    result = run("--preset", "tiny", "geolift", "--meshes", other, "--model", trained_geolift, "--out", tmp_path / "a")
    assert result.returncode == 2 and "vertices" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    result = run("--preset", "tiny", "geolift", "--meshes", meshes_path, "--model", tiny_capture, "--out", tmp_path / "b")
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_geolift_frame_shards_merge_into_the_single_run(tiny_capture, skinned_meshes, trained_geolift, tmp_path):
    from tiny_models import assert_shards_merge_into, cli_exit_code

    args = ["--preset", "tiny", "-q", "geolift", "--meshes", skinned_meshes / "test.npz", "--model", trained_geolift,
            "--capture", tiny_capture, "--seq", "test"]
    assert cli_exit_code(*args, "--out", tmp_path / "whole") == 0
    for count in (2, 4):
        parts = [tmp_path / f"part{i}of{count}" for i in range(count)]
        for i, part in enumerate(parts):
            assert cli_exit_code(*args, "--shard", f"{i}/{count}", "--out", part) == 0
        merged = assert_shards_merge_into(tmp_path / "whole", parts, tmp_path / f"merged{count}")
        assert merged["metrics"]["normal_deg"] is not None
