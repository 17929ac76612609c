"""In the wild: the headset tracker's trajectory aligned to visual odometry of the front cameras.

The tracker (``sequences/wild/head_pose.npz``) reports ``T_tracker_from_hmd`` in its own,
gravity-aligned world frame, late by an unknown latency. The front cameras' relative rotations
come from direct photometric alignment: for an in-place scan of a distant scene two frames differ
by a pure rotation, so pixels of one (their unit bearings, rotated and projected) must show the
same intensity in the other (Huber least squares over the rotation, started from the tracker's
relative rotation; direct, because a real sky or the simulator's smooth environment maps offer
few features). Pairs of frames up to ``wild.pair_span`` apart give relative HMD rotations
(through the front cameras' hand-eye ``T_cam_from_hmd``), and rotation averaging
(least squares on SO(3)) turns them into HMD orientations in the odometry frame (frame 0).

The alignment then finds the latency ``L`` and the rotation ``R_vo_from_tracker`` minimising the
angle between ``R_vo_from_tracker @ R_tracker(t + L)`` and the odometry orientations (grid search
over L, closed-form rotation average for each). The calibrated head poses are the tracker's poses
resampled at ``t + L`` (interpolated; the last frames, which would need the future, extrapolated
by the tracker's last velocity), kept in the tracker's gravity-aligned world frame; their
rotations are the odometry's mapped into that frame (``wild.rotation_source: odometry``, the
default: on the simulated captures it is 1-2x more accurate than the tracker's) or the tracker's.
During a constant-rate turn, latency and the constant rotation offset are indistinguishable, so
the latency estimate is only as good as the head's changes of speed.

What is *not* estimated: translation. Rotation-only odometry carries none (the scene is at
infinity for an in-place scan), so the 6-DoF offset is fitted as its rotation only, and the
tracker's slow drift is left as it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation, Slerp

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.geometry.rigid import mean_rotation, rotation_angle_deg
from egorelight_cli.io.calibration import HeadPoses
from egorelight_cli.io.capture import SequenceInfo
from egorelight_cli.io.npz import read_npz
from egorelight_cli.stages.calibrate_handeye import normalised

FRONT_ROLES = ("front_left", "front_right")


@dataclass
class WildResult:
    """Aligned head poses (ego ids), the fitted latency and rotation, and diagnostics."""

    poses: HeadPoses
    latency_s: float
    R_vo_from_tracker: np.ndarray
    R_vo_from_hmd: np.ndarray          # (T,3,3) odometry orientations
    tracker_T: np.ndarray              # (T,4,4) raw tracker poses
    info: dict = field(default_factory=dict)


def read_tracker(seq: SequenceInfo) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T_tracker_from_hmd (T,4,4), ego frame ids (T,), timestamps (T,) s) of the headset tracker."""
    path = seq.head_pose_path()
    if not path.exists():
        raise EgorelightError(f"sequence {seq.name!r} has no headset tracker poses (head_pose.npz)", path)
    arrays, _ = read_npz(path)
    for key in ("T_world_from_hmd", "frame_ids"):
        if key not in arrays:
            raise EgorelightError(f"tracker poses lack {key!r}", path)
    T, ids = np.asarray(arrays["T_world_from_hmd"], np.float64), np.asarray(arrays["frame_ids"], np.int64)
    if T.shape != (len(ids), 4, 4):
        raise EgorelightError(f"tracker poses have shape {T.shape} for {len(ids)} frame ids", path)
    times = np.asarray(arrays["timestamps_s"], np.float64) if "timestamps_s" in arrays else ids / seq.fps
    return T, ids, times


@dataclass(frozen=True)
class _Frame:
    """A front image prepared for direct alignment: grey float (h,w), the sampled pixels' unit
    bearings (N,3) and intensities (N,), at ``scale`` of the full resolution."""

    image: np.ndarray
    bearings: np.ndarray
    values: np.ndarray


def tracker_poses(seq: SequenceInfo) -> HeadPoses:
    """The tracker's poses as they are (ego ids), for when the alignment cannot run."""
    T, ids, _ = read_tracker(seq)
    keep = ids >= 0
    n = int(keep.sum())
    return HeadPoses(T[keep], ids[keep], np.ones(n, bool), np.zeros(n, np.int64), np.full(n, np.nan))


