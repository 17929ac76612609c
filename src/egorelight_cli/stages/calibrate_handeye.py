"""Hand-eye calibration of the HMD cameras from the ``handeye`` sequence.

A static ChArUco board (``rig/board.json``) stands in front of the subject while the head moves.
For every ego camera and ego frame the board corners are detected (small images are upsampled
first); the ego frame maps to the studio frame whose head pose ``H = T_world_from_hmd`` the
markers gave (stream offset from the flashes). Then

1. **AX = XB**: for cameras with enough frames that show the board well, per-frame PnP gives
   ``C = T_cam_from_board`` and ``cv2.calibrateHandEye`` (the best of several methods) gives ``Pi = T_cam_from_hmd``
   from the pairs (H, C); the static board pose ``B = T_world_from_board`` follows (mean over
   frames). Cameras that see only a few corners per frame (the down-facing fisheyes see the board
   at the edge of their image circle) are initialised by one PnP over *all* their corners, moved
   into the HMD frame with the head poses and ``B``.
2. **Joint refinement** (scipy least squares, Huber loss): every ``Pi``, ``B`` and (by default)
   the hand-eye sequence's head poses, minimising the board corners' reprojection error in all
   ego cameras together with the HMD markers' reprojection error in the studio cameras.

Residuals: RMS reprojection error in pixels, and in millimetres the RMS distance of the
predicted board corners from the rays through their detections. A camera with too few
detections is reported as uncalibrated (an error or a warning, ``handeye.on_missing``), never
given a made-up transform.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, invert_rigid
from egorelight_cli.geometry.markers import charuco_board, detect_charuco
from egorelight_cli.geometry.rigid import mean_rotation, rigid, rigid_from_vector, rotation_angle_deg
from egorelight_cli.io.capture import Capture, SequenceInfo
from egorelight_cli.stages.calibrate_head import MarkerObservation, project_camera_points, project_points


@dataclass
class BoardObservation:
    """Board corners seen by one ego camera in one frame (studio frame id ``frame``)."""

    role: str
    frame: int
    ego_frame: int
    corner_ids: np.ndarray   # (N,)
    points_board: np.ndarray  # (N,3) board frame, metres
    pixels: np.ndarray       # (N,2)


@dataclass
class HandEyeResult:
    """Per calibrated camera ``T_cam_from_hmd``; residuals; the board pose; refined head poses."""

    T_cam_from_hmd: dict[str, np.ndarray]
    residual_px: dict[str, float]
    residual_mm: dict[str, float]
    T_world_from_board: np.ndarray
    refined_head: dict[int, np.ndarray]
    observations: list[BoardObservation]
    missing: dict[str, str] = field(default_factory=dict)
    info: dict = field(default_factory=dict)


def _upsampled(image: np.ndarray, factor: int) -> np.ndarray:
    return image if factor <= 1 else cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC)


def detect_boards(seq: SequenceInfo, cameras: dict[str, Camera], board, stream_offset: int, cfg) -> list[BoardObservation]:
    """ChArUco corners in every ego image of ``seq`` (``cfg``: the ``handeye`` section)."""
    seq.require_stream("ego")
    chessboard = np.asarray(board.getChessboardCorners(), np.float64)
    out = []
    for role in seq.ego_roles:
        if role not in cameras:
            raise EgorelightError(f"sequence {seq.name!r} has ego images of {role!r}, which rig/hmd.json lacks",
                                  seq.root / "sequence.json")
        cam = cameras[role]
        factor = max(1, int(np.ceil(float(cfg.detect_min_size_px) / min(cam.width, cam.height))))
        for e in seq.ego_frame_ids:
            image = seq.read_ego_image(role, int(e))
            if image.shape[:2] != (cam.height, cam.width):
                raise EgorelightError(f"ego image of {role} is {image.shape[1]}x{image.shape[0]}, rig/hmd.json says "
                                      f"{cam.width}x{cam.height}", seq.ego_image_path(role, int(e)))
            ids, pixels = detect_charuco(_upsampled(image, factor), board)
            if len(ids) == 0:
                continue
            pixels = (pixels + 0.5) / factor - 0.5  # back to the original pixel grid (centres at integers)
            out.append(BoardObservation(role, int(e) - int(stream_offset), int(e), ids, chessboard[ids], pixels))
    return out


def normalised(pixels: np.ndarray, cam: Camera) -> np.ndarray:
    """(N,2) undistorted normalised image coordinates (x/z, y/z) of pixels."""
    uv = np.asarray(pixels, np.float64).reshape(-1, 1, 2)
    if cam.model == "fisheye":
        return cv2.fisheye.undistortPoints(uv, cam.K, cam.dist[:4]).reshape(-1, 2)
    return cv2.undistortPoints(uv, cam.K, cam.dist).reshape(-1, 2)


def pnp(points: np.ndarray, pixels: np.ndarray, cam: Camera) -> np.ndarray | None:
    """T_cam_from_obj (4,4) from 3D-2D correspondences (any model: PnP on undistorted points)."""
    if len(points) < 4:
        return None
    xy = normalised(pixels, cam)
    ok, rvec, tvec = cv2.solvePnP(np.asarray(points, np.float64), xy, np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    T = rigid(cv2.Rodrigues(rvec)[0], tvec)
    ok, rvec, tvec = cv2.solvePnP(np.asarray(points, np.float64), xy, np.eye(3), None, rvec, tvec,
                                  useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    return rigid(cv2.Rodrigues(rvec)[0], tvec) if ok else T


#: Tsai is left out: it rejects the small head motions of a hand-eye sequence (and logs errors).
HAND_EYE_METHODS = ("PARK", "HORAUD", "DANIILIDIS", "ANDREFF")


def _board_from(pairs, Pi: np.ndarray) -> np.ndarray:
    """Mean ``T_world_from_board`` over the frames' ``H @ inv(Pi) @ C``."""
    boards = [H @ invert_rigid(Pi) @ C for H, C in pairs]
    return rigid(mean_rotation([b[:3, :3] for b in boards]), np.mean([b[:3, 3] for b in boards], axis=0))


