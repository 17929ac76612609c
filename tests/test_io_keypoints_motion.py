"""keypoints.npz and motion.npz payloads: round trips, validation, artifacts, errors."""

from __future__ import annotations

import numpy as np
import pytest

from egorelight_cli.artifacts import ArtifactWriter
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.keypoints import (KEYPOINTS_PAYLOAD, Keypoints, load_keypoints, read_keypoints_npz,
                                         save_keypoints, write_keypoints_npz)
from egorelight_cli.io.motion import MOTION_PAYLOAD, Motion, load_motion, read_motion_npz, save_motion, write_motion_npz
from egorelight_cli.io.npz import write_npz
from egorelight_cli.structures.keypoints import KEYPOINT_NAMES


def make_keypoints(T: int = 5, fps: float | None = 30.0) -> Keypoints:
    rng = np.random.default_rng(0)
    return Keypoints(rng.normal(size=(T, 57, 3)), rng.uniform(0, 1, (T, 57)), np.arange(10, 10 + T), fps=fps)


def make_motion(T: int = 4, D: int = 5) -> Motion:
    rng = np.random.default_rng(1)
    return Motion(rng.normal(size=(T, D)), tuple(f"d{i}" for i in range(D)), np.arange(T) * 2, 25.0,
                  rng.normal(size=(T, 57, 3)), np.full((T, 57), np.nan))


def test_keypoints_round_trip(tmp_path):
    kp = make_keypoints()
    write_keypoints_npz(tmp_path / "k.npz", kp)
    back = read_keypoints_npz(tmp_path / "k.npz")
    assert back.names == KEYPOINT_NAMES and back.fps == 30.0
    np.testing.assert_array_equal(back.frame_ids, kp.frame_ids)
    np.testing.assert_allclose(back.xyz, kp.xyz)
    assert back.xyz.dtype == np.float32 and back.confidence.dtype == np.float32 and back.frame_ids.dtype == np.int64


def test_missing_keypoints_get_zero_confidence():
    xyz = np.zeros((2, 57, 3))
    xyz[0, 3] = np.nan
    kp = Keypoints(xyz, np.ones((2, 57)), [0, 1])
    assert kp.confidence[0, 3] == 0 and kp.confidence[1, 3] == 1 and np.isnan(kp.xyz[0, 3]).all()


@pytest.mark.parametrize("change, message", [
    (dict(xyz=np.zeros((2, 56, 3))), "expected (T, 57, 3)"),
    (dict(confidence=np.full((2, 57), 1.5)), "outside [0, 1]"),
    (dict(confidence=np.full((2, 57), np.nan)), "NaN"),
    (dict(frame_ids=np.array([3, 3])), "strictly increasing"),
    (dict(frame_ids=np.array([0.0, 1.0])), "integers"),
])
def test_keypoints_validation(change, message):
    args = dict(xyz=np.zeros((2, 57, 3)), confidence=np.ones((2, 57)), frame_ids=np.array([0, 1]))
    args.update(change)
    with pytest.raises(EgorelightError, match=message.replace("[", r"\[").replace("(", r"\(").replace(")", r"\)")):
        Keypoints(**args)


def test_keypoints_wrong_kind_and_version(tmp_path):
    write_npz(tmp_path / "m.npz", {"a": np.ones(2)}, {"kind": "egorelight/motion", "version": 1})
    with pytest.raises(EgorelightError, match="expected egorelight/keypoints"):
        read_keypoints_npz(tmp_path / "m.npz")
    write_npz(tmp_path / "v.npz", {"a": np.ones(2)}, {"kind": "egorelight/keypoints", "version": 99})
    with pytest.raises(EgorelightError, match="version mismatch"):
        read_keypoints_npz(tmp_path / "v.npz")


def test_keypoints_artifacts_directory_and_single_file(tmp_path):
    kp = make_keypoints()
    with ArtifactWriter(tmp_path / "kp", kind="keypoints", stage="test") as writer:
        save_keypoints(writer, kp)
    with ArtifactWriter(tmp_path / "single.npz", kind="keypoints", stage="test") as writer:
        save_keypoints(writer, kp)
    for path in (tmp_path / "kp", tmp_path / "single.npz"):
        back, artifact = load_keypoints(path)
        assert artifact is not None and artifact.kind == "keypoints"
        np.testing.assert_allclose(back.xyz, kp.xyz)
    assert (tmp_path / "kp" / KEYPOINTS_PAYLOAD).is_file()
    back, artifact = load_keypoints(tmp_path / "kp" / KEYPOINTS_PAYLOAD)  # the payload inside a directory
    assert back.num_frames == 5


