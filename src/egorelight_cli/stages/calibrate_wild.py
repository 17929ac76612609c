"""In the wild: the headset tracker's trajectory aligned to stereo visual odometry of the front cameras.

The tracker (``sequences/wild/head_pose.npz``) reports ``T_tracker_from_hmd`` in its own,
gravity-aligned world frame, usually at a higher rate than the cameras and late by an unknown
latency. The paper corrects it with a secondary visual odometry on the front cameras and a 6-DoF
offset aligning the two trajectories. Here:

1. **Stereo features** (:func:`stereo_frame`): SIFT in both front images of every ego frame,
   left-right matches (ratio test) triangulated with the hand-eye calibration's known stereo
   extrinsics, so the odometry is metric; points behind either camera, nearer than
   ``min_depth_m`` or reprojecting worse than ``max_reprojection_px`` are dropped.
2. **Relative poses** (:func:`relative_pose`): for every pair of frames whose tracker
   orientations differ by less than ``max_pair_angle_deg`` (neighbours, and the loop closure of a
   full turn), frame ``i``'s triangulated points are matched to frame ``j``'s features in both
   cameras; PnP + RANSAC in the camera with more matches starts a two-frame bundle adjustment
   of ``T_hmdj_from_hmdi`` and the points' depths over all four views (Huber; the depths
   eliminated per point, so the outer problem has 6 unknowns).
3. **Pose graph** (:func:`odometry`): the relative poses, chained from frame 0 and then refined
   together (Huber least squares on SE(3), ``sigma_rotation_deg`` / ``sigma_translation_m``
   weighting), give ``T_vo_from_hmd`` per frame with frame 0 = identity.
4. **Alignment** (:func:`align_trajectories`): the latency ``L`` (grid search) and the offset
   ``T_vo_from_tracker`` minimising the rotation angle between ``R_vo(t)`` and
   ``A @ R_tracker(t + L)`` (closed-form rotation average per ``L``), then the offset's
   translation ``b = mean(p_vo(t) - A p_tracker(t + L))``. The tracker is interpolated at
   ``t + L`` (slerp; translations extrapolated by the end velocity past its last sample).

The calibrated head poses (ego frame ids) stay in the tracker's gravity-aligned frame. With
``pose_source: odometry`` (default) they are the odometry's poses mapped into that frame,
``inv(T_vo_from_tracker) @ T_vo_from_hmd``, which carries neither the latency nor the tracker's
drift; with ``tracker`` they are the tracker's own poses at ``t + L`` (latency corrected, drift
kept). Latency is observable only through changes in the head's angular velocity (during a
constant-rate turn it trades off against the constant rotation offset); the tracker's higher
rate and the scan's head nods give it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, invert_rigid
from egorelight_cli.geometry.rigid import (
    interpolate_poses,
    mean_rotation,
    rigid,
    rigid_from_vector,
    rotation_angle_deg,
    vector_from_rigid,
)
from egorelight_cli.structures.calibration import HeadPoses
from egorelight_cli.io.capture import SequenceInfo
from egorelight_cli.io.tracker import read_tracker
from egorelight_cli.stages.calibrate_handeye import normalised

FRONT_ROLES = ("front_left", "front_right")


@dataclass
class WildResult:
    """Aligned head poses (ego ids), the fitted latency and offset, and diagnostics.

    ``T_vo_from_hmd`` (T,4,4): the odometry's HMD poses (frame 0 = identity); ``tracker_T``
    (T,4,4): the tracker's raw samples taken with the ego frames; ``T_vo_from_tracker`` (4,4).
    """

    poses: HeadPoses
    latency_s: float
    T_vo_from_tracker: np.ndarray
    T_vo_from_hmd: np.ndarray
    tracker_T: np.ndarray
    info: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------ stereo features
@dataclass(frozen=True)
class StereoFrame:
    """One ego frame's front features: per role the keypoints' normalised coordinates (K,2) and
    SIFT descriptors (K,128); the left-right matches triangulated in the HMD frame (M,3), their
    normalised coordinates in each camera (role -> (M,2)) and their left descriptors (M,128)."""

    xy: dict[str, np.ndarray]
    descriptors: dict[str, np.ndarray]
    points_hmd: np.ndarray
    point_xy: dict[str, np.ndarray]
    point_descriptors: np.ndarray


def detect_features(image: np.ndarray, cam: Camera, cfg) -> tuple[np.ndarray, np.ndarray]:
    """(normalised coordinates (K,2), SIFT descriptors (K,128) float32) of an RGB image."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    sift = cv2.SIFT_create(nfeatures=int(cfg.max_features), contrastThreshold=float(cfg.contrast_threshold))
    keypoints, descriptors = sift.detectAndCompute(grey, None)
    if descriptors is None or not keypoints:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    pixels = np.array([k.pt for k in keypoints], np.float64)
    return normalised(pixels, cam), descriptors


