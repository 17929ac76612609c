"""Equirectangular (latitude-longitude) environment maps: the one owner of the mapping.

Convention (DESIGN.md Sec. 4), for a map of ``height`` H rows and ``width`` W = 2 H columns:

* row 0 is straight up (+Y); the polar angle from +Y of continuous row coordinate ``y`` is
  ``theta = pi * y / H``, so the centre of row ``i`` is at ``y = i + 0.5``;
* column ``u`` maps to azimuth ``phi = 2 pi (u + 0.5) / W - pi``, measured from -Z towards +X;
  in continuous column coordinates ``x``, ``phi = 2 pi x / W - pi`` and the centre of column
  ``u`` is at ``x = u + 0.5`` (the map's left edge ``x = 0`` is azimuth -pi, i.e. +Z, the
  centre column is -Z, three quarters across is +X);
* the direction of ``(theta, phi)`` is ``(sin(theta) sin(phi), cos(theta), -sin(theta) cos(phi))``
  (world frame: metres, right-handed, +Y up).

Continuous *equirect coordinates* ``(x, y)`` (column, row) therefore put pixel centres at
``+0.5`` offsets -- unlike camera pixels (``geometry/cameras.py``), whose centres are at
integers. To sample with ``cv2.remap`` subtract 0.5; :func:`sample_equirect` does it for you.

Maps are (H,W,C) arrays of linear radiance (C = 3 for RGB). Nothing else in the project
re-derives this mapping: use these helpers.
"""

from __future__ import annotations

import math

import numpy as np

from egorelight_cli.errors import EgorelightError


def _check_size(height: int, width: int | None) -> tuple[int, int]:
    """(H, W) with W defaulting to 2 H; both positive."""
    height = int(height)
    width = 2 * height if width is None else int(width)
    if height <= 0 or width <= 0:
        raise EgorelightError(f"equirect size must be positive, got {height}x{width}")
    return height, width


def check_envmap(envmap: np.ndarray, name: str = "environment map") -> np.ndarray:
    """Validate an (H,W,C) map with W = 2 H and return it as a float array (no copy if already float)."""
    envmap = np.asarray(envmap)
    if envmap.ndim != 3 or envmap.shape[1] != 2 * envmap.shape[0] or envmap.shape[0] == 0:
        raise EgorelightError(f"{name} must be (H, 2H, C), got shape {envmap.shape}")
    if not np.issubdtype(envmap.dtype, np.floating):
        envmap = envmap.astype(np.float32)
    return envmap


