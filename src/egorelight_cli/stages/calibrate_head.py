"""Head tracking in the studio: the HMD's ArUco markers seen by the calibrated studio cameras.

Per studio frame: every studio camera image (linear HDR) is tone-mapped to 8 bit and searched
for the HMD markers (``rig/hmd.json``: dictionary and corner layout in the HMD frame). The pose
``T_world_from_hmd`` is initialised from corners triangulated in two or more cameras (DLT, then
a rigid fit to the layout) or, failing that, from single-camera PnP, and refined by minimising
the reprojection error of every detected corner in every camera (Huber loss). A frame gets a
pose only with enough evidence (``head.min_observations`` marker detections, seen by two cameras
or as two markers, RMS residual under ``head.max_residual_px``, and a rotation standard deviation
-- from the fit's Jacobian and ``head.pixel_noise_px`` -- under ``head.max_rotation_std_deg``);
otherwise it is flagged
(``valid = False``) and its pose is NaN, never invented.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.geometry.markers import aruco_dictionary, detect_markers, refine_marker_edges
from egorelight_cli.geometry.rigid import kabsch, rigid, rigid_from_vector
from egorelight_cli.structures.calibration import HeadPoses
from egorelight_cli.io.capture import Capture, SequenceInfo
from egorelight_cli.io.exr import read_exr
from egorelight_cli.io.images import read_image, srgb_to_linear, tonemap


@dataclass(frozen=True)
class MarkerLayout:
    """The HMD's markers: dictionary name and corners (4,3) in the HMD frame per marker id."""

    dictionary: str
    corners: dict[int, np.ndarray]

    @property
    def cells(self) -> int:
        """Marker width in cells: the dictionary's bits plus a one-cell border on each side."""
        return int(aruco_dictionary(self.dictionary).markerSize) + 2

    @classmethod
    def from_hmd(cls, capture: Capture) -> "MarkerLayout":
        path = capture.root / "rig" / "hmd.json"
        try:
            doc = capture.hmd["markers"]
            corners = {int(m["id"]): np.asarray(m["corners_hmd"], np.float64) for m in doc["markers"]}
            dictionary = str(doc.get("dictionary", "DICT_4X4_50"))
            aruco_dictionary(dictionary)
        except (KeyError, TypeError, ValueError) as exc:
            raise EgorelightError(f"HMD description has no usable marker layout ({type(exc).__name__}: {exc})",
                                  path) from None
        if not corners or any(c.shape != (4, 3) for c in corners.values()):
            raise EgorelightError("HMD marker layout must list markers with 4 corners (x,y,z) each", path)
        return cls(dictionary, corners)


@dataclass
class MarkerObservation:
    """One marker seen by one camera: pixel corners (4,2) and the layout corners (4,3)."""

    camera: str
    marker_id: int
    pixels: np.ndarray
    corners_hmd: np.ndarray


