"""``animate --fit-recon`` / ``--fit-truth`` (stages/animate_fit.py): the character's mesh deformed onto
the capture's reconstruction or a true surface."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from egorelight_cli.geometry.cameras import transform_points
from egorelight_cli.geometry.depth_encoding import skinned_template
from egorelight_cli.structures.mesh_sequence import MeshSequence, SurfaceSequence
from tiny_models import cli_exit_code as _run


@pytest.fixture(scope="module")
def skinning(character):
    """An untrained (zero-output) animate model and its skinned prediction of two posed frames."""
    from egorelight_cli.stages.animate import AnimationModel, DepthSettings, NetSettings

    rng = np.random.default_rng(5)
    theta = np.tile(character.rest_theta, (2, 1)).astype(np.float64)
    theta[:, 6:] += rng.normal(scale=0.1, size=theta[:, 6:].shape)
    model = AnimationModel(character, NetSettings(uv_resolution=32, base_channels=4, hidden=8), DepthSettings())
    vertices = skinned_template(character, theta).vertices.astype(np.float32)
    N, V = character.graph.num_nodes, character.num_vertices
    meshes = MeshSequence(vertices, character.faces, theta, np.zeros((2, N, 3)), np.zeros((2, N, 3)),
                          np.zeros((2, V, 3)), np.array([3, 4]), 10.0)
    return model, meshes


def _settings(steps: int):
    from egorelight_cli.stages.animate import TrainSettings
    from egorelight_cli.stages.animate_fit import FitSettings

    return TrainSettings(), FitSettings(steps=steps, recon_steps=steps, lr=0.05, chunk=8, target_points=6000)


def test_a_surface_moved_1_cm_is_followed_to_a_millimetre(character, skinning):
    from egorelight_cli.stages.animate_fit import fit_to_surface, true_targets

    model, meshes = skinning
    shift = np.eye(4)
    shift[:3, 3] = [0.004, 0.01, -0.003]  # 1.1 cm, well inside the Chamfer's 8 cm pair cut
    moved = transform_points(shift, meshes.vertices.astype(np.float64))
    truth = SurfaceSequence(moved[:1], character.faces, meshes.frame_ids[:1])  # the truth has frame 3 only
    targets = true_targets(truth, meshes.frame_ids, 6000, np.eye(4))
    assert sorted(targets) == [3]
    fitted, summary = fit_to_surface(model, meshes, targets, *_settings(120))
    assert summary["fit_frames"] == 1
    assert summary["fit_chamfer_cm_after"] < 0.25 * summary["fit_chamfer_cm_before"]
    assert 0.3 < summary["fit_chamfer_cm_before"] < 1.2  # point-to-plane: ~|cos| of the shift
    error_cm = 100 * np.linalg.norm(fitted.vertices[0] - moved[0], axis=1)
    assert np.median(error_cm) < 0.1 and error_cm.mean() < 0.2
    # the frame without a truth keeps its prediction, and the arrays stay one consistent posing
    np.testing.assert_array_equal(fitted.vertices[1], meshes.vertices[1])
    reposed, _ = model.pose(torch.as_tensor(fitted.theta[:1], dtype=torch.float32),
                            *(torch.as_tensor(a[:1]) for a in (fitted.eg_rotation, fitted.eg_translation,
                                                               fitted.offsets)))
    np.testing.assert_allclose(reposed.numpy()[0], fitted.vertices[0], atol=1e-5)


def test_the_targets_are_taken_into_the_frame_of_the_meshes(character, skinning):
    from egorelight_cli.stages.animate_fit import true_targets

    _, meshes = skinning
    truth = SurfaceSequence(meshes.vertices, character.faces, meshes.frame_ids)
    T = np.eye(4)
    T[:3, 3] = [1.0, -2.0, 0.5]
    plain = true_targets(truth, meshes.frame_ids, 500, np.eye(4), seed=1)
    moved = true_targets(truth, meshes.frame_ids, 500, T, seed=1)
    for fid in (3, 4):
        np.testing.assert_allclose(moved[fid][0].numpy(), plain[fid][0].numpy() + T[:3, 3], atol=1e-5)
        np.testing.assert_allclose(np.linalg.norm(moved[fid][1].numpy(), axis=1), 1.0, atol=1e-5)


@pytest.fixture(scope="module")
def tiny_skinning_model(tiny_capture, tmp_path_factory):
    """A no-depth animate model trained one step on the tiny capture (near-zero output: skinning)."""
    model = tmp_path_factory.mktemp("fit") / "model"
    gt = Path(tiny_capture) / "groundtruth"
    assert _run("--preset", "tiny", "-q", "--set", "train.steps=1", "train", "animate", "--capture", tiny_capture,
                "--motion", gt / "ego_train" / "motion.npz", "--no-depth", "--out", model) == 0
    return model


def _fit_on_tiny(tiny_capture, model, out, *options) -> dict:
    gt = Path(tiny_capture) / "groundtruth"
    assert _run("--preset", "tiny", "-q", "--set", "fit.steps=40", "--set", "fit.recon_steps=40", "animate", "--no-depth", "--motion",
                gt / "test" / "motion.npz", "--model", model, "--capture", tiny_capture, *options,
                "--out", out) == 0
    return json.loads((out / "manifest.json").read_text())


def _one_line_error(capsys, tiny_capture, model, out, *options) -> str:
    capsys.readouterr()
    code = _run("--preset", "tiny", "animate", "--no-depth", "--motion",
                Path(tiny_capture) / "groundtruth" / "test" / "motion.npz", "--model", model, *options, "--out", out)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("egorelight: error: ")
    assert not out.exists()
    return err[0]


def test_fit_truth_on_tiny_lands_on_the_true_surface(tiny_capture, tiny_skinning_model, tmp_path, capsys):
    """The skinned prediction fitted to the tiny capture's truth, 40 steps."""
    manifest = _fit_on_tiny(tiny_capture, tiny_skinning_model, tmp_path / "meshes_fit", "--fit-truth")
    metrics = manifest["metrics"]
    assert metrics["fitted_to_groundtruth"] is True and metrics["fitted_to"] == "truth"
    assert metrics["fit_frames"] == metrics["eval_frames"] > 0
    assert metrics["fit_chamfer_cm_after"] < 0.5 * metrics["fit_chamfer_cm_before"]
    # the written meshes (scored as no_depth) lie far closer to the truth than skinning, both ways
    for measure in ("pred_to_true", "true_to_pred"):
        assert metrics[f"no_depth_p2s_{measure}_cm"] < 0.6 * metrics[f"skinning_p2s_{measure}_cm"], measure
    assert manifest["config"]["options"]["fit_truth"] is True
    # without a capture to fit to: one line, exit 2, nothing written
    assert "--fit-truth" in _one_line_error(capsys, tiny_capture, tiny_skinning_model, tmp_path / "nothing",
                                            "--fit-truth")


