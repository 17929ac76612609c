"""An LDR panorama from posed HMD camera images, and the inpainting of what no camera saw.

The paper (Sec. "Affordable Egocentric HDR Environment Map Capture") samples ~20 frames of a
10-second in-place scan with the front-facing cameras, places them with a 3D reconstruction and
unprojects them into an axis-aligned equirect map ``E_o``, then inpaints its unobserved part to
``E_l``. Here the poses come from the calibration (metric head poses and hand-eye), so the
geometry is known and the map is built by *gathering*:

* every texel of the equirect map (:mod:`egorelight_cli.geometry.equirect`, row 0 = +Y) looks
  in its direction ``d``; each view projects ``d`` (a point at infinity: only the camera's
  rotation matters) or, with a finite ``proxy_radius_m``, the point ``centre + r d`` on a sphere
  around the wearer (parallax of a room) into its image with the camera model
  (:func:`~egorelight_cli.geometry.cameras.project`);
* the image is first area-averaged by the integer factor that brings its pixel footprint to
  about one texel (so a texel averages the pixels it covers instead of aliasing fine detail),
  then sampled bilinearly;
* views are averaged per texel with weights that fall towards the image border
  (``centre_weight``: ``(1 - x^2)(1 - y^2)`` in normalised image coordinates, x, y in [-1, 1];
  feathering hides the seams of exposure and vignetting differences);
* the coverage mask is the set of texels with total weight above ``min_weight``.

Images are linear radiance (the caller linearises the cameras' 8-bit sRGB; the per-camera
response -- exposure, colour cross-talk, white balance -- is unknown to the stages and stays in
the panorama: the colour model of the ``envmap`` stage absorbs it).

:func:`inpaint_equirect` fills the unobserved texels (OpenCV Telea per channel, or a push-pull
pyramid) on a map padded with its own wrap-around in longitude and its reflection over the
poles, so that the fill is continuous across the 0/360 degree seam.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, project
from egorelight_cli.geometry.equirect import check_envmap, equirect_directions
from egorelight_cli.runtime import single_torch_thread

INPAINT_METHODS = ("telea", "push_pull")


@dataclass(frozen=True)
class PanoramaView:
    """One linear image and the posed camera that took it.

    Attributes:
        image: (h,w,3) float32 linear radiance (h, w = the camera's height, width).
        camera: the camera, extrinsics ``T_cam_from_world`` in the panorama's world frame.
        valid: optional (h,w) bool mask of usable pixels (e.g. not saturated, not the body).
    """

    image: np.ndarray
    camera: Camera
    valid: np.ndarray | None = None


@dataclass(frozen=True)
class Panorama:
    """An equirect panorama and its observation weights.

    Attributes:
        radiance: (H,2H,3) float32 weighted mean radiance; 0 where unobserved.
        weight: (H,2H) float32 summed view weights (0 = no view saw the texel).
        coverage: (H,2H) bool, ``weight > min_weight``.
        views: (H,2H) int16 number of views that saw the texel.
    """

    radiance: np.ndarray
    weight: np.ndarray
    coverage: np.ndarray
    views: np.ndarray

    @property
    def coverage_fraction(self) -> float:
        """Solid-angle fraction of the sphere that was observed."""
        from egorelight_cli.geometry.equirect import equirect_solid_angles

        omega = equirect_solid_angles(*self.coverage.shape)
        return float((omega * self.coverage).sum() / omega.sum())


def _area_factor(camera: Camera, texel_rad: float) -> int:
    """Integer downsampling factor that makes one pixel span about one texel at the image centre."""
    focal = float(max(camera.K[0, 0], camera.K[1, 1]))
    pixel_rad = 1.0 / max(focal, 1e-9)
    return max(1, int(math.floor(texel_rad / pixel_rad)))


def _downsampled(image: np.ndarray, camera: Camera, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """(image area-averaged by ``factor``, intrinsics of the smaller image). Pixel centres are at
    integers (OpenCV), so ``u' = (u + 0.5) / factor - 0.5``."""
    if factor == 1:
        return image, camera.K
    h, w = image.shape[0] // factor, image.shape[1] // factor
    small = cv2.resize(np.ascontiguousarray(image[: h * factor, : w * factor]), (w, h), interpolation=cv2.INTER_AREA)
    K = np.array(camera.K, dtype=np.float64)
    K[0, 0] /= factor
    K[1, 1] /= factor
    K[0, 1] /= factor
    K[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / factor - 0.5
    return small.reshape(h, w, -1), K


def centre_weights(width: int, height: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Feathering weight ``(1 - x^2)(1 - y^2)`` of pixel coordinates (u, v) (any shape), with
    x, y the coordinates normalised to [-1, 1] over the image (0 outside)."""
    x = (np.asarray(u, np.float64) + 0.5) / width * 2.0 - 1.0
    y = (np.asarray(v, np.float64) + 0.5) / height * 2.0 - 1.0
    return np.clip(1.0 - x * x, 0.0, 1.0) * np.clip(1.0 - y * y, 0.0, 1.0)


def accumulate_panorama(views: Sequence[PanoramaView], height: int, centre_weight: bool = True,
                        proxy_radius_m: float | None = None, centre=None, min_weight: float = 1e-3) -> Panorama:
    """Gather posed linear images into an equirect panorama of ``height`` rows (see the module docstring).

    Args:
        views: the images and their posed cameras.
        height: rows H of the (H,2H) map.
        centre_weight: feather the views towards their borders (False: uniform weights).
        proxy_radius_m: None or inf: the scene is at infinity; else the radius (metres) of a
            sphere around ``centre`` the scene is painted on (a texel's direction is seen from
            that centre).
        centre: (3,) world point the map is centred on (needed with a finite proxy radius).
        min_weight: a texel counts as observed above this total weight (a view's weight is
            1 at its image centre).

    Returns:
        the :class:`Panorama`.
    """
    height = int(height)
    if height < 2:
        raise EgorelightError(f"panorama height must be at least 2, got {height}")
    if not views:
        raise EgorelightError("no views to build a panorama from")
    finite = proxy_radius_m is not None and math.isfinite(float(proxy_radius_m))
    if finite:
        if centre is None or float(proxy_radius_m) <= 0:
            raise EgorelightError("a finite panorama proxy radius needs a positive radius and a centre")
        centre = np.asarray(centre, dtype=np.float64).reshape(3)
    dirs = equirect_directions(height).reshape(-1, 3)  # (N,3)
    texel_rad = math.pi / height
    total = np.zeros((dirs.shape[0], 3))
    weight = np.zeros(dirs.shape[0])
    count = np.zeros(dirs.shape[0], np.int16)
    for view in views:
        camera = view.camera
        image = np.asarray(view.image, dtype=np.float32)
        if image.shape != (camera.height, camera.width, 3):
            raise EgorelightError(f"view image of {camera.name or 'a camera'} has shape {image.shape}, "
                                  f"expected ({camera.height}, {camera.width}, 3)")
        valid_px = np.ones(image.shape[:2], np.float32) if view.valid is None else np.asarray(view.valid, np.float32)
        factor = _area_factor(camera, texel_rad)
        stacked = np.concatenate([image * valid_px[..., None], valid_px[..., None]], axis=-1)
        small, K = _downsampled(stacked, camera, factor)
        R, t = camera.T_cam_from_world[:3, :3], camera.T_cam_from_world[:3, 3]
        points_cam = (dirs * float(proxy_radius_m) + centre) @ R.T + t if finite else dirs @ R.T
        with single_torch_thread():
            pixels, ok = project(points_cam, K, camera.dist, camera.model, return_valid=True)
        h, w = small.shape[:2]
        u, v = pixels[:, 0], pixels[:, 1]
        ok = ok & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
        if not ok.any():
            continue
        idx = np.flatnonzero(ok)
        map_x = np.ascontiguousarray(u[idx], dtype=np.float32).reshape(-1, 1)
        map_y = np.ascontiguousarray(v[idx], dtype=np.float32).reshape(-1, 1)
        sampled = cv2.remap(np.ascontiguousarray(small, dtype=np.float32), map_x, map_y, cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE).reshape(-1, 4)
        coverage = sampled[:, 3]  # fraction of usable pixels under the sample
        usable = coverage > 0.5
        idx, sampled, coverage = idx[usable], sampled[usable], coverage[usable]
        wts = centre_weights(w, h, u[idx], v[idx]) if centre_weight else np.ones(idx.size)
        wts = np.maximum(wts, 1e-6)
        total[idx] += wts[:, None] * sampled[:, :3] / coverage[:, None]
        weight[idx] += wts
        count[idx] += 1
    seen = weight > min_weight
    radiance = np.zeros_like(total)
    radiance[seen] = total[seen] / weight[seen, None]
    shape = (height, 2 * height)
    return Panorama(radiance=radiance.reshape(*shape, 3).astype(np.float32), weight=weight.reshape(shape).astype(np.float32),
                    coverage=seen.reshape(shape), views=count.reshape(shape))


# ------------------------------------------------------------------------------- inpainting
def pad_equirect(array: np.ndarray, pad_x: int, pad_y: int) -> np.ndarray:
    """Pad an equirect array (H,W[,C]) by its own wrap-around in longitude (``pad_x`` columns each
    side) and its reflection over the poles (``pad_y`` rows each side: the row above row 0 at
    column u is row 0 at column u + W/2)."""
    H, W = array.shape[:2]
    pad_y = min(int(pad_y), H)
    if pad_y:
        top = np.roll(array[:pad_y][::-1], W // 2, axis=1)
        bottom = np.roll(array[H - pad_y:][::-1], W // 2, axis=1)
        array = np.concatenate([top, array, bottom], axis=0)
    pad_x = min(int(pad_x), W)
    if pad_x:
        array = np.concatenate([array[:, W - pad_x:], array, array[:, :pad_x]], axis=1)
    return array


def _push_pull(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Fill unknown pixels of (H,W,C) ``values`` by a push-pull pyramid: weighted 2x2 averages down
    to a level where every pixel is known (at the coarsest, 1 pixel high or wide, the holes left
    take the mean of the known pixels), then each level's holes take the bilinear upsampling of the
    coarser filled level."""
    if known.all():
        return values
    weights = known.astype(np.float64)
    if not weights.any():
        raise EgorelightError("nothing to inpaint from: no texel was observed")
    H, W = values.shape[:2]
    if min(H, W) <= 1:  # the coarsest level: what is still unknown takes the mean of what is known
        mean = (values * weights[..., None]).sum(axis=(0, 1)) / weights.sum()
        return np.where(known[..., None], values, mean)
    h, w = (H + 1) // 2, (W + 1) // 2
    pv = np.pad(values * weights[..., None], ((0, 2 * h - H), (0, 2 * w - W), (0, 0)), mode="edge")
    pw = np.pad(weights, ((0, 2 * h - H), (0, 2 * w - W)), mode="edge")
    coarse_w = pw.reshape(h, 2, w, 2).sum(axis=(1, 3))
    coarse_v = pv.reshape(h, 2, w, 2, -1).sum(axis=(1, 3)) / np.maximum(coarse_w, 1e-12)[..., None]
    filled = _push_pull(coarse_v, coarse_w > 0)
    up = cv2.resize(np.ascontiguousarray(filled, dtype=np.float32), (2 * w, 2 * h), interpolation=cv2.INTER_LINEAR)
    up = up.reshape(2 * h, 2 * w, -1)[:H, :W]
    return np.where(known[..., None], values, up)


def inpaint_equirect(envmap: np.ndarray, observed: np.ndarray, method: str = "telea", radius_px: float = 3.0,
                     pad_fraction: float = 0.25) -> np.ndarray:
    """Fill the texels of an equirect map that ``observed`` marks False.

    Args:
        envmap: (H,2H,3) linear radiance (unobserved texels' values are ignored).
        observed: (H,2H) bool.
        method: ``telea`` (``cv2.inpaint`` with ``INPAINT_TELEA`` per channel, float32 scaled to
            [0, 255]) or
            ``push_pull`` (a smooth multi-resolution fill).
        radius_px: Telea's neighbourhood radius (texels).
        pad_fraction: wrap/pole padding as a fraction of H (columns: of W/2), so that the fill
            sees across the 0/360 degree seam and over the poles.

    Returns:
        (H,2H,3) float32: observed texels unchanged, the rest filled, non-negative.
    """
    envmap = check_envmap(envmap)
    observed = np.asarray(observed, dtype=bool)
    if observed.shape != envmap.shape[:2]:
        raise EgorelightError(f"coverage mask has shape {observed.shape}, the map {envmap.shape[:2]}")
    if method not in INPAINT_METHODS:
        raise EgorelightError(f"unknown inpainting method {method!r}; expected one of {', '.join(INPAINT_METHODS)}")
    if not observed.any():
        raise EgorelightError("nothing to inpaint from: no texel was observed")
    if observed.all():
        return envmap.astype(np.float32)
    H, W = observed.shape
    pad_y = int(round(pad_fraction * H))
    pad_x = int(round(pad_fraction * W / 2))
    values = pad_equirect(np.where(observed[..., None], envmap, 0.0).astype(np.float32), pad_x, pad_y)
    known = pad_equirect(observed, pad_x, pad_y)
    if method == "telea":
        # OpenCV's float Telea works in absolute units (values near 1 come back wrong), so each
        # channel is scaled to an 8-bit-like range [0, 255] first and back afterwards.
        holes = np.ascontiguousarray((~known).astype(np.uint8))
        scale = np.maximum(values.reshape(-1, values.shape[2])[known.reshape(-1)].max(axis=0), 1e-12) / 255.0
        filled = np.stack([cv2.inpaint(np.ascontiguousarray(values[..., c] / scale[c], dtype=np.float32), holes,
                                       float(radius_px), cv2.INPAINT_TELEA) * scale[c]
                           for c in range(values.shape[2])], axis=-1)
    else:
        filled = _push_pull(values.astype(np.float64), known)
    out = filled[pad_y: pad_y + H, pad_x: pad_x + W]
    out = np.where(observed[..., None], envmap, np.maximum(out, 0.0))
    return np.ascontiguousarray(out, dtype=np.float32)