def studio_image(seq: SequenceInfo, camera: str, frame_id: int, percentile: float) -> tuple[np.ndarray, np.ndarray]:
    """A studio frame as (H,W,3) uint8 for detection (EXR: tone-mapped per image, the
    ``percentile`` of lit pixels to ~0.9; PNG: as stored) and (H,W) float linear intensity."""
    path = seq.studio_image_path(camera, frame_id)
    if path.suffix == ".exr":
        hdr = read_exr(path).layer("")[..., :3]
        return tonemap(hdr, hdr.max(axis=-1) > 0, percentile), hdr.mean(axis=-1)
    if path.suffix == ".png":
        image = read_image(path)
        image = image if image.dtype == np.uint8 else (image // 257).astype(np.uint8)
        image = image[..., :3] if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
        return image, srgb_to_linear(image / 255.0).mean(axis=-1)
    raise EgorelightError(f"studio frame format {path.suffix} is not supported by calibrate", path)


def detect_frame(seq: SequenceInfo, frame_id: int, cameras: dict[str, Camera], layout: MarkerLayout,
                 cfg) -> list[MarkerObservation]:
    """Every layout marker found in the studio images of one frame."""
    out = []
    for name in seq.studio_cameras:
        if name not in cameras:
            raise EgorelightError(f"sequence {seq.name!r} lists studio camera {name!r}, which the rig lacks",
                                  seq.root / "sequence.json")
        image, intensity = studio_image(seq, name, frame_id, float(cfg.tonemap_percentile))
        cam = cameras[name]
        if image.shape[:2] != (cam.height, cam.width):
            raise EgorelightError(f"studio image of {name} is {image.shape[1]}x{image.shape[0]}, the rig says "
                                  f"{cam.width}x{cam.height}", seq.studio_image_path(name, frame_id))
        edges = str(cfg.corner_refinement) == "edges"
        ids, corners = detect_markers(image, layout.dictionary, "contour" if edges else str(cfg.corner_refinement))
        if edges:
            corners = np.array([refine_marker_edges(intensity, c, layout.cells) for c in corners]).reshape(-1, 4, 2)
        seen = set()
        for marker_id, pixels in zip(ids, corners):
            if int(marker_id) in layout.corners and int(marker_id) not in seen:  # ignore duplicates/foreign ids
                seen.add(int(marker_id))
                out.append(MarkerObservation(name, int(marker_id), pixels, layout.corners[int(marker_id)]))
    return out


def _triangulate(rays: list[tuple[Camera, np.ndarray]]) -> np.ndarray:
    """World point closest (least squares) to the rays through pixel ``uv`` of each camera."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam, uv in rays:
        ray = cv2.undistortPoints(uv.reshape(1, 1, 2), cam.K, cam.dist).reshape(2)
        d = cam.T_world_from_cam[:3, :3] @ np.array([ray[0], ray[1], 1.0])
        d /= np.linalg.norm(d)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.centre_world
    return np.linalg.solve(A, b)


def _init_triangulated(obs: list[MarkerObservation], cameras: dict[str, Camera]) -> np.ndarray | None:
    by_marker: dict[int, list[MarkerObservation]] = {}
    for o in obs:
        by_marker.setdefault(o.marker_id, []).append(o)
    src, dst = [], []
    for views in by_marker.values():
        if len(views) < 2:
            continue
        for k in range(4):
            dst.append(_triangulate([(cameras[v.camera], v.pixels[k]) for v in views]))
            src.append(views[0].corners_hmd[k])
    return kabsch(np.array(src), np.array(dst)) if len(src) >= 4 else None


def _init_pnp(obs: list[MarkerObservation], cameras: dict[str, Camera]) -> list[np.ndarray]:
    """One candidate pose per camera (PnP on all its markers; planar IPPE for a single marker)."""
    out = []
    for name in sorted({o.camera for o in obs}):
        mine = [o for o in obs if o.camera == name]
        obj = np.concatenate([o.corners_hmd for o in mine])
        img = np.concatenate([o.pixels for o in mine])
        cam = cameras[name]
        flag = cv2.SOLVEPNP_SQPNP if len(mine) >= 2 else cv2.SOLVEPNP_IPPE
        ok, rvec, tvec = cv2.solvePnP(obj, img, cam.K, cam.dist, flags=flag)
        if ok:
            T_cam_from_hmd = rigid(cv2.Rodrigues(rvec)[0], tvec)
            out.append(cam.T_world_from_cam @ T_cam_from_hmd)
    return out


def project_camera_points(points_cam: np.ndarray, camera) -> np.ndarray:
    """(N,2) pixels of camera-frame points (N,3) (pinhole or fisheye ``Camera``): OpenCV's C
    projection, the same models as :func:`egorelight_cli.geometry.cameras.project` but much faster
    in least-squares loops. Points behind the camera get pixels 1e4 (a large, finite residual)."""
    obj = np.asarray(points_cam, np.float64).reshape(-1, 1, 3)
    zero = np.zeros((3, 1))
    if camera.model == "fisheye":
        uv, _ = cv2.fisheye.projectPoints(obj, zero, zero, camera.K, camera.dist[:4])
    else:
        uv, _ = cv2.projectPoints(obj, zero, zero, camera.K, camera.dist)
    return np.where((obj[:, 0, 2] > 1e-6)[:, None], uv.reshape(-1, 2), 1e4)


def project_points(T_cam_from_obj: np.ndarray, points: np.ndarray, camera) -> np.ndarray:
    """(N,2) pixels of object points (N,3) posed by ``T_cam_from_obj`` (see :func:`project_camera_points`)."""
    points = np.asarray(points, np.float64)
    return project_camera_points(points @ T_cam_from_obj[:3, :3].T + T_cam_from_obj[:3, 3], camera)


def reprojection_residuals(T_world_from_hmd: np.ndarray, obs: list[MarkerObservation],
                           cameras: dict[str, Camera]) -> np.ndarray:
    """(N*4*2,) pixel residuals (projected - detected) of every observed corner."""
    res = [project_points(cameras[o.camera].T_cam_from_world @ T_world_from_hmd, o.corners_hmd, cameras[o.camera])
           - o.pixels for o in obs]
    return np.concatenate(res).ravel() if res else np.zeros(0)


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r ** 2))) if r.size else float("nan")


def solve_head_pose(obs: list[MarkerObservation], cameras: dict[str, Camera], cfg) -> tuple[np.ndarray, bool, float]:
    """(T_world_from_hmd (4,4) or NaN, valid, RMS residual px) of one frame's observations."""
    nan = np.full((4, 4), np.nan)
    n_cams = len({o.camera for o in obs})
    n_markers = len({o.marker_id for o in obs})
    if len(obs) < int(cfg.min_observations) or (n_cams < 2 and n_markers < 2):
        return nan, False, float("nan")
    candidates = _init_pnp(obs, cameras)
    triangulated = _init_triangulated(obs, cameras)
    if triangulated is not None:
        candidates.append(triangulated)
    if not candidates:
        return nan, False, float("nan")
    best = min(candidates, key=lambda T: _rms(reprojection_residuals(T, obs, cameras)))
    fit = least_squares(lambda v: reprojection_residuals(rigid_from_vector(v) @ best, obs, cameras),
                        np.zeros(6), loss="huber", f_scale=float(cfg.huber_px))
    T = rigid_from_vector(fit.x) @ best
    rms = _rms(reprojection_residuals(T, obs, cameras))
    if not np.isfinite(rms) or rms > float(cfg.max_residual_px):
        return nan, False, rms
    if rotation_std_deg(fit.jac, max(rms, float(cfg.pixel_noise_px))) > float(cfg.max_rotation_std_deg):
        return nan, False, rms  # e.g. one small marker: a pose, but its rotation is a guess
    return T, True, rms


def rotation_std_deg(jacobian: np.ndarray, noise_px: float) -> float:
    """Largest standard deviation (degrees) of the rotation of a pose fit, from its (N,6) Jacobian
    (rotation increments first) and the pixel noise: ``sqrt(max eig((J^T J)^-1)) * noise``."""
    JtJ = jacobian.T @ jacobian
    try:
        cov = np.linalg.inv(JtJ)[:3, :3]
    except np.linalg.LinAlgError:
        return float("inf")
    return float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0)) * noise_px))


@dataclass
class HeadTrack:
    """Head poses of one sequence plus the observations that made them (for refinement, previews)."""

    poses: HeadPoses
    observations: dict[int, list[MarkerObservation]]


def track_head(capture: Capture, seq: SequenceInfo, cfg) -> HeadTrack:
    """HMD poses of every studio frame of ``seq`` (``cfg``: the ``head`` config section)."""
    seq.require_stream("studio")
    cameras = capture.studio_cameras
    layout = MarkerLayout.from_hmd(capture)
    frames = seq.frame_ids
    T = np.full((len(frames), 4, 4), np.nan)
    valid = np.zeros(len(frames), bool)
    count = np.zeros(len(frames), np.int64)
    residual = np.full(len(frames), np.nan)
    observations = {}
    for i, fid in enumerate(frames):
        obs = detect_frame(seq, int(fid), cameras, layout, cfg)
        observations[int(fid)] = obs
        count[i] = len(obs)
        T[i], valid[i], residual[i] = solve_head_pose(obs, cameras, cfg)
    return HeadTrack(HeadPoses(T, frames.astype(np.int64), valid, count, residual), observations)
