"""egopose's preview: per previewed frame both down-facing views with the ground-truth keypoints
(green) and the estimates (red)."""

from __future__ import annotations

import cv2
import numpy as np

from egorelight_cli.geometry.cameras import project
from egorelight_cli.io.capture import Capture
from egorelight_cli.nn.egopose_net import RigGeometry
from egorelight_cli.render import sheets
from egorelight_cli.stages.egopose import DOWN_ROLES, EgoFrames, Prediction
from egorelight_cli.structures.keypoints import Keypoints, keypoint_edges


def _draw(image: np.ndarray, pixels: np.ndarray, colour, scale: int) -> None:
    """Bones and dots of (J,2) original-image pixels on an image upscaled by ``scale``."""
    pixels = (np.asarray(pixels, np.float64) + 0.5) * scale - 0.5
    for a, b in keypoint_edges():
        if np.isfinite(pixels[[a, b]]).all():
            cv2.line(image, tuple(int(round(c)) for c in pixels[a]), tuple(int(round(c)) for c in pixels[b]),
                     colour, 1, cv2.LINE_AA)
    for p in pixels:
        if np.isfinite(p).all():
            cv2.circle(image, (int(round(p[0])), int(round(p[1]))), 2, colour, -1, cv2.LINE_AA)


def preview_rows(usable: np.ndarray, count: int) -> np.ndarray:
    """Rows (positions among the output frames) the preview shows: ``count`` evenly spread usable
    frames (any frames when none is usable)."""
    candidates = np.nonzero(usable)[0] if usable.any() else np.arange(len(usable))
    return candidates[np.unique(np.linspace(0, len(candidates) - 1, max(min(count, len(candidates)), 1)).round()
                                .astype(int))]


def preview_image(capture: Capture, frames: EgoFrames, rig: RigGeometry, prediction: Prediction,
                  truth: Keypoints | None, rows: np.ndarray, tile: int = 256) -> list[np.ndarray]:
    """Preview rows (H,W,3) uint8, one per row of ``frames`` in ``rows``: both down-facing views
    with ground-truth keypoints in green and predictions in red."""
    info = capture.sequence(frames.sequence)
    T_cam_from_hmd = rig.T_cam_from_hmd.double().numpy()
    scale = max(1, tile // rig.width)
    out_rows = []
    for row in rows:
        tiles = []
        T_hmd_from_world = np.linalg.inv(frames.T_world_from_hmd[row])
        sets = [(prediction.keypoints.xyz[row], (255, 40, 40))]
        if truth is not None and frames.frame_ids[row] in truth.frame_ids:
            sets.insert(0, (truth.xyz[np.searchsorted(truth.frame_ids, frames.frame_ids[row])], (40, 230, 40)))
        for v, role in enumerate(DOWN_ROLES):
            image = info.read_ego_image(role, int(frames.ego_ids[row]))
            image = np.ascontiguousarray(cv2.resize(image, (rig.width * scale, rig.height * scale),
                                                    interpolation=cv2.INTER_NEAREST))
            for xyz, colour in sets:
                cam = (np.einsum("ij,kj->ki", T_cam_from_hmd[v] @ T_hmd_from_world, np.c_[xyz, np.ones(len(xyz))]))[:, :3]
                pixels = project(cam, rig.K[v].double().numpy(), rig.dist[v].double().numpy(), "fisheye")
                _draw(image, np.asarray(pixels), colour, scale)
            tiles.append(sheets.label(image, f"{role} frame {int(frames.frame_ids[row])}"))
        out_rows.append(np.concatenate(tiles, axis=1))
    return out_rows
