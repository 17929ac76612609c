"""PNG previews of an ``egodepth`` run: per frame the ego images with predicted and true range,
and the fused point cloud over the true mesh coloured by its distance to it."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from egorelight_cli.stages.egodepth import EgoView

def colour_depth(range_map: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(H,W,3) uint8 turbo colours of a range map in [lo, hi]; black where there is none."""
    import cv2

    t = np.clip((range_map - lo) / max(hi - lo, 1e-6), 0, 1)
    colour = cv2.applyColorMap((255 - t * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    return np.where(range_map[..., None] > 0, colour, 0).astype(np.uint8)


def depth_preview_row(views: Sequence[EgoView], ranges: dict, truth: dict | None, scale: int) -> np.ndarray:
    """One row: per view the ego image, predicted range and (when known) true range."""
    import cv2

    tiles = []
    values = np.concatenate([r[r > 0] for r in ranges.values()] + [np.array([0.2, 0.8])])
    lo, hi = np.percentile(values, 2), np.percentile(values, 98)
    for v in views:
        tiles += [v.image, colour_depth(ranges[v.role], lo, hi)]
        if truth is not None:
            r, mask = truth[v.role]
            tiles.append(colour_depth(np.where(mask, r, 0), lo, hi))
    row = np.concatenate([np.pad(t, ((1, 1), (1, 1), (0, 0)), constant_values=255) for t in tiles], axis=1)
    return cv2.resize(row, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)


def pointcloud_preview(points: np.ndarray, normals: np.ndarray, distance: np.ndarray | None, mesh: tuple | None,
                       width: int, height: int) -> np.ndarray:
    """The fused points drawn over the true mesh (grey), coloured by their distance to it
    (green 0 -> red >= 3 cm; blue without ground truth), seen against the points' mean normal
    (the side of the body the ego cameras see)."""
    import cv2

    from egorelight_cli.geometry.cameras import project_world
    from egorelight_cli.render.preview import framing_camera
    from egorelight_cli.render.raster import rasterize

    anchor = mesh[0] if mesh is not None else points
    forward = -normals.mean(axis=0) if len(normals) else np.array([0.0, 0.0, -1.0])
    forward[1] = np.clip(forward[1], -0.5, 0.5)  # keep the view off the vertical (framing_camera's up is +y)
    if np.linalg.norm(forward) < 1e-6:
        forward = np.array([0.0, 0.0, -1.0])
    forward /= np.linalg.norm(forward)
    camera = framing_camera(np.asarray(anchor, np.float64), forward, width, height, "preview")
    image = np.full((height, width, 3), 255, np.uint8)
    if mesh is not None:
        raster = rasterize(mesh[0], mesh[1], camera)
        image[raster.mask] = (90 + 120 * np.abs(raster.normal[raster.mask] @ camera.T_cam_from_world[2, :3]))[:, None]
    pixels = project_world(camera, points)
    keep = np.isfinite(pixels).all(axis=1)
    if distance is not None:
        t = np.clip(distance / 0.03, 0, 1)
        colours = np.stack([255 * t, 255 * (1 - t), np.zeros_like(t)], axis=1)
    else:
        colours = np.tile([40.0, 90.0, 255.0], (len(points), 1))
    depth = (camera.T_cam_from_world[:3, :3] @ np.asarray(points, np.float64).T)[2] if len(points) else np.zeros(0)
    order = np.argsort(-depth)
    for (u, v), c in zip(pixels[order][keep[order]], colours[order][keep[order]]):
        cv2.circle(image, (int(round(u)), int(round(v))), 1, tuple(int(x) for x in c), -1)
    return image