def match_descriptors(a: np.ndarray, b: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of Lowe-ratio-test matches from descriptors ``a`` (N,128) to ``b`` (M,128),
    one match per ``b`` feature at most."""
    if len(a) == 0 or len(b) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a, b, k=2)
    good = [(p[0].queryIdx, p[0].trainIdx, p[0].distance) for p in pairs
            if len(p) == 2 and p[0].distance < float(ratio) * p[1].distance]
    best: dict[int, tuple[int, float]] = {}
    for ia, ib, d in good:
        if ib not in best or d < best[ib][1]:
            best[ib] = (ia, d)
    ib = np.array(sorted(best), np.int64)
    return np.array([best[i][0] for i in ib], np.int64), ib


def _reprojection_px(points_cam: np.ndarray, xy: np.ndarray, focal: float) -> np.ndarray:
    """Pixel-scaled distance (N,) between normalised projections of camera points and ``xy``."""
    z = np.maximum(points_cam[:, 2], 1e-9)
    return focal * np.linalg.norm(points_cam[:, :2] / z[:, None] - xy, axis=1)


def stereo_frame(images: dict[str, np.ndarray], cameras: dict[str, Camera], T_cam_from_hmd: dict[str, np.ndarray],
                 cfg) -> StereoFrame:
    """Features of both front images and their triangulated stereo matches (see the module docstring)."""
    left, right = FRONT_ROLES
    xy, desc = {}, {}
    for role in FRONT_ROLES:
        xy[role], desc[role] = detect_features(images[role], cameras[role], cfg)
    il, ir = match_descriptors(desc[left], desc[right], cfg.match_ratio)
    T_left_from_hmd = T_cam_from_hmd[left]
    T_right_from_left = T_cam_from_hmd[right] @ invert_rigid(T_left_from_hmd)
    if len(il) == 0:
        return StereoFrame(xy, desc, np.zeros((0, 3)), {r: np.zeros((0, 2)) for r in FRONT_ROLES},
                           np.zeros((0, 128), np.float32))
    homogeneous = cv2.triangulatePoints(np.eye(3, 4), T_right_from_left[:3], xy[left][il].T, xy[right][ir].T)
    w = homogeneous[3]
    safe = np.abs(w) > 1e-12
    X_left = (homogeneous[:3] / np.where(safe, w, 1.0)).T
    X_right = X_left @ T_right_from_left[:3, :3].T + T_right_from_left[:3, 3]
    focal = _focal(cameras[left])
    ok = safe & (X_left[:, 2] > float(cfg.min_depth_m)) & (X_right[:, 2] > float(cfg.min_depth_m))
    ok &= _reprojection_px(X_left, xy[left][il], focal) < float(cfg.max_reprojection_px)
    ok &= _reprojection_px(X_right, xy[right][ir], _focal(cameras[right])) < float(cfg.max_reprojection_px)
    points_hmd = (X_left[ok] - T_left_from_hmd[:3, 3]) @ T_left_from_hmd[:3, :3]
    return StereoFrame(xy, desc, points_hmd, {left: xy[left][il[ok]], right: xy[right][ir[ok]]}, desc[left][il[ok]])


def _focal(cam: Camera) -> float:
    return float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))


# ----------------------------------------------------------------------------- relative poses
def _project_normalised(points_hmd: np.ndarray, T_cam_from_hmd: np.ndarray) -> np.ndarray:
    """(N,3) camera-frame points of HMD-frame points (N,3)."""
    return points_hmd @ T_cam_from_hmd[:3, :3].T + T_cam_from_hmd[:3, 3]


@dataclass
class _TwoFrameProblem:
    """A stereo frame pair's observations for :func:`relative_pose`'s refinement.

    Points are frame ``a``'s, by inverse depth ``rho`` along their left-camera ray (``ray / rho``
    in frame ``a``'s left camera; well conditioned for far points). Observation ``o`` is point
    ``point_of[o]`` seen by role index ``role_of[o]`` in frame ``b`` (``in_b``) or ``a`` (its right
    view) at normalised ``xy[o]``; ``scale[o]`` (the focal length) turns residuals into pixels.
    The unknown pose is a 6-vector update of ``T_hmdb_from_hmda = rigid_from_vector(x) @ T_start``.
    """

    rays: np.ndarray
    point_of: np.ndarray
    role_of: np.ndarray
    in_b: np.ndarray
    xy: np.ndarray
    scale: np.ndarray
    T_cam_from_hmd: np.ndarray   # (2,4,4) left, right
    T_start: np.ndarray

    def cameras(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(O,3,3), (O,3): each observation's transform from frame ``a``'s left camera."""
        T_left = self.T_cam_from_hmd[0]
        T_from_left = self.T_cam_from_hmd @ invert_rigid(T_left)
        T_b = self.T_cam_from_hmd @ rigid_from_vector(x) @ self.T_start @ invert_rigid(T_left)
        T_obs = np.where(self.in_b[:, None, None], T_b[self.role_of], T_from_left[self.role_of])
        return T_obs[:, :3, :3], T_obs[:, :3, 3]

    def residuals(self, cameras, rho: np.ndarray, derivative: bool = False):
        """(O,2) pixel residuals (and, with ``derivative``, their derivative by each point's ``rho``)."""
        R, t = cameras
        ray = np.einsum("oij,oj->oi", R, self.rays[self.point_of])
        inverse = rho[self.point_of, None]
        X = ray / inverse + t
        z = np.maximum(X[:, 2:], 1e-9)
        r = self.scale[:, None] * (X[:, :2] / z - self.xy)
        if not derivative:
            return r
        dX = -ray / inverse ** 2
        return r, self.scale[:, None] * (dX[:, :2] * z - X[:, :2] * dX[:, 2:]) / z ** 2

    def best_depths(self, cameras, use: np.ndarray, rho: np.ndarray, max_rho: float, steps: int = 3) -> np.ndarray:
        """Per-point Gauss-Newton on the inverse depths with the cameras fixed (observations ``use``)."""
        n = len(rho)
        for _ in range(steps):
            r, J = self.residuals(cameras, rho, derivative=True)
            g = np.bincount(self.point_of, use * (J * r).sum(1), n)
            H = np.bincount(self.point_of, use * (J * J).sum(1), n)
            rho = np.clip(rho - g / np.maximum(H, 1e-12), 1e-3, max_rho)
        return rho


def _pnp_start(a: StereoFrame, b: StereoFrame, matches: dict, focal: dict, T_cam_from_hmd: dict,
               cfg) -> np.ndarray | None:
    """``T_hmdb_from_hmda`` by PnP + RANSAC in the camera of frame ``b`` with more matches."""
    role = max(FRONT_ROLES, key=lambda r: len(matches[r][0]))
    ia, ib = matches[role]
    if len(ia) < int(cfg.min_inliers):
        return None
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(a.points_hmd[ia], b.xy[role][ib], np.eye(3), None,
                                                 iterationsCount=200,
                                                 reprojectionError=float(cfg.max_reprojection_px) / focal[role],
                                                 flags=cv2.SOLVEPNP_SQPNP)
    if not ok or inliers is None or len(inliers) < int(cfg.min_inliers):
        return None
    return invert_rigid(T_cam_from_hmd[role]) @ rigid(cv2.Rodrigues(rvec)[0], tvec)


def relative_pose(a: StereoFrame, b: StereoFrame, cameras: dict[str, Camera], T_cam_from_hmd: dict[str, np.ndarray],
                  cfg) -> tuple[np.ndarray | None, int, float]:
    """(``T_hmdb_from_hmda`` (4,4) or None, inlier count in frame ``b``, inlier RMS px) of two
    stereo frames.

    Frame ``a``'s triangulated points are matched to frame ``b``'s features in both cameras;
    :func:`_pnp_start` starts, reprojection gating (2x, then 1x ``max_reprojection_px``) keeps
    inliers, and a two-frame bundle adjustment refines the pose *and* the points' depths against
    all their views (Huber on the pose, the depths eliminated per point by Gauss-Newton: variable
    projection). Holding the triangulated points fixed instead biases the translation towards
    zero: their depth noise (a few percent at a few metres with a 6 cm baseline) is noise in the
    regressor (errors in variables); on the simulated scan it shrank translations by ~5%.
    """
    focal = {role: _focal(cameras[role]) for role in FRONT_ROLES}
    matches = {role: match_descriptors(a.point_descriptors, b.descriptors[role], cfg.match_ratio) for role in FRONT_ROLES}
    T_start = _pnp_start(a, b, matches, focal, T_cam_from_hmd, cfg)
    if T_start is None:
        return None, 0, float("nan")
    threshold = float(cfg.max_reprojection_px)
    points, roles, xys = [], [], []
    for r, role in enumerate(FRONT_ROLES):  # frame b's views within 2x the gate of the start
        ia, ib = matches[role]
        X = _project_normalised(a.points_hmd[ia], T_cam_from_hmd[role] @ T_start)
        good = (X[:, 2] > 0) & (_reprojection_px(X, b.xy[role][ib], focal[role]) < 2 * threshold)
        points.append(ia[good])
        roles.append(np.full(good.sum(), r))
        xys.append(b.xy[role][ib[good]])
    seen_in_b = np.concatenate(points)
    if len(seen_in_b) < int(cfg.min_inliers):
        return None, 0, float("nan")
    seen = np.unique(seen_in_b)
    left, right = FRONT_ROLES
    roles_of = np.concatenate(roles + [np.ones(len(seen), np.int64)])  # + frame a's right views
    stack = np.stack([T_cam_from_hmd[left], T_cam_from_hmd[right]])
    problem = _TwoFrameProblem(
        rays=np.concatenate([a.point_xy[left][seen], np.ones((len(seen), 1))], axis=1),
        point_of=np.searchsorted(seen, np.concatenate([seen_in_b, seen])), role_of=roles_of,
        in_b=np.arange(len(roles_of)) < len(seen_in_b), xy=np.concatenate(xys + [a.point_xy[right][seen]]),
        scale=np.array([focal[left], focal[right]])[roles_of], T_cam_from_hmd=stack, T_start=T_start)
    rho = 1.0 / _project_normalised(a.points_hmd[seen], T_cam_from_hmd[left])[:, 2]
    max_rho = 1.0 / float(cfg.min_depth_m)

    def residuals(x, use):
        cams = problem.cameras(x)
        return problem.residuals(cams, problem.best_depths(cams, use, rho, max_rho))[use].ravel()

    x = np.zeros(6)
    use = np.ones(len(roles_of), bool)
    for gate in (2 * threshold, threshold):  # refine, re-gate, refine
        if (use & problem.in_b).sum() < int(cfg.min_inliers):
            return None, 0, float("nan")
        x = least_squares(residuals, x, args=(use,), loss="huber", f_scale=1.0, diff_step=1e-6).x
        cams = problem.cameras(x)
        rho = problem.best_depths(cams, use, rho, max_rho)
        error = np.linalg.norm(problem.residuals(cams, rho), axis=1)
        use = error < gate
    count = int((use & problem.in_b).sum())
    if count < int(cfg.min_inliers):
        return None, 0, float("nan")
    return rigid_from_vector(x) @ T_start, count, float(np.sqrt(np.mean(error[use] ** 2)))


# --------------------------------------------------------------------------------- pose graph
def _edge_residuals(T_hmd_from_vo: np.ndarray, i: np.ndarray, j: np.ndarray, inverse_measured: np.ndarray,
                    scale: np.ndarray) -> np.ndarray:
    """(E*6,) scaled 6-vectors of ``inv(T_ij) @ T_j @ inv(T_i)`` for edges ``i -> j`` measuring
    ``T_ij = T_hmdj_from_hmdi`` (``inverse_measured``: their inverses, (E,4,4))."""
    error = inverse_measured @ T_hmd_from_vo[j] @ np.linalg.inv(T_hmd_from_vo[i])
    return (vector_from_rigid(error) / scale).ravel()


def odometry(seq: SequenceInfo, cameras: dict[str, Camera], T_cam_from_hmd: dict[str, np.ndarray],
             R_prior: np.ndarray, cfg) -> tuple[np.ndarray, dict]:
    """(T_vo_from_hmd (T,4,4) with frame 0 = identity, info) of the ego frames by stereo odometry;
    ``R_prior`` (T,3,3) (the tracker's orientations) only chooses which frame pairs to match."""
    missing = [r for r in FRONT_ROLES if r not in T_cam_from_hmd or r not in seq.ego_roles]
    if missing:
        raise EgorelightError(f"wild alignment needs both calibrated front cameras; missing {', '.join(missing)}",
                              seq.root)
    ids = seq.ego_frame_ids
    frames = [stereo_frame({r: seq.read_ego_image(r, int(e)) for r in FRONT_ROLES}, cameras, T_cam_from_hmd, cfg)
              for e in ids]
    n = len(ids)
    edges, inliers, rms_px = [], [], []
    for i in range(n):
        for j in range(i + 1, n):
            if rotation_angle_deg(R_prior[i], R_prior[j]) > float(cfg.max_pair_angle_deg):
                continue
            T, count, rms = relative_pose(frames[i], frames[j], cameras, T_cam_from_hmd, cfg)
            if T is not None:
                edges.append((i, j, T))
                inliers.append(count)
                rms_px.append(rms)
    connected = {0}
    for _ in range(n):
        connected |= {j for i, j, _ in edges if i in connected} | {i for i, j, _ in edges if j in connected}
    if len(connected) < n:
        raise EgorelightError(f"visual odometry lost track in sequence {seq.name!r}: frames "
                              f"{sorted(set(range(n)) - connected)[:5]} match no other frame", seq.root)
    start: list[np.ndarray | None] = [np.eye(4)] + [None] * (n - 1)  # T_hmd_from_vo, chained
    for _ in range(n):
        for i, j, T in edges:
            if start[i] is not None and start[j] is None:
                start[j] = T @ start[i]
            elif start[j] is not None and start[i] is None:
                start[i] = invert_rigid(T) @ start[j]
    scale = np.array([np.radians(float(cfg.sigma_rotation_deg))] * 3 + [float(cfg.sigma_translation_m)] * 3)

    def nodes(x):
        return np.concatenate([np.eye(4)[None], rigid_from_vector(x.reshape(-1, 6))])

    graph = (np.array([e[0] for e in edges]), np.array([e[1] for e in edges]),
             np.linalg.inv(np.stack([e[2] for e in edges])))
    x0 = vector_from_rigid(np.stack(start[1:])).ravel()
    fit = least_squares(lambda x: _edge_residuals(nodes(x), *graph, scale), x0, loss="huber", f_scale=1.0)
    residual = _edge_residuals(nodes(fit.x), *graph, np.ones(6)).reshape(-1, 6)
    T_vo_from_hmd = np.linalg.inv(nodes(fit.x))
    return T_vo_from_hmd, {
        "odometry_pairs": len(edges), "odometry_inliers_mean": float(np.mean(inliers)),
        "odometry_reprojection_px": float(np.mean(rms_px)),
        "odometry_points_per_frame": float(np.mean([len(f.points_hmd) for f in frames])),
        "odometry_graph_rotation_deg": float(np.degrees(np.sqrt(np.mean(np.sum(residual[:, :3] ** 2, 1))))),
        "odometry_graph_translation_m": float(np.sqrt(np.mean(np.sum(residual[:, 3:] ** 2, 1))))}


# ---------------------------------------------------------------------------------- alignment
def align_trajectories(T_vo_from_hmd: np.ndarray, frame_times: np.ndarray, T_tracker: np.ndarray,
                       tracker_times: np.ndarray, cfg) -> tuple[float, np.ndarray, dict]:
    """(latency s, ``T_vo_from_tracker`` (4,4), fit statistics): see the module docstring, step 4."""
    R_vo = T_vo_from_hmd[:, :3, :3]
    best = None
    for latency in np.arange(-float(cfg.max_latency_s), float(cfg.max_latency_s) + 1e-9, float(cfg.latency_step_s)):
        R_tr = interpolate_poses(T_tracker, tracker_times, frame_times + latency, extrapolate=True)[:, :3, :3]
        A = mean_rotation(R_vo @ np.swapaxes(R_tr, 1, 2))
        rms = float(np.sqrt(np.mean(rotation_angle_deg(R_vo, A @ R_tr) ** 2)))
        if best is None or rms < best[2]:
            best = (float(latency), A, rms)
    latency, A, rms = best
    tracked = interpolate_poses(T_tracker, tracker_times, frame_times + latency, extrapolate=True)
    b = np.mean(T_vo_from_hmd[:, :3, 3] - tracked[:, :3, 3] @ A.T, axis=0)
    residual = T_vo_from_hmd[:, :3, 3] - (tracked[:, :3, 3] @ A.T + b)
    return latency, rigid(A, b), {"alignment_rms_deg": rms,
                                  "alignment_rms_m": float(np.sqrt(np.mean(np.sum(residual ** 2, axis=1))))}


def align_wild(seq: SequenceInfo, cameras: dict[str, Camera], T_cam_from_hmd: dict[str, np.ndarray], cfg) -> WildResult:
    """The whole in-the-wild step (``cfg``: the ``wild`` config section)."""
    seq.require_stream("ego")
    T_tr, ids, times = read_tracker(seq)
    ego = seq.ego_frame_ids
    with_frame = ids >= 0
    if not np.array_equal(np.sort(ids[with_frame]), np.sort(ego)):
        raise EgorelightError(f"tracker frame ids do not match the ego frames of sequence {seq.name!r}",
                              seq.head_pose_path())
    if len(ego) < 3:
        raise EgorelightError(f"sequence {seq.name!r} has {len(ego)} ego frames; wild alignment needs at least 3", seq.root)
    at_frame = {int(f): k for k, f in enumerate(ids) if f >= 0}
    rows = np.array([at_frame[int(e)] for e in ego])
    frame_times = times[rows]
    T_vo, info = odometry(seq, cameras, T_cam_from_hmd, T_tr[rows, :3, :3], cfg)
    latency, T_vo_from_tracker, fit = align_trajectories(T_vo, frame_times, T_tr, times, cfg)
    if str(cfg.pose_source) == "odometry":
        T = invert_rigid(T_vo_from_tracker) @ T_vo
    elif str(cfg.pose_source) == "tracker":
        T = interpolate_poses(T_tr, times, frame_times + latency, extrapolate=True)
    else:
        raise EgorelightError(f"wild.pose_source must be odometry or tracker, got {cfg.pose_source!r}")
    info.update({"latency_s": latency, **fit, "pose_source": str(cfg.pose_source),
                 "tracker_rate_hz": float((len(times) - 1) / (times[-1] - times[0])) if len(times) > 1 else 0.0,
                 "extrapolated_frames": int(np.sum(frame_times + latency > times[-1]))})
    n = len(ego)
    poses = HeadPoses(T, ego.astype(np.int64), np.ones(n, bool), np.full(n, info["odometry_pairs"], np.int64),
                      np.full(n, np.nan))
    return WildResult(poses, latency, T_vo_from_tracker, T_vo, T_tr[rows], info)