def test_fit_recon_on_tiny_moves_the_meshes_towards_the_truth(tiny_capture, tiny_skinning_model, tmp_path, capsys):
    """Fitted to the reconstructions (noisy, decimated, smoothed: what a lightstage records), the
    meshes land nearer the truth they were never shown than the skinned prediction."""
    manifest = _fit_on_tiny(tiny_capture, tiny_skinning_model, tmp_path / "meshes_recon", "--fit-recon")
    metrics = manifest["metrics"]
    assert metrics["fitted_to"] == "recon" and metrics["fitted_to_groundtruth"] is False
    assert 0 < metrics["fit_frames"] <= metrics["eval_frames"]  # the tiny capture reconstructs some frames
    assert metrics["fit_chamfer_cm_after"] < 0.5 * metrics["fit_chamfer_cm_before"]
    # scored over every frame, the unreconstructed ones still skinned (measured: 0.68 / 0.65 of skinning)
    for measure in ("pred_to_true", "true_to_pred"):
        assert metrics[f"no_depth_p2s_{measure}_cm"] < 0.8 * metrics[f"skinning_p2s_{measure}_cm"], measure
    assert manifest["config"]["options"]["fit_recon"] is True
    # a sequence without reconstructions, and both surfaces at once: one line each, nothing written
    error = _one_line_error(capsys, tiny_capture, tiny_skinning_model, tmp_path / "nothing", "--capture",
                            tiny_capture, "--seq", "wild", "--fit-recon")
    assert "--fit-recon" in error and "'wild'" in error
    error = _one_line_error(capsys, tiny_capture, tiny_skinning_model, tmp_path / "nothing", "--capture",
                            tiny_capture, "--fit-recon", "--fit-truth")
    assert "exclude each other" in error
    # a motion none of whose frames the sequence reconstructs (another sequence's): an error, not a
    # manifest that says fitted with nothing fitted
    from egorelight_cli.io.motion import read_motion_npz, write_motion_npz

    motion = read_motion_npz(Path(tiny_capture) / "groundtruth" / "test" / "motion.npz")
    shifted = tmp_path / "elsewhere.npz"
    write_motion_npz(shifted, dataclasses.replace(motion, frame_ids=motion.frame_ids + 100000))
    capsys.readouterr()
    out = tmp_path / "unfitted"
    assert _run("--preset", "tiny", "animate", "--no-depth", "--motion", shifted, "--model", tiny_skinning_model,
                "--capture", tiny_capture, "--seq", "test", "--fit-recon", "--out", out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no frame of the motion" in err[0] and "'test'" in err[0], err
    assert not out.exists()
