"""ik --fit-recon: skeleton DoFs fitted to a surface (stages/ik_surface.py)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from egorelight_cli.geometry.embedded_graph import pose_character
from egorelight_cli.stages.animate import surface_target
from egorelight_cli.stages.ik_surface import SurfaceFitSettings, fit_motion_to_surface, surface_fit_dofs
from test_ik import assert_one_line_error


def test_dofs_return_to_a_surface_posed_by_known_dofs(character):
    """The skinned character posed by known DoFs is the target; from DoFs bent 0.2 rad off on a few
    body joints and 3 cm off at the root, the fit comes back to the surface and most of the way to
    the DoFs; the fingers and a frame without a target keep theirs."""
    free = surface_fit_dofs(character)
    body = np.flatnonzero(free)
    rng = np.random.default_rng(3)
    truth = np.zeros((3, character.skeleton.num_dofs))
    truth[:, body] = rng.normal(0.0, 0.05, (3, body.size))
    truth = np.clip(truth, *character.skeleton.dof_limits.T)
    start = truth.copy()
    bent = rng.choice(body[6:], 5, replace=False)  # the first six are the root's
    start[:, bent] += 0.2
    start[:, :3] += 0.03  # root translation, m
    fingers = np.flatnonzero(~free)
    start[:, fingers] += 0.01
    vertices = pose_character(character, torch.as_tensor(truth)).numpy()
    targets = {f: surface_target(vertices[f], character.faces, 3000, rng) for f in (0, 1)}  # frame 2: none
    settings = replace(SurfaceFitSettings(), steps=150, lr=0.01, target_points=3000)

    theta, summary = fit_motion_to_surface(character, start, np.arange(3), targets, settings)

    assert summary["surface_fit_frames"] == 2
    assert summary["surface_fit_chamfer_cm_after"] < 0.25 * summary["surface_fit_chamfer_cm_before"], summary
    np.testing.assert_array_equal(theta[2], start[2])
    np.testing.assert_array_equal(theta[:, fingers], start[:, fingers])
    before = np.abs(start[:2, bent] - truth[:2, bent]).mean()
    after = np.abs(theta[:2, bent] - truth[:2, bent]).mean()
    assert after < 0.35 * before, (before, after)
    assert np.abs(theta[:2, :3] - truth[:2, :3]).max() < 0.01
    low, high = character.skeleton.dof_limits[free].T
    assert np.all(theta[:2, free] >= low) and np.all(theta[:2, free] <= high)


def test_the_head_returns_to_a_surface_its_dofs_posed(character):
    """A head turned 0.25 rad on each neck/head DoF of the chain in the target surface, left at
    the pose's value in the start: the fit turns it back most of the way; ``head: false`` leaves it."""
    from egorelight_cli.stages.ik_head import head_chain

    chain = head_chain(character).dofs
    rng = np.random.default_rng(5)
    start = np.zeros((2, character.skeleton.num_dofs))
    truth = start.copy()
    truth[:, chain] = np.clip(0.25, *character.skeleton.dof_limits[chain].T)
    vertices = pose_character(character, torch.as_tensor(truth)).numpy()
    targets = {f: surface_target(vertices[f], character.faces, 3000, rng) for f in (0, 1)}
    settings = replace(SurfaceFitSettings(), steps=150, lr=0.01, target_points=3000)

    theta, _ = fit_motion_to_surface(character, start, np.arange(2), targets, settings)
    kept, _ = fit_motion_to_surface(character, start, np.arange(2), targets, replace(settings, head=False))

    before = np.abs(start[:, chain] - truth[:, chain]).mean()
    assert np.abs(theta[:, chain] - truth[:, chain]).mean() < 0.35 * before
    np.testing.assert_array_equal(kept[:, chain], start[:, chain])


def test_the_fit_moves_root_body_and_head_only(character):
    """Root, body and the head chain's neck/head DoFs (the reconstruction sees the face); with
    ``head=False`` root and body alone; never the fingers or the unobservable DoFs off the chain."""
    from egorelight_cli.stages.ik_head import head_chain
    from egorelight_cli.stages.ik_model import classify_dofs

    groups = classify_dofs(character)
    chain = head_chain(character).dofs
    free = surface_fit_dofs(character)
    assert free[groups.root].all() and free[groups.body].all() and free[chain].all()
    assert np.array_equal(np.flatnonzero(free[groups.unobservable]), np.flatnonzero(np.isin(groups.unobservable, chain)))
    assert not surface_fit_dofs(character, head=False)[groups.unobservable].any()
    for hand in groups.hands.values():
        assert not free[hand].any()


@pytest.fixture(scope="module")
def recon_sequence(tiny_capture):
    """(sequence name, mocap path) of the tiny capture's first sequence with reconstructions."""
    from egorelight_cli.io.capture import open_capture

    capture, _ = open_capture(tiny_capture)
    for name in capture.sequence_names():
        seq = capture.sequence(name)
        if any(seq.recon_path(int(f)).is_file() for f in seq.frame_ids) and seq.mocap_path().is_file():
            return name, seq.mocap_path()
    pytest.skip("the tiny capture has no sequence with mocap and reconstructions")


def test_cli_fit_recon_lowers_the_chamfer_and_writes_it(run, tiny_capture, recon_sequence, tmp_path):
    name, mocap = recon_sequence
    common = ("ik", "--preset", "tiny", "--in", mocap, "--character", "default")
    assert run(*common, "--out", tmp_path / "plain").returncode == 0
    result = run(*common, "--set", "surface_fit.steps=40", "--fit-recon", tiny_capture, "--seq", name,
                 "--gt", tiny_capture / "groundtruth" / name, "--out", tmp_path / "fitted")
    assert result.returncode == 0, result.stderr
    metrics = json.loads((tmp_path / "fitted" / "manifest.json").read_text())["metrics"]
    assert metrics["surface_fit_frames"] > 0
    assert metrics["surface_fit_chamfer_cm_after"] < metrics["surface_fit_chamfer_cm_before"], metrics
    # the keypoint fit it started from is scored beside it (the baseline); the body's DoFs come closer
    # to the simulator's (tiny capture, 40 steps: 7.65 -> 7.33 deg)
    assert metrics["keypoint_fit_gt_frames"] == metrics["gt_frames"] > 0
    assert metrics["gt_dof_error_body_deg"] < 0.98 * metrics["keypoint_fit_gt_dof_error_body_deg"], metrics
    from egorelight_cli.io.motion import load_motion

    plain, fitted = load_motion(tmp_path / "plain")[0], load_motion(tmp_path / "fitted")[0]
    assert plain.theta.shape == fitted.theta.shape and not np.allclose(plain.theta, fitted.theta)
    np.testing.assert_array_equal(plain.frame_ids, fitted.frame_ids)


def test_cli_fit_recon_errors(run, tiny_capture, recon_sequence, tmp_path):
    name, mocap = recon_sequence
    common = ("ik", "--preset", "tiny", "--in", mocap, "--character", "default")
    assert_one_line_error(run(*common, "--seq", name, "--out", tmp_path / "a"), "--seq", "--fit-recon")
    assert_one_line_error(run(*common, "--fit-recon", tiny_capture, "--out", tmp_path / "b"), "--fit-recon needs --seq")
    assert_one_line_error(run(*common, "--fit-recon", tiny_capture, "--seq", "wild", "--out", tmp_path / "c"),
                          "reconstructions", "'wild'")
    assert not any((tmp_path / d).exists() for d in "abc")
