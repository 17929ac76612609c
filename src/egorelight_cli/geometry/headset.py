"""Where the headset is in a studio image: a box in the HMD frame, posed per frame and projected.

The relightable avatar is trained with the headset off and has no headset; the paper scores its
relit renders with "the head region excluded". The head of the *render* is easy to exclude (the
avatar's own head faces), but a worn headset sticks out in front of the face by several
centimetres, so in the captured test images part of it lies outside the rendered head: pixels the
avatar never draws and the scores would count as its error (on the cpu demo, ~2 % of the scored
pixels carrying ~40 % of the squared error).

:func:`headset_box` bounds the headset from what every capture's rig description and calibration
give, never from ground truth: the HMD markers' corners (``rig/hmd.json``) and the ego cameras'
centres (the hand-eye ``T_cam_from_hmd``), as an axis-aligned box in the HMD frame (whose axes
are the visor's) grown by a margin. :func:`headset_mask` poses that box with the frame's
``T_world_from_hmd`` and fills its projection's convex hull in a camera image; with the box's
nearest depth, a scorer keeps what a render draws in front of the headset (a hand before the
visor, the back of the head seen from behind).
"""

from __future__ import annotations

import itertools

import cv2
import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, project, transform_points, world_to_camera

#: the box's growth on every side (metres): the markers' white quiet zone, the visor's edges
#: beyond the outermost markers and the head pose's error
HEADSET_MARGIN_M = 0.015
#: samples per box edge: under lens distortion an edge projects to a curve, not a segment
EDGE_SAMPLES = 8


def headset_box(marker_corners_hmd: np.ndarray, camera_centres_hmd: np.ndarray,
                margin_m: float = HEADSET_MARGIN_M) -> np.ndarray:
    """(2,3) the minimum and maximum corners (HMD frame, metres) of the box around the markers'
    corners ``(...,3)`` and the ego cameras' centres ``(...,3)``, grown by ``margin_m``."""
    points = np.concatenate([np.asarray(marker_corners_hmd, np.float64).reshape(-1, 3),
                             np.asarray(camera_centres_hmd, np.float64).reshape(-1, 3)])
    if len(points) < 2 or not np.isfinite(points).all():
        raise EgorelightError("the headset box needs finite marker corners or camera centres")
    return np.stack([points.min(axis=0) - margin_m, points.max(axis=0) + margin_m])


def box_surface_points(box: np.ndarray, samples: int = EDGE_SAMPLES) -> np.ndarray:
    """(12 * samples, 3) points along the 12 edges of the axis-aligned box ``box`` (2,3)."""
    corners = np.array([[box[i, 0], box[j, 1], box[k, 2]] for i, j, k in itertools.product((0, 1), repeat=3)])
    edges = [(a, b) for a, b in itertools.combinations(range(8), 2)
             if np.count_nonzero(corners[a] != corners[b]) == 1]
    t = np.linspace(0.0, 1.0, samples)[:, None]
    return np.concatenate([corners[a] + t * (corners[b] - corners[a]) for a, b in edges])


def headset_mask(box: np.ndarray, T_world_from_hmd: np.ndarray, camera: Camera) -> tuple[np.ndarray, float]:
    """The pixels of ``camera`` inside the projection of the headset box ``box`` (2,3) posed by
    ``T_world_from_hmd`` (4,4): (H,W) bool (the convex hull of its projected edges; empty when fewer
    than three edge points project: in front of the camera and inside the lens model's valid range),
    and the nearest depth of those points (metres along the camera's z, inf when none project;
    anything drawn nearer is in front of the headset). The depth is z, as a pinhole render's
    depth is: the studio cameras this scores are pinhole."""
    points_world = transform_points(np.asarray(T_world_from_hmd, np.float64), box_surface_points(box))
    points_cam = np.asarray(world_to_camera(camera, points_world))
    pixels, valid = project(points_cam, camera.K, camera.dist, camera.model, return_valid=True)
    valid = np.asarray(valid)
    depth = points_cam[valid, 2]
    mask = np.zeros((camera.height, camera.width), np.uint8)
    pixels = np.asarray(pixels)[valid]
    if len(pixels) >= 3:
        hull = cv2.convexHull(np.round(pixels).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool), float(depth.min()) if len(depth) else float("inf")
