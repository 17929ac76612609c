"""Scoring an ``envmap`` estimate against the simulator's in-the-wild truth (evaluation code only).

**The truth in the estimate's frame.** The simulator lights the wild sequence with
``groundtruth/envmaps/<name>.exr`` rotated by ``yaw_deg`` (``groundtruth/<seq>/surroundings.json``)
in its own world. The estimate lives in the frame of the calibration's head poses: for ``calibrate``
output that is the headset tracker's gravity-aligned frame (``T_tracker_from_world``, plus the
alignment's residual drift, see ``stages/calibrate_wild.py``); for an oracle calibration it is
the simulator's world. Rather than assume either, the frame is measured the way ``calibrate``
scores its wild trajectory: ``Q = mean_rotation(R_true R_cal^T)`` over the scan frames maps
directions of the pose frame into the world. The tracker frame is gravity-aligned, so ``Q`` is
taken as its nearest rotation about +Y (yaw ``q``; the remaining tilt is reported), and the true
map in the estimate's frame is ``rotate_envmap(E, yaw_deg - q)`` (exact, energy-preserving in
azimuth).

**Metrics** (:func:`envmap_metrics`; the paper reports none for this part):

* light vector ``S(E)`` on the capture's light stage: relative L2 error and cosine of
  ``S(E_est)`` against ``S(E_true)``, and the relative error after the best single gain (the LDR
  panorama's exposure is arbitrary);
* dominant-light direction error (degrees) of the luminance-weighted mean light direction
  ``sum_l Y(S_l) Omega_l w_l`` and of the brightest light;
* log-L1 ``|log(eps + E_est) - log(eps + E_true)|`` per texel (channel mean, solid-angle
  weighted) over the observed and the unobserved (inpainted) texels, the truth area-averaged to
  the estimate's resolution;
* with the inverse rendering, the colour synchronisation's gain and matrix against the simulated
  down cameras' true response (:func:`colour_sync_truth`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import cv2
import numpy as np

from egorelight_cli.geometry.equirect import check_envmap, equirect_solid_angles, rotate_envmap, yaw_rotation
from egorelight_cli.geometry.rigid import mean_frame_change, rotation_angle_deg
from egorelight_cli.io.calibration import Calibration
from egorelight_cli.io.capture import Capture
from egorelight_cli.render.envmaps import load_envmap
from egorelight_cli.render.lightstage import LightStage

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


@dataclass(frozen=True)
class WildTruth:
    """The true environment in the estimate's (head-pose) frame.

    Attributes:
        envmap: (Ht,2Ht,3) float32 true radiance, in the frame of the calibrated head poses.
        name: the map's name in ``groundtruth/envmaps``.
        frame_yaw_deg: yaw ``q`` of the pose frame in the simulator world.
        frame_tilt_deg: what ``Q`` holds beyond a yaw (0 for a gravity-aligned frame).
        frames: how many frames measured ``Q``.
    """

    envmap: np.ndarray
    name: str
    frame_yaw_deg: float
    frame_tilt_deg: float
    frames: int


def yaw_of(R: np.ndarray) -> float:
    """Degrees of the rotation about +Y nearest ``R`` (3,3), in the :func:`yaw_rotation` sense."""
    return math.degrees(math.atan2(R[0, 2] - R[2, 0], R[0, 0] + R[2, 2]))


def pose_frame_rotation(T_cal: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """(3,3) ``Q`` with ``R_true ~ Q R_cal``: directions of the calibration's frame -> world."""
    return mean_frame_change(T_true, T_cal)[:3, :3]


