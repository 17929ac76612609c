"""envmap's inverse rendering (issue 19 item 4): the colour model recovered on a synthetic case,
optical flow helpers, and the stage with --meshes/--uvmaps/--model on the tiny capture."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.nn.colour_model import RootPolynomialColour
from egorelight_cli.render import optical_flow as of
from egorelight_cli.render.lighting import EnvmapPooling
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.stages.envmap_inverse import (EgoView, InverseSettings, fit_colour_model, observe, part_l1,
                                                 range_regulariser, sync_matrix)
from tiny_models import cli_exit_code as _main  # the CLI in-process


def test_inverse_rendering_recovers_a_known_colour_model():
    """A linear stand-in renderer (pixel = transfer @ S(E_h)) with images made under a known A, gamma:
    Adam through S(E) and the colour model finds a map and light vector within a few per cent."""
    rng = np.random.default_rng(0)
    stage = LightStage.dome(num_lights=24)
    H = 8
    E_l = torch.from_numpy(rng.uniform(0.05, 1.0, (H, 2 * H, 3)))
    pooling = EnvmapPooling(stage, H)
    A = np.concatenate([np.diag([1.6, 1.2, 0.8]), np.zeros((3, 3))], axis=1)
    A[0, 1], A[2, 3] = 0.1, 0.2
    truth = RootPolynomialColour(A, 1.5)
    views = []
    for _ in range(3):
        transfer = torch.from_numpy(rng.uniform(0, 1, (100, 24)) * (rng.uniform(size=(1, 24)) < 0.6))
        with torch.no_grad():
            target = (transfer @ pooling(truth(E_l))).reshape(10, 10, 3).float()
        views.append(SimpleNamespace(transfer=transfer, target=target, masks=torch.ones(2, 10, 10, dtype=torch.bool)))
    fit = fit_colour_model(E_l, pooling, views, lambda v, e: (v.transfer @ e).reshape(10, 10, 3).float(), steps=400,
                           lr=3e-2, views_per_step=3, reg_weight=0.0, reg_max=10.0)
    with torch.no_grad():
        E_true, E_fit = truth(E_l), fit.colour(E_l)
        identity = float((pooling(E_l) - pooling(E_true)).norm() / pooling(E_true).norm())
        lights = float((pooling(E_fit) - pooling(E_true)).norm() / pooling(E_true).norm())
        texels = float((E_fit - E_true).norm() / E_true.norm())
    assert identity > 0.2  # the identity start is far off
    assert lights < 0.06 and texels < 0.08, (lights, texels)
    assert float(fit.colour.gamma.detach()) == pytest.approx(1.5, abs=0.15)
    assert fit.curve[-1]["loss"] < 0.2 * fit.curve[0]["loss"]


def test_colour_sync_gains_transfer_where_a_full_matrix_fitted_to_misaligned_pixels_does_not():
    rng = np.random.default_rng(0)
    true = np.diag([0.82, 0.85, 0.93])
    # studio: body colours with correlated channels (skin, a pink shirt), the photograph's pixels misaligned
    # against the render's (a pixel's partner is often another body pixel), plus sensor noise
    base = rng.uniform(0.2, 0.8, (4000, 1))
    render = np.clip(base * [1.0, 0.75, 0.9] + rng.normal(0, 0.08, (4000, 3)), 0, None)
    partner = render[rng.permutation(4000)]
    aligned = rng.random(4000) < 0.6
    ego = np.where(aligned[:, None], render, partner) @ true.T + rng.normal(0, 0.01, (4000, 3))
    diagonal, matrix = sync_matrix(render, ego, "diagonal"), sync_matrix(render, ego, "matrix")
    assert np.allclose(diagonal, np.diag(np.diag(diagonal)))
    assert np.abs(diagonal - true).max() < 0.5 * np.abs(matrix - true).max()
    # the wild light is another colour: the diagonal model maps its grey nearer the truth
    grey = np.ones(3)
    assert np.abs(diagonal @ grey - true @ grey).max() < np.abs(matrix @ grey - true @ grey).max()
    # on exact pairs the full matrix recovers a cross-talk matrix exactly
    cross = np.array([[0.9, 0.05, 0.02], [0.03, 0.8, 0.06], [0.0, 0.04, 1.1]])
    clean = rng.uniform(0, 1, (200, 3))
    np.testing.assert_allclose(sync_matrix(clean, clean @ cross.T, "matrix"), cross, atol=1e-12)
    with pytest.raises(EgorelightError, match="inverse.sync.model"):
        sync_matrix(clean, clean, "affine")


def test_part_l1_balances_parts_and_regulariser_bounds_the_range():
    image, target = torch.zeros(4, 4, 3), torch.zeros(4, 4, 3)
    target[0] = 1.0  # one row of 4 pixels wrong
    big = torch.zeros(2, 4, 4, dtype=torch.bool)
    big[0, :3], big[1, 3] = True, True  # part 0: 12 pixels (4 wrong), part 1: 4 pixels (none wrong)
    assert float(part_l1(image, target, big)) == pytest.approx(0.5 * (4 / 12))
    assert part_l1(image, target, torch.zeros(1, 4, 4, dtype=torch.bool)) is None
    assert float(range_regulariser(torch.full((2, 4, 3), 0.5), 1.0)) < 1e-9
    assert float(range_regulariser(torch.full((2, 4, 3), 3.0), 1.0)) == pytest.approx(2.0, rel=1e-6)
    assert float(range_regulariser(torch.full((2, 4, 3), -0.5), 1.0)) == pytest.approx(0.5, rel=1e-6)


def test_auto_reg_max_is_the_training_lights_range_times_their_scale(tmp_path):
    from egorelight_cli.render.envmaps import write_envmap
    from egorelight_cli.stages.envmap_inverse import auto_reg_max

    (tmp_path / "envmaps").mkdir()
    write_envmap(tmp_path / "envmaps" / "dim.exr", np.full((8, 16, 3), 0.5, np.float32))
    write_envmap(tmp_path / "envmaps" / "bright.exr", np.full((8, 16, 3), 4.0, np.float32))
    sequences = {"relight_train": [{"pattern": "envmap", "envmap": "dim", "scale": 3.0}, {"pattern": "flat"}],
                 "test": [{"pattern": "envmap", "envmap": "bright"}]}
    capture = SimpleNamespace(root=tmp_path, sequence_names=lambda: sorted(sequences),
                              sequence=lambda name: SimpleNamespace(lights=sequences[name]))
    assert auto_reg_max(capture, "relight_train") == pytest.approx(1.5)  # the training map, times its scale
    assert auto_reg_max(capture, None) == pytest.approx(4.0)  # unknown: every sequence's lights
    sequences["relight_train"] = [{"pattern": "flat"}]
    assert auto_reg_max(capture, "relight_train") == 1.0  # no map to take a range from


def test_observed_masks_leave_out_render_pixels_nearer_than_min_depth():
    """A view whose render has a splat at the lens (depth 2 cm) over its left half: with
    min_depth_m = 0.1 those pixels leave every part mask and count in near_fraction; with 0 they stay."""
    h, w = 16, 16
    alpha = np.ones((h, w), np.float32)
    parts = np.zeros((h, w, 5), np.float32)
    parts[..., 0] = 1.0  # all upper body
    depth = np.full((h, w), 0.4, np.float32)
    depth[:, : w // 2] = 0.02
    ego = np.full((h, w, 3), 0.5, np.float32)
    unclipped = np.ones((h, w), bool)
    for min_depth, near_share in ((0.1, 0.5), (0.0, 0.0)):
        settings = InverseSettings(("down_left",), 1, 1, 1e-2, 1, 1.0, None, "none", None, 0.02, 0.1, 0.3, 0,
                                   min_depth, 1, ("flat",), ("fitted",))
        view = EgoView(0, "down_left", None, ego, unclipped)
        observe(view, ego, alpha, parts, depth, False, True, settings, "none")
        assert view.near_fraction == pytest.approx(near_share)
        assert int(view.masks.sum()) == int(h * w * (1 - near_share))
        assert not bool(view.masks[:, :, : w // 2].any()) if min_depth else bool(view.masks[0].all())


def test_dis_flow_warps_a_shifted_image_back_and_flags_occlusions():
    rng = np.random.default_rng(3)
    import cv2

    texture = cv2.GaussianBlur(rng.uniform(0, 255, (96, 96)).astype(np.float32), (0, 0), 2.0)
    source = np.clip(texture, 0, 255).astype(np.uint8)
    target = np.roll(source, 3, axis=1)  # the content moved 3 px right
    forward = of.estimate_flow(source, target)
    backward = of.estimate_flow(target, source)
    inner = (slice(10, -10), slice(10, -10))
    assert np.median(forward[inner][..., 0]) == pytest.approx(3.0, abs=0.3)
    warped = of.warp(target.astype(np.float32), forward)
    assert np.abs(warped[inner] - source[inner]).mean() < 0.2 * np.abs(target[inner].astype(float) - source[inner]).mean()
    consistent = of.consistent_flow(forward, backward, 1.0)
    assert consistent[inner].mean() > 0.9
    assert of.flow_method("raft", "/nonexistent/raft.pth")[0] == "dis"  # no weights: DIS, with the reason
    assert "not found" in of.flow_method("raft", None)[1]


@pytest.fixture(scope="module")
def avatar(tiny_avatar):
    """A tiny geolift model, uvmaps of wild / ego_train / relight_train and a (briefly) trained relight
    model: the session's (conftest.tiny_avatar)."""
    return tiny_avatar


