"""End-to-end: ``egorelight synth --preset tiny`` and the physics of what it wrote.

One tiny capture is simulated per test session (about half a minute on 2 cores) and checked
against its own ground truth with independent tools (OpenCV's fisheye model, ArUco/ChArUco
detection and PnP, brightness cross-correlation).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from egorelight_cli.artifacts import open_artifact
from egorelight_cli.cli import main
from egorelight_cli.geometry.cameras import Camera, invert_rigid, project_world
from egorelight_cli.geometry.markers import aruco_dictionary, charuco_board
from egorelight_cli.io.exr import read_exr
from egorelight_cli.io.images import read_image, srgb_to_linear
from egorelight_cli.io.keypoints import load_keypoints
from egorelight_cli.io.meshes import read_mesh
from egorelight_cli.io.motion import load_motion
from egorelight_cli.io.npz import read_npz
from egorelight_cli.render.envmaps import make_envmap, write_envmap
from egorelight_cli.synth.hmd import EGO_ROLES
from egorelight_cli.io.images import tonemap
from egorelight_cli.synth.sequences import PURPOSES, SEQUENCES
from egorelight_cli.geometry.rigid import interpolate_poses


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a.T @ b) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


@pytest.fixture(scope="module")
def capture(tiny_capture) -> Path:
    return tiny_capture


def _json(path: Path):
    return json.loads(path.read_text())


def _studio_cameras(capture: Path) -> dict[str, Camera]:
    return {c["name"]: Camera.from_dict(c) for c in _json(capture / "rig/studio_cameras.json")["cameras"]}


def _roles(capture: Path) -> dict[str, str]:
    return {c["name"]: c["role"] for c in _json(capture / "rig/studio_cameras.json")["cameras"]}


def _hdr(path: Path) -> np.ndarray:
    return read_exr(path).layer("", ("R", "G", "B"))


# ----------------------------------------------------------------------------------- layout
def test_capture_validates_and_lists_every_file(capture):
    artifact = open_artifact(capture, kind="capture", verify=True)
    listed = {o["path"] for o in artifact.manifest["outputs"]}
    on_disk = {p.relative_to(capture).as_posix() for p in capture.rglob("*") if p.is_file()} - {"manifest.json"}
    assert listed == on_disk
    metrics = artifact.metrics
    assert metrics["aruco_detection_rate"] > 0.8
    assert metrics["board_detection_rate"] > 0.8
    assert 0.05 < metrics["ego_body_pixel_fraction"] < 0.9
    assert metrics["ego_clipped_fraction"] < 0.2
    assert {"studio", "tracking", "ego"} <= set(artifact.manifest["timing"]["render_s_per_frame_per_camera"])


def test_capture_layout_is_complete(capture):
    for name in ("studio_cameras.json", "lights.json", "hmd.json", "board.json"):
        assert (capture / "rig" / name).is_file()
    lights = _json(capture / "rig/lights.json")
    assert len(lights["positions"]) == len(lights["rgb_gain"]) == 32
    hmd = _json(capture / "rig/hmd.json")
    assert [c["role"] for c in hmd["cameras"]] == list(EGO_ROLES)
    assert all("T_cam_from_hmd" not in c for c in hmd["cameras"])  # extrinsics are ground truth only
    assert hmd["markers"]["dictionary"] == "DICT_4X4_50"
    assert all(np.shape(m["corners_hmd"]) == (4, 3) for m in hmd["markers"]["markers"])
    roles = _roles(capture)
    for seq in SEQUENCES:
        folder = capture / "sequences" / seq
        info = _json(folder / "sequence.json")
        assert info["purpose"] == PURPOSES.get(seq, seq) and info["fps"] > 0
        assert len(info["lights"]) == len(info["frame_ids"])
        for cam in info["streams"]["studio"]:
            for fid in info["frame_ids"]:
                assert (folder / "studio" / cam / f"{fid:06d}.exr").is_file()
                assert (folder / "masks" / cam / f"{fid:06d}.png").is_file() == info["streams"]["masks"]
            for fid in info["content_frame_ids"]:
                assert (folder / "normals" / cam / f"{fid:06d}.exr").is_file() == info["streams"]["normals"]
        for role in info["streams"]["ego"]:
            for eid in info["ego_frame_ids"]:
                assert (folder / "ego" / role / f"{eid:06d}.png").is_file()
        if info["streams"]["recon"]:
            assert all((folder / "recon" / f"{f:06d}.ply").is_file() for f in info["content_frame_ids"])
        if info["streams"]["mocap"]:
            mocap, _ = load_keypoints(folder / "mocap.npz")
            assert list(mocap.frame_ids) == info["frame_ids"]
        gt = capture / "groundtruth" / seq
        for name in ("motion.npz", "keypoints.npz", "meshes.npz", "clothing.npz"):
            assert (gt / name).is_file()
        assert (gt / "head_pose.npz").is_file() == info["hmd_worn"]
    test = _json(capture / "sequences/test/sequence.json")
    assert len(test["held_out_cameras"]) == 1 and set(test["held_out_cameras"]) <= set(test["streams"]["studio"])
    train = _json(capture / "sequences/ego_train/sequence.json")
    assert not set(test["held_out_cameras"]) & set(train["streams"]["studio"])
    assert any(roles[c] == "tracking" for c in train["streams"]["studio"])
    # the headset-only sequence: head-tracking cameras and down-facing views only, for ego training
    bulk = _json(capture / "sequences/ego_bulk/sequence.json")
    assert bulk["purpose"] == "ego_train" and bulk["hmd_worn"] and bulk["streams"]["mocap"]
    assert {roles[c] for c in bulk["streams"]["studio"]} == {"tracking"}
    assert bulk["streams"]["ego"] == ["down_left", "down_right"]
    assert not (bulk["streams"]["masks"] or bulk["streams"]["normals"] or bulk["streams"]["recon"])
    assert not (capture / "sequences/ego_bulk/ego/front_left").exists()
    # the user's --envmap lights the test sequence; the in-the-wild map is hidden in groundtruth
    lit = [light for light in test["lights"] if light["pattern"] == "envmap"]
    assert lit[-1]["envmap"] == "user_my_room"
    # the test sequence ends with its OLAT / group-light tail
    assert [light["pattern"] for light in test["lights"][-2:]] == ["olat", "group"]
    assert (capture / "envmaps/user_my_room.exr").is_file()
    assert not list((capture / "envmaps").glob("wild_*")) and list((capture / "groundtruth/envmaps").glob("wild_*"))
    assert (capture / "sequences/wild/head_pose.npz").is_file()
    for seq in SEQUENCES:
        assert (capture / "previews" / f"{seq}.png").is_file()


def test_ground_truth_payloads_are_standalone_artifacts(capture):
    keypoints, artifact = load_keypoints(capture / "groundtruth/test/keypoints.npz")
    assert artifact is None and keypoints.has_standard_layout
    motion, _ = load_motion(capture / "groundtruth/test/motion.npz")
    info = _json(capture / "sequences/test/sequence.json")
    assert list(motion.frame_ids) == list(keypoints.frame_ids) == info["frame_ids"]
    meshes, meta = read_npz(capture / "groundtruth/test/meshes.npz")
    assert meta["kind"] == "egorelight/synth_surface" and meshes["vertices"].shape[0] == len(info["frame_ids"])
    assert meshes["face_uvs"].shape == meshes["faces"].shape + (2,) and meshes["garment_faces"].any()


# ---------------------------------------------------------------------------------- physics
def _fisheye_silhouette(vertices: np.ndarray, faces: np.ndarray, camera: Camera, max_theta_deg: float = 85.0) -> np.ndarray:
    """Union of the projected triangles in front of the camera, with OpenCV's own fisheye model."""
    cam_points = vertices @ camera.T_cam_from_world[:3, :3].T + camera.T_cam_from_world[:3, 3]
    theta = np.degrees(np.arctan2(np.linalg.norm(cam_points[:, :2], axis=1), cam_points[:, 2]))
    pixels, _ = cv2.fisheye.projectPoints(cam_points[None].astype(np.float64), np.zeros(3), np.zeros(3),
                                          camera.K, camera.dist[:4])
    pixels = pixels[0]
    front = (theta < max_theta_deg)[faces].all(axis=1)
    silhouette = np.zeros((camera.height * 4, camera.width * 4), np.uint8)
    tris = np.round((pixels[faces[front]] + 0.5) * 4 - 0.5).astype(np.int32)
    cv2.fillPoly(silhouette, list(tris), 1)
    return cv2.resize(silhouette, (camera.width, camera.height), interpolation=cv2.INTER_AREA) > 0.5