def truth_in_pose_frame(world_map: np.ndarray, world_yaw_deg: float, Q: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(map in the pose frame, frame yaw q (deg), tilt (deg)) of the map ``rotate_envmap(world_map,
    world_yaw_deg)`` of the world, for pose-frame -> world rotation ``Q`` taken as its yaw."""
    q = yaw_of(Q)
    tilt = float(rotation_angle_deg(Q, yaw_rotation(q)))
    return rotate_envmap(world_map, float(world_yaw_deg) - q), q, tilt


def wild_truth(capture: Capture, calibration: Calibration, sequence: str, frame_ids: np.ndarray) -> WildTruth | None:
    """The true map of ``sequence`` in the calibration's frame, or None without ground truth."""
    from egorelight_cli.synth.groundtruth import read_head_poses

    path = capture.groundtruth_file(sequence, "surroundings.json")
    root = capture.groundtruth_root()
    if path is None or root is None or not (root / "groundtruth" / sequence / "head_pose.npz").is_file():
        return None
    doc = json.loads(path.read_text())
    world_map = load_envmap(root / "groundtruth" / "envmaps" / f"{doc['envmap']}.exr")
    truth = read_head_poses(root, sequence)
    index = {int(f): i for i, f in enumerate(truth["frame_ids"])}
    frames = [int(f) for f in frame_ids if int(f) in index]
    if not frames:
        return None
    T_cal = np.stack([calibration.head_poses[sequence].pose(f) for f in frames])
    T_true = np.asarray(truth["T_world_from_hmd"])[[index[f] for f in frames]]
    envmap, q, tilt = truth_in_pose_frame(world_map, float(doc["yaw_deg"]), pose_frame_rotation(T_cal, T_true))
    return WildTruth(envmap, str(doc["envmap"]), q, tilt, len(frames))


def _resize_to(envmap: np.ndarray, height: int) -> np.ndarray:
    if envmap.shape[0] == height:
        return envmap
    interpolation = cv2.INTER_AREA if envmap.shape[0] > height else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(envmap, dtype=np.float32), (2 * height, height), interpolation=interpolation)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return float("nan")
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def light_vector_metrics(estimate: np.ndarray, truth: np.ndarray, lightstage: LightStage) -> dict:
    """Relative error, cosine, gain-corrected relative error and dominant-light direction errors
    of light intensities (L,3) ``estimate`` against ``truth``."""
    e, t = np.asarray(estimate, np.float64), np.asarray(truth, np.float64)
    norm_t = float(np.linalg.norm(t))
    dot, norm_e = float((e * t).sum()), float(np.linalg.norm(e))
    gain = dot / norm_e ** 2 if norm_e > 0 else 0.0
    lum_e, lum_t = e @ LUMINANCE, t @ LUMINANCE
    weights = lightstage.cell_solid_angles()
    dirs = lightstage.directions
    return {
        "light_relative_error": float(np.linalg.norm(e - t) / norm_t) if norm_t > 0 else float("nan"),
        "light_cosine": dot / (norm_e * norm_t) if norm_e > 0 and norm_t > 0 else float("nan"),
        "light_gain": gain,
        "light_relative_error_after_gain": float(np.linalg.norm(gain * e - t) / norm_t) if norm_t > 0 else float("nan"),
        "dominant_light_direction_error_deg": _angle_deg((lum_e * weights) @ dirs, (lum_t * weights) @ dirs),
        "brightest_light_direction_error_deg": _angle_deg(dirs[int(np.argmax(lum_e))], dirs[int(np.argmax(lum_t))]),
    }


def colour_sync_truth(capture: Capture, sync: dict[str, dict]) -> dict[str, dict] | None:
    """The fitted colour synchronisation of each down role against the simulator's camera response
    (``groundtruth/ego_response.json``): the true ``M = exposure C / studio_exposure`` (the ego
    camera's exposure and colour matrix over the studio cameras' HDR exposure, from the capture's
    recorded synth config, 1 when absent). Per role ``{"true_gain": mean row sum, "gain_error":
    fitted / true - 1, "matrix_max_abs_error"}``; None without ground truth."""
    root = capture.groundtruth_root()
    path = None if root is None else root / "groundtruth" / "ego_response.json"
    if path is None or not path.is_file():
        return None
    responses = json.loads(path.read_text())
    manifest = root / "manifest.json"
    config = json.loads(manifest.read_text()).get("config", {}) if manifest.is_file() else {}
    studio_exposure = float(config.get("studio", {}).get("exposure", 1.0))
    out = {}
    for role, fit in sync.items():
        if role not in responses:
            continue
        true = np.asarray(responses[role]["colour_matrix"], np.float64) * float(responses[role]["exposure"]) / studio_exposure
        fitted = np.asarray(fit["matrix"], np.float64)
        true_gain = float(true.sum(axis=1).mean())
        out[role] = {"true_gain": true_gain, "gain_error": float(fitted.sum(axis=1).mean() / true_gain - 1.0),
                     "matrix_max_abs_error": float(np.abs(fitted - true).max())}
    return out


