"""Depth maps of calibrated cameras: rendering a mesh by ray casting, and unprojection to points.

Two per-pixel depth quantities are used, both in metres:

* ``range``: distance from the camera centre along the pixel's unit ray (well defined for every
  ray of a >180 degree fisheye; what the depth network predicts);
* ``z`` (depth): the coordinate along the optical axis, ``z = range * ray_z``, what the
  ``pointcloud`` artifact stores in its EXRs (channel ``Z``, 0 = no depth). For fisheye rays more
  than 90 degrees off-axis ``z`` is negative; rays within :data:`MIN_AXIS_COS` of 90 degrees
  cannot carry a ``z`` and get none.

The paper's unprojection ``z = (K Pi H)^-1 d`` is :func:`unproject_depth`: pixel -> unit ray
(``unproject_to_rays``, fisheye or pinhole) scaled to the depth, then ``T_world_from_cam``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, camera_rays_world, pixel_grid, transform_points, unproject_to_rays
from egorelight_cli.geometry.raycast import RayCaster

#: |cos| of the off-axis angle below which a ray carries no axial depth z (89.94 degrees).
MIN_AXIS_COS = 1e-3


@dataclass(frozen=True, eq=False)
class DepthRender:
    """A mesh rendered into one camera; all maps (H,W).

    Attributes:
        z: float32 depth along the optical axis, metres; 0 where nothing was hit.
        range: float32 distance along the pixel ray, metres; 0 where nothing was hit.
        hit: bool, the ray hit the mesh (and carries a z).
        front_facing: bool, the hit face's geometric normal points towards the camera.
    """

    z: np.ndarray
    range: np.ndarray
    hit: np.ndarray
    front_facing: np.ndarray


def camera_ray_map(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Unit rays (H,W,3) float64 in the camera frame through every pixel centre, and the (H,W)
    bool mask of pixels that have a ray (inside the lens' image circle)."""
    return unproject_to_rays(pixel_grid(camera.width, camera.height), camera.K, camera.dist, camera.model,
                             return_valid=True)


def render_depth(camera: Camera, caster: RayCaster, near: float = 0.0) -> DepthRender:
    """Ray-cast the caster's mesh into ``camera`` (its ``T_cam_from_world`` places it).

    Args:
        camera: pinhole or fisheye camera with its pose.
        caster: the mesh (world frame, metres).
        near: hits closer than this to the camera centre are ignored, metres.
    """
    origins, dirs_world, valid = camera_rays_world(camera)
    hits = caster.first_hit(origins, dirs_world, near=near)
    ray_z = dirs_world @ camera.T_world_from_cam[:3, 2]  # = rays_cam[..., 2]
    hit = hits.hit & valid & (np.abs(ray_z) >= MIN_AXIS_COS)
    distance = np.where(hit, hits.distance, 0.0)
    tri = caster.vertices[caster.faces[np.where(hit, hits.face_id, 0)]].astype(np.float64)
    normal = np.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
    front = hit & (np.sum(normal * dirs_world, axis=-1) < 0)
    return DepthRender(z=(distance * ray_z).astype(np.float32), range=distance.astype(np.float32), hit=hit,
                       front_facing=front)


def range_to_depth(range_map: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Axial depth z (H,W) float32 of a range map (H,W) with unit camera rays (H,W,3); 0 where the
    range is 0 or the ray is too close to 90 degrees off-axis."""
    ray_z = rays[..., 2]
    keep = (range_map > 0) & (np.abs(ray_z) >= MIN_AXIS_COS)
    return np.where(keep, range_map * ray_z, 0.0).astype(np.float32)


def depth_to_range(depth: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Range (H,W) float32 of an axial depth map (H,W) (0 = none) with unit camera rays (H,W,3)."""
    ray_z = rays[..., 2]
    keep = (depth != 0) & (np.abs(ray_z) >= MIN_AXIS_COS) & (depth * ray_z > 0)
    safe = np.where(keep, ray_z, 1.0)
    return np.where(keep, depth / safe, 0.0).astype(np.float32)


def unproject_depth(camera: Camera, depth: np.ndarray, T_world_from_cam: np.ndarray | None = None,
                    rays: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points of an axial depth map: ``z = (K Pi H)^-1 d`` of the paper.

    Args:
        camera: intrinsics (its pose is used unless ``T_world_from_cam`` is given).
        depth: (H,W) axial depth z, metres, 0 = none (signed: fisheye rays past 90 degrees).
        T_world_from_cam: (4,4) pose (``H @ inv(Pi)``); default ``camera.T_world_from_cam``;
            pass ``np.eye(4)`` for camera-frame points.
        rays: precomputed :func:`camera_ray_map` of ``camera`` (speed).

    Returns:
        points (H,W,3) float64 (zeros where invalid), valid (H,W) bool.
    """
    depth = np.asarray(depth)
    if depth.shape != (camera.height, camera.width):
        raise EgorelightError(f"depth map of camera {camera.name!r} has shape {depth.shape}, "
                              f"expected ({camera.height}, {camera.width})")
    if not np.isfinite(depth).all():
        raise EgorelightError(f"depth map of camera {camera.name!r} holds NaN or inf")
    ray_map, ray_valid = rays if rays is not None else camera_ray_map(camera)
    range_map = depth_to_range(depth, ray_map)
    valid = ray_valid & (range_map > 0)
    points = np.where(valid[..., None], ray_map * range_map[..., None].astype(np.float64), 0.0)
    T = camera.T_world_from_cam if T_world_from_cam is None else np.asarray(T_world_from_cam, np.float64)
    points = np.where(valid[..., None], transform_points(T, points), 0.0)
    return points, valid


def depth_edges(range_map: np.ndarray, valid: np.ndarray, relative_jump: float) -> np.ndarray:
    """(H,W) bool: valid pixels next to a depth discontinuity (a 4-neighbour whose range differs by
    more than ``relative_jump`` of the pixel's own, or an invalid neighbour). Dropping them removes
    the "flying pixels" a depth estimator produces at silhouettes."""
    r = np.where(valid, range_map, 0.0).astype(np.float64)
    padded = np.pad(r, 1, mode="constant")
    edge = np.zeros(r.shape, dtype=bool)
    H, W = r.shape
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        neighbour = padded[dy:dy + H, dx:dx + W]
        edge |= (neighbour <= 0) | (np.abs(neighbour - r) > relative_jump * r)
    return edge & valid
