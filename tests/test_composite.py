"""``egorelight composite`` (issue 20 item 1): the inverse colour mapping, the placement, the stage on
the tiny capture with its scores against the oracle, and one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from egorelight_cli.geometry.equirect import yaw_rotation
from egorelight_cli.errors import EgorelightError
from egorelight_cli.nn.colour_inverse import CameraMapping, camera_mapping, diagonal_inverse, invert_colour
from egorelight_cli.nn.colour_model import RootPolynomialColour
from egorelight_cli.stages import composite as cp
from tiny_models import cli_exit_code as _main  # the CLI in-process


def _model() -> RootPolynomialColour:
    A = np.concatenate([np.diag([1.6, 1.2, 0.8]), np.zeros((3, 3))], axis=1)
    A[0, 1], A[2, 3], A[1, 5], A[0, 4] = 0.1, 0.2, -0.15, 0.05
    return RootPolynomialColour(A, 1.5)


def test_inverse_colour_mapping_round_trips_the_forward_model():
    rng = np.random.default_rng(0)
    model = _model()
    E_l = rng.uniform(0.0, 3.0, (60, 50, 3))
    E_l[0, 0] = 0.0  # black
    E_l[0, 1] = [0.0, 0.5, 1.0]  # a zero channel
    E_l[0, 2] = [0.05, 2.0, 0.02]  # saturated colour (projected Newton stalls on these)
    E_h = model.apply_numpy(E_l).astype(np.float64)
    back, residual = invert_colour(model, E_h)
    assert float(residual.max()) < 1e-5  # every pixel solved, none stuck
    # forward of the inverse reproduces E_h (the stage maps E_h -> E_l; the envmap maps back)
    np.testing.assert_allclose(model.apply_numpy(back), E_h, rtol=1e-4, atol=1e-5)
    # E_l itself: exact where no channel is near 0 (there the inverse is ill-conditioned)
    clear = E_l.min(axis=-1) > 0.05
    assert clear.mean() > 0.9
    np.testing.assert_allclose(back[clear], E_l[clear], rtol=1e-4, atol=1e-5)
    assert np.abs(back[0, 0]).max() < 1e-6 and np.abs(back[0, 1] - E_l[0, 1]).max() < 1e-2
    # fewer steps are measurably worse: the iterations do the work
    _, coarse = invert_colour(model, E_h, iterations=2)
    assert float(coarse.max()) > 100 * float(residual.max())
    # the identity model inverts to the input; (A, gamma) tuples work too
    same, _ = invert_colour((np.eye(3, 6), 1.0), np.abs(E_h))
    np.testing.assert_allclose(same, np.abs(E_h), rtol=1e-5, atol=1e-7)


def test_avatar_colour_is_inverted_unpremultiplied_and_composited_in_linear_light():
    model = _model()
    straight = np.array([0.2, 0.4, 0.3])
    E_h = model.apply_numpy(straight)
    alpha = np.array([[0.5, 0.0]], np.float32)
    premult = (E_h[None, None] * alpha[..., None]).astype(np.float32)
    mapped, residual = cp.avatar_to_camera(premult, alpha, CameraMapping("exact", model=model))
    np.testing.assert_allclose(mapped[0, 0], 0.5 * straight, rtol=1e-4)
    assert np.all(mapped[0, 1] == 0) and residual < 1e-4
    background = np.full((1, 2, 3), 128, np.uint8)
    out = cp.composite_image(background, mapped, alpha)
    from egorelight_cli.io.images import linear_to_srgb, srgb_to_linear

    expected = linear_to_srgb(0.5 * straight + 0.5 * srgb_to_linear(np.full(3, 128 / 255)))
    np.testing.assert_array_equal(out[0, 0], np.round(expected * 255).astype(np.uint8))
    np.testing.assert_array_equal(out[0, 1], background[0, 1])


def test_diagonal_inverse_is_exact_for_channel_gains_and_leaves_an_albedo_as_it_is():
    rng = np.random.default_rng(2)
    sky = rng.uniform(0.05, 1.0, (16, 32, 3)) * np.array([0.7, 0.85, 1.0])  # a bluish panorama E_l
    # a model that is a gain per channel: the diagonal inverse is its exact inverse
    gains = RootPolynomialColour(np.concatenate([np.diag([1.6, 1.2, 0.8]), np.zeros((3, 3))], axis=1), 1.0)
    g = diagonal_inverse(gains, gains.apply_numpy(sky))
    np.testing.assert_allclose(g, 1.0 / np.array([1.6, 1.2, 0.8]), rtol=1e-5)
    # with cross terms: the gains are the least-squares fit of E_l ~ g E_h over the map's texels,
    # each weighted by its solid angle
    from egorelight_cli.geometry.equirect import equirect_solid_angles

    model = _model()
    E_h = model.apply_numpy(sky).astype(np.float64)
    g = diagonal_inverse(model, E_h)
    E_l = invert_colour(model, E_h)[0].astype(np.float64).reshape(-1, 3)
    root_w = np.sqrt(equirect_solid_angles(16, 32).reshape(-1))
    for c in range(3):
        best = np.linalg.lstsq(root_w[:, None] * E_h.reshape(-1, 3)[:, c:c + 1], root_w * E_l[:, c], rcond=None)[0][0]
        unweighted = np.linalg.lstsq(E_h.reshape(-1, 3)[:, c:c + 1], E_l[:, c], rcond=None)[0][0]
        assert abs(g[c] - best) < 1e-6 * abs(best) and abs(g[c] - unweighted) > 1e-5 * abs(best)
    # an avatar colour = albedo x light: a gain per channel (any) keeps the albedo's ratios, the exact
    # inverse of the cross terms does not (on a saturated red albedo it moves the hue the light did not have)
    albedo = np.array([0.6, 0.15, 0.1])
    light = E_h.reshape(-1, 3).mean(axis=0)
    diagonal = camera_mapping(model, E_h, "diagonal")
    exact = camera_mapping(model, E_h, "exact")
    lit = (albedo * light)[None]
    np.testing.assert_allclose(diagonal.apply(lit)[0][0], albedo * diagonal.apply(light[None])[0][0], rtol=1e-5)
    ratio_exact = exact.apply(lit)[0][0] / exact.apply(light[None])[0][0]
    assert np.abs(ratio_exact / albedo - 1).max() > 0.1  # the exact inverse distorts the albedo by > 10 %
    assert diagonal.to_json()["method"] == "linear" and exact.to_json()["method"] == "exact"
    with pytest.raises(EgorelightError, match="colour.inverse must be one of"):
        camera_mapping(model, E_h, "full")


def test_a_linear_camera_mapping_is_the_simulated_camera_response():
    from egorelight_cli.render.camera_response import CameraResponse

    # a non-symmetric colour matrix: the orientation matters
    response = CameraResponse(exposure=0.7, colour_matrix=[[0.9, 0.2, 0.0], [0.05, 1.0, 0.1], [-0.1, 0.0, 1.1]])
    radiance = np.random.default_rng(4).uniform(0.0, 1.5, (50, 3))
    mapping = CameraMapping("linear", matrix=response.exposure * response.colour_matrix)
    mapped, residual = mapping.apply(radiance)
    np.testing.assert_allclose(mapped, np.maximum(response.sensor(radiance), 0.0), rtol=1e-5, atol=1e-6)
    assert not residual.any()
    for bad, needle in ((dict(method="linear"), "3x3 matrix"), (dict(method="exact"), "colour model"),
                        (dict(method="cubic", matrix=np.eye(3)), "exact or linear")):
        with pytest.raises(EgorelightError, match=needle):
            CameraMapping(**bad)


def test_composite_scores_pool_the_pixels_of_all_frames():
    import torch

    from egorelight_cli.render.image_metrics import psnr, ssim
    from egorelight_cli.stages.composite_eval import frame_errors, pooled_scores

    rng = np.random.default_rng(3)
    truth = rng.integers(0, 256, (2, 40, 50, 3), dtype=np.uint8)
    image = truth.copy()
    big = np.zeros((40, 50), bool)
    big[5:35, 5:45] = True  # 1200 pixels, 10 grey levels off
    image[0][big] = np.clip(truth[0][big].astype(int) + 10, 0, 255)
    small = np.zeros((40, 50), bool)
    small[20:22, 20:22] = True  # 4 pixels, far off
    image[1][small] = 255 - truth[1][small]
    errors = [frame_errors(image[k], truth[k], m) for k, m in enumerate((big, small))]
    # one frame alone: the plain masked PSNR / SSIM of image_metrics
    a, b = (torch.from_numpy(x[0].astype(np.float64) / 255) for x in (image, truth))
    one = pooled_scores(errors[:1])
    assert abs(one["psnr"] - float(psnr(a, b, torch.from_numpy(big)))) < 1e-9
    assert abs(one["ssim"] - 100 * float(ssim(a, b, torch.from_numpy(big)))) < 1e-9
    # pooled: the squared error over all 1204 pixels, so the 4-pixel frame moves it by < 2 dB, where a
    # mean of the two frames' PSNRs loses > 5 dB to it
    both = pooled_scores(errors)
    expected = 10 * np.log10(3 * 1204 / (errors[0][0] + errors[1][0]))
    assert abs(both["psnr"] - expected) < 1e-9 and one["psnr"] - both["psnr"] < 2.0
    per_frame_mean = np.mean([pooled_scores([e])["psnr"] for e in errors])
    assert one["psnr"] - per_frame_mean > 5.0
    assert pooled_scores([]) == {"psnr": None, "ssim": None}


@pytest.mark.parametrize("yaw", [0.0, 35.0, -120.0])
def test_placement_puts_the_feet_on_the_floor_at_the_requested_spot(yaw):
    rng = np.random.default_rng(1)
    # an avatar facing +X in the studio (its right hip towards +Z), standing 3 cm above its floor
    vertices = rng.uniform([-0.2, 0.03, -0.25], [0.2, 1.7, 0.25], (500, 3)) + [1.0, 0.0, -0.5]
    left_hip, right_hip = np.array([1.0, 0.95, -0.6]), np.array([1.0, 0.95, -0.4])
    # User 2 at (0.5, 1.62, 2.0) in a tracker frame, looking along azimuth 70 deg, camera tilted down
    head = np.array([0.5, 1.62, 2.0])
    R = yaw_rotation(-70.0) @ np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1.0]])  # cam +z -> -Z, then turned
    tilt = np.array([[1, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]])
    T_cam = np.eye(4)
    T_cam[:3, :3], T_cam[:3, 3] = R @ tilt, head + [0.05, -0.03, 0.02]
    forward = np.array([np.sin(np.radians(70.0)), 0.0, -np.cos(np.radians(70.0))])
    right = np.cross(forward, [0.0, 1.0, 0.0])
    assert T_cam[:3, 2] @ forward > 0.9  # the camera looks (roughly) along forward
    placement = cp.place_avatar(vertices, left_hip, right_hip, T_cam, head, 2.0, -0.5, yaw, floor_y=0.12)
    moved = vertices @ placement.T[:3, :3].T + placement.T[:3, 3]
    assert moved[:, 1].min() == pytest.approx(0.12, abs=1e-9)  # feet on the floor
    hips = (0.5 * (left_hip + right_hip)) @ placement.T[:3, :3].T + placement.T[:3, 3]
    spot = head + 2.0 * forward - 0.5 * right
    np.testing.assert_allclose(hips[[0, 2]], spot[[0, 2]], atol=1e-9)  # hips above the spot
    np.testing.assert_allclose(placement.spot, [spot[0], 0.12, spot[2]], atol=1e-9)
    facing = placement.T[:3, :3] @ np.array([1.0, 0.0, 0.0])
    np.testing.assert_allclose(facing, yaw_rotation(yaw) @ -forward, atol=1e-9)  # yaw 0: faces User 2
    np.testing.assert_allclose(placement.T[:3, :3] @ [0, 1.0, 0], [0, 1.0, 0], atol=1e-12)  # upright
    # the camera expressed in the studio sees the studio avatar where User 2's camera sees the placed one
    from egorelight_cli.geometry.cameras import Camera, invert_rigid

    camera = Camera("pinhole", np.eye(3), np.zeros(5), 10, 10, invert_rigid(T_cam), "front_left")
    studio = placement.camera_in_studio(camera)
    p_studio = np.append(vertices[0], 1.0)
    np.testing.assert_allclose(studio.T_cam_from_world @ p_studio,
                               camera.T_cam_from_world @ np.append(moved[0], 1.0), atol=1e-9)


def test_place_option_and_settings_are_checked():
    assert cp.parse_place("2, 0.5, -90") == (2.0, 0.5, -90.0)
    for bad in ("2,0", "a,b,c", "1,2,3,4", "nan,0,0", "500,0,0"):
        with pytest.raises(EgorelightError):
            cp.parse_place(bad)


def test_auto_eye_height_takes_the_studio_head_poses_only():
    from types import SimpleNamespace

    def poses(height: float, n: int = 5):
        T = np.repeat(np.eye(4)[None], n, axis=0)
        T[:, 1, 3] = height
        return SimpleNamespace(T_world_from_hmd=T, valid=np.ones(n, bool))

    head_poses = {"ego_train": poses(1.62), "test": poses(1.70), "wild": poses(-0.3, 50)}  # wild: a tracker's frame
    calibration = SimpleNamespace(head_poses=head_poses, source=None,
                                  head_poses_in_studio_world=lambda name: name != "wild")
    assert cp.eye_height(calibration, exclude="test") == pytest.approx(1.62)
    assert cp.eye_height(calibration, exclude="wild") == pytest.approx(1.66)
    with pytest.raises(EgorelightError, match="eye_height_m"):
        cp.eye_height(SimpleNamespace(head_poses={"wild": poses(-0.3)}, source=None,
                                      head_poses_in_studio_world=lambda name: False), exclude="test")


@pytest.fixture(scope="module")
def avatar(tiny_capture, skinned_meshes, oracle_calibration_artifact, tiny_avatar):
    """A tiny geolift model, uvmaps of test / wild / ego_train / relight_train, a (briefly) trained
    relight model and the wild envmap fitted by inverse rendering."""
    root = tiny_avatar  # the session's (conftest.tiny_avatar); the envmap below is this module's own
    assert _main("envmap", "--preset", "tiny", "-q", "--capture", tiny_capture, "--calibration",
                 oracle_calibration_artifact, "--meshes", skinned_meshes / "wild.npz", "--uvmaps", root / "uvmaps_wild",
                 "--model", root / "relight", "--sync-meshes", skinned_meshes / "ego_train.npz", "--sync-uvmaps",
                 root / "uvmaps_ego_train", "--out", root / "envmap") == 0
    return root


def _args(tiny_capture, calibration, skinned_meshes, avatar):
    return ["composite", "--preset", "tiny", "--meshes", skinned_meshes / "test.npz", "--uvmaps",
            avatar / "uvmaps_test", "--model", avatar / "relight", "--capture", tiny_capture, "--calibration",
            calibration, "--envmap", avatar / "envmap", "--seq", "wild"]


def test_composite_on_the_tiny_capture(tiny_capture, oracle_calibration_artifact, skinned_meshes, avatar, tmp_path,
                                       run):
    out = tmp_path / "composite"
    args = _args(tiny_capture, oracle_calibration_artifact, skinned_meshes, avatar)
    result = run(*args, "--place", "2.0,0.0,0.0", "--out", out, "-q")
    assert result.returncode == 0, result.stderr
    from egorelight_cli.artifacts import open_artifact
    from egorelight_cli.io.images import read_image

    artifact = open_artifact(out, kind="composite")  # schema-valid, digests verified
    manifest = artifact.manifest
    m = manifest["metrics"]
    frames = sorted((out / "frames").glob("*.png"))
    assert len(frames) == m["frames"] == 2 and (out / "preview.png").is_file()
    first = read_image(frames[0])
    assert first.shape == (150, 200, 3) and first.dtype == np.uint8  # tiny: half the 400x300 front camera
    assert m["frames_with_avatar"] == 2 and min(m["avatar_coverage"]) > 0.01  # the avatar is in view
    assert "imageio-ffmpeg" in manifest["video"] or (out / "composite.mp4").is_file()
    placement = json.loads((out / "placement.json").read_text())
    assert placement["floor"] == "head" and np.asarray(placement["T_user2_from_studio"]).shape == (4, 4)
    assert manifest["timing"]["per_frame_s"] > 0 and manifest["runtime"]["device"] == "cpu"
    # scored against the oracle: every row (the baselines, the true-light oracle) is scored
    rows = m["rows"]
    assert set(rows) == {"composite", "flat_studio", "ldr_panorama_only", "true_light"} and m["scored_frames"] == 2
    for row in rows.values():
        assert np.isfinite(row["psnr"]) and np.isfinite(row["ssim"])
    assert m["psnr"] == rows["composite"]["psnr"] > 12.0, rows
    assert m["mask_iou"] > 0.5
    # floor at y = 0 of the (oracle, metric) frame: the same spot within the eye-height estimate
    world = tmp_path / "world"
    assert run(*args, "--set", "placement.floor=world", "--set", "colour.inverse=exact", "--out", world,
               "-q").returncode == 0
    moved = json.loads((world / "placement.json").read_text())
    assert moved["floor_y_m"] == 0.0 and abs(placement["floor_y_m"]) < 0.15
    # the avatar's colour mapping: a gain per channel by default, the colour model's inverse on request
    assert placement["colour_mapping"]["avatar_to_camera"]["method"] == "linear"
    assert moved["colour_mapping"]["avatar_to_camera"]["method"] == "exact"
    # a virtual camera: the envmap's view (LDR, inverse colour model) as background
    camera = {"model": "pinhole", "K": [[150, 0, 100], [0, 150, 75], [0, 0, 1]], "width": 200, "height": 150,
              "T_cam_from_world": np.linalg.inv(np.asarray(placement["T_user2_from_studio"]) @ _look_at()).tolist()}
    (tmp_path / "camera.json").write_text(json.dumps(camera))
    virtual = tmp_path / "virtual"
    result = run(*args, "--camera-json", tmp_path / "camera.json", "--out", virtual, "-q")
    assert result.returncode == 0, result.stderr
    vm = json.loads((virtual / "manifest.json").read_text())["metrics"]
    assert vm["frames"] == 2 and vm["frames_with_avatar"] == 2


def _look_at() -> np.ndarray:
    """(4,4) ``T_studio_from_cam`` of a camera 3 m in front of the studio origin at 1 m height,
    looking back along -Z (x right = +X, y down = -Y)."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.0, 1.0, 3.0]
    return T


