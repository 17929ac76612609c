"""train relight / relight through the CLI on the tiny capture (the character skinned with the true motion
stands in for tracking)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from egorelight_cli.io.exr import read_exr
from tiny_models import cli_exit_code as _main, tiny_geolift_uvmaps  # the CLI in-process, shared setup


@pytest.fixture(scope="module")
def relight_inputs(tiny_capture, skinned_meshes, tmp_path_factory):
    """A tiny geolift model and uvmaps (with lighting features) of relight_train and test."""
    root = tmp_path_factory.mktemp("relight")
    tiny_geolift_uvmaps(root, tiny_capture, skinned_meshes, ("relight_train", "test"))
    return root


@pytest.fixture(scope="module")
def relight_model(tiny_capture, skinned_meshes, relight_inputs):
    out = relight_inputs / "relight"
    assert _main("--preset", "tiny", "-q", "--set", "train.steps=40", "train", "relight", "--capture", tiny_capture,
                 "--meshes", skinned_meshes / "relight_train.npz", "--uvmaps",
                 relight_inputs / "uvmaps_relight_train", "--out", out) == 0
    return out


def test_a_tiny_relight_training_lowers_its_loss(relight_model):
    manifest = json.loads((relight_model / "manifest.json").read_text())
    metrics = manifest["metrics"]
    curve = json.loads((relight_model / "curve.json").read_text())
    assert np.mean([r["loss"] for r in curve[-5:]]) < np.mean([r["loss"] for r in curve[:5]])
    for key in ("val_psnr", "val_ssim", "val_lambert_psnr", "val_baked_psnr", "val_diffuse_only_psnr"):
        assert np.isfinite(metrics[key]), key
    assert metrics["val_lpips"] is None and "VGG" in metrics["id_mrf"]


def test_relight_renders_held_out_cameras_and_scores_them(tiny_capture, skinned_meshes, relight_inputs, relight_model,
                                                          tmp_path):
    out = tmp_path / "renders"
    code = _main("--preset", "tiny", "-q", "relight", "--capture", tiny_capture, "--meshes",
                 skinned_meshes / "test.npz", "--uvmaps", relight_inputs / "uvmaps_test",
                 "--model", relight_model, "--seq", "test", "--export", "ply", "--out", out)
    assert code == 0
    manifest = json.loads((out / "manifest.json").read_text())
    sequence = json.loads((tiny_capture / "sequences" / "test" / "sequence.json").read_text())
    assert manifest["metrics"]["cameras"] == sequence["held_out_cameras"]
    camera = sequence["held_out_cameras"][0]
    exrs = sorted((out / camera).glob("*.exr"))
    assert len(exrs) == manifest["metrics"]["views"] > 0
    exr = read_exr(exrs[0])
    colour, diffuse, specular = exr.layer("", ("R", "G", "B")), exr.layer("diffuse"), exr.layer("specular")
    np.testing.assert_allclose(colour, diffuse + specular, atol=1e-4)  # the passes add up (black background)
    assert (specular >= 0).all() and exr.layer("alpha").max() > 0.5
    assert (out / camera / exrs[0].name.replace(".exr", ".png")).is_file() and (out / "preview.png").is_file()
    for key in ("psnr", "ssim", "lambert_psnr", "baked_psnr"):
        assert np.isfinite(manifest["metrics"][key]), key
    assert 0 < manifest["metrics"]["head_excluded_fraction"] < 0.5
    from egorelight_cli.io.gaussian_ply import read_gaussian_ply

    gaussians, rgb = read_gaussian_ply(out / "gaussians" / exrs[0].name.replace(".exr", ".ply"))
    assert len(gaussians) > 100 and (rgb >= 0).all() and (rgb <= 1).all()
    # --cameras all is another output, not "up to date"
    code = _main("--preset", "tiny", "-q", "relight", "--capture", tiny_capture, "--meshes",
                 skinned_meshes / "test.npz", "--uvmaps", relight_inputs / "uvmaps_test",
                 "--model", relight_model, "--seq", "test", "--export", "ply", "--cameras", "all", "--out", out)
    assert code == 0
    assert len(json.loads((out / "manifest.json").read_text())["metrics"]["cameras"]) > len(sequence["held_out_cameras"])


def test_relight_needs_lighting_features(tiny_capture, skinned_meshes, relight_inputs, relight_model, tmp_path,
                                         capsys):
    # uvmaps made without --capture carry no rho/chi: a one-line error, no output
    plain = tmp_path / "plain_uvmaps"
    gt = skinned_meshes / "test.npz"
    assert _main("--preset", "tiny", "-q", "geolift", "--meshes", gt, "--model", relight_inputs / "geolift",
                 "--out", plain) == 0
    capsys.readouterr()
    code = _main("--preset", "tiny", "relight", "--capture", tiny_capture, "--meshes", gt, "--uvmaps", plain,
                 "--model", relight_model, "--out", tmp_path / "renders")
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "egorelight: error:" in err
    assert not (tmp_path / "renders").exists()
