"""The headset's built-in tracker in the wild: true head poses seen with latency, drift and an
unknown world frame.

``T_tracker(t) = T_tracker_from_world @ D(t) @ T_world_from_hmd(t - latency)`` where ``D(t)`` is
a slowly growing rigid drift (smooth random walk in translation and yaw) and the true pose at a
fractional time is interpolated (linear translation, slerp rotation) between the samples the
caller gives (the motion evaluated at the tracker's rate). The paper aligns this
trajectory to visual odometry with a 6-DoF offset; the ground truth keeps every part.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from egorelight_cli.geometry.rigid import interpolate_poses


def simulate_tracker(T_world_from_hmd: np.ndarray, fps: float, cfg, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """(tracker poses (T,4,4), ground-truth description)."""
    n = len(T_world_from_hmd)
    times = np.arange(n) / fps
    delayed = interpolate_poses(T_world_from_hmd, times, times - cfg.latency_s)
    sigma = max(1.0 * fps, 1.0)
    walk = ndimage.gaussian_filter1d(np.cumsum(rng.normal(size=(n, 4)), axis=0), sigma, axis=0, mode="nearest")
    walk /= np.sqrt(max(n, 1))
    drift_t = cfg.drift_m_per_s * walk[:, :3] * np.sqrt(times[-1] + 1.0 / fps)
    drift_yaw = np.radians(cfg.drift_deg_per_s) * walk[:, 3] * np.sqrt(times[-1] + 1.0 / fps)
    D = np.tile(np.eye(4), (n, 1, 1))
    D[:, :3, :3] = Rotation.from_euler("y", drift_yaw[:, None]).as_matrix()
    D[:, :3, 3] = drift_t
    offset = np.eye(4)
    offset[:3, :3] = Rotation.from_euler("y", rng.uniform(-180, 180), degrees=True).as_matrix()
    offset[:3, 3] = rng.uniform(-2, 2, size=3) * np.array([1.0, 0.1, 1.0])
    tracked = offset @ D @ delayed
    truth = {"latency_s": float(cfg.latency_s), "T_tracker_from_world": offset.tolist(),
             "drift": {"translation_m": drift_t.tolist(), "yaw_rad": drift_yaw.tolist()},
             "model": "T_tracker(t) = T_tracker_from_world @ D(t) @ T_world_from_hmd(t - latency_s)"}
    return tracked, truth