def angles_to_directions(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit directions (...,3) of polar angles ``theta`` (from +Y) and azimuths ``phi`` (from -Z towards +X)."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    sin_theta = np.sin(theta)
    return np.stack(np.broadcast_arrays(sin_theta * np.sin(phi), np.cos(theta), -sin_theta * np.cos(phi)), axis=-1)


def directions_to_angles(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Polar angle theta in [0, pi] from +Y and azimuth phi in (-pi, pi] of directions (...,3) (any length)."""
    dirs = np.asarray(dirs, dtype=np.float64)
    norm = np.linalg.norm(dirs, axis=-1)
    if not np.all(norm > 0):
        raise EgorelightError("directions must be non-zero")
    theta = np.arccos(np.clip(dirs[..., 1] / norm, -1.0, 1.0))
    phi = np.arctan2(dirs[..., 0], -dirs[..., 2])
    return theta, phi


def equirect_directions(height: int, width: int | None = None) -> np.ndarray:
    """(H,W,3) float64 unit world directions of the pixel centres of an equirect map (W defaults to 2 H)."""
    height, width = _check_size(height, width)
    theta = math.pi * (np.arange(height) + 0.5) / height
    phi = 2.0 * math.pi * (np.arange(width) + 0.5) / width - math.pi
    return angles_to_directions(theta[:, None], phi[None, :])


def directions_to_equirect(dirs: np.ndarray, height: int = 1, width: int | None = None) -> np.ndarray:
    """Continuous equirect coordinates (...,2) ``(x, y) = (column, row)`` of directions (...,3).

    ``x = W (phi + pi) / (2 pi)`` in [0, W], ``y = H theta / pi`` in [0, H]; pixel centres are
    at ``+0.5`` (see the module docstring). With the default ``height=1`` (W = 2) the
    coordinates are in units of the map height, resolution-free.
    """
    height, width = _check_size(height, width)
    theta, phi = directions_to_angles(dirs)
    x = width * (phi + math.pi) / (2.0 * math.pi)
    y = height * theta / math.pi
    return np.stack([x, y], axis=-1)


def equirect_solid_angles(height: int, width: int | None = None) -> np.ndarray:
    """(H,W) float64 exact solid angle (sr) of each pixel: ``(2 pi / W) (cos theta_top - cos theta_bottom)``; sums to 4 pi."""
    height, width = _check_size(height, width)
    edges = np.cos(math.pi * np.arange(height + 1) / height)
    per_row = (2.0 * math.pi / width) * (edges[:-1] - edges[1:])
    return np.repeat(per_row[:, None], width, axis=1)


def equirect_bilinear_weights(dirs: np.ndarray, height: int, width: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Flat texel indices (...,4) int64 and weights (...,4) of the bilinear lookup in directions (...,3).

    Columns wrap around in azimuth; rows clamp at the poles. ``sum(weights * map.reshape(-1, C)[indices])``
    is :func:`sample_equirect`.
    """
    height, width = _check_size(height, width)
    coords = directions_to_equirect(dirs, height, width)
    x = coords[..., 0] - 0.5
    y = np.clip(coords[..., 1] - 0.5, 0.0, height - 1.0)
    x0 = np.floor(x)
    y0 = np.minimum(np.floor(y), height - 2) if height > 1 else np.zeros_like(y)
    fx = x - x0
    fy = y - y0 if height > 1 else np.zeros_like(y)
    c0 = np.mod(x0, width).astype(np.int64)
    c1 = np.mod(c0 + 1, width)
    r0 = y0.astype(np.int64)
    r1 = np.minimum(r0 + 1, height - 1)
    indices = np.stack([r0 * width + c0, r0 * width + c1, r1 * width + c0, r1 * width + c1], axis=-1)
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=-1)
    return indices, weights


def sample_equirect(envmap: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an equirect map (H,W,C) in directions (...,3) -> (...,C) float32.

    Columns wrap around in azimuth; rows clamp at the poles.
    """
    envmap = check_envmap(envmap)
    height, width = envmap.shape[:2]
    indices, weights = equirect_bilinear_weights(dirs, height, width)
    texels = envmap.reshape(height * width, -1)[indices]  # (...,4,C)
    return np.einsum("...k,...kc->...c", weights, texels).astype(np.float32)


def yaw_rotation(yaw_deg: float) -> np.ndarray:
    """(3,3) right-handed rotation about +Y by ``yaw_deg``: maps azimuth phi to phi - yaw (-Z turns towards -X)."""
    a = math.radians(float(yaw_deg))
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotate_envmap(envmap: np.ndarray, yaw_deg: float) -> np.ndarray:
    """Rotate an environment about +Y by ``yaw_deg`` degrees (right-handed rotation :func:`yaw_rotation`).

    Sign: content seen in direction ``d`` before is seen in direction ``R_y(yaw) d`` after, i.e.
    a feature at azimuth ``phi`` moves to ``phi - yaw`` (towards smaller column indices; a sun
    in -Z at yaw 0 is in -X at yaw 90). Formally ``E'(d) = E(R_y(yaw)^T d)``. Whole-column
    shifts are exact; fractional shifts interpolate linearly in azimuth.

    Returns:
        (H,W,C) rotated map, same dtype.
    """
    envmap = check_envmap(envmap)
    width = envmap.shape[1]
    shift = (float(yaw_deg) / 360.0 * width) % width  # E'[:, j] = E[:, j + shift]
    whole = math.floor(shift)
    frac = shift - whole
    rolled = np.roll(envmap, -whole, axis=1)
    if frac < 1e-9:
        return rolled.copy()
    return ((1.0 - frac) * rolled + frac * np.roll(rolled, -1, axis=1)).astype(envmap.dtype)
