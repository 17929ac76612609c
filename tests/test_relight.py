"""train relight / relight through the CLI on the tiny capture (the character skinned with the true motion
stands in for tracking)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from egorelight_cli.io.exr import read_exr
from tiny_models import assert_resumes_to_the_same_model, cli_exit_code as _main  # the CLI in-process

pytestmark = pytest.mark.slow  # handed out first under pytest-xdist (conftest)


@pytest.fixture(scope="module")
def relight_inputs(tiny_avatar):
    """A tiny geolift model and uvmaps (with lighting features) of relight_train and test: the
    session's (conftest.tiny_avatar; read-only)."""
    return tiny_avatar


@pytest.fixture(scope="module")
def relight_model(tiny_capture, skinned_meshes, relight_inputs, tmp_path_factory):
    out = tmp_path_factory.mktemp("relight") / "relight"
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


def test_train_relight_resumes_an_interrupted_run_to_the_same_model(tiny_capture, skinned_meshes, relight_inputs,
                                                                   tmp_path, monkeypatch):
    """Issue 18 ("resumable only on request"): Ctrl-C in step 3 of 4 (checkpoints every 2 steps),
    then --resume, gives the weights of one uninterrupted run (one view per step: one loss call)."""
    from egorelight_cli.stages import relight as rl

    args = ["--preset", "tiny", "-q", "--set", "train.steps=4", "--set", "train.checkpoint_every=2", "train", "relight",
            "--capture", tiny_capture, "--meshes", skinned_meshes / "relight_train.npz", "--uvmaps",
            relight_inputs / "uvmaps_relight_train"]
    assert_resumes_to_the_same_model(args, tmp_path / "resumed", tmp_path / "whole", monkeypatch, rl, "relight_loss",
                                     fail_at_call=3, resumed_from_call=2)


@pytest.mark.parametrize("albedo", ["gain", "texture"])
def test_a_learned_albedo_trains_saves_and_relights(tiny_capture, skinned_meshes, relight_inputs, albedo, tmp_path):
    from egorelight_cli.stages.relight_commands import load_relight_model

    model_dir = tmp_path / "relight"
    assert _main("--preset", "tiny", "-q", "--set", "train.steps=4", "--set", f"net.albedo={albedo}", "train",
                 "relight", "--capture", tiny_capture, "--meshes", skinned_meshes / "relight_train.npz", "--uvmaps",
                 relight_inputs / "uvmaps_relight_train", "--out", model_dir) == 0
    model, net, _ = load_relight_model(model_dir)
    size = net["uv_resolution"]
    assert model.config["albedo"] == albedo and model.albedo_map.shape == (3, size, size)
    learned = model.albedo_map.detach()
    # the gain starts at 0 and the texture at the training frames' albedo: four steps leave either near its start
    assert (float(learned.abs().max()) < 0.05) == (albedo == "gain")
    assert _main("--preset", "tiny", "-q", "relight", "--capture", tiny_capture, "--meshes",
                 skinned_meshes / "test.npz", "--uvmaps", relight_inputs / "uvmaps_test", "--model", model_dir,
                 "--seq", "test", "--out", tmp_path / "renders") == 0
    assert np.isfinite(json.loads((tmp_path / "renders" / "manifest.json").read_text())["metrics"]["psnr"])


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
    assert manifest["metrics"]["headset_excluded"].startswith("no")  # no --calibration: its pixels are scored
    # each body part of the character's segmentation is scored apart (the shiny garment: pants)
    for row in ("", "diffuse_only_", "lambert_", "baked_"):
        assert np.isfinite(manifest["metrics"]["parts"]["pants"][f"{row}psnr"]), row
    assert "olat_tail_psnr" in manifest["metrics"]["parts"]["pants"]
    assert not {"hair", "face"} & set(manifest["metrics"]["parts"])
    # the OLAT / group tail of test is rendered and scored apart from its HDR-lit frames
    from egorelight_cli.io.npz import read_npz

    rows, _ = read_npz(out / "scores.npz", check_finite=False)
    patterns = {str(p) for p in rows["light"]}
    assert patterns == {"envmap", "olat", "group"}
    envmap = rows["light"] == "envmap"
    assert manifest["metrics"]["psnr"] == pytest.approx(np.nanmean(rows["psnr"][envmap]))
    for pattern in ("olat", "group"):
        chosen = rows["light"] == pattern
        assert manifest["metrics"][f"{pattern}_tail_views"] == chosen.sum()
        assert manifest["metrics"][f"{pattern}_tail_lambert_psnr"] == pytest.approx(np.nanmean(rows["lambert_psnr"][chosen]))
    from egorelight_cli.io.gaussian_ply import read_gaussian_ply

    gaussians, rgb = read_gaussian_ply(out / "gaussians" / exrs[0].name.replace(".exr", ".ply"))
    assert len(gaussians) > 100 and (rgb >= -1e-6).all() and (rgb <= 1 + 1e-6).all()  # f_dc is float32
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


