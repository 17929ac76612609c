"""BVH reading, forward kinematics, keypoint mapping, and retargeting the shared CMU clip."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import BVH_EXAMPLE
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.bvh import (BvhClip, bvh_joint_positions, bvh_keypoints, format_bvh, map_bvh_joints, parse_bvh,
                                   read_bvh, write_bvh)

TWO_BONES = """HIERARCHY
ROOT Hips
{
\tOFFSET 0 0 0
\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
\tJOINT LeftUpLeg
\t{
\t\tOFFSET 0.1 0 0
\t\tCHANNELS 3 Zrotation Xrotation Yrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0 -0.5 0
\t\t}
\t}
}
MOTION
Frames: 2
Frame Time: 0.04
1 2 3 0 0 0 0 0 0
0 1 0 90 0 0 0 90 0
"""


def test_parse_and_forward_kinematics():
    clip = parse_bvh(TWO_BONES)
    assert clip.joint_names == ("Hips", "LeftUpLeg", "LeftUpLeg_End")
    assert list(clip.parents) == [-1, 0, 1] and clip.num_frames == 2 and clip.fps == pytest.approx(25.0)
    pos = bvh_joint_positions(clip)
    np.testing.assert_allclose(pos[0], [[1, 2, 3], [1.1, 2, 3], [1.1, 1.5, 3]], atol=1e-12)
    # frame 1: hips rotated +90 deg about z (x -> y), leg rotated +90 deg about x (in the hips' frame)
    # Rz(90) @ [0.1,0,0] = [0,0.1,0]; leg end: Rz(90) @ Rx(90) @ [0,-0.5,0] = Rz(90) @ [0,0,-0.5] = [0,0,-0.5]
    np.testing.assert_allclose(pos[1], [[0, 1, 0], [0, 1.1, 0], [0, 1.1, -0.5]], atol=1e-12)


def test_channel_order_is_file_order():
    a = parse_bvh(TWO_BONES.replace("Zrotation Xrotation Yrotation", "Xrotation Zrotation Yrotation")
                  .replace("0 1 0 90 0 0 0 90 0", "0 0 0 0 0 0 90 90 0"))
    b = parse_bvh(TWO_BONES.replace("0 1 0 90 0 0 0 90 0", "0 0 0 0 0 0 90 90 0"))
    # leg channels (90, 90, 0): Rx(90) Rz(90) vs Rz(90) Rx(90) move the end site differently
    assert not np.allclose(bvh_joint_positions(a)[1, 2], bvh_joint_positions(b)[1, 2])


def test_format_round_trip(tmp_path):
    clip = parse_bvh(TWO_BONES)
    back = read_bvh(write_bvh(clip, tmp_path / "c.bvh"))
    assert back.joint_names == clip.joint_names and back.channels == clip.channels
    np.testing.assert_allclose(back.motion, clip.motion)
    assert format_bvh(back) == format_bvh(clip)


@pytest.mark.parametrize("text, message", [
    (TWO_BONES.replace("0 1 0 90 0 0 0 90 0\n", "0 1 0 90 0 0 0 90\n"), "holds 17 values, expected 2 frames"),
    (TWO_BONES.replace("Yrotation Xrotation\n", "Yrotation Wrotation\n"), "unknown channel 'Wrotation'"),
    (TWO_BONES.replace("OFFSET 0.1 0 0", "OFFSET 0.1 x 0"), "line 8: an OFFSET value is not a number"),
    (TWO_BONES.replace("Frame Time: 0.04", "Frame Time: 0"), "frame time must be positive"),
    ("HIERARCHY\nROOT A\n{\n", "file ends"),
])
def test_parse_errors_name_the_problem(text, message):
    with pytest.raises(EgorelightError, match=message):
        parse_bvh(text, "x.bvh")


def test_read_missing_file(tmp_path):
    with pytest.raises(EgorelightError, match="BVH file not found"):
        read_bvh(tmp_path / "none.bvh")


def test_joint_name_mapping_conventions():
    cmu = ["Hips", "LHipJoint", "LeftHip", "LeftKnee", "LeftAnkle", "LeftToe", "lowerneck", "Neck", "LeftCollar",
           "LeftShoulder", "LeftElbow", "LeftWrist", "lhand"]
    mapping = {k: cmu[j] for k, j in map_bvh_joints(cmu).items()}
    assert mapping["LeftUpLeg"] == "LeftHip" and mapping["LeftLeg"] == "LeftKnee" and mapping["LeftFoot"] == "LeftAnkle"
    assert mapping["LeftArm"] == "LeftShoulder" and mapping["LeftForeArm"] == "LeftElbow"
    assert mapping["LeftHand"] == "LeftWrist" and mapping["Neck"] == "lowerneck" and "RightArm" not in mapping
    mixamo = ["mixamorig:Hips", "mixamorig:LeftShoulder", "mixamorig:LeftArm", "mixamorig:LeftForeArm",
              "mixamorig:LeftHand", "mixamorig:LeftHandIndex1", "mixamorig:LeftHandIndex4"]
    mapping = {k: mixamo[j] for k, j in map_bvh_joints(mixamo).items()}
    assert mapping["LeftArm"] == "mixamorig:LeftArm"  # the clavicle (LeftShoulder) is not the shoulder joint
    assert mapping["LeftHandIndex1"] == "mixamorig:LeftHandIndex1" and mapping["LeftHandIndexEE"] == "mixamorig:LeftHandIndex4"


def test_bvh_keypoints_units_and_up_axis():
    names = ("Hips", "LeftHip", "LeftKnee")
    clip = BvhClip(names, np.array([-1, 0, 1]), np.array([[0, 0, 0], [10, 0, 0], [0, 0, -40.0]]),
                   (("Xposition", "Yposition", "Zposition"), (), ()), np.array([[0, 0, 90.0]]), 0.01)
    kp, mapping = bvh_keypoints(clip, unit_scale=0.01, up_axis="z")
    assert mapping == {"LeftUpLeg": "LeftHip", "LeftLeg": "LeftKnee"}
    knee = kp.xyz[0, kp.names.index("LeftLeg")]
    np.testing.assert_allclose(knee, [0.1, 0.5, 0.0], atol=1e-6)  # z up (0.9 - 0.4 = 0.5) became y
    assert kp.confidence[0, kp.names.index("Neck")] == 0 and np.isnan(kp.xyz[0, 0]).all()
    with pytest.raises(EgorelightError, match="up axis"):
        bvh_keypoints(clip, up_axis="x")


@pytest.fixture
def cmu_clip():
    if not BVH_EXAMPLE.exists():
        pytest.skip("../shared/data/motion is not available")
    return read_bvh(BVH_EXAMPLE)


def test_cmu_clip_reads(cmu_clip):
    assert cmu_clip.num_frames == 995 and cmu_clip.fps == pytest.approx(120, rel=1e-3)
    kp, mapping = bvh_keypoints(cmu_clip)
    assert len(mapping) == 17  # 15 body keypoints + both hand wrists; fingers are absent
    feet = kp.xyz[:, [kp.names.index(n) for n in ("LeftToeBase", "RightToeBase")], 1]
    assert -0.02 < feet.min() < 0.06  # metres, Y up, floor at 0


def test_cmu_retargeting_is_plausible(cmu_clip):
    from egorelight_cli.io.character import load_default_character
    from egorelight_cli.stages.ik import IKSettings, fit_global_scale, fit_metrics, scale_keypoints, solve_ik

    character = load_default_character()
    kp, _ = bvh_keypoints(cmu_clip)
    kp = kp.select(slice(0, None, 10))  # 100 frames at 12 fps
    scale = fit_global_scale(character, kp)
    assert 0.8 < scale < 1.5
    result = solve_ik(character, scale_keypoints(kp, scale), settings=IKSettings(lm_iterations=15))
    metrics = fit_metrics(result)
    assert metrics["mpjpe_input_body_cm"] < 6.0  # joint placement differs between the CMU rig and ours
    names = character.keypoint_names
    feet = result.fitted_keypoints[:, [names.index(n) for n in ("LeftFoot", "RightFoot", "LeftToeBase", "RightToeBase")], 1]
    lowest = feet.min(axis=1)  # the lower foot of each frame is near the floor while walking
    assert np.median(lowest) < 0.12 and lowest.min() > -0.05
    hips = result.fitted_keypoints[:, names.index("LeftUpLeg"), 1]
    assert 0.7 < np.median(hips) < 1.2  # standing, not crouched or flying
