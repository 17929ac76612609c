"""The ``calibration`` artifact payload: hand-eye transforms, head poses and stream offsets.

A calibration artifact directory holds

* ``calibration.json``: per ego camera (keyed by role: ``down_left``, ``down_right``,
  ``front_left``, ``front_right``) its hand-eye transform ``T_cam_from_hmd`` (4x4, metres) and
  residuals; per sequence the stream offset and how its head poses were obtained;
* ``head_poses/<sequence>.npz``: ``T_world_from_hmd`` (T,4,4) float64, ``frame_ids`` (T,)
  int64, ``valid`` (T,) bool (False = too little evidence: flagged, never invented),
  ``num_markers`` (T,) int64 and ``residual_px`` (T,) float64 (NaN where invalid).

**Frame ids.** Every per-frame artifact of this tool (head poses, keypoints, motion, point
clouds, meshes, ...) is indexed by the capture's master clock, the studio frame ids of
``sequence.json``. An ego image of frame ``f`` is ``ego/<role>/<f + stream_offset>.png``, with
``stream_offset`` from this artifact (found from the light flashes). Sequences without a studio
stream (``wild``) use the ego frame ids and offset 0.

The unprojection of the paper, ``z = (K Pi H)^-1 d``, is ``T_world_from_cam = H @ inv(Pi)`` with
``H = T_world_from_hmd`` and ``Pi = T_cam_from_hmd`` (:meth:`Calibration.T_world_from_cam`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import read_npz, write_npz
from egorelight_cli.structures.calibration import Calibration, EgoCameraCalibration, HeadPoses

CALIBRATION_JSON = "calibration.json"
HEAD_POSES_DIR = "head_poses"
HEAD_POSES_KIND = "egorelight/calibration"  # the npz payloads carry the artifact's kind
VERSION = 1


def write_calibration(root: str | Path, calibration: Calibration) -> list[Path]:
    """Write the payload files into directory ``root`` (an ArtifactWriter's work dir)."""
    root = Path(root)
    doc = {
        "version": VERSION,
        "ego_cameras": {
            role: {"name": cam.name, "T_cam_from_hmd": np.asarray(cam.T_cam_from_hmd, float).tolist(),
                   "residual_px": _num(cam.residual_px), "residual_mm": _num(cam.residual_mm)}
            for role, cam in calibration.ego_cameras.items()
        },
        "stream_offsets": {seq: int(off) for seq, off in calibration.stream_offsets.items()},
        "head_pose_sequences": sorted(calibration.head_poses),
        "extras": calibration.extras,
    }
    (root / CALIBRATION_JSON).write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    written = [root / CALIBRATION_JSON]
    (root / HEAD_POSES_DIR).mkdir(parents=True, exist_ok=True)
    for seq, poses in calibration.head_poses.items():
        path = root / HEAD_POSES_DIR / f"{seq}.npz"
        write_npz(path, {
            "T_world_from_hmd": np.asarray(poses.T_world_from_hmd, np.float64),
            "frame_ids": np.asarray(poses.frame_ids, np.int64),
            "valid": np.asarray(poses.valid, bool),
            "num_markers": np.asarray(poses.num_markers, np.int64),
            "residual_px": np.asarray(poses.residual_px, np.float64),
        }, {"kind": HEAD_POSES_KIND, "version": VERSION, "sequence": seq, "units": {"T_world_from_hmd": "m"},
            "frame_ids": [int(f) for f in poses.frame_ids]})
        written.append(path)
    return written


def _num(value: float) -> float | None:
    value = float(value)
    return value if np.isfinite(value) else None


def read_calibration(root: str | Path) -> Calibration:
    """Read the payload of a calibration artifact directory."""
    root = Path(root)
    path = root / CALIBRATION_JSON
    if not path.is_file():
        raise EgorelightError("calibration payload not found", path)
    try:
        doc = json.loads(path.read_text())
        cameras = {
            role: EgoCameraCalibration(role=role, name=entry["name"],
                                       T_cam_from_hmd=_rigid(entry["T_cam_from_hmd"], path, role),
                                       residual_px=_nan(entry.get("residual_px")),
                                       residual_mm=_nan(entry.get("residual_mm")))
            for role, entry in doc["ego_cameras"].items()
        }
        offsets = {seq: int(off) for seq, off in doc["stream_offsets"].items()}
        sequences = list(doc.get("head_pose_sequences", []))
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise EgorelightError(f"malformed calibration ({type(exc).__name__}: {exc})", path) from None
    head_poses = {}
    for seq in sequences:
        npz = root / HEAD_POSES_DIR / f"{seq}.npz"
        head_poses[seq] = _head_poses(npz)
    return Calibration(ego_cameras=cameras, stream_offsets=offsets, head_poses=head_poses, extras=doc.get("extras", {}),
                       source=path)


def _head_poses(npz: Path) -> HeadPoses:
    """The :class:`HeadPoses` of ``head_poses/<seq>.npz``, its arrays' keys, shapes and types checked."""
    arrays, _ = read_npz(npz, check_finite=False)
    keys = ("T_world_from_hmd", "frame_ids", "valid", "num_markers", "residual_px")
    missing = [k for k in keys if k not in arrays]
    if missing:
        raise EgorelightError(f"head poses lack {', '.join(missing)}", npz)
    T, frame_ids, valid = arrays["T_world_from_hmd"], arrays["frame_ids"], arrays["valid"]
    n = len(frame_ids) if frame_ids.ndim == 1 else -1
    if T.shape != (n, 4, 4) or any(arrays[k].shape != (n,) for k in keys[2:]):
        raise EgorelightError(f"head poses need T_world_from_hmd (T,4,4) and frame_ids, valid, num_markers, "
                              f"residual_px (T,); got {', '.join(f'{k} {arrays[k].shape}' for k in keys)}", npz)
    if valid.dtype != np.bool_ or not np.issubdtype(frame_ids.dtype, np.integer):
        raise EgorelightError(f"head poses need a bool valid and integer frame_ids, got {valid.dtype} and "
                              f"{frame_ids.dtype}", npz)
    if not np.all(np.isfinite(T[valid])):
        raise EgorelightError("valid head poses hold NaN/inf", npz)
    return HeadPoses(**{k: arrays[k] for k in keys})


def posed_ego_camera(capture, calibration: Calibration, role: str, sequence: str, frame_id: int):
    """The HMD camera ``role`` of ``capture`` (an :class:`~egorelight_cli.io.capture.Capture`)
    placed in the world by ``calibration`` at master-clock ``frame_id``: a
    :class:`~egorelight_cli.geometry.cameras.Camera` with extrinsics ``inv(H @ inv(Pi))``."""
    from egorelight_cli.geometry.cameras import Camera, invert_rigid

    c = capture.ego_camera(role)
    T_world_from_cam = calibration.T_world_from_cam(role, sequence, int(frame_id))
    return Camera(c.model, c.K, c.dist, c.width, c.height, invert_rigid(T_world_from_cam), role)


def open_calibration(path: str | Path) -> tuple[Calibration, "Artifact"]:  # noqa: F821
    """Open a calibration artifact directory: its kind and version checked, its payload read."""
    from egorelight_cli.artifacts import open_artifact

    artifact = open_artifact(path, kind="calibration")
    if artifact.single_file:
        raise EgorelightError("a calibration is a directory artifact", path)
    return read_calibration(artifact.root), artifact


def _nan(value) -> float:
    return float("nan") if value is None else float(value)


def _rigid(values, path: Path, role: str) -> np.ndarray:
    T = np.asarray(values, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise EgorelightError(f"T_cam_from_hmd of {role} is not a finite 4x4 matrix", path)
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise EgorelightError(f"T_cam_from_hmd of {role} is not a rigid transform", path)
    return T