def test_load_keypoints_rejects_other_artifact_kinds(tmp_path):
    with ArtifactWriter(tmp_path / "m", kind="motion", stage="test") as writer:
        save_motion(writer, make_motion())
    with pytest.raises(EgorelightError, match="wrong artifact kind"):
        load_keypoints(tmp_path / "m")
    with pytest.raises(EgorelightError, match="not found"):
        load_keypoints(tmp_path / "nothing")


def test_motion_round_trip_and_artifact(tmp_path):
    motion = make_motion()
    write_motion_npz(tmp_path / "m.npz", motion)
    back = read_motion_npz(tmp_path / "m.npz")
    assert back.dof_names == motion.dof_names and back.fps == 25.0
    np.testing.assert_allclose(back.theta, motion.theta.astype(np.float32))
    assert np.isnan(back.residual_m).all() and back.fitted_keypoints.shape == (4, 57, 3)
    with ArtifactWriter(tmp_path / "art", kind="motion", stage="test") as writer:
        save_motion(writer, motion)
    loaded, artifact = load_motion(tmp_path / "art")
    assert artifact.kind == "motion" and (tmp_path / "art" / MOTION_PAYLOAD).is_file()
    np.testing.assert_array_equal(loaded.frame_ids, motion.frame_ids)


def test_motion_validation():
    with pytest.raises(EgorelightError, match="NaN"):
        Motion(np.full((2, 3), np.nan), ("a", "b", "c"), [0, 1], 30.0)
    with pytest.raises(EgorelightError, match=r"expected \(T, 2\)"):
        Motion(np.zeros((2, 3)), ("a", "b"), [0, 1], 30.0)
    with pytest.raises(EgorelightError, match="fps"):
        Motion(np.zeros((2, 2)), ("a", "b"), [0, 1], 0.0)
    motion = Motion(np.zeros((2, 2)), ("a", "b"), [0, 1], 30.0)
    motion.check_dofs(("a", "b"))
    with pytest.raises(EgorelightError, match="has 2 DoFs but the character has 3"):
        motion.check_dofs(("a", "b", "c"))
    with pytest.raises(EgorelightError, match="DoF 1 is 'b'"):
        motion.check_dofs(("a", "x"))


def test_lone_npz_with_a_bad_fps_text_arrays_or_no_frame_are_errors_naming_the_file(tmp_path):
    """Hand-made lone payloads: an fps vector or text where numbers belong ended in internal
    TypeError / ValueError; a motion of no frame in an IndexError inside synth."""
    T = 3
    keypoints = dict(xyz=np.zeros((T, 57, 3), np.float32), confidence=np.ones((T, 57), np.float32),
                     frame_ids=np.arange(T))
    cases = {
        "kp_fps.npz": ({**keypoints, "fps": np.array([30.0, 30.0])}, "keypoints", "fps must be one number"),
        "kp_text.npz": ({**keypoints, "xyz": np.full((T, 57, 3), "a")}, "keypoints", "wrong type"),
        "motion_fps.npz": ({"theta": np.zeros((T, 5)), "dof_names": np.array(list("abcde")), "frame_ids": np.arange(T),
                            "fps": np.array([30.0, 30.0])}, "motion", "fps must be one number"),
        "motion_zero_fps.npz": ({"theta": np.zeros((T, 5)), "dof_names": np.array(list("abcde")),
                                 "frame_ids": np.arange(T), "fps": np.array(0.0)}, "motion", "positive"),
        "motion_empty.npz": ({"theta": np.zeros((0, 5)), "dof_names": np.array(list("abcde")),
                              "frame_ids": np.arange(0), "fps": np.array(30.0)}, "motion", "no frame"),
    }
    for name, (arrays, kind, says) in cases.items():
        write_npz(tmp_path / name, arrays, {"kind": f"egorelight/{kind}", "version": 1})
        load = load_keypoints if kind == "keypoints" else load_motion
        with pytest.raises(EgorelightError, match=says) as info:
            load(tmp_path / name)
        assert name in str(info.value)