def test_relight_under_another_light_recomputes_the_features_and_scores_nothing(
        tiny_capture, skinned_meshes, relight_inputs, relight_model, character, tmp_path, capsys):
    from egorelight_cli.io.capture import open_capture
    from egorelight_cli.io.mesh_sequence import load_meshes
    from egorelight_cli.artifacts import open_artifact
    from egorelight_cli.stages.relight_commands import LightingOverride, RelightData

    # under the flat light the features are the flat-lit ones: the Lambert relighting of the
    # flat-lit texture is the texture itself (chi = pi rho s_flat up to the lights' colour gains,
    # the uvmaps' flat_scale is 1)
    capture, _ = open_capture(tiny_capture)
    meshes, _ = load_meshes(skinned_meshes / "test.npz")
    uvmaps = open_artifact(relight_inputs / "uvmaps_test", kind="uvmaps")
    resolution = read_exr(next((relight_inputs / "uvmaps_test" / "maps").glob("*.exr"))).shape[0]
    data = RelightData(capture, capture.sequence("test"), meshes, uvmaps, character, resolution, 1, 4,
                       LightingOverride.parse(True, None, None))
    frame = data.frame(int(meshes.frame_ids[0]))
    albedo = frame.maps[0:3].permute(1, 2, 0)[data.coverage]
    lit = frame.flat_irradiance[:, 0] > 0.05  # (texels in deep shadow are floored)
    relative = np.abs(frame.lambert[lit].numpy() / np.maximum(albedo[lit].numpy(), 1e-6) - 1)
    assert np.median(relative) < 0.02 and relative.max() < 0.15

    envmap = sorted((tiny_capture / "envmaps").glob("*.exr"))[0]
    for option in (["--flat"], ["--olat", "3"], ["--envmap", envmap, "--yaw", "30"]):
        out = tmp_path / f"renders_{option[0].strip('-')}"
        assert _main("--preset", "tiny", "-q", "relight", "--capture", tiny_capture, "--meshes",
                     skinned_meshes / "test.npz", "--uvmaps", relight_inputs / "uvmaps_test", "--model", relight_model,
                     "--seq", "test", *option, "--out", out) == 0
        metrics = json.loads((out / "manifest.json").read_text())["metrics"]
        assert metrics["scored"].startswith("no") and "psnr" not in metrics
        assert metrics["views"] == meshes.num_frames * len(metrics["cameras"])  # every frame, whatever its light
        assert option[0].strip("-") in metrics["lighting"]
    capsys.readouterr()
    for bad in (["--flat", "--olat", "1"], ["--olat", "100000"], ["--envmap", tmp_path / "missing.exr"],
                ["--yaw", "30"], ["--flat", "--yaw", "30"]):
        out = tmp_path / "renders_bad"
        code = _main("--preset", "tiny", "relight", "--capture", tiny_capture, "--meshes", skinned_meshes / "test.npz",
                     "--uvmaps", relight_inputs / "uvmaps_test", "--model", relight_model, *bad, "--out", out)
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and "egorelight: error:" in err, (bad, err)
        assert not out.exists()


