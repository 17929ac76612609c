"""The head from the headset (stages/ik_head.py, ``ik --hmd-reference``): the chain, the mounting, the fit."""

from __future__ import annotations

import json

import numpy as np
from scipy.spatial.transform import Rotation

from egorelight_cli.geometry.rigid import rigid
from test_cli import assert_one_line_error
from egorelight_cli.stages.ik_head import (HEAD_MARKER_NAMES, calibrate_hmd_from_head, fit_head_to_hmd, head_chain,
                                           head_marker_keypoints, head_offset_summary, head_transforms,
                                           with_head_markers)


def _names(character, chain):
    return character.skeleton.joint_names[chain.joint], {character.skeleton.dof_names[d] for d in chain.dofs}


def test_the_head_chain_is_the_neck_and_head_not_the_jaw_or_toes(character):
    joint, dofs = _names(character, head_chain(character))
    assert joint.lower().startswith("head")
    assert dofs == {"neck_bend", "neck_lean", "neck_twist", "head_bend", "head_lean", "head_twist"}


def test_the_mounting_is_recovered_from_exact_pairs_and_its_spread_grows_with_noise():
    rng = np.random.default_rng(3)
    T_hmd_from_head = rigid(Rotation.from_rotvec([0.2, -0.4, 0.1]).as_matrix(), np.array([0.01, -0.08, 0.05]))
    heads = np.stack([rigid(Rotation.random(random_state=i).as_matrix(), rng.normal(size=3)) for i in range(20)])
    hmds = heads @ np.linalg.inv(T_hmd_from_head)
    found, spread = calibrate_hmd_from_head(hmds, heads)
    np.testing.assert_allclose(found, T_hmd_from_head, atol=1e-9)
    assert spread["hmd_mount_frames"] == 20 and spread["hmd_mount_spread_cm"] < 1e-6
    assert spread["hmd_mount_spread_deg"] < 1e-4
    jitter = np.stack([rigid(Rotation.from_rotvec(rng.normal(scale=0.02, size=3)).as_matrix(),
                             rng.normal(scale=0.005, size=3)) for _ in range(20)])
    noisy, spread = calibrate_hmd_from_head(hmds @ jitter, heads)
    assert 0.2 < spread["hmd_mount_spread_cm"] < 1.5 and 0.5 < spread["hmd_mount_spread_deg"] < 3.0
    assert np.linalg.norm(noisy[:3, 3] - T_hmd_from_head[:3, 3]) < 0.005  # averaged down


def test_the_fit_puts_the_head_where_it_is_wanted_and_moves_nothing_else(character):
    chain = head_chain(character)
    theta = np.tile(character.rest_theta.astype(np.float32), (3, 1))
    wanted = theta.copy()
    wanted[:, chain.dofs] = np.array([0.2, -0.1, 0.3, -0.2, 0.15, -0.25])[None] * np.array([[1.0], [0.5], [-1.0]])
    targets = dict(enumerate(head_transforms(character, wanted, chain.joint)))
    del targets[1]  # a frame without a head pose keeps its DoFs
    fitted, summary = fit_head_to_hmd(character, theta, targets, chain)
    assert summary["hmd_head_frames"] == 2 and summary["hmd_head_angle_deg_before"] > 5.0
    assert summary["hmd_head_offset_cm_after"] < 0.05 and summary["hmd_head_angle_deg_after"] < 0.1
    got = head_transforms(character, fitted, chain.joint)
    for row, target in targets.items():
        np.testing.assert_allclose(got[row], target, atol=1e-3)
    others = np.setdiff1d(np.arange(theta.shape[1]), chain.dofs)
    np.testing.assert_array_equal(fitted[:, others], theta[:, others])
    np.testing.assert_array_equal(fitted[1], theta[1])