def _hand_eye(pairs: list[tuple[np.ndarray, np.ndarray]], obs: list[BoardObservation], heads,
              cam: Camera) -> np.ndarray | None:
    """T_cam_from_hmd from (T_world_from_hmd, T_cam_from_board) pairs: ``cv2.calibrateHandEye``
    with each of :data:`HAND_EYE_METHODS` (small head motions make some of them fail), keeping the
    one whose board pose reprojects best."""
    R_g = [H[:3, :3] for H, _ in pairs]
    t_g = [H[:3, 3] for H, _ in pairs]
    R_t = [C[:3, :3] for _, C in pairs]
    t_t = [C[:3, 3] for _, C in pairs]
    best, best_px = None, np.inf
    for method in HAND_EYE_METHODS:
        try:
            R, t = cv2.calibrateHandEye(R_g, t_g, R_t, t_t, method=getattr(cv2, f"CALIB_HAND_EYE_{method}"))
        except cv2.error:
            continue
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            continue
        Pi = invert_rigid(rigid(R, t))
        px = _reprojection_rms(Pi, _board_from(pairs, Pi), heads, obs, cam)
        if px < best_px:
            best, best_px = Pi, px
    return best


def _reprojection_rms(Pi, B, heads, obs: list[BoardObservation], cam: Camera) -> float:
    errors = [project_points(Pi @ invert_rigid(heads[o.frame]) @ B, o.points_board, cam) - o.pixels
              for o in obs if o.frame in heads]
    return float(np.sqrt(np.mean(np.concatenate(errors) ** 2))) if errors else np.inf


def _rotation_spread_deg(Hs: list[np.ndarray]) -> float:
    """Largest angle between any head rotation and the first (diversity of the motion)."""
    if not Hs:
        return 0.0
    Rs = np.asarray(Hs)[:, :3, :3]
    return float(rotation_angle_deg(Rs[0], Rs).max())


def initialise(obs: list[BoardObservation], heads: dict[int, np.ndarray], cameras: dict[str, Camera],
               cfg) -> tuple[dict[str, np.ndarray], np.ndarray | None, dict[str, str]]:
    """(Pi per camera, B, why-missing per camera) before refinement."""
    Pi, missing = {}, {}
    boards = []
    roles = sorted({o.role for o in obs} | set(cameras))
    for role in roles:
        pairs = []
        for o in obs:
            if o.role == role and o.frame in heads and len(o.corner_ids) >= int(cfg.min_corners):
                C = pnp(o.points_board, o.pixels, cameras[role])
                if C is not None:
                    pairs.append((heads[o.frame], C))
        if len(pairs) >= int(cfg.min_frames) and _rotation_spread_deg([H for H, _ in pairs]) >= float(cfg.min_rotation_deg):
            mine = [o for o in obs if o.role == role]
            found = _hand_eye(pairs, mine, heads, cameras[role])
            if found is not None:
                Pi[role] = found
                boards += [H @ invert_rigid(found) @ C for H, C in pairs]
    if not boards:
        return {}, None, {r: "no camera saw the board well enough in enough frames" for r in roles}
    B = rigid(mean_rotation([b[:3, :3] for b in boards]), np.mean([b[:3, 3] for b in boards], axis=0))
    for role in roles:
        if role in Pi:
            continue
        mine = [o for o in obs if o.role == role and o.frame in heads]
        n = sum(len(o.corner_ids) for o in mine)
        if n < int(cfg.min_pooled_corners):
            missing[role] = f"{n} board corners with a head pose (need {int(cfg.min_pooled_corners)})"
            continue
        points = np.concatenate([(invert_rigid(heads[o.frame]) @ B)[:3, :3] @ o.points_board.T
                                 + (invert_rigid(heads[o.frame]) @ B)[:3, 3:4] for o in mine], axis=1).T
        pixels = np.concatenate([o.pixels for o in mine])
        T = pnp(points, pixels, cameras[role])
        if T is None:
            missing[role] = "pooled PnP failed"
        else:
            Pi[role] = T
    return Pi, B, missing


