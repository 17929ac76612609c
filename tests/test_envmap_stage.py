"""The ``egorelight envmap`` stage (LDR-panorama row) and its evaluation against the wild truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from egorelight_cli.geometry.equirect import equirect_directions, yaw_rotation
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.stages.envmap_eval import light_vector_metrics, pose_frame_rotation, truth_in_pose_frame, yaw_of


def test_truth_is_rotated_into_the_pose_frame():
    H = 32
    dirs = equirect_directions(H)
    spot = np.array([0.6, 0.3, -0.74])
    spot /= np.linalg.norm(spot)
    world_map = (np.exp(300.0 * (dirs @ spot - 1.0))[..., None] * np.ones(3)).astype(np.float32)
    world_yaw, frame_yaw = 40.0, -75.0
    # poses in a frame rotated by frame_yaw from the world: T_cal = [R_y(frame_yaw)]^T-ish offset of T_true
    T_true = np.tile(np.eye(4), (5, 1, 1))
    for i in range(5):
        T_true[i, :3, :3] = yaw_rotation(30.0 * i)
    offset = np.eye(4)
    offset[:3, :3] = yaw_rotation(-frame_yaw)  # T_frame_from_world
    offset[:3, 3] = [1.0, 0.0, -2.0]
    T_cal = offset @ T_true
    Q = pose_frame_rotation(T_cal, T_true)
    assert yaw_of(Q) == pytest.approx(frame_yaw)
    estimate_frame_map, q, tilt = truth_in_pose_frame(world_map, world_yaw, Q)
    assert q == pytest.approx(frame_yaw) and tilt == pytest.approx(0.0, abs=1e-6)
    # the spot is seen in the world at R_y(world_yaw) spot, in the pose frame at Q^T of that
    expected = Q.T @ yaw_rotation(world_yaw) @ spot
    found = dirs[np.unravel_index(np.argmax(estimate_frame_map[..., 0]), (H, 2 * H))]
    assert np.degrees(np.arccos(np.clip(found @ expected, -1, 1))) < 4.0


def test_light_vector_metrics():
    stage = LightStage.dome(num_lights=40)
    truth = np.random.default_rng(0).uniform(0.1, 1.0, (40, 3))
    same = light_vector_metrics(truth, truth, stage)
    assert same["light_relative_error"] == pytest.approx(0.0) and same["light_cosine"] == pytest.approx(1.0)
    assert same["dominant_light_direction_error_deg"] == pytest.approx(0.0, abs=1e-5)
    half = light_vector_metrics(0.5 * truth, truth, stage)
    assert half["light_relative_error"] == pytest.approx(0.5) and half["light_gain"] == pytest.approx(2.0)
    assert half["light_relative_error_after_gain"] == pytest.approx(0.0, abs=1e-9)
    flipped = light_vector_metrics(truth[::-1], truth, stage)
    assert flipped["light_relative_error"] > 0.1 and flipped["dominant_light_direction_error_deg"] > 1.0


def _metrics(path):
    return json.loads((path / "manifest.json").read_text())["metrics"]


def _rotated_calibration(source, out, yaw_deg: float):
    """The calibration ``source`` with its wild head poses expressed in a frame turned by ``yaw_deg``
    and shifted (as the headset tracker's frame is)."""
    from egorelight_cli.artifacts import ArtifactWriter
    from egorelight_cli.io.calibration import HeadPoses, read_calibration, write_calibration

    calibration = read_calibration(source)
    offset = np.eye(4)
    offset[:3, :3] = yaw_rotation(yaw_deg)
    offset[:3, 3] = [0.7, 0.0, -1.2]
    poses = calibration.head_poses["wild"]
    moved = HeadPoses(offset @ poses.T_world_from_hmd, poses.frame_ids, poses.valid, poses.num_markers,
                      poses.residual_px)
    calibration.head_poses["wild"] = moved
    with ArtifactWriter(out, kind="calibration", stage="test", config={"yaw": yaw_deg}) as writer:
        write_calibration(writer.workdir, calibration)
    return out


def test_envmap_stage_on_the_tiny_capture(tiny_capture, oracle_calibration_artifact, tmp_path, run):
    out = tmp_path / "envmap" / "wild"
    result = run("envmap", "--preset", "tiny", "--capture", tiny_capture, "--calibration", oracle_calibration_artifact,
                 "--out", out, "-q")
    assert result.returncode == 0, result.stderr
    for name in ("envmap.exr", "panorama.exr", "coverage.png", "colour_model.json", "light_intensities.npz",
                 "preview.png"):
        assert (out / name).is_file(), name
    from egorelight_cli.io.exr import read_exr
    from egorelight_cli.io.images import read_image
    from egorelight_cli.io.npz import read_npz
    from egorelight_cli.render.envmaps import load_envmap

    envmap = load_envmap(out / "envmap.exr")
    coverage = read_image(out / "coverage.png") > 0
    panorama = read_exr(out / "panorama.exr")
    assert envmap.shape == (16, 32, 3) and coverage.shape == (16, 32) and "weight.Y" in panorama.channels
    np.testing.assert_allclose(envmap[coverage], panorama.layer("")[coverage], rtol=1e-5)  # A = I, gamma = 1
    assert (envmap >= 0).all() and envmap[~coverage].max() > 0  # inpainted
    model = json.loads((out / "colour_model.json").read_text())
    assert model["row"] == "ldr_panorama_only" and np.allclose(model["A"], np.eye(3, 6)) and model["gamma"] == 1.0
    arrays, meta = read_npz(out / "light_intensities.npz")
    lights = LightStage.from_json(tiny_capture / "rig" / "lights.json")
    np.testing.assert_allclose(arrays["intensities"], lights.envmap_to_intensities(envmap), rtol=1e-5)
    from egorelight_cli.artifacts import validate_manifest
    from egorelight_cli.errors import EgorelightError

    manifest = json.loads((out / "manifest.json").read_text())
    validate_manifest(manifest)
    with pytest.raises(EgorelightError):  # the schema requires the map and its colour model
        validate_manifest(dict(manifest, outputs=[o for o in manifest["outputs"] if o["name"] != "envmap.exr"]))
    m = _metrics(out)
    assert m["scan_frames"] == 8 and 0.25 < m["coverage_fraction"] < 0.6
    assert m["truth_frame_yaw_deg"] == pytest.approx(0.0, abs=1e-6)  # the oracle's poses are in the world
    # the LDR panorama of the right place in the right frame: light from the right side, textures close
    assert m["dominant_light_direction_error_deg"] < 20.0
    assert m["log_l1_observed"] < 0.7 and m["log_l1_unobserved"] < 0.7
    assert 0.0 < m["light_cosine"] <= 1.0
    # up to date: a second run is a no-op
    before = (out / "manifest.json").read_bytes()
    assert run("envmap", "--preset", "tiny", "--capture", tiny_capture, "--calibration", oracle_calibration_artifact,
               "--out", out, "-q").returncode == 0
    assert (out / "manifest.json").read_bytes() == before

    # poses in another frame (the headset tracker's): the map turns with them, the scores stay
    turned = _rotated_calibration(oracle_calibration_artifact, tmp_path / "turned_calibration", 90.0)
    out2 = tmp_path / "envmap_turned"
    assert run("envmap", "--preset", "tiny", "--capture", tiny_capture, "--calibration", turned, "--out", out2,
               "-q").returncode == 0
    m2 = _metrics(out2)
    assert m2["truth_frame_yaw_deg"] == pytest.approx(-90.0, abs=1e-6)
    assert m2["log_l1_observed"] == pytest.approx(m["log_l1_observed"], abs=2e-3)
    assert m2["log_l1_unobserved"] == pytest.approx(m["log_l1_unobserved"], abs=0.05)
    assert m2["coverage_fraction"] == pytest.approx(m["coverage_fraction"], abs=1e-3)
    turned_map = load_envmap(out2 / "envmap.exr")
    np.testing.assert_allclose(np.roll(turned_map, 8, axis=1)[coverage], envmap[coverage], atol=2e-3)  # rotate_envmap(E, 90)


@pytest.mark.parametrize("args, message", [
    (("--seq", "nope"), "no sequence"),
    (("--set", "panorama.height=2"), "panorama.height"),
    (("--set", "roles=[down_left,front_up]"), "front_up"),
    (("--set", "inpaint.method=gemini"), "inpainting method"),
])
def test_envmap_bad_inputs_are_one_line_errors(tiny_capture, oracle_calibration_artifact, tmp_path, run, args, message):
    out = tmp_path / "envmap"
    result = run("envmap", "--preset", "tiny", "--capture", tiny_capture, "--calibration", oracle_calibration_artifact,
                 "--out", out, *args)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert not out.exists() and not any(p.name.startswith("envmap.tmp") for p in tmp_path.iterdir())


def test_envmap_needs_head_poses_of_the_sequence(tiny_capture, tmp_path, run):
    from egorelight_cli.artifacts import ArtifactWriter
    from egorelight_cli.io.calibration import write_calibration
    from egorelight_cli.synth.groundtruth import oracle_calibration

    calibration = oracle_calibration(tiny_capture)
    del calibration.head_poses["wild"]
    with ArtifactWriter(tmp_path / "calibration", kind="calibration", stage="test", config={}) as writer:
        write_calibration(writer.workdir, calibration)
    result = run("envmap", "--preset", "tiny", "--capture", tiny_capture, "--calibration", tmp_path / "calibration",
                 "--out", tmp_path / "envmap")
    assert result.returncode == 2 and "no head poses for sequence 'wild'" in result.stderr
    assert not (tmp_path / "envmap").exists()