def test_the_headset_markers_make_the_head_observable_to_the_keypoint_ik(character):
    """Keypoints of a motion whose neck and head turn (no keypoint sees them): the plain IK leaves the
    head at the mean pose; solved with the head markers where the head is (one frame without a head
    pose), it turns the head there, the keypoints still fit, and the markers' names and rows follow
    the layout."""
    from egorelight_cli.stages.ik import IKSettings, solve_ik
    from egorelight_cli.stages.ik_eval import fitted_keypoints
    from egorelight_cli.structures.keypoints import Keypoints

    chain = head_chain(character)
    truth = np.tile(character.rest_theta, (4, 1))
    turn = np.array([0.2, -0.1, 0.3, -0.2, 0.15, -0.25])[None] * np.linspace(0.6, 1.0, 4)[:, None]
    truth[:, chain.dofs] = np.clip(turn, *character.skeleton.dof_limits[chain.dofs].T)
    K = len(character.keypoint_names)
    keypoints = Keypoints(fitted_keypoints(character, truth), np.ones((4, K)), np.arange(4))
    targets = dict(enumerate(head_transforms(character, truth, chain.joint)))
    del targets[2]
    marked_keypoints = head_marker_keypoints(keypoints, targets, 0.1)
    assert marked_keypoints.names[K:] == HEAD_MARKER_NAMES
    assert np.isnan(marked_keypoints.xyz[2, K:]).all() and (marked_keypoints.confidence[2, K:] == 0).all()
    np.testing.assert_allclose(marked_keypoints.xyz[0, K], targets[0][:3, 3], atol=1e-6)

    settings = IKSettings()
    plain = solve_ik(character, keypoints, None, settings)
    marked = with_head_markers(character, chain.joint, 0.1)
    solved = solve_ik(marked, marked_keypoints, None, settings, np.r_[np.ones(K), np.full(3, 10.0)])

    summary = head_offset_summary(character, plain.theta, solved.theta, targets, chain.joint)
    assert summary["hmd_head_frames"] == 3 and summary["hmd_head_angle_deg_before"] > 4.0, summary
    assert summary["hmd_head_angle_deg_after"] < 0.3 and summary["hmd_head_offset_cm_after"] < 0.1, summary
    assert np.nanmean(solved.residual_m[:, :K]) < np.nanmean(plain.residual_m) + 0.001  # the keypoints fit as well (m)


def test_cli_ik_places_the_head_by_the_headset(run, tiny_capture, oracle_calibration_artifact, tmp_path):
    """The truth's motion of ego_train as the reference (its mounting then exact in rotation; in
    position up to the simulated subject's own bone lengths), the truth's keypoints as input: every
    frame's head turns towards its HMD pose and moves towards it (the neck's reach bounds how far: the
    tiny preset's IK leaves the torso centimetres off; the exact solve is in the tests above)."""
    from egorelight_cli.artifacts import ArtifactWriter
    from egorelight_cli.io.motion import read_motion_npz, save_motion

    truth = tiny_capture / "groundtruth" / "ego_train"
    with ArtifactWriter(tmp_path / "reference", kind="motion", stage="ik",
                        config={"options": {"sequence": "ego_train"}}) as writer:
        save_motion(writer, read_motion_npz(truth / "motion.npz"))
    common = ("ik", "--preset", "tiny", "--in", truth / "keypoints.npz", "--character", "default")
    result = run(*common, "--calibration", oracle_calibration_artifact, "--hmd-reference", tmp_path / "reference",
                 "--seq", "ego_train", "--gt", truth, "--out", tmp_path / "motion")
    assert result.returncode == 0, result.stderr
    metrics = json.loads((tmp_path / "motion" / "manifest.json").read_text())["metrics"]
    assert metrics["hmd_mount_sequence"] == "ego_train" and metrics["hmd_mount_spread_deg"] < 0.01
    assert metrics["hmd_mount_spread_cm"] < 2.0  # the simulated subject's bones are not the character's
    assert metrics["hmd_head_frames"] == metrics["hmd_mount_frames"] > 0
    # the markers' pull (weight 10) against keypoints of another skeleton: 14 -> 5.4 deg, 7.8 -> 0.8 cm
    assert metrics["hmd_head_angle_deg_before"] > 5.0
    assert metrics["hmd_head_angle_deg_after"] < 0.5 * metrics["hmd_head_angle_deg_before"]
    assert metrics["hmd_head_offset_cm_after"] < metrics["hmd_head_offset_cm_before"] - 1.0
    assert "gt_dof_error_neck_head_deg" in metrics
    assert_one_line_error(run(*common, "--hmd-reference", tmp_path / "reference", "--seq", "ego_train",
                              "--out", tmp_path / "bad"), "--hmd-reference needs --calibration")
    assert not (tmp_path / "bad").exists()
    # a sequence without head poses (the headset not worn): the head stays where IK put it
    result = run(*common, "--calibration", oracle_calibration_artifact, "--hmd-reference", tmp_path / "reference",
                 "--seq", "relight_train", "--out", tmp_path / "unworn")
    assert result.returncode == 0, result.stderr
    unworn = json.loads((tmp_path / "unworn" / "manifest.json").read_text())["metrics"]
    assert unworn["hmd_head_frames"] == 0 and "no head poses of sequence 'relight_train'" in result.stderr