def test_bad_inputs_are_one_line_errors_with_nothing_written(tiny_capture, oracle_calibration_artifact,
                                                             skinned_meshes, avatar, tmp_path, run):
    args = _args(tiny_capture, oracle_calibration_artifact, skinned_meshes, avatar)
    (tmp_path / "bad_camera.json").write_text('{"model": "pinhole"}')
    cases = [
        (["--place", "2,0"], "--place"),
        (["--camera", "down_middle"], "down_middle"),
        (["--camera-json", tmp_path / "bad_camera.json"], "bad_camera.json"),
        (["--camera", "front_left", "--camera-json", tmp_path / "bad_camera.json"], "not both"),
        (["--set", "placement.floor=ceiling"], "placement.floor"),
        (["--set", "frames=0"], "frames"),
        (["--set", "colour.inverse=full"], "colour.inverse"),
        (["--place", "-2,0,0"], "in view in none"),   # behind the viewer: nothing to composite
    ]
    for k, (extra, needle) in enumerate(cases):
        out = tmp_path / f"out{k}"
        result = run(*args, *extra, "--out", out, "-q")
        assert result.returncode == 2, (extra, result.stderr)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("egorelight: error:") and needle in lines[0], lines
        assert not out.exists()
    # an envmap path that is not an envmap artifact
    out = tmp_path / "wrong_kind"
    swapped = [a if a != avatar / "envmap" else avatar / "relight" for a in args]
    result = run(*swapped, "--out", out, "-q")
    assert result.returncode == 2 and result.stderr.startswith("egorelight: error:") and not out.exists()