def log_l1(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray, eps: float) -> float | None:
    """Solid-angle-weighted mean over ``mask`` texels of the channel-mean ``|log(eps+a) - log(eps+b)|``."""
    if not mask.any():
        return None
    omega = equirect_solid_angles(*mask.shape)
    diff = np.abs(np.log(eps + np.maximum(estimate, 0.0)) - np.log(eps + np.maximum(truth, 0.0))).mean(axis=-1)
    return float((diff * omega)[mask].sum() / omega[mask].sum())


def envmap_metrics(estimate: np.ndarray, observed: np.ndarray, truth: np.ndarray, lightstage: LightStage,
                   log_eps: float = 1e-3) -> dict:
    """Every metric of the module docstring for an (H,2H,3) estimate with its (H,2H) observed mask
    against a true map (any height) in the same frame."""
    estimate, truth = check_envmap(estimate), check_envmap(truth, "true environment map")
    out = light_vector_metrics(lightstage.envmap_to_intensities(estimate), lightstage.envmap_to_intensities(truth),
                               lightstage)
    small = _resize_to(truth, estimate.shape[0])
    out["log_l1_observed"] = log_l1(estimate, small, observed, log_eps)
    out["log_l1_unobserved"] = log_l1(estimate, small, ~observed, log_eps)
    return out


def relit_psnr(capture_root, estimates: dict[str, np.ndarray], truth: np.ndarray, cameras: int = 2,
               sequence: str = "test") -> dict:
    """Relit-render PSNR (dB) of the TRUE subject (the oracle renderer: true surface, materials,
    headset) under each estimate's light vector (L,3) against the same subject under the true
    ``truth`` (L,3), at the first ``cameras`` held-out studio cameras of ``sequence``'s first
    environment-lit frame. Both images share one exposure, the one that maps the 99th percentile
    of the true render's subject pixels to 1, then the metric tone mapping
    (:func:`~egorelight_cli.render.image_metrics.tonemap_for_metrics`); scored over the pixels
    either image covers. Returns ``{"relit_psnr": {name: dB}, "relit_views": [...]}``."""
    import torch

    from egorelight_cli.render.image_metrics import psnr, tonemap_for_metrics
    from egorelight_cli.synth.oracle import Oracle

    oracle = Oracle(capture_root)
    doc = json.loads((oracle.root / "sequences" / sequence / "sequence.json").read_text())
    lit = [int(f) for f, e in zip(doc["frame_ids"], doc["lights"]) if e.get("pattern") == "envmap"]
    rig = json.loads((oracle.root / "rig" / "studio_cameras.json").read_text())["cameras"]
    studio = [c["name"] for c in rig if c.get("role", "studio") == "studio"]
    held = list(doc.get("held_out_cameras", []))
    names = (held + [c for c in studio if c not in held])[:cameras]
    if not lit or not names:
        return {"relit_psnr": None, "relit_views": []}
    scores = {name: [] for name in estimates}
    for camera in names:
        reference = oracle.render(sequence, lit[0], camera, lighting=truth)
        level = np.percentile(reference.radiance.max(axis=-1)[reference.mask], 99.0) if reference.mask.any() else 1.0
        exposure = 1.0 / max(float(level), 1e-12)
        expected = tonemap_for_metrics(torch.from_numpy(reference.radiance), exposure)
        for name, intensities in estimates.items():
            render = oracle.render(sequence, lit[0], camera, lighting=intensities)
            mask = torch.from_numpy(reference.mask | render.mask)
            scores[name].append(float(psnr(tonemap_for_metrics(torch.from_numpy(render.radiance), exposure), expected,
                                           mask)))
    return {"relit_psnr": {name: float(np.mean(v)) for name, v in scores.items()},
            "relit_views": [f"{sequence}/{lit[0]}/{camera}" for camera in names]}
