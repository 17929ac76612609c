"""Classical stereo on a calibrated fisheye pair: rectification to a common pinhole view, OpenCV
semi-global block matching (``cv2.StereoSGBM``), and the result mapped back to depth in each
fisheye camera. The baseline the egodepth stage compares its network with.

Rectification is done directly from the camera models (no ``cv2.fisheye.stereoRectify``, which
assumes lenses under 180 degrees): both cameras are rotated to a common frame whose x axis is
the baseline (left -> right) and whose z axis is the mean optical axis, and each fisheye image
is resampled into a pinhole image of ``fov_deg`` horizontal field of view. Fisheye pixels
outside that field (the far periphery of the >180 degree lenses) get no stereo depth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, invert_rigid, pixel_grid, project
from egorelight_cli.geometry.depth import camera_ray_map

#: Rectified rays closer than this (cosine) to 90 degrees off the rectified axis get no depth.
_MIN_RECT_COS = 0.05


@dataclass(frozen=True, eq=False)
class RectifiedPair:
    """A rectified stereo pair (left = reference, right at +x along the baseline).

    Attributes:
        R_rect_from_cam: {"left": (3,3), "right": (3,3)} rotations camera -> rectified frame.
        K: (3,3) pinhole intrinsics of both rectified images.
        width, height: rectified image size.
        baseline_m: distance between the camera centres.
        maps: {"left": (H,W,2), "right": (H,W,2)} float32 fisheye pixel of each rectified pixel
            (``cv2.remap`` maps; -1 where the ray is outside the lens).
    """

    R_rect_from_cam: dict
    K: np.ndarray
    width: int
    height: int
    baseline_m: float
    maps: dict


def rectify_pair(left: Camera, right: Camera, T_right_from_left: np.ndarray, width: int, height: int,
                 fov_deg: float, pitch_deg: float = 0.0) -> RectifiedPair:
    """Rectification of a fisheye (or pinhole) pair with known relative pose ``T_right_from_left``.

    ``pitch_deg`` turns the rectified view about the baseline, towards the image bottom for
    positive values (where a down-facing headset camera sees the body); any turn about the
    baseline keeps the pair rectified.
    """
    if not 10.0 <= fov_deg < 175.0:
        raise EgorelightError(f"rectified field of view must be in [10, 175) degrees, got {fov_deg}")
    T_left_from_right = invert_rigid(T_right_from_left)
    baseline = T_left_from_right[:3, 3]
    B = float(np.linalg.norm(baseline))
    if B < 1e-6:
        raise EgorelightError("stereo cameras share one centre (no baseline)")
    x = baseline / B
    z = np.array([0.0, 0.0, 1.0]) + T_left_from_right[:3, 2]
    z = z - (z @ x) * x
    if np.linalg.norm(z) < 1e-6:
        raise EgorelightError("stereo cameras look along their baseline; cannot rectify")
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    pitch = math.radians(pitch_deg)
    z, y = math.cos(pitch) * z + math.sin(pitch) * y, math.cos(pitch) * y - math.sin(pitch) * z
    R_rect_from_left = np.stack([x, y, z])
    R_rect_from_right = R_rect_from_left @ T_left_from_right[:3, :3]
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    grid = pixel_grid(width, height)
    rays_rect = np.concatenate([(grid - K[:2, 2]) / f, np.ones((height, width, 1))], axis=-1)
    maps = {}
    for name, camera, R in (("left", left, R_rect_from_left), ("right", right, R_rect_from_right)):
        rays_cam = rays_rect @ R  # R^T applied to each ray
        pixels = project(rays_cam, camera.K, camera.dist, camera.model)
        maps[name] = np.nan_to_num(pixels, nan=-1.0).astype(np.float32)
    return RectifiedPair({"left": R_rect_from_left, "right": R_rect_from_right}, K, width, height, B, maps)


def _gray(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def sgbm_matcher(num_disparities: int, block_size: int) -> "cv2.StereoSGBM":
    """OpenCV SGBM with the usual P1/P2 smoothness penalties for ``block_size``."""
    num = max(16, int(math.ceil(num_disparities / 16)) * 16)
    b = int(block_size) | 1
    return cv2.StereoSGBM_create(minDisparity=0, numDisparities=num, blockSize=b, P1=8 * b * b, P2=32 * b * b,
                                 disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=50, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def stereo_ranges(pair: RectifiedPair, cameras: dict, images: dict, min_depth_m: float = 0.1,
                  block_size: int = 5) -> dict:
    """SGBM depth of a rectified pair, returned as a range map in each fisheye camera.

    Args:
        pair: :func:`rectify_pair` of ``cameras["left"]`` and ``cameras["right"]``.
        cameras: {"left": Camera, "right": Camera} (intrinsics).
        images: {"left": (H,W,3) uint8, "right": (H,W,3) uint8} fisheye images.
        min_depth_m: nearest depth to search (sets the disparity range).
        block_size: SGBM block size (odd).

    Returns:
        {"left": (H,W) float32, "right": (H,W) float32} distance along each fisheye pixel's ray,
        metres, 0 = no stereo depth.
    """
    f = float(pair.K[0, 0])
    fB = f * pair.baseline_m
    matcher = sgbm_matcher(fB / min_depth_m, block_size)
    rect = {k: cv2.remap(_gray(images[k]), pair.maps[k][..., 0], pair.maps[k][..., 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0) for k in ("left", "right")}
    disparity = {
        "left": matcher.compute(rect["left"], rect["right"]).astype(np.float32) / 16.0,
        # right-reference disparity: match the mirrored pair (right becomes the left image)
        "right": matcher.compute(rect["right"][:, ::-1].copy(), rect["left"][:, ::-1].copy())[:, ::-1]
        .astype(np.float32) / 16.0,
    }
    out = {}
    for key in ("left", "right"):
        d = disparity[key]
        z_rect = np.where(d > 0.5, fB / np.maximum(d, 0.5), 0.0).astype(np.float32)
        out[key] = _rect_to_fisheye_range(z_rect, pair, key, cameras[key])
    return out


def _rect_to_fisheye_range(z_rect: np.ndarray, pair: RectifiedPair, key: str, camera: Camera) -> np.ndarray:
    """Sample a rectified z map (nearest) at every fisheye pixel's ray; range along that ray."""
    rays, ray_valid = camera_ray_map(camera)
    r = rays @ pair.R_rect_from_cam[key].T  # (H,W,3) in the rectified frame
    ahead = ray_valid & (r[..., 2] > _MIN_RECT_COS)
    safe_z = np.where(ahead, r[..., 2], 1.0)
    u = pair.K[0, 0] * r[..., 0] / safe_z + pair.K[0, 2]
    v = pair.K[1, 1] * r[..., 1] / safe_z + pair.K[1, 2]
    u = np.where(ahead, u, -1).astype(np.float32)
    v = np.where(ahead, v, -1).astype(np.float32)
    z = cv2.remap(z_rect, u, v, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return np.where(ahead & (z > 0), z / safe_z, 0.0).astype(np.float32)