def _inverse_args(tiny_capture, calibration, skinned_meshes, avatar):
    return ["envmap", "--preset", "tiny", "--capture", tiny_capture, "--calibration", calibration,
            "--meshes", skinned_meshes / "wild.npz", "--uvmaps", avatar / "uvmaps_wild", "--model", avatar / "relight",
            "--sync-meshes", skinned_meshes / "ego_train.npz", "--sync-uvmaps", avatar / "uvmaps_ego_train"]


def test_envmap_inverse_rendering_on_the_tiny_capture(tiny_capture, oracle_calibration_artifact, skinned_meshes,
                                                      avatar, tmp_path, run):
    out = tmp_path / "envmap"
    result = run(*_inverse_args(tiny_capture, oracle_calibration_artifact, skinned_meshes, avatar), "--out", out, "-q")
    assert result.returncode == 0, result.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    m = manifest["metrics"]
    assert m["row"] == "fitted" and set(m["rows"]) == {"ldr_panorama_only", "fitted", "no_flow", "no_part_masks",
                                                       "no_panorama"}
    for row in m["rows"].values():
        for key in ("light_relative_error", "light_cosine", "dominant_light_direction_error_deg", "log_l1_observed",
                    "log_l1_unobserved", "relit_psnr"):
            assert row[key] is not None and np.isfinite(row[key]), key
    assert m["light_relative_error"] == m["rows"]["fitted"]["light_relative_error"]
    # gradients reached A and gamma through the renderer: the image loss fell and the model moved
    assert m["inverse_loss_last"] < m["inverse_loss_first"]
    model = json.loads((out / "colour_model.json").read_text())
    assert model["row"] == "fitted" and model["fitted"] is True
    assert not np.allclose(model["A"], np.eye(3, 6)) and model["gamma"] != 1.0
    assert np.allclose(model["rows"]["ldr_panorama_only"]["A"], np.eye(3, 6))
    assert model["rows"]["no_panorama"]["model"].startswith("free") and "A" not in model["rows"]["no_panorama"]
    curves = json.loads((out / "curve.json").read_text())  # the free map was fitted too: its image loss fell
    assert curves["no_panorama"][-1]["image"] < curves["no_panorama"][0]["image"]
    responses = json.loads((tiny_capture / "groundtruth" / "ego_response.json").read_text())
    studio_exposure = json.loads((tiny_capture / "manifest.json").read_text())["config"]["studio"].get("exposure", 1.0)
    for role in ("down_left", "down_right"):
        sync = model["colour_sync"][role]
        assert np.asarray(sync["matrix"]).shape == (3, 3) and sync["pixels"] > 30
        assert len(sync["near_fraction"]) == len(sync["frames"])
        # scored against the simulated camera response: the metrics recomputed from the written files
        # (a 4-step avatar's sync is far off, so the values themselves say nothing here)
        true = (np.asarray(responses[role]["colour_matrix"]) * responses[role]["exposure"] / studio_exposure)
        fitted = np.asarray(sync["matrix"])
        truth = m["colour_sync_truth"][role]
        assert truth["true_gain"] == pytest.approx(true.sum(axis=1).mean())
        assert truth["gain_error"] == pytest.approx(fitted.sum(axis=1).mean() / true.sum(axis=1).mean() - 1)
        assert truth["matrix_max_abs_error"] == pytest.approx(np.abs(fitted - true).max())
    assert 0.0 <= m["near_excluded_fraction"] <= 1.0
    from egorelight_cli.render.envmaps import load_envmap

    envmap = load_envmap(out / "envmap.exr")
    expected = np.maximum(RootPolynomialColour.from_json(model).apply_numpy(_inpainted(out)), 0.0)  # radiance >= 0
    np.testing.assert_allclose(envmap, expected, rtol=1e-4, atol=1e-6)
    curve = json.loads((out / "curve.json").read_text())
    assert len(curve["fitted"]) == 10 and (out / "inverse_preview.png").is_file()
    assert m["relit_views"] and m["flow"] == "dis"