def _prepare(image: np.ndarray, cam: Camera, cfg) -> _Frame:
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    grey = cv2.GaussianBlur(grey, (0, 0), float(cfg.blur_px))
    step = int(cfg.sample_step_px)
    v, u = np.mgrid[step // 2:cam.height:step, step // 2:cam.width:step]
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    xy = normalised(pixels, cam)
    rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    return _Frame(grey, rays / np.linalg.norm(rays, axis=1, keepdims=True), grey[v.ravel(), u.ravel()])


def relative_rotation(a: _Frame, b: _Frame, cam: Camera, R_init: np.ndarray, cfg) -> tuple[np.ndarray | None, float]:
    """(R_b_from_a, RMS intensity residual) of a pure camera rotation between two images of a
    distant scene, by direct photometric alignment (Huber) from ``R_init``; None when too few
    pixels overlap."""
    from egorelight_cli.stages.calibrate_head import project_camera_points

    h, w = b.image.shape

    def residuals(x):
        R = Rotation.from_rotvec(x).as_matrix() @ R_init
        uv = project_camera_points(a.bearings @ R.T, cam).astype(np.float32)
        inside = (uv[:, 0] > 1) & (uv[:, 0] < w - 2) & (uv[:, 1] > 1) & (uv[:, 1] < h - 2)
        sampled = cv2.remap(b.image, uv[:, None, 0].copy(), uv[:, None, 1].copy(), cv2.INTER_LINEAR).ravel()
        return np.where(inside, sampled - a.values, 0.0)

    start = residuals(np.zeros(3))
    if np.count_nonzero(start) < int(cfg.min_overlap_pixels):
        return None, float("nan")
    fit = least_squares(residuals, np.zeros(3), loss="huber", f_scale=float(cfg.huber_intensity), diff_step=1e-4)
    used = fit.fun != 0
    if used.sum() < int(cfg.min_overlap_pixels):
        return None, float("nan")
    return Rotation.from_rotvec(fit.x).as_matrix() @ R_init, float(np.sqrt(np.mean(fit.fun[used] ** 2)))


def odometry(seq: SequenceInfo, cameras: dict[str, Camera], T_cam_from_hmd: dict[str, np.ndarray],
             R_prior: np.ndarray, cfg) -> tuple[np.ndarray, dict]:
    """(R_vo_from_hmd (T,3,3) with frame 0 = identity, info) by rotation averaging of pairwise
    direct alignments; ``R_prior`` (T,3,3) (the tracker's orientations) only initialises them."""
    roles = [r for r in FRONT_ROLES if r in T_cam_from_hmd and r in seq.ego_roles]
    if not roles:
        raise EgorelightError("wild alignment needs a calibrated front camera (front_left/front_right)", seq.root)
    ids = seq.ego_frame_ids
    edges, photometric = [], []  # (i, j, R_hmdj_from_hmdi)
    for role in roles:
        cam, Pi = cameras[role], T_cam_from_hmd[role][:3, :3]
        frames = [_prepare(seq.read_ego_image(role, int(e)), cam, cfg) for e in ids]
        for i in range(len(ids)):
            for j in range(i + 1, min(i + 1 + int(cfg.pair_span), len(ids))):
                prior = Pi @ R_prior[j].T @ R_prior[i] @ Pi.T  # R_cj_from_ci
                R, rms = relative_rotation(frames[i], frames[j], cam, prior, cfg)
                if R is not None:
                    edges.append((i, j, Pi.T @ R @ Pi))
                    photometric.append(rms)
    n = len(ids)
    connected = {0}
    for _ in range(n):
        connected |= {j for i, j, _ in edges if i in connected} | {i for i, j, _ in edges if j in connected}
    if len(connected) < n:
        raise EgorelightError(f"visual odometry lost track in sequence {seq.name!r}: frames "
                              f"{sorted(set(range(n)) - connected)[:5]} overlap no other frame", seq.root)
    R0 = [np.eye(3)] + [None] * (n - 1)  # chain, then least squares over all edges
    for _ in range(n):
        for i, j, R in edges:
            if R0[i] is not None and R0[j] is None:
                R0[j] = R0[i] @ R.T
            elif R0[j] is not None and R0[i] is None:
                R0[i] = R0[j] @ R

    def residuals(x):
        Rs = np.concatenate([np.eye(3)[None], Rotation.from_rotvec(x.reshape(-1, 3)).as_matrix()])
        return np.concatenate([Rotation.from_matrix(R @ Rs[i].T @ Rs[j]).as_rotvec() for i, j, R in edges])

    fit = least_squares(residuals, Rotation.from_matrix(np.array(R0[1:])).as_rotvec().ravel(), loss="huber",
                        f_scale=np.radians(1.0))
    Rs = np.concatenate([np.eye(3)[None], Rotation.from_rotvec(fit.x.reshape(-1, 3)).as_matrix()])
    res = np.degrees(np.linalg.norm(residuals(fit.x).reshape(-1, 3), axis=1))
    return Rs, {"odometry_pairs": len(edges), "odometry_residual_deg": float(np.sqrt(np.mean(res ** 2))),
                "odometry_photometric_rms": float(np.mean(photometric))}


def _interpolate(T: np.ndarray, times: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses at ``query`` (slerp rotation, linear translation; linear extrapolation outside)."""
    q = np.clip(query, times[0], times[-1])
    out = np.tile(np.eye(4), (len(query), 1, 1))
    out[:, :3, :3] = Slerp(times, Rotation.from_matrix(T[:, :3, :3]))(q).as_matrix() if len(T) > 1 else T[0, :3, :3]
    for c in range(3):
        out[:, c, 3] = np.interp(q, times, T[:, c, 3])
    if len(T) > 1:  # translations: extend with the end velocities
        lo, hi = query < times[0], query > times[-1]
        v0 = (T[1, :3, 3] - T[0, :3, 3]) / (times[1] - times[0])
        v1 = (T[-1, :3, 3] - T[-2, :3, 3]) / (times[-1] - times[-2])
        out[lo, :3, 3] += (query[lo] - times[0])[:, None] * v0
        out[hi, :3, 3] += (query[hi] - times[-1])[:, None] * v1
    return out


def _rotation_fit(R_vo: np.ndarray, R_tr: np.ndarray) -> tuple[np.ndarray, float]:
    A = mean_rotation(R_vo @ np.swapaxes(R_tr, 1, 2))
    err = rotation_angle_deg(R_vo, A @ R_tr)
    return A, float(np.sqrt(np.mean(err ** 2)))


def align_wild(seq: SequenceInfo, cameras: dict[str, Camera], T_cam_from_hmd: dict[str, np.ndarray], cfg) -> WildResult:
    """The whole in-the-wild step (``cfg``: the ``wild`` config section)."""
    seq.require_stream("ego")
    T_tr, ids, times = read_tracker(seq)
    ego = seq.ego_frame_ids
    if not np.array_equal(np.sort(ids[ids >= 0]), np.sort(ego)):
        raise EgorelightError(f"tracker frame ids do not match the ego frames of sequence {seq.name!r}",
                              seq.head_pose_path())
    order = np.argsort(times)
    T_tr, ids, times = T_tr[order], ids[order], times[order]
    if len(ego) < 3:
        raise EgorelightError(f"sequence {seq.name!r} has {len(ego)} ego frames; wild alignment needs at least 3", seq.root)
    frame_times = np.interp(ego, ids, times)
    R_vo, info = odometry(seq, cameras, T_cam_from_hmd, T_tr[np.searchsorted(ids, ego), :3, :3], cfg)
    best = None
    for latency in np.arange(-float(cfg.max_latency_s), float(cfg.max_latency_s) + 1e-9, float(cfg.latency_step_s)):
        R_tr = _interpolate(T_tr, times, frame_times + latency)[:, :3, :3]
        A, rms = _rotation_fit(R_vo, R_tr)
        if best is None or rms < best[2]:
            best = (float(latency), A, rms)
    latency, A, rms = best
    T = _interpolate(T_tr, times, frame_times + latency)
    future = frame_times + latency > times[-1]
    if str(cfg.rotation_source) == "odometry":  # the odometry's orientations, in the tracker's frame
        T[:, :3, :3] = A.T @ R_vo
    elif future.any():  # rotations the tracker has not reported yet: from the odometry
        T[future, :3, :3] = A.T @ R_vo[future]
    raw_rms = _rotation_fit(R_vo, T_tr[np.searchsorted(ids, ego), :3, :3])[1]
    info.update({"latency_s": latency, "alignment_rms_deg": rms, "alignment_rms_deg_without_latency": raw_rms,
                 "extrapolated_frames": int(future.sum())})
    n = len(ego)
    poses = HeadPoses(T, ego.astype(np.int64), np.ones(n, bool), np.full(n, info["odometry_pairs"], np.int64),
                      np.full(n, np.nan))
    return WildResult(poses, latency, A, R_vo, T_tr[np.searchsorted(ids, ego)], info)
