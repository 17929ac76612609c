"""relight_eval: per-view scoring in the subject mask without the head, and per body part."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorelight_cli.render.gaussians import GaussianRender
from egorelight_cli.render.image_metrics import psnr, ssim, tonemap_for_metrics
from egorelight_cli.stages.relight_eval import (PARTS_PASS, RelightScores, part_channels, part_groups, relight_metrics,
                                                score_view)

NAMES = {2: "hair", 5: "upper_clothes", 9: "pants", 13: "face", 14: "left_arm", 15: "right_arm", 18: "left_shoe",
         19: "right_shoe"}


def test_part_groups_join_left_and_right_and_leave_out_the_head():
    groups = part_groups(NAMES)
    assert groups == {"arm": [14, 15], "pants": [9], "shoe": [18, 19], "upper_clothes": [5]}
    segmentation = np.array([2, 5, 9, 14, 15, 19])
    channels = part_channels(segmentation, groups, np.array([5, 3, 4, 0, 1, 2]))
    # texel -> vertex -> label: 19 shoe, 14 arm, 15 arm, 2 hair (no part), 5 upper clothes, 9 pants
    np.testing.assert_array_equal(channels.numpy(), [[0, 0, 1, 0], [1, 0, 0, 0], [1, 0, 0, 0], [0, 0, 0, 0],
                                                     [0, 0, 0, 1], [0, 1, 0, 0]])


def _render(rng, height=40, width=48):
    """A fabricated render: left half part 0 ("pants"), right half part 1, a head block on top."""
    alpha = torch.ones(height, width)
    parts = torch.zeros(height, width, 2)
    parts[:, : width // 2, 0] = 1.0
    parts[:, width // 2:, 1] = 1.0
    head = torch.zeros(height, width, 1)
    head[:6] = 1.0
    colour = torch.from_numpy(rng.uniform(0, 1, (height, width, 3)))
    passes = {"diffuse": colour * 0.9, "lambert": colour * 0.8, "baked": colour * 0.5, "head": head, PARTS_PASS: parts}
    return GaussianRender(colour=colour, alpha=alpha, depth=alpha, passes=passes)


def test_score_view_scores_each_part_in_its_own_pixels():
    rng = np.random.default_rng(0)
    render = _render(rng)
    target = torch.from_numpy(rng.uniform(0, 1, (40, 48, 3)))
    mask = torch.ones(40, 48, dtype=torch.bool)
    mask[:, -3:] = False  # outside the subject
    scores = RelightScores()
    scores.start_view()
    score_view(scores, render, target, mask, parts=("pants", "shirt"))
    row = scores.views[0]
    shown, truth = tonemap_for_metrics(render.colour), tonemap_for_metrics(target)
    body = mask.clone()
    body[:6] = False
    left = body.clone()
    left[:, 24:] = False
    right = body & ~left
    assert row["psnr"] == pytest.approx(float(psnr(shown, truth, body)))
    assert row["part.pants.psnr"] == pytest.approx(float(psnr(shown, truth, left)))
    assert row["part.shirt.psnr"] == pytest.approx(float(psnr(shown, truth, right)))
    assert row["part.pants.ssim"] == pytest.approx(100 * float(ssim(shown, truth, left)))
    lambert = tonemap_for_metrics(render.passes["lambert"])
    assert row["part.shirt.lambert_psnr"] == pytest.approx(float(psnr(lambert, truth, right)))
    assert row["head_excluded_fraction"] == pytest.approx(6 / 40)
    # a part covering too few scored pixels gets no row; without parts there are none
    small = _render(rng)
    small.passes[PARTS_PASS][:] = 0.0
    small.passes[PARTS_PASS][10:13, 10:13, 1] = 1.0
    scores.start_view()
    score_view(scores, small, target, mask, parts=("pants", "shirt"))
    assert not any(key.startswith("part.") for key in scores.views[1])
    scores.start_view()
    score_view(scores, render, target, mask)
    assert not any(key.startswith("part.") for key in scores.views[2])


def test_part_means_nest_under_parts():
    rows = {"psnr": np.array([20.0, 22.0, 10.0]), "part.pants.psnr": np.array([18.0, np.nan, 8.0]),
            "part.upper_clothes.lambert_psnr": np.array([15.0, 17.0, 9.0])}
    metrics = relight_metrics(rows, np.array(["envmap", "envmap", "olat"]))
    assert metrics["psnr"] == 21.0 and metrics["olat_tail_psnr"] == 10.0
    assert metrics["parts"] == {"pants": {"psnr": 18.0, "olat_tail_psnr": 8.0},
                                "upper_clothes": {"lambert_psnr": 16.0, "olat_tail_lambert_psnr": 9.0}}
    assert not any(key.startswith("part.") or "_part." in key for key in metrics)


def test_the_headset_leaves_the_scores_with_the_head():
    rng = np.random.default_rng(1)
    render = _render(rng)
    target = torch.from_numpy(rng.uniform(0, 1, (40, 48, 3)))
    mask = torch.ones(40, 48, dtype=torch.bool)
    headset = torch.zeros(40, 48, dtype=torch.bool)
    headset[4:10, 30:40] = True  # rows 4, 5 are the render's head already: 4 rows x 10 columns are new
    scores = RelightScores()
    scores.start_view()
    score_view(scores, render, target, mask, headset=headset)
    region = mask.clone()
    region[:6] = False
    region &= ~headset
    row = scores.views[0]
    assert row["psnr"] == pytest.approx(float(psnr(tonemap_for_metrics(render.colour), tonemap_for_metrics(target), region)))
    assert row["headset_excluded_fraction"] == pytest.approx(40 / (40 * 48))
    assert row["head_excluded_fraction"] == pytest.approx((6 * 48 + 40) / (40 * 48))
    # a frame without a head pose: nothing more excluded, counted
    scores.start_view()
    score_view(scores, render, target, mask, unposed_headset=True)
    assert np.isnan(scores.views[1]["headset_excluded_fraction"])
    body = mask.clone()
    body[:6] = False
    assert scores.views[1]["psnr"] == pytest.approx(float(psnr(tonemap_for_metrics(render.colour),
                                                               tonemap_for_metrics(target), body)))
    assert scores.metrics()["headset_unposed_views"] == 1


def test_headset_pixels_keep_what_the_render_draws_in_front_of_it():
    from egorelight_cli.geometry.cameras import Camera
    from egorelight_cli.structures.calibration import HeadPoses
    from egorelight_cli.stages.relight_eval import HeadsetExclusion

    camera = Camera(model="pinhole", K=np.array([[40.0, 0, 23.5], [0, 40.0, 19.5], [0, 0, 1]]), dist=np.zeros(5),
                    width=48, height=40, T_cam_from_world=np.eye(4))
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 2.0]
    poses = HeadPoses(pose[None], np.array([7]), np.array([True]), np.array([4]), np.array([0.5]))
    exclusion = HeadsetExclusion(np.array([[-0.2, -0.2, -0.1], [0.2, 0.2, 0.1]]), poses)
    render = _render(np.random.default_rng(2))
    depth = torch.full((40, 48), 3.0)  # behind the headset (its front is at 1.9 m) ...
    depth[:, :24] = 1.0  # ... except the left half, in front of it
    render = GaussianRender(render.colour, render.alpha, depth * render.alpha, render.passes)
    pixels = exclusion.pixels(7, camera, render)
    rows, cols = np.nonzero(pixels.numpy())
    assert pixels.any() and cols.min() == 24  # the box spans columns 15..32: its left part is drawn in front
    assert exclusion.pixels(8, camera, render) is None  # no head pose for frame 8
    assert "box" in exclusion.describe()