def _ego_camera(capture: Path, seq: str, role: str, row: int) -> Camera:
    hmd = {c["role"]: c for c in _json(capture / "rig/hmd.json")["cameras"]}
    hand_eye = _json(capture / "groundtruth/hand_eye.json")
    head, _ = read_npz(capture / f"groundtruth/{seq}/head_pose.npz")
    T = np.asarray(hand_eye[role]["T_cam_from_hmd"]) @ invert_rigid(head["T_world_from_hmd"][row])
    return Camera.from_dict(hmd[role], T_cam_from_world=T)


def test_fisheye_pixels_land_where_the_camera_model_projects_the_body(capture):
    """The rendered ego image agrees with OpenCV's fisheye projection of the true body surface."""
    seq = "ego_train"
    info = _json(capture / f"sequences/{seq}/sequence.json")
    offset = _json(capture / "groundtruth/streams.json")[seq]["ego_offset"]
    meshes, _ = read_npz(capture / f"groundtruth/{seq}/meshes.npz")
    keypoints, _ = load_keypoints(capture / f"groundtruth/{seq}/keypoints.npz")
    checked = 0
    for fid in info["content_frame_ids"]:
        row = info["frame_ids"].index(fid)
        for role in ("down_left", "down_right"):
            camera = _ego_camera(capture, seq, role, row)
            image = read_image(capture / f"sequences/{seq}/ego/{role}/{fid - offset:06d}.png")
            body = _fisheye_silhouette(meshes["vertices"][row].astype(np.float64), meshes["faces"], camera)
            core = cv2.erode(body.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            far = ~(cv2.dilate(body.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0)
            # the studio dome behind the body is dark apart from small LEDs; the lit body is not
            bright = image.max(axis=-1) > 100
            grid = np.stack(np.meshgrid(np.arange(camera.width), np.arange(camera.height)), -1) - camera.K[:2, 2]
            inner = np.linalg.norm(grid, axis=-1) < 0.75 * camera.K[0, 0] * np.radians(80)
            assert core.sum() > 20
            assert bright[core].mean() > 0.85, (fid, role)
            assert bright[far & inner].mean() < 0.1, (fid, role)
            # keypoints in view project onto the body (hands, arms in front of the camera)
            px, valid = project_world(camera, keypoints.xyz[row].astype(np.float64), return_valid=True)
            inside = valid & np.all((px >= 1) & (px < [camera.width - 1, camera.height - 1]), axis=1)
            cols, rows = np.round(px[inside]).astype(int).T
            assert body[rows, cols].mean() > 0.7
            checked += 1
    assert checked >= 2


def test_studio_keypoints_project_into_the_masks(capture):
    seq = "ego_train"
    info = _json(capture / f"sequences/{seq}/sequence.json")
    cameras = _studio_cameras(capture)
    keypoints, _ = load_keypoints(capture / f"groundtruth/{seq}/keypoints.npz")
    roles = _roles(capture)
    for name in info["streams"]["studio"]:
        if roles[name] != "studio":
            continue
        fid = info["content_frame_ids"][0]
        mask = read_image(capture / f"sequences/{seq}/masks/{name}/{fid:06d}.png") > 0
        hdr = _hdr(capture / f"sequences/{seq}/studio/{name}/{fid:06d}.exr")
        assert hdr[mask].max(axis=-1).min() >= 0 and hdr[~mask].max() == 0  # black dome interior
        px = project_world(cameras[name], keypoints.xyz[info["frame_ids"].index(fid), :15].astype(np.float64))
        ok = np.all(np.isfinite(px), axis=1) & np.all((px >= 0) & (px < [mask.shape[1] - 1, mask.shape[0] - 1]), axis=1)
        cols, rows = np.round(px[ok]).astype(int).T
        hits = np.array([mask[r - 1:r + 2, c - 1:c + 2].any() for r, c in zip(rows, cols)])
        assert hits.mean() > 0.9, name


def _multiview_pose(observations: list, initial: np.ndarray) -> np.ndarray:
    """T_world_from_hmd minimising the reprojection error of marker corners in several cameras."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def residuals(x):
        R, t = Rotation.from_rotvec(x[:3]).as_matrix(), x[3:]
        out = []
        for cam, obj, img in observations:
            out.append((project_world(cam, obj @ R.T + t) - img).ravel())
        return np.concatenate(out)

    x0 = np.concatenate([Rotation.from_matrix(initial[:3, :3]).as_rotvec(), initial[:3, 3]])
    x = least_squares(residuals, x0, method="lm").x
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_rotvec(x[:3]).as_matrix(), x[3:]
    return T


def test_aruco_markers_give_the_true_head_pose(capture):
    """Markers detected in the studio images + their layout in rig/hmd.json -> PnP, refined over all
    tracking cameras -> the true HMD pose."""
    layout = {m["id"]: np.asarray(m["corners_hmd"]) for m in _json(capture / "rig/hmd.json")["markers"]["markers"]}
    cameras, roles = _studio_cameras(capture), _roles(capture)
    detector = cv2.aruco.ArucoDetector(aruco_dictionary())
    errors_t, errors_r = [], []
    for seq in ("handeye", "ego_train", "test"):
        info = _json(capture / f"sequences/{seq}/sequence.json")
        head, _ = read_npz(capture / f"groundtruth/{seq}/head_pose.npz")
        for fid in info["content_frame_ids"]:
            observations, initial = [], None
            for name in info["streams"]["studio"]:
                if roles[name] != "tracking":
                    continue
                hdr = _hdr(capture / f"sequences/{seq}/studio/{name}/{fid:06d}.exr")
                grey = cv2.cvtColor(tonemap(hdr, hdr.max(axis=-1) > 0), cv2.COLOR_RGB2GRAY)
                corners, ids, _ = detector.detectMarkers(grey)
                if ids is None:
                    continue
                cam = cameras[name]
                obj = np.concatenate([layout[int(i)] for i in ids.ravel()])
                img = np.concatenate([c.reshape(4, 2) for c in corners])
                observations.append((cam, obj, img))
                if initial is None and len(ids) >= 2:
                    ok, rvec, tvec = cv2.solvePnP(obj, img, cam.K, cam.dist, flags=cv2.SOLVEPNP_SQPNP)
                    assert ok
                    T_cam_from_hmd = np.eye(4)
                    T_cam_from_hmd[:3, :3], T_cam_from_hmd[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
                    initial = cam.T_world_from_cam @ T_cam_from_hmd
            if initial is None:
                continue
            estimate = _multiview_pose(observations, initial)
            truth = head["T_world_from_hmd"][info["frame_ids"].index(fid)]
            errors_t.append(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))
            errors_r.append(rotation_error_deg(estimate[:3, :3], truth[:3, :3]))
    assert len(errors_t) >= 6
    assert np.median(errors_t) < 0.01 and np.median(errors_r) < 1.5


def test_charuco_board_gives_the_true_board_pose_in_the_front_cameras(capture):
    """The board the front cameras see sits where T_cam_from_hmd, the head pose and the board pose say."""
    board_cfg = _json(capture / "rig/board.json")

    class Cfg:
        squares_x, squares_y = board_cfg["squares_x"], board_cfg["squares_y"]
        square_length_m, marker_length_m = board_cfg["square_length_m"], board_cfg["marker_length_m"]

    board = charuco_board(Cfg)
    detector = cv2.aruco.CharucoDetector(board)
    T_world_from_board = np.asarray(_json(capture / "groundtruth/board_pose.json")["T_world_from_board"])
    info = _json(capture / "sequences/handeye/sequence.json")
    offset = _json(capture / "groundtruth/streams.json")["handeye"]["ego_offset"]
    errors = []
    for fid in info["content_frame_ids"]:
        row = info["frame_ids"].index(fid)
        for role in ("front_left", "front_right"):
            camera = _ego_camera(capture, "handeye", role, row)
            image = read_image(capture / f"sequences/handeye/ego/{role}/{fid - offset:06d}.png")
            corners, ids, _, _ = detector.detectBoard(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
            assert corners is not None and len(corners) >= 6
            obj = board.getChessboardCorners()[ids.ravel()]
            _ok, rvec, tvec = cv2.solvePnP(obj, corners.reshape(-1, 2), camera.K, camera.dist)
            truth = camera.T_cam_from_world @ T_world_from_board
            errors.append(np.linalg.norm(tvec.ravel() - truth[:3, 3]))
            assert rotation_error_deg(cv2.Rodrigues(rvec)[0], truth[:3, :3]) < 3.0
    assert np.median(errors) < 0.01


def test_flash_code_recovers_the_stream_offset(capture):
    """Per-frame brightness of a studio and an ego stream, cross-correlated, gives the ground-truth offset."""
    truth = _json(capture / "groundtruth/streams.json")
    for seq in ("handeye", "ego_train", "test"):
        info = _json(capture / f"sequences/{seq}/sequence.json")
        cam = info["streams"]["studio"][0]
        studio = np.array([_hdr(capture / f"sequences/{seq}/studio/{cam}/{f:06d}.exr").mean() for f in info["frame_ids"]])
        ego = np.array([srgb_to_linear(read_image(capture / f"sequences/{seq}/ego/down_left/{e:06d}.png") / 255.0).mean()
                        for e in info["ego_frame_ids"]])
        # the sync window: the OLAT / group tail of test is a robustness check, not part of the code
        plain = [i for i, light in enumerate(info["lights"]) if light["pattern"] not in ("olat", "group")]
        studio = studio[:max(plain) + 1]
        scores = {}
        for k in range(len(studio) - len(info["sync"]["code"])):
            n = min(len(ego), len(studio) - k)
            scores[k] = float(np.corrcoef(studio[k:k + n], ego[:n])[0, 1])
        assert max(scores, key=scores.get) == truth[seq]["ego_offset"], (seq, scores)


def test_recon_is_close_to_the_true_outer_surface(capture):
    import trimesh
    from scipy.spatial import cKDTree

    info = _json(capture / "sequences/relight_train/sequence.json")
    meshes, _ = read_npz(capture / "groundtruth/relight_train/meshes.npz")
    fid = info["content_frame_ids"][0]
    v, _f = read_mesh(capture / f"sequences/relight_train/recon/{fid:06d}.ply")
    truth = trimesh.Trimesh(meshes["vertices"][info["frame_ids"].index(fid)], meshes["faces"], process=False)
    assert len(v) != len(truth.vertices)  # its own tessellation
    surface, _ = trimesh.sample.sample_surface(truth, 300000, seed=0)
    distance, _ = cKDTree(surface).query(v)
    assert np.median(distance) < 0.005 and np.percentile(distance, 99) < 0.03


def test_normal_estimates_are_noisy_camera_frame_normals(capture):
    info = _json(capture / "sequences/ego_train/sequence.json")
    cam = info["streams"]["studio"][0]
    fid = info["content_frame_ids"][0]
    normals = read_exr(capture / f"sequences/ego_train/normals/{cam}/{fid:06d}.exr").layer("normal")
    mask = read_image(capture / f"sequences/ego_train/masks/{cam}/{fid:06d}.png") > 0
    length = np.linalg.norm(normals, axis=-1)
    assert np.allclose(length[mask], 1, atol=0.01) and np.all(length[~mask] == 0)
    # camera frame: visible surfaces face the camera (negative z), mostly
    assert np.mean(normals[mask][:, 2] < 0.2) > 0.9


def test_wild_tracker_poses_have_latency_drift_and_their_own_frame(capture):
    tracker, _ = read_npz(capture / "sequences/wild/head_pose.npz")
    truth, _ = read_npz(capture / "groundtruth/wild/head_pose.npz")
    info = _json(capture / "groundtruth/wild/tracker.json")
    fps = _json(capture / "sequences/wild/sequence.json")["fps"]
    # k samples per ego frame: every k-th one is taken with an ego frame, the others carry -1
    k = len(tracker["frame_ids"]) // len(truth["frame_ids"])
    assert k > 1 and len(tracker["frame_ids"]) == k * len(truth["frame_ids"])
    np.testing.assert_array_equal(tracker["frame_ids"][::k], truth["frame_ids"])
    assert (np.delete(tracker["frame_ids"], np.arange(0, len(tracker["frame_ids"]), k)) == -1).all()
    np.testing.assert_allclose(np.diff(tracker["timestamps_s"]), 1.0 / (k * fps))
    offset = np.asarray(info["T_tracker_from_world"])
    aligned = invert_rigid(offset) @ tracker["T_world_from_hmd"][::k]
    times = np.arange(len(aligned)) / fps
    delayed = interpolate_poses(truth["T_world_from_hmd"], times, times - info["latency_s"])
    # without the unknown world offset and the latency, only the (small) drift remains
    drift = np.linalg.norm(np.asarray(info["drift"]["translation_m"])[::k], axis=1)
    gap = np.linalg.norm(aligned[:, :3, 3] - delayed[:, :3, 3], axis=1)
    assert np.all(gap < drift + 0.03) and info["latency_s"] > 0
    assert np.max(np.linalg.norm(tracker["T_world_from_hmd"][::k, :3, 3] - truth["T_world_from_hmd"][:, :3, 3],
                                 axis=1)) > 0.05
    # the HMD cameras see a place around the wearer, above the ground
    place = _json(capture / "groundtruth/wild/surroundings.json")
    assert place["radius_m"] > 1.0 and place["floor_y"] == 0.0 and place["envmap"].startswith("wild_")


def test_sequences_simulated_side_by_side_give_the_same_capture(tmp_path):
    """``--threads 2`` simulates two sequences at a time in worker processes; each sequence has
    its own seeded random state, so every file, and the artifact's digest, is the same as one by
    one. (Each run is a fresh
    process, as on the command line: inside this test process, after other tests have used
    pymeshlab, the reconstructions' decimation can come out differently.)"""
    import subprocess
    import sys

    from egorelight_cli.artifacts import open_artifact

    digests, artifact_digests = [], []
    for threads in ("1", "2"):
        out = tmp_path / f"capture{threads}"
        result = subprocess.run([sys.executable, "-m", "egorelight_cli.cli", "--threads", threads, "synth", "--preset",
                                 "tiny", "--set", "sequences_enabled=[ego_train,ego_bulk]", "--set",
                                 "groundtruth.uv_sequences=[]", "--out", str(out), "-q"], capture_output=True, text=True)
        assert result.returncode == 0, result.stderr
        manifest = _json(out / "manifest.json")
        digests.append({o["path"]: o["digest"] for o in manifest["outputs"]})
        artifact_digests.append(open_artifact(out, verify=False).digest)
        assert set(manifest["metrics"]["sequences"]) == {"ego_train", "ego_bulk"}
    assert digests[0] == digests[1] and any(p.startswith("sequences/ego_bulk/ego/") for p in digests[0])
    # the manifest too, timings aside (they are in its `timing`): what comes after stays up to date
    assert artifact_digests[0] == artifact_digests[1]
