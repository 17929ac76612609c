"""Inverse kinematics: Jacobians, the banded solve, recovery, limits, smoothing, characters, CLI."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.ik_jacobian import (KeypointJacobian, dof_influence, finite_difference_jacobian,
                                                 root_chain_joints)
from egorelight_cli.io.keypoints import Keypoints, write_keypoints_npz
from egorelight_cli.io.motion import Motion, read_motion_npz, write_motion_npz
from egorelight_cli.stages import ik as IK
from egorelight_cli.stages.ik import (IKSettings, classify_dofs, clamp_to_limits, default_ik_model, fit_metrics, fit_pca,
                                      fitted_keypoints, gt_metrics, jitter_m, solve_ik, train_ik_model)

FAST = IKSettings(hand_samples=1000)


@pytest.fixture(scope="module")
def model(character):
    return default_ik_model(character, FAST)


def smooth_motion(character, model, T: int, seed: int = 0, amplitude: float = 0.25) -> np.ndarray:
    """A smooth motion inside the limits (not on them), hands in the PCA subspace, walking forward."""
    sk = character.skeleton
    groups = classify_dofs(character)
    rng = np.random.default_rng(seed)
    t = np.arange(T) / 30.0
    theta = np.repeat(model.theta_bar[None], T, axis=0)
    for d in groups.body:
        lo, hi = np.clip(sk.dof_limits[d], -1.0, 1.0)
        mid = 0.5 * (lo + hi)
        theta[:, d] = mid + amplitude * (hi - lo) * np.sin(2 * np.pi * rng.uniform(0.3, 0.8) * t + rng.uniform(0, 6))
    for h in model.hands:
        eta = np.sqrt(h.variance) * 0.5 * np.sin(2 * np.pi * rng.uniform(0.2, 0.6, h.num_components) * t[:, None]
                                                   + rng.uniform(0, 6, h.num_components))
        theta[:, h.dof_index] = h.reconstruct(eta)
    root = groups.root
    theta[:, root[0]] = 0.4 * t
    theta[:, root[1]] += 0.9 if sk.dof_names[root[1]] == "translate_y" and abs(model.theta_bar[root[1]]) < 0.1 else 0.0
    theta[:, root[3]] = (2.0 + 0.5 * t) / np.abs(sk.dof_joint_weights[root[3]]).max()
    return theta


def keypoints_of(character, theta, noise: float = 0.0, seed: int = 0) -> Keypoints:
    xyz = fitted_keypoints(character, theta)
    xyz = xyz + np.random.default_rng(seed).normal(0, noise, xyz.shape) if noise else xyz
    return Keypoints(xyz, np.ones(xyz.shape[:2]), np.arange(len(theta)), character.keypoint_names, fps=30.0)


# ------------------------------------------------------------------------------ structure
def test_dof_classes_of_the_default_character(character):
    groups = classify_dofs(character)
    names = character.skeleton.dof_names
    assert [names[d] for d in groups.root] == ["translate_x", "translate_y", "translate_z", "rotate_y", "rotate_z", "rotate_x"]
    assert len(groups.hands["Left"]) == 14 and len(groups.hands["Right"]) == 14
    assert all(names[d].startswith("left_") for d in groups.hands["Left"])
    assert {"jaw_open", "head_bend", "left_toes"} <= {names[d] for d in groups.unobservable}
    assert len(groups.fixed) == 0 and "left_elbow" in {names[d] for d in groups.body}
    chain = root_chain_joints(character.skeleton)
    assert [character.skeleton.joint_names[j] for j in np.nonzero(chain)[0]] == \
        ["Root_tx", "Root_ty", "Root_tz", "Root_ry", "Root_rz", "Root_rx"]


def test_dof_classes_of_the_ddc_example(ddc_example):
    from egorelight_cli.stages.character_commands import load_character

    ddc, _ = load_character(ddc_example / "ddc.character")
    groups = classify_dofs(ddc)
    names = ddc.skeleton.dof_names
    assert len(groups.root) == 6 and len(groups.hands["Left"]) == 20 and len(groups.hands["Right"]) == 20
    fixed = {names[d] for d in groups.fixed}
    assert {"global_scale", "arm_scale", "hand_knuckles_width", "spine_stretch"} <= fixed  # shape DoFs stay put
    assert not fixed & {names[d] for d in groups.body}


@pytest.mark.parametrize("which", ["default", "ddc"])
def test_analytic_jacobian_matches_finite_differences(character, which, request):
    if which == "ddc":
        from egorelight_cli.stages.character_commands import load_character

        character, _ = load_character(request.getfixturevalue("ddc_example") / "ddc.character")
    sk = character.skeleton
    rng = np.random.default_rng(3)
    theta = character.rest_theta + rng.normal(0, 0.4, (2, sk.num_dofs))
    dofs = rng.permutation(sk.num_dofs)[:40]  # a subset, in a scrambled order, prismatic DoFs included
    dofs = np.union1d(dofs, [0, 1, 2])[rng.permutation(len(np.union1d(dofs, [0, 1, 2])))]
    plan = KeypointJacobian.build(sk, character.keypoint_joints, character.keypoint_offsets, dofs)
    kp, J = plan(torch.as_tensor(theta))
    for f in range(2):
        numeric = finite_difference_jacobian(theta[f], sk, character.keypoint_joints, character.keypoint_offsets, dofs)
        np.testing.assert_allclose(J[f].numpy(), numeric, atol=2e-7)
    from egorelight_cli.geometry.skeleton import keypoint_positions

    np.testing.assert_allclose(kp.numpy(), keypoint_positions(torch.as_tensor(theta), character).numpy(), atol=1e-12)
    influence = dof_influence(sk, character.keypoint_joints, character.keypoint_offsets)[:, dofs]
    assert np.all((np.abs(J.numpy()).max(axis=(0, 2)) > 1e-9) <= influence)


def dense_normal_matrix(A: np.ndarray, w_temporal: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """``blockdiag(A) + D2^T D2 (x) diag(w)``, damped as the banded solve damps it, densely."""
    T, n = A.shape[:2]
    P = np.zeros((T, T))
    for r in range(T - 2):
        c = np.zeros(T)
        c[r:r + 3] = [1, -2, 1]
        P += np.outer(c, c)
    H = np.kron(P, np.diag(w_temporal))
    for t in range(T):
        H[t * n:(t + 1) * n, t * n:(t + 1) * n] += A[t]
    diag = np.diag(H).copy()
    H[np.diag_indices_from(H)] += np.repeat(lam, n) * diag + 1e-9 * diag.max() + 1e-12
    return H


def test_banded_solve_matches_dense(character, model):
    """The banded normal equations (data + temporal + damping + held variables) against a dense solve."""
    T, n = 7, 5
    rng = np.random.default_rng(0)
    D = character.skeleton.num_dofs
    S = np.zeros((D, n))
    S[np.arange(6, 6 + n), np.arange(n)] = 1.0
    problem = IK._StageProblem("t", character, S, np.zeros((T, D)), np.zeros((T, n)), np.zeros((T, 57, 3)),
                               np.ones((T, 57)), rng.uniform(1, 3, n), np.arange(D), model.theta_bar, 0.01, 0.1,
                               True, 64)
    M = rng.normal(size=(T, n, n))
    A = M @ np.swapaxes(M, 1, 2) + np.eye(n)
    g = rng.normal(size=(T, n))
    lam = rng.uniform(0, 0.1, T)
    H = dense_normal_matrix(A, problem.w_temporal, lam)
    np.testing.assert_allclose(problem.solve(A, g, lam).ravel(), np.linalg.solve(H, -g.ravel()), rtol=1e-9, atol=1e-12)
    held = np.full((T, n), np.nan)
    held[2, 1], held[5, 4] = 0.0, 0.3  # prescribed steps
    fixed = ~np.isnan(held.ravel())
    expected = np.where(fixed, held.ravel(), 0.0)
    rhs = -g.ravel() - H[:, fixed] @ expected[fixed]
    expected[~fixed] = np.linalg.solve(H[np.ix_(~fixed, ~fixed)], rhs[~fixed])
    np.testing.assert_allclose(problem.solve(A, g, lam, held).ravel(), expected, rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------------------------ solving
def test_recovers_a_known_motion_noise_free(character, model):
    theta = smooth_motion(character, model, T=40)
    result = solve_ik(character, keypoints_of(character, theta), model, FAST)
    metrics = fit_metrics(result)
    assert metrics["mpjpe_input_all_cm"] < 0.1  # under 1 mm
    assert result.theta.shape == theta.shape and result.fitted_keypoints.shape == (40, 57, 3)
    truth = gt_metrics(character, result, gt_motion=Motion(theta, character.skeleton.dof_names, np.arange(40), 30.0))
    assert truth["gt_mpjpe_all_cm"] < 0.1 and truth["gt_root_translation_error_cm"] < 1.0
    assert truth["gt_dof_error_hands_deg"] < 1.0  # hands lie in the PCA subspace: recovered exactly


def test_frame_runs_split_the_ids_where_frames_are_missing():
    from egorelight_cli.stages.ik import frame_runs

    assert frame_runs(np.array([0, 1, 2, 1000, 1001, 1002])) == [slice(0, 3), slice(3, 6)]
    assert frame_runs(np.arange(0, 50, 5)) == [slice(0, 10)]  # evenly subsampled: one run
    assert frame_runs(np.array([3, 4, 6, 7, 8])) == [slice(0, 2), slice(2, 5)]
    assert frame_runs(np.array([7])) == [slice(0, 1)] and frame_runs(np.array([2, 1, 3])) == [slice(0, 3)]


def test_the_temporal_term_does_not_couple_frames_across_a_gap(character, model):
    """Two stretches of motion 1000 frames apart, the second 1 m away: solved together they give
    what each gives alone (the temporal term used to pull them towards each other)."""
    theta = smooth_motion(character, model, T=12, seed=4)
    theta[6:, classify_dofs(character).root[0]] += 1.0
    keypoints = keypoints_of(character, theta)
    ids = np.array([0, 1, 2, 3, 4, 5, 1000, 1001, 1002, 1003, 1004, 1005])
    whole = solve_ik(character, Keypoints(keypoints.xyz, keypoints.confidence, ids, keypoints.names, 30.0), model, FAST)
    halves = [solve_ik(character, Keypoints(keypoints.xyz[run], keypoints.confidence[run], ids[run], keypoints.names,
                                            30.0), model, FAST) for run in (slice(0, 6), slice(6, 12))]
    np.testing.assert_allclose(whole.theta, np.concatenate([h.theta for h in halves]), atol=1e-9)
    np.testing.assert_array_equal(whole.frame_ids, ids)


def test_lbfgs_baseline_runs_and_fits(character, model):
    theta = smooth_motion(character, model, T=10, seed=2)
    settings = IKSettings(solver="lbfgs", lbfgs_iterations=30, hand_samples=1000)
    result = solve_ik(character, keypoints_of(character, theta), model, settings)
    assert result.solver == "lbfgs" and [s.name for s in result.stages] == ["global", "body", "hands"]
    assert fit_metrics(result)["mpjpe_input_body_cm"] < 5.0


def test_limits_are_respected(character, model):
    sk = character.skeleton
    theta = smooth_motion(character, model, T=12, seed=1, amplitude=0.1)
    names = sk.dof_names
    for name in ("left_elbow", "right_knee", "left_hip_flex"):  # beyond their limits in the targets
        d = names.index(name)
        theta[:, d] = sk.dof_limits[d, 0] - 0.5
    result = solve_ik(character, keypoints_of(character, theta), model, FAST)
    limits = sk.dof_limits
    assert np.all(result.theta >= limits[:, 0] - 1e-9) and np.all(result.theta <= limits[:, 1] + 1e-9)
    for name in ("left_elbow", "right_knee", "left_hip_flex"):  # pushed towards (often onto) the limit
        d = names.index(name)
        assert np.all(result.theta[:, d] < limits[d, 0] + 0.25 * (limits[d, 1] - limits[d, 0]))
    assert np.any(np.isclose(result.theta, limits[:, 0]) | np.isclose(result.theta, limits[:, 1]))


def test_temporal_term_smooths_jitter(character, model):
    theta = smooth_motion(character, model, T=40, seed=4, amplitude=0.15)
    noisy = keypoints_of(character, theta, noise=0.01, seed=5)
    clean = fitted_keypoints(character, theta)
    smooth = solve_ik(character, noisy, model, FAST)
    rough = solve_ik(character, noisy, model, IKSettings(w_temporal=0.0, w_hand_temporal=0.0, hand_samples=1000))
    jitter_in = jitter_m(noisy.xyz)
    jitter_smooth, jitter_rough = jitter_m(smooth.fitted_keypoints), jitter_m(rough.fitted_keypoints)
    assert jitter_smooth < jitter_rough < jitter_in
    assert jitter_smooth < 0.6 * jitter_in
    error = lambda r: np.linalg.norm(r.fitted_keypoints - clean, axis=-1).mean()  # noqa: E731
    assert error(smooth) < error(rough)  # smoother and closer to the truth


def test_missing_and_low_confidence_keypoints(character, model):
    theta = smooth_motion(character, model, T=20, seed=6)
    kp = keypoints_of(character, theta)
    xyz, conf = kp.xyz.copy(), kp.confidence.copy()
    xyz[5:9, :] = np.nan  # whole frames missing: filled in by the temporal term
    xyz[:, 20:30] = np.nan  # a hand partly missing
    conf[:, 3] = 0.0
    result = solve_ik(character, Keypoints(xyz, conf, kp.frame_ids, kp.names, 30.0), model, FAST)
    assert np.isfinite(result.theta).all() and np.isnan(result.residual_m[5:9]).all()
    truth = np.linalg.norm(result.fitted_keypoints - fitted_keypoints(character, theta), axis=-1)
    assert truth[5:9, :15].mean() < 0.05  # interpolated frames stay close (5 cm)
    with pytest.raises(EgorelightError, match="no usable keypoints"):
        solve_ik(character, Keypoints(np.full_like(xyz, np.nan), conf, kp.frame_ids), model, FAST)


def test_works_on_the_ddc_example(ddc_example):
    from egorelight_cli.stages.character_commands import load_character

    ddc, _ = load_character(ddc_example / "ddc.character")
    ddc_model = default_ik_model(ddc, FAST)
    theta = smooth_motion(ddc, ddc_model, T=30, seed=7, amplitude=0.15)
    groups = classify_dofs(ddc)
    theta[:, groups.fixed] = ddc.rest_theta[groups.fixed]
    result = solve_ik(ddc, keypoints_of(ddc, theta), ddc_model, FAST)
    assert result.theta.shape == (30, 107)
    assert fit_metrics(result)["mpjpe_input_all_cm"] < 0.1
    np.testing.assert_allclose(result.theta[:, groups.fixed], np.repeat(ddc.rest_theta[None, groups.fixed], 30, 0))


def _joint_weight(character, d: int) -> float:
    return float(np.abs(character.skeleton.dof_joint_weights[d]).max())


def test_default_hand_prior_bends_fingers_in_joint_angles_not_dof_units(ddc_example):
    """The DDC fingers drive their joints with weight 3, so their DoF limits [-1.57, 0.3] allow
    -270 deg of joint rotation: the prior curls at most ``max_flexion_deg`` of joint rotation."""
    from egorelight_cli.stages.character_commands import load_character
    from egorelight_cli.stages.ik_model import finger_of, synthetic_hand_poses

    ddc, _ = load_character(ddc_example / "ddc.character")
    index = classify_dofs(ddc).hands["Left"]
    curl = np.array([finger_of(ddc, int(d))[1] and _joint_weight(ddc, int(d)) > 1 for d in index])
    weight = np.array([_joint_weight(ddc, int(d)) for d in index])
    rest = ddc.rest_theta[index]
    poses = synthetic_hand_poses(ddc, index, 2000, np.random.default_rng(0), max_flexion_rad=np.radians(100))
    joint_deg = np.degrees((poses - rest) * weight)[:, curl]
    assert curl.sum() >= 8 and np.abs(joint_deg).max() <= 100.01
    assert -75 < joint_deg.mean() < -25  # half a fist on average (it was -134 deg)
    uncapped = synthetic_hand_poses(ddc, index, 2000, np.random.default_rng(0), max_flexion_rad=1e6)
    assert np.degrees((uncapped - rest) * weight)[:, curl].mean() < -100  # what the cap fixes
    with pytest.raises(EgorelightError, match="hand_pca.max_flexion_deg"):
        IKSettings(hand_max_flexion_deg=0.0)


@pytest.mark.parametrize("which", ["default", "ddc"])
def test_trained_hand_prior_beats_the_default_on_held_out_fingers(character, which, request):
    """Fingers curling independently (outside the default model's coupled grasp subspace): a
    model trained on the first half of the motion fits the second half's hands better, noise-free.
    On the shipped character (runs in CI) and on the DDC example (needs ../shared)."""
    from egorelight_cli.stages.ik_model import finger_of

    ddc = character
    if which == "ddc":
        from egorelight_cli.stages.character_commands import load_character

        ddc, _ = load_character(request.getfixturevalue("ddc_example") / "ddc.character")
    default = default_ik_model(ddc, FAST)
    T = 80
    theta = smooth_motion(ddc, default, T=T, seed=3, amplitude=0.1)
    rng = np.random.default_rng(5)
    t = np.arange(T) / 30.0
    for index in classify_dofs(ddc).hands.values():
        for d in index:
            finger, is_curl = finger_of(ddc, int(d))
            lo, hi = ddc.skeleton.dof_limits[d]
            if is_curl and np.isfinite([lo, hi]).all():
                phase = {"Thumb": 0, "Index": 1, "Middle": 2, "Ring": 3, "Pinky": 4}[finger] + rng.uniform(0, 0.3)
                amount = 0.5 + 0.5 * np.sin(2 * np.pi * 0.6 * t + 1.3 * phase)
                theta[:, d] = np.clip(-np.radians(80) * amount / _joint_weight(ddc, int(d)), lo, hi)
    half = T // 2
    trained = train_ik_model(ddc, [theta[:half]], FAST)
    held_out = keypoints_of(ddc, theta[half:])
    hands = slice(15, None)
    errors = {}
    for name, model in (("default", default), ("trained", trained)):
        result = solve_ik(ddc, held_out, model, FAST)
        errors[name] = float(np.linalg.norm(result.fitted_keypoints - held_out.xyz, axis=-1)[:, hands].mean())
    # the DDC fingers (DoF weight 3) lie far outside the default grasp subspace; the shipped
    # character's less so (measured: 0.14 -> 0.086 cm, ratio 0.61)
    assert errors["trained"] < (0.6 if which == "ddc" else 0.75) * errors["default"], errors


def test_model_training_and_pca(character):
    rng = np.random.default_rng(0)
    base = default_ik_model(character, FAST)
    motions = [np.repeat(base.theta_bar[None], 50, 0) + rng.normal(0, 0.1, (50, character.skeleton.num_dofs))]
    trained = train_ik_model(character, motions, FAST)
    groups = classify_dofs(character)
    assert trained.source == "motions" and trained.num_training_frames == 50
    np.testing.assert_allclose(trained.theta_bar[groups.body],
                               clamp_to_limits(motions[0].mean(0), character.skeleton.dof_limits)[groups.body])
    for h in trained.hands:
        np.testing.assert_allclose(h.basis.T @ h.basis, np.eye(6), atol=1e-10)
    static = train_ik_model(character, [np.repeat(base.theta_bar[None], 5, 0)], FAST)  # hands never move
    for h in static.hands:
        assert h.basis.shape == (14, 6) and h.variance.min() > 0  # completed from synthetic poses
    mean, basis, variance = fit_pca(rng.normal(size=(100, 4)) * [3, 2, 1, 0.01], 2)
    assert basis.shape == (4, 2) and variance[0] > variance[1]


# ------------------------------------------------------------------------------------ CLI
def assert_one_line_error(result, *fragments):
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("egorelight: error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.fixture(scope="module")
def sequence(tmp_path_factory, character, model):
    root = tmp_path_factory.mktemp("ik")
    theta = smooth_motion(character, model, T=12, seed=8)
    write_keypoints_npz(root / "kp.npz", keypoints_of(character, theta, noise=0.003))
    write_motion_npz(root / "gt.npz", Motion(theta, character.skeleton.dof_names, np.arange(12), 30.0))
    return root


def test_cli_ik_single_file_and_directory(run, sequence, tmp_path):
    result = run("ik", "--in", str(sequence / "kp.npz"), "--character", "default", "--out", str(tmp_path / "m.npz"),
                 "--preset", "tiny")
    assert result.returncode == 0, result.stderr
    motion = read_motion_npz(tmp_path / "m.npz")
    assert motion.theta.shape == (12, 92) and motion.fitted_keypoints.shape == (12, 57, 3)
    assert (tmp_path / "m.npz.json").is_file()
    result = run("ik", "--in", str(sequence / "kp.npz"), "--out", str(tmp_path / "dir"), "--gt", str(sequence / "gt.npz"),
                 "--solver", "lm", "--preset", "tiny")
    assert result.returncode == 0, result.stderr
    import json

    manifest = json.loads((tmp_path / "dir" / "manifest.json").read_text())
    assert (tmp_path / "dir" / "preview.png").is_file() and manifest["config"]["solver"] == "lm"
    metrics = manifest["metrics"]
    assert metrics["mpjpe_input_body_cm"] < 2 and metrics["gt_mpjpe_all_cm"] < 2 and "gt_dof_error_deg" in metrics


def test_cli_ground_truth_folder(run, sequence, tmp_path, character, model):
    """``--gt`` a folder like the simulator's ``capture/groundtruth/<seq>/`` (lone npz files)."""
    import json
    import shutil

    folder = tmp_path / "groundtruth" / "test"
    folder.mkdir(parents=True)
    shutil.copy(sequence / "gt.npz", folder / "motion.npz")
    theta = read_motion_npz(folder / "motion.npz").theta
    write_keypoints_npz(folder / "keypoints.npz", keypoints_of(character, theta))
    result = run("ik", "--in", sequence / "kp.npz", "--gt", folder, "--out", tmp_path / "m", "--preset", "tiny")
    assert result.returncode == 0, result.stderr
    metrics = json.loads((tmp_path / "m" / "manifest.json").read_text())["metrics"]
    assert metrics["gt_frames"] == 12 and metrics["gt_mpjpe_body_cm"] < 2 and metrics["gt_dof_error_deg"] < 20
    assert_one_line_error(run("ik", "--in", sequence / "kp.npz", "--gt", tmp_path, "--out", tmp_path / "n"),
                          "neither keypoints.npz nor motion.npz")


def test_cli_wild_truth_is_scored_in_the_frame_of_the_trackers_head_poses(run, tiny_capture, oracle_calibration,
                                                                         tmp_path):
    """Keypoints placed by head poses in a tracker's own world (one yaw and shift off the truth's)
    are scored against the truth taken into that world when ``--calibration`` says so; without it
    they miss by metres, so keypoints that record the calibration that placed them are refused
    without it. A ``--calibration`` without a ground-truth folder is a one-line error."""
    import json
    from dataclasses import replace

    from egorelight_cli.artifacts import ArtifactWriter, open_artifact
    from egorelight_cli.geometry.cameras import transform_points
    from egorelight_cli.geometry.equirect import yaw_rotation
    from egorelight_cli.geometry.rigid import rigid
    from egorelight_cli.io.calibration import write_calibration
    from egorelight_cli.io.keypoints import read_keypoints_npz, save_keypoints

    T_tracker_from_world = rigid(yaw_rotation(-63.0), np.array([1.5, 0.0, -2.0]))
    wild = oracle_calibration.head_poses["wild"]
    tracker = replace(oracle_calibration, head_poses={**oracle_calibration.head_poses, "wild": replace(
        wild, T_world_from_hmd=T_tracker_from_world @ wild.T_world_from_hmd)},
        extras={"head_pose_sources": {"wild": "headset tracker aligned to visual odometry"}})
    with ArtifactWriter(tmp_path / "calibration", kind="calibration", stage="oracle", config={}) as writer:
        write_calibration(writer.workdir, tracker)
    folder = tiny_capture / "groundtruth" / "wild"
    truth = read_keypoints_npz(folder / "keypoints.npz")
    placed = replace(truth, xyz=transform_points(T_tracker_from_world, truth.xyz))
    with ArtifactWriter(tmp_path / "keypoints", kind="keypoints", stage="egopose", config={}) as writer:
        save_keypoints(writer, placed)  # no provenance: what placed them cannot be told
    with ArtifactWriter(tmp_path / "keypoints_posed", kind="keypoints", stage="egopose", config={},
                        inputs=[open_artifact(tmp_path / "calibration")]) as writer:
        save_keypoints(writer, placed)  # as egopose records it: placed by this calibration's head poses
    common = ("ik", "--preset", "tiny", "--in", tmp_path / "keypoints", "--gt", folder)
    for flags, out in ((("--calibration", tmp_path / "calibration"), "posed"), ((), "plain")):
        result = run(*common, *flags, "--out", tmp_path / out)
        assert result.returncode == 0, result.stderr
    posed, plain = (json.loads((tmp_path / out / "manifest.json").read_text())["metrics"] for out in ("posed", "plain"))
    assert posed["gt_mpjpe_body_cm"] < 5.0 and plain["gt_mpjpe_body_cm"] > 100.0, (posed, plain)
    assert "own world" in posed["groundtruth_frame"] and "gt_dof_error_deg" not in posed
    assert_one_line_error(run("ik", "--preset", "tiny", "--in", tmp_path / "keypoints_posed", "--gt", folder,
                              "--out", tmp_path / "unposed"), "give --calibration")
    assert not (tmp_path / "unposed").exists()
    assert_one_line_error(run("ik", "--in", tmp_path / "keypoints", "--gt", folder / "keypoints.npz",
                              "--calibration", tmp_path / "calibration", "--out", tmp_path / "bad"),
                          "--calibration with --gt needs --gt to be a capture/groundtruth/<seq> folder")


def test_cli_train_ik_then_use_the_model(run, sequence, tmp_path):
    assert run("train", "ik", str(sequence / "gt.npz"), "--out", str(tmp_path / "model"), "--preset", "tiny").returncode == 0
    assert (tmp_path / "model" / "model.pt").is_file()
    result = run("ik", "--in", str(sequence / "kp.npz"), "--model", str(tmp_path / "model"), "--out",
                 str(tmp_path / "m.npz"), "--preset", "tiny")
    assert result.returncode == 0, result.stderr


def test_cli_bad_inputs_are_one_line_errors(run, sequence, tmp_path):
    assert_one_line_error(run("ik", "--in", str(sequence / "gt.npz"), "--out", str(tmp_path / "a.npz")),
                          "wrong payload kind", "gt.npz")
    nan = Keypoints(np.full((3, 57, 3), np.nan), np.ones((3, 57)), np.arange(3))
    write_keypoints_npz(tmp_path / "nan.npz", nan)
    assert_one_line_error(run("ik", "--in", str(tmp_path / "nan.npz"), "--out", str(tmp_path / "b.npz")),
                          "no usable keypoints")
    short = Keypoints(np.zeros((3, 56, 3)), np.ones((3, 56)), np.arange(3), names=tuple(f"k{i}" for i in range(56)))
    write_keypoints_npz(tmp_path / "short.npz", short)
    assert_one_line_error(run("ik", "--in", str(tmp_path / "short.npz"), "--out", str(tmp_path / "c.npz")),
                          "56 keypoints", "57")
    assert_one_line_error(run("ik", "--in", str(tmp_path / "none.npz"), "--out", str(tmp_path / "d.npz")), "not found")
    assert_one_line_error(run("ik", "--in", str(sequence / "kp.npz"), "--model", str(sequence / "kp.npz"),
                              "--out", str(tmp_path / "e.npz")), "not a finished egorelight artifact")


def test_cli_ddc_motion_input(run, ddc_example, tmp_path):
    from egorelight_cli.io.ddc import MotionFile, write_motion

    values = np.repeat(np.loadtxt(ddc_example / "ddc.motion", skiprows=1, ndmin=2)[:, 1:], 3, axis=0)
    write_motion(MotionFile(np.arange(3), values), tmp_path / "x.motion")
    result = run("ik", "--in", str(tmp_path / "x.motion"), "--character", str(ddc_example / "ddc.character"),
                 "--out", str(tmp_path / "m.npz"), "--preset", "tiny")
    assert result.returncode == 0, result.stderr
    np.testing.assert_allclose(read_motion_npz(tmp_path / "m.npz").theta, values, atol=1e-6)
    assert_one_line_error(run("ik", "--in", str(tmp_path / "x.motion"), "--out", str(tmp_path / "n.npz")),
                          "107 DoF values but the skeleton has 92 DoFs")


def test_stage_yaml_defaults_match_the_settings_defaults():
    from egorelight_cli.config import resolve_config

    assert IKSettings.from_config(resolve_config("ik", "cpu")) == IKSettings()
    tiny = IKSettings.from_config(resolve_config("ik", "tiny", ("solver=lbfgs", "weights.reg=0.5")))
    assert tiny.solver == "lbfgs" and tiny.w_reg == 0.5 and tiny.lbfgs_iterations < IKSettings().lbfgs_iterations
    with pytest.raises(EgorelightError, match="'solver' must be one of lm, lbfgs"):
        IKSettings.from_config(resolve_config("ik", "cpu", ("solver=newton",)))


# ------------------------------------------------------------------------------ robustness
def test_huber_data_term_energy_and_gradient_agree(character, model):
    """The reweighted Gauss-Newton terms (``local_terms``) are the Huber energy and half its
    gradient (autograd of ``energy``), and far keypoints cost less than their squared distance."""
    T, rng = 4, np.random.default_rng(9)
    theta = smooth_motion(character, model, T=T, seed=9)
    index = classify_dofs(character).body[:8]
    S = np.zeros((character.skeleton.num_dofs, len(index)))
    S[index, np.arange(len(index))] = 1.0
    base = theta.copy()
    base[:, index] = 0.0
    x = theta[:, index] + 0.05 * rng.normal(size=(T, len(index)))
    targets = fitted_keypoints(character, theta)
    targets[:, ::4] += 0.5  # every 4th keypoint half a metre off: beyond delta

    def problem(delta):
        return IK._StageProblem("t", character, S, base, x, targets, np.full((T, 57), 10.0), np.zeros(len(index)),
                                np.zeros(0, np.int64), model.theta_bar, 0.0, 0.0, False, 64, huber_delta_m=delta)
    huber = problem(0.1)
    e, _, g = huber.local_terms(x)
    xt = torch.tensor(x, requires_grad=True)
    energy = huber.energy(xt)
    energy.backward()
    np.testing.assert_allclose(e.sum(), float(energy.detach()), rtol=1e-6)
    np.testing.assert_allclose(g, 0.5 * xt.grad.numpy(), rtol=1e-3, atol=1e-4 * np.abs(g).max())
    assert float(problem(None).energy(torch.tensor(x))) > 2 * float(energy.detach())


def test_one_absurd_keypoint_is_rejected_and_the_fit_unharmed(character, model):
    theta = smooth_motion(character, model, T=20, seed=10)
    kp = keypoints_of(character, theta, noise=0.005, seed=11)
    clean = solve_ik(character, kp, model, FAST)
    assert not clean.rejected.any() and fit_metrics(clean)["rejected_keypoints"] == 0
    xyz = kp.xyz.copy()
    xyz[7, 5, 0] = 1e9  # one coordinate of one keypoint
    result = solve_ik(character, Keypoints(xyz, kp.confidence, kp.frame_ids, kp.names, 30.0), model, FAST)
    assert result.rejected.sum() == 1 and result.rejected[7, 5] and np.isnan(result.residual_m[7, 5])
    assert fit_metrics(result)["rejected_keypoints"] == 1 and fit_metrics(result)["rejected_frames"] == 1
    moved = np.linalg.norm(result.fitted_keypoints - clean.fitted_keypoints, axis=-1)
    assert moved.max() < 0.03  # within a few cm of the clean fit everywhere


def test_a_keypoint_far_off_the_first_fit_is_rejected(character, model):
    """1.5 m off (inside the body-distance threshold): the Huber term bounds its pull, the
    residual test after the first fit drops it and the refit matches the clean fit."""
    theta = smooth_motion(character, model, T=20, seed=12)
    kp = keypoints_of(character, theta, noise=0.005, seed=13)
    clean = solve_ik(character, kp, model, FAST)
    xyz = kp.xyz.copy()
    xyz[9:12, 4] += [1.5, 0.0, 0.0]  # a wrist/elbow keypoint swept away in three frames
    dirty = Keypoints(xyz, kp.confidence, kp.frame_ids, kp.names, 30.0)
    result = solve_ik(character, dirty, model, FAST)
    assert result.rejected[9:12, 4].all() and result.rejected.sum() == 3
    assert np.linalg.norm(result.fitted_keypoints - clean.fitted_keypoints, axis=-1).max() < 0.03
    plain = solve_ik(character, dirty, model, IKSettings(hand_samples=1000, robust_loss="l2", outlier_residual_factor=0))
    assert np.linalg.norm(plain.fitted_keypoints - clean.fitted_keypoints, axis=-1).max() > 0.1  # the paper's l2 is dragged


def test_keypoints_in_the_wrong_unit_are_refused(character, model):
    kp = keypoints_of(character, smooth_motion(character, model, T=5, seed=14))
    for factor, hint in ((1000.0, "millimetres"), (0.001, "not metres")):
        scaled = Keypoints(kp.xyz * factor, kp.confidence, kp.frame_ids, kp.names, 30.0)
        with pytest.raises(EgorelightError, match=f"keypoints span .* m, a body spans about 2 m.*{hint}"):
            solve_ik(character, scaled, model, FAST)


def test_cli_outlier_metrics_units_and_invalid_config(run, sequence, tmp_path, character):
    import json

    from egorelight_cli.io.keypoints import read_keypoints_npz

    keypoints = read_keypoints_npz(sequence / "kp.npz")
    xyz = keypoints.xyz.copy()
    xyz[3, 2, 1] = 1e9
    write_keypoints_npz(tmp_path / "outlier.npz", Keypoints(xyz, keypoints.confidence, keypoints.frame_ids, keypoints.names))
    result = run("ik", "--in", tmp_path / "outlier.npz", "--out", tmp_path / "m", "--preset", "tiny")
    assert result.returncode == 0, result.stderr
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert manifest["metrics"]["rejected_keypoints"] == 1 and manifest["metrics"]["mpjpe_input_all_cm"] < 2
    assert np.abs(read_motion_npz(tmp_path / "m" / "motion.npz").theta[:, :3]).max() < 10  # root in metres, not 1e7
    write_keypoints_npz(tmp_path / "mm.npz", Keypoints(np.round(keypoints.xyz * 1000), keypoints.confidence,
                                                       keypoints.frame_ids, keypoints.names))
    assert_one_line_error(run("ik", "--in", tmp_path / "mm.npz", "--out", tmp_path / "n"), "keypoints span", "mm.npz")
    (tmp_path / "x.bvh").write_text("HIERARCHY\n")
    for key_value, inp, fragment in (("lm.iterations=-5", "kp.npz", "lm.iterations"),
                                     ("lm.chunk_frames=0", "kp.npz", "lm.chunk_frames"),
                                     ("hand_pca.components=100", "kp.npz", "hand_pca.components"),
                                     ("global_keypoints=[Neck,Nose,LeftArm]", "kp.npz", "'Nose'"),
                                     ("robust.loss=cauchy", "kp.npz", "robust.loss"),
                                     ("bvh.scale=-1", "x.bvh", "bvh.scale")):
        source = tmp_path / inp if inp == "x.bvh" else sequence / inp
        assert_one_line_error(run("ik", "--in", source, "--out", tmp_path / "bad", "--set", key_value), fragment)
    assert not (tmp_path / "bad").exists()