def _inpainted(out):
    """E_l as the stage had it, re-derived from panorama.exr, coverage.png and the stage's inpainting."""
    from egorelight_cli.io.exr import read_exr
    from egorelight_cli.io.images import read_image
    from egorelight_cli.render.panorama import inpaint_equirect

    manifest = json.loads((out / "manifest.json").read_text())
    inpaint = manifest["config"]["inpaint"]
    radiance = read_exr(out / "panorama.exr").layer("", ("R", "G", "B"))
    return inpaint_equirect(radiance, read_image(out / "coverage.png") > 0, inpaint["method"],
                            float(inpaint["radius_px"]))


@pytest.mark.parametrize("drop, extra, message", [
    ("--model", (), "missing --model"),
    (None, ("--set", "inverse.flow.method=farneback"), "optical flow method"),
    (None, ("--set", "inverse.rows=[no_flow]"), "inverse.rows"),
    (None, ("--set", "inverse.image_pass=specular"), "inverse.image_pass"),
    (None, ("--set", "inverse.min_depth_m=-1"), "inverse.min_depth_m"),
    (None, ("--set", "inverse.roles=[down_up]"), "down_up"),
    (None, ("--set", "inverse.sync.sequence=wild"), "wild"),
])
def test_envmap_inverse_bad_inputs_are_one_line_errors(tiny_capture, oracle_calibration_artifact, skinned_meshes,
                                                       avatar, tmp_path, run, drop, extra, message):
    args = _inverse_args(tiny_capture, oracle_calibration_artifact, skinned_meshes, avatar)
    if drop is not None:
        i = args.index(drop)
        del args[i:i + 2]
    out = tmp_path / "envmap"
    result = run(*args, *extra, "--out", out)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert not out.exists()


def test_the_free_map_of_the_no_panorama_row_is_smooth_non_negative_and_wraps():
    from egorelight_cli.stages.envmap_inverse import FREE_MAP_INIT, FreeEnvmap

    free = FreeEnvmap(4)
    panorama = torch.rand(16, 32, 3, dtype=torch.float64)
    np.testing.assert_allclose(free(panorama).detach().numpy(), FREE_MAP_INIT)  # ignores the panorama
    with torch.no_grad():
        free.logits[:, :, 0] = 4.0  # the first longitude cell bright
    out = free(panorama).detach().numpy()
    assert (out > 0).all()
    # bilinear with wrap-around: the last columns (next to longitude 0) are lifted, the middle is not
    assert out[:, -1].mean() > out[:, 16].mean() + 0.5 and np.allclose(out[:, 16], FREE_MAP_INIT)
    loss = free(panorama)[:, :4].sum()
    loss.backward()
    assert free.logits.grad[:, :, 0].abs().sum() > 0 and free.logits.grad[:, :, 2].abs().sum() == 0