def test_relight_into_named_and_virtual_cameras(tiny_capture, skinned_meshes, relight_inputs, relight_model,
                                                tmp_path, capsys):
    """A named studio camera is rendered and scored; a camera JSON that copies it under another
    name renders the same images, unscored (it captured nothing); bad selections are one-line
    errors with nothing written."""
    sequence = json.loads((tiny_capture / "sequences" / "test" / "sequence.json").read_text())
    name = sequence["held_out_cameras"][0]
    entry = next(c for c in json.loads((tiny_capture / "rig" / "studio_cameras.json").read_text())["cameras"]
                 if c["name"] == name)
    (tmp_path / "virtual.json").write_text(json.dumps({**entry, "name": "orbit"}))
    (tmp_path / "clash.json").write_text(json.dumps(entry))
    common = ("--preset", "tiny", "-q", "relight", "--capture", tiny_capture, "--meshes", skinned_meshes / "test.npz",
              "--uvmaps", relight_inputs / "uvmaps_test", "--model", relight_model, "--seq", "test")
    assert _main(*common, "--cameras", name, "--out", tmp_path / "named") == 0
    assert _main(*common, "--camera-json", tmp_path / "virtual.json", "--out", tmp_path / "virtual") == 0
    named = json.loads((tmp_path / "named" / "manifest.json").read_text())["metrics"]
    virtual = json.loads((tmp_path / "virtual" / "manifest.json").read_text())["metrics"]
    assert named["cameras"] == [name] and np.isfinite(named["psnr"])
    assert not (tmp_path / "named" / "gaussians").exists()  # no --export ply: no (empty) gaussians folder
    assert virtual["cameras"] == ["orbit"] and virtual["scored"].startswith("no") and "psnr" not in virtual
    frames = sorted(p.name for p in (tmp_path / "named" / name).glob("*.exr"))
    assert frames and frames == sorted(p.name for p in (tmp_path / "virtual" / "orbit").glob("*.exr"))
    np.testing.assert_array_equal(read_exr(tmp_path / "named" / name / frames[0]).layer("", ("R", "G", "B")),
                                  read_exr(tmp_path / "virtual" / "orbit" / frames[0]).layer("", ("R", "G", "B")))
    capsys.readouterr()
    for bad in (["--cameras", "nosuchcamera"], ["--camera-json", tmp_path / "clash.json"],
                ["--cameras", "all", "--camera-json", tmp_path / "virtual.json"],
                ["--camera-json", tmp_path / "missing.json"]):
        out = tmp_path / "bad"
        code = _main(*common[:2], *common[3:], *bad, "--out", out)
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and "egorelight: error:" in err, (bad, err)
        assert not out.exists()


@pytest.mark.parametrize("seq, lighting, counts", [
    ("relight_train", [], (2,)),    # its 2 HDR-lit frames, scored against the captured views
    ("test", ["--flat"], (2, 4)),   # every frame with a mesh (11), under a flat light: not scored
])
def test_relight_frame_shards_merge_into_the_single_run(tiny_capture, skinned_meshes, relight_inputs, relight_model,
                                                        tmp_path, seq, lighting, counts):
    from tiny_models import assert_shards_merge_into

    args = ["--preset", "tiny", "-q", "relight", "--capture", tiny_capture, "--meshes",
            skinned_meshes / f"{seq}.npz", "--uvmaps", relight_inputs / f"uvmaps_{seq}",
            "--model", relight_model, "--seq", seq, "--cameras", "all", *lighting]
    assert _main(*args, "--out", tmp_path / "whole") == 0
    metrics = json.loads((tmp_path / "whole" / "manifest.json").read_text())["metrics"]
    assert ("psnr" in metrics) == (not lighting)
    for count in counts:
        parts = [tmp_path / f"part{i}of{count}" for i in range(count)]
        for i, part in enumerate(parts):
            assert _main(*args, "--shard", f"{i}/{count}", "--out", part) == 0
        assert_shards_merge_into(tmp_path / "whole", parts, tmp_path / f"merged{count}")


@pytest.mark.parametrize("setting, says", [
    ("train.validation_fraction=0.9", "holds out all 2"),   # relight_train's 2 HDR-lit frames, none left
    ("train.validation_fraction=1.5", "validation_fraction"),
    ("net.attention_level=3", "attention_level"),           # the tiny U-Net has 2 levels
])
def test_train_relight_refuses_a_config_it_cannot_train(tiny_capture, skinned_meshes, relight_inputs, tmp_path,
                                                       capsys, setting, says):
    out = tmp_path / "relight"
    code = _main("--preset", "tiny", "--set", setting, "train", "relight", "--capture", tiny_capture, "--meshes",
                 skinned_meshes / "relight_train.npz", "--uvmaps", relight_inputs / "uvmaps_relight_train",
                 "--out", out)
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and err.startswith("egorelight: error:") and says in err, err
    assert not out.exists()


