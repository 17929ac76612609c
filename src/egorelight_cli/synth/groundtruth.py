"""Ground truth of a simulated capture (``capture/groundtruth/``), read only by evaluation and tests.

Global files::

    groundtruth/hand_eye.json        {role: {"T_cam_from_hmd": 4x4, "T_cam_from_hmd_nominal": 4x4}}
    groundtruth/streams.json         {seq: {"ego_offset": k}}: ego frame e <-> studio frame e + k
    groundtruth/ego_response.json    {role: CameraResponse.to_dict()} of every HMD camera
    groundtruth/appearance.exr       UV maps (the template's UV layout): albedo.R/G/B, specular.Y, roughness.Y,
                                     material.Y, detail.R/G/B (tangent-space normal map x/y/z of the sub-mesh detail)
    groundtruth/subject.json         what the seed chose for the subject's body, rig and garments
    groundtruth/appearance.json      what the seed chose (skin tone, shirt pattern, ...)
    groundtruth/hmd_mount.json       head joint name and T_joint_from_hmd
    groundtruth/board_pose.json      T_world_from_board of the hand-eye sequence
    groundtruth/envmaps/<name>.exr   maps no stage may read (the in-the-wild environment)

Per sequence ``groundtruth/<seq>/``::

    motion.npz       motion payload (theta, dof_names, frame_ids, fps), standalone with __meta__
    keypoints.npz    keypoints payload (xyz, confidence = 1, frame_ids, names); __meta__ ego_frame_ids
    meshes.npz       vertices (T,V',3) float32 the subject's true outer surface (skin + garments, its own
                     topology), faces (F',3), face_uvs (F',3,2), garment_faces (F',) bool, theta, frame_ids
    clothing.npz     displacement_pose, displacement_random (T,G,3) float16: the garment vertices'
                     canonical displacements (pose part, random part), frame_ids
    head_pose.npz    T_world_from_hmd (T,4,4) float64, frame_ids, ego_frame_ids  (HMD worn)
    uv_truth.npz     studio sequences in ``groundtruth.uv_sequences``: true UV normals with the detail and
                     the true flat-lit diffuse texture per content frame (:mod:`egorelight_cli.synth.uv_truth`)
    tracker.json     wild only: latency, drift (per tracker sample), the tracker's world offset
    surroundings.json  wild only: the map the HMD cameras see, its yaw, and the sphere it is on
                     (radius_m, centre) around the wearer

``frame_ids`` are the sequence's studio frame ids (for ``wild``: ego frame ids); the arrays
``ego_frame_ids`` give the ego frame exposed at each (-1: none).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from egorelight_cli.io.exr import write_exr_layers
from egorelight_cli.io.keypoints import Keypoints, write_keypoints_npz
from egorelight_cli.io.motion import Motion, write_motion_npz
from egorelight_cli.io.npz import write_npz
from egorelight_cli.synth.appearance import Appearance
from egorelight_cli.synth.subject import Subject

GT = "groundtruth"


def write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")


def write_appearance(root: Path, appearance: Appearance) -> None:
    layers = {"albedo": appearance.albedo, "specular": appearance.specular, "roughness": appearance.roughness,
              "material": appearance.material.astype(np.float32)[..., None]}
    if appearance.normal_map is not None:
        layers["detail"] = appearance.normal_map
    write_exr_layers(root / GT / "appearance.exr", layers)
    write_json(root / GT / "appearance.json", appearance.description)


def write_sequence_truth(root: Path, seq: str, subject: Subject, frame_ids: np.ndarray, ego_ids: np.ndarray,
                         fps: float, theta: np.ndarray, keypoints: np.ndarray, surfaces: np.ndarray,
                         displacement_pose: np.ndarray, displacement_random: np.ndarray,
                         head_poses: np.ndarray | None) -> None:
    folder = root / GT / seq
    folder.mkdir(parents=True, exist_ok=True)
    frame_ids = np.asarray(frame_ids, dtype=np.int64)
    body = subject.body
    write_motion_npz(folder / "motion.npz", Motion(theta, body.skeleton.dof_names, frame_ids, fps),
                     source="synth ground truth")
    kp = Keypoints(keypoints, np.ones(keypoints.shape[:2], np.float32), frame_ids, body.keypoint_names, fps)
    write_keypoints_npz(folder / "keypoints.npz", kp, source="synth ground truth (the subject's own rig)",
                        ego_frame_ids=[int(e) for e in ego_ids])
    write_npz(folder / "meshes.npz", {
        "vertices": surfaces.astype(np.float32), "faces": subject.faces.astype(np.int32),
        "face_uvs": subject.face_uvs.astype(np.float32), "garment_faces": subject.garment_faces,
        "theta": theta.astype(np.float32), "frame_ids": frame_ids, "ego_frame_ids": ego_ids,
    }, {"kind": "egorelight/synth_surface", "version": 2, "units": {"vertices": "m"},
        "frame_ids": frame_ids.tolist(), "fps": fps,
        "source": "synth ground truth: the subject's outer surface (own topology; UVs in the template's layout)"})
    write_npz(folder / "clothing.npz", {
        "displacement_pose": displacement_pose.astype(np.float16),
        "displacement_random": displacement_random.astype(np.float16), "frame_ids": frame_ids,
    }, {"kind": "egorelight/synth_clothing", "version": 2, "units": {"displacement": "m (canonical space)"},
        "frame_ids": frame_ids.tolist()})
    if head_poses is not None:
        write_npz(folder / "head_pose.npz", {"T_world_from_hmd": head_poses.astype(np.float64),
                                             "frame_ids": frame_ids, "ego_frame_ids": ego_ids},
                  {"kind": "egorelight/head_pose", "version": 1, "units": {"T_world_from_hmd": "m"},
                   "frame_ids": frame_ids.tolist(), "fps": fps})


# ---------------------------------------------------------------- reading (evaluation and tests only)

def read_json(root: str | Path, name: str):
    """A global ground-truth JSON file (``hand_eye.json``, ``streams.json``, ...) of capture ``root``."""
    from egorelight_cli.errors import EgorelightError

    path = Path(root) / GT / name
    if not path.exists():
        raise EgorelightError("ground truth file not found (only simulated captures have one)", path)
    return json.loads(path.read_text())


def read_head_poses(root: str | Path, seq: str) -> dict[str, np.ndarray]:
    """True ``T_world_from_hmd`` (T,4,4), ``frame_ids`` (studio ids; wild: ego ids), ``ego_frame_ids``."""
    from egorelight_cli.io.npz import read_npz

    arrays, _ = read_npz(Path(root) / GT / seq / "head_pose.npz")
    return arrays


def T_pose_frame_from_truth_world(root: str | Path, calibration, seq: str) -> np.ndarray:
    """(4,4) rigid transform from the simulated world into the frame of ``calibration``'s head
    poses of ``seq``, so that ground truth can be scored against what the stages put there.

    Identity where the head poses are in the studio's world
    (:meth:`~egorelight_cli.structures.calibration.Calibration.head_poses_in_studio_world`);
    otherwise (a headset tracker's own world, the wild sequence) the one rigid change of frame
    that best maps the true head poses onto the calibrated ones over the frames both have
    (:func:`~egorelight_cli.geometry.rigid.mean_frame_change`): the score then measures the
    stage, not where the tracker put its origin.
    """
    from egorelight_cli.errors import EgorelightError
    from egorelight_cli.geometry.rigid import mean_frame_change

    if calibration.head_poses_in_studio_world(seq):
        return np.eye(4)
    poses = calibration.head_poses.get(seq)
    if poses is None:
        raise EgorelightError(f"calibration has no head poses for sequence {seq!r}", calibration.source)
    truth = read_head_poses(root, seq)
    ids, ours, theirs = np.intersect1d(poses.frame_ids[poses.valid], truth["frame_ids"], return_indices=True)
    if len(ids) == 0:
        raise EgorelightError(f"the calibrated head poses of {seq!r} share no frame with the ground truth",
                              calibration.source)
    return mean_frame_change(poses.T_world_from_hmd[poses.valid][ours], truth["T_world_from_hmd"][theirs])


def truth_frame_note(calibration, seq: str) -> str:
    """How :func:`T_pose_frame_from_truth_world` placed the ground truth of ``seq`` (manifest text)."""
    if calibration.head_poses_in_studio_world(seq):
        return "the studio's world (as calibrated)"
    return ("the head poses' own world frame: one rigid change of frame fitted to the true head poses, "
            "so the score leaves out where the tracker put its origin")


def oracle_calibration(root: str | Path):
    """A :class:`~egorelight_cli.io.calibration.Calibration` built from ground truth: true hand-eye
    transforms, true stream offsets and true head poses of every sequence with a worn HMD.

    For evaluation and tests of the stages downstream of ``calibrate`` (isolating their error
    from calibration error); no stage uses it.
    """
    from egorelight_cli.io.calibration import Calibration, EgoCameraCalibration, HeadPoses

    root = Path(root)
    hand_eye = read_json(root, "hand_eye.json")
    hmd = json.loads((root / "rig" / "hmd.json").read_text())
    names = {cam["role"]: cam["name"] for cam in hmd["cameras"]}
    cameras = {role: EgoCameraCalibration(role, names.get(role, role), np.asarray(doc["T_cam_from_hmd"], np.float64),
                                          residual_px=0.0, residual_mm=0.0)
               for role, doc in hand_eye.items()}
    offsets = {seq: -int(doc["ego_offset"]) for seq, doc in read_json(root, "streams.json").items()}
    head_poses = {}
    for folder in sorted((root / GT).iterdir()):
        if (folder / "head_pose.npz").exists():
            arrays = read_head_poses(root, folder.name)
            offsets.setdefault(folder.name, 0)
            T = len(arrays["frame_ids"])
            head_poses[folder.name] = HeadPoses(arrays["T_world_from_hmd"].astype(np.float64),
                                                arrays["frame_ids"].astype(np.int64), np.ones(T, bool),
                                                np.zeros(T, np.int64), np.zeros(T))
    return Calibration(cameras, offsets, head_poses, extras={"source": "ground truth (oracle)"})


def write_oracle_calibration(root: str | Path, out: str | Path) -> Path:
    """Write :func:`oracle_calibration` of capture ``root`` as a calibration artifact at ``out``
    (marked ``source: ground truth (oracle)`` in its manifest); for tests and evaluation."""
    from egorelight_cli.artifacts import ArtifactWriter
    from egorelight_cli.io.calibration import write_calibration

    with ArtifactWriter(out, kind="calibration", stage="oracle", config={"source": "groundtruth"}) as writer:
        write_calibration(writer.workdir, oracle_calibration(root))
        writer.extra["source"] = "ground truth (oracle)"
    return Path(out)