# ---------------------------------------------------------------------------------- refinement
def _rigid_batch(x: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(N,4,4) ``exp(x_i) @ base_i`` for increments x (N,6) and transforms base (N,4,4)."""
    return rigid_from_vector(x.reshape(-1, 6)) @ base if len(base) else base


def refine(Pi: dict[str, np.ndarray], B: np.ndarray, heads: dict[int, np.ndarray], board_obs: list[BoardObservation],
           marker_obs: dict[int, list[MarkerObservation]], cameras: dict[str, Camera], studio: dict[str, Camera],
           cfg) -> tuple[dict[str, np.ndarray], np.ndarray, dict[int, np.ndarray], dict]:
    """Joint least squares over Pi (per camera), B and (``cfg.refine_head_poses``) the head poses.

    Parameters are left-multiplied increments (6 each: B, then every Pi, then every refined head
    pose), so no rotation vector nears its singularity; residuals are pixels (marker corners
    weighted by ``cfg.marker_weight``), vectorised per camera."""
    roles = sorted(Pi)
    frames = sorted(heads)
    refine_heads = bool(cfg.refine_head_poses)
    frame_index = {f: i for i, f in enumerate(frames)}
    role_index = {r: i for i, r in enumerate(roles)}
    studio_names = sorted({m.camera for f in frames for m in marker_obs.get(f, [])}) if refine_heads else []
    studio_index = {n: i for i, n in enumerate(studio_names)}
    # per block: (kind 0 board / 1 marker, camera key, role or studio index, frame index, points, pixels, weight)
    blocks = [(0, ("ego", o.role), role_index[o.role], frame_index[o.frame], o.points_board, o.pixels, 1.0)
              for o in board_obs if o.role in Pi and o.frame in heads]
    if refine_heads:
        for f in frames:
            for m in marker_obs.get(f, []):
                blocks.append((1, ("studio", m.camera), studio_index[m.camera], frame_index[f], m.corners_hmd,
                               m.pixels, float(cfg.marker_weight)))
    kind = np.array([b[0] for b in blocks])
    which = np.array([b[2] for b in blocks])
    frame_of = np.array([b[3] for b in blocks])
    counts = np.array([len(b[4]) for b in blocks])
    point_block = np.repeat(np.arange(len(blocks)), counts)
    points = np.concatenate([b[4] for b in blocks])
    pixels = np.concatenate([b[5] for b in blocks])
    weight = np.repeat([b[6] for b in blocks], counts)[:, None]
    keys = sorted({b[1] for b in blocks})
    groups = [(cameras[k[1]] if k[0] == "ego" else studio[k[1]],
               np.flatnonzero(np.repeat([b[1] == k for b in blocks], counts))) for k in keys]
    T_cw = np.array([studio[n].T_cam_from_world for n in studio_names]).reshape(-1, 4, 4)
    P0 = np.array([Pi[r] for r in roles])
    H0 = np.array([heads[f] for f in frames])
    n_p, n_h = len(roles), (len(frames) if refine_heads else 0)
    x0 = np.zeros(6 * (1 + n_p + n_h))

    def unpack(x):
        B_ = rigid_from_vector(x[:6]) @ B
        P_ = _rigid_batch(x[6:6 + 6 * n_p], P0)
        H_ = _rigid_batch(x[6 + 6 * n_p:], H0) if refine_heads else H0
        return B_, P_, H_

    def residuals(x):
        B_, P_, H_ = unpack(x)
        T = np.empty((len(blocks), 4, 4))
        board = kind == 0
        T[board] = P_[which[board]] @ invert_rigid(H_[frame_of[board]]) @ B_
        T[~board] = T_cw[which[~board]] @ H_[frame_of[~board]]
        Tp = T[point_block]
        cam_points = np.einsum("nij,nj->ni", Tp[:, :3, :3], points) + Tp[:, :3, 3]
        out = np.empty_like(pixels)
        for cam, rows in groups:
            out[rows] = project_camera_points(cam_points[rows], cam)
        r = weight * (out - pixels)
        return r.ravel()

    row_role = np.repeat(np.where(kind == 0, which, -1), 2 * counts)
    row_frame = np.repeat(frame_of, 2 * counts)

    def jacobian(x):
        """Forward differences, 18 evaluations: the Pi (and head pose) columns of different cameras
        (frames) touch disjoint residual rows, so one perturbation measures them all."""
        f0 = residuals(x)
        J = np.zeros((len(f0), len(x)))
        step = 1e-7
        for g in range(6):
            x1 = x.copy()
            x1[g] += step
            J[:, g] = (residuals(x1) - f0) / step
            x1 = x.copy()
            x1[6 + g:6 + 6 * n_p:6] += step
            d = (residuals(x1) - f0) / step
            for i in range(n_p):
                J[row_role == i, 6 + 6 * i + g] = d[row_role == i]
            if n_h:
                x1 = x.copy()
                x1[6 + 6 * n_p + g::6] += step
                d = (residuals(x1) - f0) / step
                for i in range(n_h):
                    J[row_frame == i, 6 + 6 * (n_p + i) + g] = d[row_frame == i]
        return J

    fit = least_squares(residuals, x0, jac=jacobian, loss="huber", f_scale=float(cfg.huber_px),
                        x_scale="jac", tr_solver="exact", max_nfev=int(cfg.max_iterations))
    B_, P_, H_ = unpack(fit.x)
    info = {"refine_cost_initial": float(0.5 * np.sum(residuals(x0) ** 2)), "refine_cost_final": float(fit.cost),
            "refine_evaluations": int(fit.nfev), "refine_status": str(fit.message),
            "refined_head_frames": n_h, "residual_blocks": len(blocks)}
    refined = {f: H_[i] for i, f in enumerate(frames)} if refine_heads else {}
    return dict(zip(roles, P_)), B_, refined, info


def residual_stats(role: str, Pi: np.ndarray, B: np.ndarray, heads: dict[int, np.ndarray],
                   obs: list[BoardObservation], cam: Camera) -> tuple[float, float, int]:
    """(RMS reprojection px, RMS point-to-ray distance mm, corners) of one camera's board corners."""
    px, mm = [], []
    for o in obs:
        if o.role != role or o.frame not in heads:
            continue
        T = Pi @ invert_rigid(heads[o.frame]) @ B
        px.append(np.linalg.norm(project_points(T, o.points_board, cam) - o.pixels, axis=1))
        points = (T[:3, :3] @ o.points_board.T).T + T[:3, 3]
        xy = normalised(o.pixels, cam)
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        along = np.sum(points * rays, axis=1, keepdims=True)
        mm.append(1000 * np.linalg.norm(points - along * rays, axis=1))
    if not px:
        return float("nan"), float("nan"), 0
    px, mm = np.concatenate(px), np.concatenate(mm)
    return float(np.sqrt(np.mean(px ** 2))), float(np.sqrt(np.mean(mm ** 2))), int(len(px))


def calibrate_hand_eye(capture: Capture, seq: SequenceInfo, stream_offset: int, heads: dict[int, np.ndarray],
                       marker_obs: dict[int, list[MarkerObservation]], cfg) -> HandEyeResult:
    """The whole hand-eye step (``cfg``: the ``handeye`` section); ``heads``: valid head poses by
    studio frame id of ``seq``."""
    try:
        board = charuco_board(capture.board)
    except ValueError as exc:
        raise EgorelightError(str(exc), capture.root / "rig" / "board.json") from None
    cameras = capture.ego_cameras
    obs = detect_boards(seq, cameras, board, stream_offset, cfg)
    if not obs:
        raise EgorelightError(f"no ego camera sees the calibration board in sequence {seq.name!r}", seq.root / "ego")
    Pi, B, missing = initialise(obs, heads, cameras, cfg)
    if B is None:
        raise EgorelightError(
            f"too few board detections for hand-eye calibration in sequence {seq.name!r}: no camera shows "
            f">= {int(cfg.min_corners)} corners in >= {int(cfg.min_frames)} frames with a head pose and "
            f">= {float(cfg.min_rotation_deg):g} degrees of head rotation", seq.root)
    info = {"board_detections": {r: sum(1 for o in obs if o.role == r) for r in sorted(cameras)},
            "board_corners": {r: int(sum(len(o.corner_ids) for o in obs if o.role == r)) for r in sorted(cameras)},
            "frames_with_head_pose": len(heads)}
    refined: dict[int, np.ndarray] = {}
    if bool(cfg.refine):
        Pi, B, refined, more = refine(Pi, B, heads, obs, marker_obs, cameras, capture.studio_cameras, cfg)
        info.update(more)
    final_heads = {**heads, **refined}
    res_px, res_mm = {}, {}
    for role in Pi:
        res_px[role], res_mm[role], _ = residual_stats(role, Pi[role], B, final_heads, obs, cameras[role])
    return HandEyeResult(Pi, res_px, res_mm, B, refined, obs, missing, info)