def test_relight_loss_takes_any_subject_mask():
    """A subject at the image's edge, a single pixel or none at all: the SSIM box still fits the window."""
    import torch

    from egorelight_cli.render.gaussians import GaussianRender
    from egorelight_cli.stages.relight import relight_loss

    rng = np.random.default_rng(4)
    colour, target = (torch.from_numpy(rng.uniform(0, 1, (40, 50, 3))) for _ in range(2))
    render = GaussianRender(colour=colour, alpha=torch.ones(40, 50), depth=torch.ones(40, 50),
                            passes={"diffuse": colour})
    for rows, cols in ((slice(0, 2), slice(10, 30)), (slice(39, 40), slice(49, 50)), (slice(0, 0), slice(0, 0))):
        mask = torch.zeros(40, 50, dtype=torch.bool)
        mask[rows, cols] = True
        terms = relight_loss(render, target, mask, torch.tensor(0.0), "linear")
        assert all(torch.isfinite(v) for v in terms.values())
        # nothing to compare in an empty mask; a subject pixel or more gives a positive loss
        assert (float(terms["ssim"]) > 0.0 and float(terms["l1"]) > 0.0) == bool(mask.any())


def test_relight_loss_terms_are_means_over_the_subject_whatever_the_framing():
    import torch

    from egorelight_cli.render.gaussians import GaussianRender
    from egorelight_cli.stages.relight import relight_loss

    rng = np.random.default_rng(3)
    colour, target = (torch.from_numpy(rng.uniform(0, 1, (30, 30, 3))) for _ in range(2))
    mask = torch.zeros(30, 30, dtype=torch.bool)
    mask[8:22, 10:20] = True

    def loss(pad: int, weights: dict | None = None) -> dict:
        grow = lambda x: torch.nn.functional.pad(x.permute(2, 0, 1), (pad,) * 4).permute(1, 2, 0)
        render = GaussianRender(colour=grow(colour), alpha=grow(torch.ones(30, 30, 1))[..., 0],
                                depth=grow(torch.ones(30, 30, 1))[..., 0], passes={"diffuse": grow(colour * 0.5)})
        return relight_loss(render, grow(target), grow(mask[..., None].double())[..., 0] > 0.5, torch.tensor(0.0),
                            "linear", weights)

    near, far = loss(0), loss(40)  # the same subject framed in a 30 or a 110 pixel image
    expected = float((colour - target).abs()[mask].mean())
    assert float(near["l1"]) == pytest.approx(expected) and float(far["l1"]) == pytest.approx(expected)
    assert float(far["diffuse"]) == pytest.approx(float((colour * 0.5 - target).abs()[mask].mean()))
    assert float(near["ssim"]) == pytest.approx(float(far["ssim"]))
    squared = float((colour - target).square()[mask].mean())  # the MSE a PSNR is computed from
    assert float(near["l2"]) == pytest.approx(squared) and float(far["l2"]) == pytest.approx(squared)
    weights = {"l1": 2.0, "ssim": 3.0, "reg": 0.0, "diffuse": 0.5, "l2": 7.0}
    assert float(loss(0, weights)["loss"]) == pytest.approx(sum(w * float(near[k]) for k, w in weights.items()))


def test_relight_with_a_calibration_leaves_the_headset_out_of_the_scores(
        tiny_capture, skinned_meshes, relight_inputs, relight_model, oracle_calibration, oracle_calibration_artifact,
        tmp_path):
    import dataclasses

    from egorelight_cli.errors import EgorelightError
    from egorelight_cli.io.capture import open_capture
    from egorelight_cli.io.npz import read_npz
    from egorelight_cli.stages.relight_eval import HeadsetExclusion

    out = tmp_path / "renders"
    assert _main("--preset", "tiny", "-q", "relight", "--capture", tiny_capture, "--meshes", skinned_meshes / "test.npz",
                 "--uvmaps", relight_inputs / "uvmaps_test", "--model", relight_model, "--seq", "test",
                 "--calibration", oracle_calibration_artifact, "--out", out) == 0
    metrics = json.loads((out / "manifest.json").read_text())["metrics"]
    assert metrics["headset_excluded"].startswith("yes") and metrics["headset_unposed_views"] == 0
    rows, _ = read_npz(out / "scores.npz", check_finite=False)
    # the tiny subject wears the headset in every test view: some of its pixels lie outside the rendered head
    assert (rows["headset_excluded_fraction"] > 0).all() and metrics["headset_excluded_fraction"] < 0.2
    capture, _ = open_capture(tiny_capture)
    without = dataclasses.replace(oracle_calibration, head_poses={})
    with pytest.raises(EgorelightError, match="no head poses for sequence 'test'"):
        HeadsetExclusion.from_calibration(capture, without, "test")
