"""Camera models: pinhole (radial-tangential) and OpenCV fisheye.

Conventions (DESIGN.md Sec. 4):

* metres; OpenCV camera frame: x right, y down, z forward;
* extrinsics are world->camera 4x4 matrices, ``T_cam_from_world``;
* pixel coordinates are OpenCV's: ``(u, v) = (column, row)`` and the *centre* of pixel
  ``(row i, column j)`` is at ``(u, v) = (j, i)`` (integer coordinates are pixel centres), so
  :func:`project` agrees with ``cv2.projectPoints`` and images sampled with ``cv2.remap``.

Models:

* ``pinhole``: ``K`` (3,3) and ``dist = (k1, k2, p1, p2, k3)`` (shorter vectors are zero-padded),
  exactly ``cv2.projectPoints``;
* ``fisheye``: ``K`` (3,3) and ``dist = (k1, k2, k3, k4)``, exactly ``cv2.fisheye.projectPoints``
  for points in front of the camera, extended past 90 degrees off-axis by measuring the
  angle ``theta = atan2(sqrt(x^2 + y^2), z)`` so that 180+ degree lenses work.

``K[0, 1]`` (skew) is applied as an affine term, ``u = K00 x + K01 y + K02``; it is zero for
every camera the project writes.

:func:`project` and :func:`unproject_to_rays` take numpy arrays or torch tensors and return the
same kind. The math is one torch implementation: numpy inputs run it in float64 without
gradients; torch inputs keep their dtype (float32 or float64) and device and are
differentiable with respect to points, pixels, ``K`` and ``dist``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry import rotations
from egorelight_cli.geometry.rotations import invert_rigid

CAMERA_MODELS = ("pinhole", "fisheye")
_DIST_SIZES = {"pinhole": 5, "fisheye": 4}

# Newton iterations for inverse distortion; convergence is quadratic, so this is generous.
_MAX_NEWTON_ITERATIONS = 50
# Samples of the distortion curve used to find where it stops being monotonic.
_MONOTONIC_SAMPLES = 4096
# Largest undistorted pinhole radius (tan of the off-axis angle) considered: ~89.4 degrees.
_PINHOLE_MAX_RADIUS = 100.0


# --------------------------------------------------------------------------------------------
# Camera record
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera.

    Attributes:
        model: ``"pinhole"`` or ``"fisheye"``.
        K: (3,3) float64 intrinsics, pixels.
        dist: (n,) float64 distortion (pinhole: k1 k2 p1 p2 k3; fisheye: k1..k4).
        width, height: image size in pixels.
        T_cam_from_world: (4,4) float64 world->camera rigid transform, metres.
        name: camera name.
    """

    model: str
    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    T_cam_from_world: np.ndarray
    name: str = ""

    def __post_init__(self) -> None:
        check_model(self.model)
        try:  # private read-only copies, so a Camera never changes under its users
            K = np.array(self.K, dtype=np.float64)
            dist = np.array(self.dist, dtype=np.float64).reshape(-1)
            T = np.array(self.T_cam_from_world, dtype=np.float64)
        except (TypeError, ValueError) as error:
            raise EgorelightError(
                f"camera {self.name!r}: K, dist and T_cam_from_world must be numeric arrays"
            ) from error
        if K.shape != (3, 3):
            raise EgorelightError(f"camera {self.name!r}: K must be 3x3, got {K.shape}")
        if T.shape != (4, 4):
            raise EgorelightError(f"camera {self.name!r}: T_cam_from_world must be 4x4, got {T.shape}")
        if dist.size > _DIST_SIZES[self.model]:
            raise EgorelightError(
                f"camera {self.name!r}: {self.model} takes at most {_DIST_SIZES[self.model]} "
                f"distortion coefficients, got {dist.size}"
            )
        if not (np.isfinite(K).all() and np.isfinite(dist).all() and np.isfinite(T).all()):
            raise EgorelightError(f"camera {self.name!r}: non-finite intrinsics or extrinsics")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise EgorelightError(f"camera {self.name!r}: image size must be positive")
        for array in (K, dist, T):
            array.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "T_cam_from_world", T)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def T_world_from_cam(self) -> np.ndarray:
        """(4,4) camera->world transform."""
        return invert_rigid(self.T_cam_from_world)

    @property
    def centre_world(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, metres."""
        return self.T_world_from_cam[:3, 3]

    @classmethod
    def from_dict(cls, entry: Mapping[str, Any], T_cam_from_world=None) -> "Camera":
        """Build from one ``rig/studio_cameras.json`` entry (keys as in :meth:`to_dict`).

        ``T_cam_from_world`` (4,4), when given, is used instead of the entry's own; this reads
        ``rig/hmd.json`` ego cameras, whose pose comes from calibration and head tracking.
        """
        missing = [k for k in ("model", "K", "width", "height") if k not in entry]
        if T_cam_from_world is None and "T_cam_from_world" not in entry:
            missing.append("T_cam_from_world")
        if missing:
            raise EgorelightError(f"camera entry {entry.get('name', '?')!r} lacks {', '.join(missing)}")
        if T_cam_from_world is None:
            T_cam_from_world = entry["T_cam_from_world"]
        return cls(
            model=str(entry["model"]),
            K=entry["K"],
            dist=entry.get("dist", []),
            width=int(entry["width"]),
            height=int(entry["height"]),
            T_cam_from_world=T_cam_from_world,
            name=str(entry.get("name", "")),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict: name, model, K, dist, T_cam_from_world, width, height."""
        return {
            "name": self.name,
            "model": self.model,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "T_cam_from_world": self.T_cam_from_world.tolist(),
            "width": self.width,
            "height": self.height,
        }


def check_model(model: str) -> None:
    """Raise :class:`EgorelightError` unless ``model`` is a known camera model."""
    if model not in CAMERA_MODELS:
        raise EgorelightError(f"unknown camera model {model!r}; expected one of {', '.join(CAMERA_MODELS)}")


# --------------------------------------------------------------------------------------------
# Placement
# --------------------------------------------------------------------------------------------


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """``T_cam_from_world`` (4,4) of an OpenCV camera at ``eye`` looking at ``target``.

    The camera's z axis points at the target, its y axis points down (away from ``up``) and its
    x axis to the image right. ``up`` must not be parallel to the viewing direction.
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    norm = np.linalg.norm(x)
    if norm < 1e-9:
        raise EgorelightError("look_at: the up vector is parallel to the viewing direction")
    x /= norm
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])
    T[:3, 3] = -T[:3, :3] @ eye
    return T


def transform_points(T, points):
    """Apply homogeneous transforms (...,4,4) to points (...,3); numpy or torch, broadcasting.

    ``T`` broadcasts against the points' leading dims: a single (4,4) applies to all points,
    a (B,4,4) to points (B,N,3) needs ``T[:, None]``.
    """
    if isinstance(points, torch.Tensor) or isinstance(T, torch.Tensor):
        points_t = torch.as_tensor(points)
        return rotations.transform_points(torch.as_tensor(T, dtype=points_t.dtype, device=points_t.device), points_t)
    T = np.asarray(T)
    points = np.asarray(points)
    return np.einsum("...ij,...j->...i", T[..., :3, :3], points) + T[..., :3, 3]


def world_to_camera(camera_or_T, points_world):
    """Points (...,3) world -> camera frame; takes a :class:`Camera` or a (4,4) ``T_cam_from_world``."""
    T = camera_or_T.T_cam_from_world if isinstance(camera_or_T, Camera) else camera_or_T
    return transform_points(T, points_world)


# --------------------------------------------------------------------------------------------
# numpy <-> torch dispatch
# --------------------------------------------------------------------------------------------


def _as_torch(x, like: torch.Tensor | None = None) -> torch.Tensor:
    """A tensor for ``x``: float64 for numpy input, or ``like``'s dtype/device."""
    if isinstance(x, torch.Tensor):
        if like is not None:
            return x.to(dtype=like.dtype, device=like.device)
        return x if x.is_floating_point() else x.to(torch.float64)
    array = np.asarray(x, dtype=np.float64)
    if not array.flags.writeable:  # torch cannot wrap read-only memory
        array = array.copy()
    tensor = torch.from_numpy(array)
    return tensor if like is None else tensor.to(dtype=like.dtype, device=like.device)


def _any_torch(*values) -> bool:
    """True when any input is a torch tensor (the result is then a tensor too)."""
    return any(isinstance(v, torch.Tensor) for v in values)


def _result_numpy_dtype(*arrays) -> np.dtype:
    """Floating dtype to return for numpy inputs: float32 only if every input is float32."""
    dtypes = [np.asarray(a).dtype for a in arrays]
    return np.dtype(np.float32) if all(d == np.float32 for d in dtypes) else np.dtype(np.float64)


def _pad_dist(dist: torch.Tensor, model: str) -> torch.Tensor:
    """Zero-pad distortion (...,n) to the model's full length (...,5) or (...,4)."""
    n = _DIST_SIZES[model]
    if dist.shape[-1] > n:
        raise EgorelightError(f"{model} takes at most {n} distortion coefficients, got {dist.shape[-1]}")
    if dist.shape[-1] == n:
        return dist
    pad = torch.zeros(dist.shape[:-1] + (n - dist.shape[-1],), dtype=dist.dtype, device=dist.device)
    return torch.cat([dist, pad], dim=-1)


def _prepare(first, K, dist, model: str):
    """Check the model and bring (first, K, dist) to tensors of one dtype/device."""
    check_model(model)
    first_t = _as_torch(first)
    K_t = _as_torch(K, like=first_t)
    if K_t.shape[-2:] != (3, 3):
        raise EgorelightError(f"K must be (...,3,3), got {tuple(K_t.shape)}")
    dist_t = _as_torch(dist if dist is not None else [], like=first_t)
    if dist_t.dim() == 0:
        raise EgorelightError("distortion coefficients must be a vector (n,) or (...,n)")
    dist_t = _pad_dist(dist_t, model)
    try:
        batch = np.broadcast_shapes(tuple(K_t.shape[:-2]), tuple(dist_t.shape[:-1]))  # not torch's: see make_transform
    except ValueError as error:
        raise EgorelightError(f"K {tuple(K_t.shape)} and dist {tuple(dist_t.shape)} batch shapes differ") from error
    return first_t, K_t.expand(*batch, 3, 3), dist_t.expand(*batch, dist_t.shape[-1])


# --------------------------------------------------------------------------------------------
# Distortion curves
# --------------------------------------------------------------------------------------------


def _fisheye_theta_d(theta: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Fisheye distorted angle theta_d = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8)."""
    t2 = theta * theta
    return theta * (1 + t2 * (d[..., 0:1] + t2 * (d[..., 1:2] + t2 * (d[..., 2:3] + t2 * d[..., 3:4]))))


def _fisheye_dtheta_d(theta: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """d theta_d / d theta = 1 + 3 k1 t^2 + 5 k2 t^4 + 7 k3 t^6 + 9 k4 t^8."""
    t2 = theta * theta
    return 1 + t2 * (3 * d[..., 0:1] + t2 * (5 * d[..., 1:2] + t2 * (7 * d[..., 2:3] + t2 * 9 * d[..., 3:4])))


def _pinhole_radial(r2: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Radial factor 1 + k1 r^2 + k2 r^4 + k3 r^6 (d (...,5) = k1 k2 p1 p2 k3)."""
    return 1 + r2 * (d[..., 0:1] + r2 * (d[..., 1:2] + r2 * d[..., 4:5]))


def _pinhole_radial_slope(r2: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """d radial / d r^2 = k1 + 2 k2 r^2 + 3 k3 r^4."""
    return d[..., 0:1] + r2 * (2 * d[..., 1:2] + r2 * 3 * d[..., 4:5])


def _first_non_increasing(values: torch.Tensor, grid: torch.Tensor, default: float) -> torch.Tensor:
    """Per batch row, the first grid value where ``values`` (...,S) <= 0, else ``default``."""
    bad = values <= 0
    any_bad = bad.any(dim=-1)
    first = torch.argmax(bad.to(torch.int8), dim=-1)
    limit = grid[first]
    return torch.where(any_bad, limit, torch.full_like(limit, default))


@torch.no_grad()
def fisheye_max_theta(dist) -> torch.Tensor | np.ndarray:
    """Largest off-axis angle (radians, <= pi) where the fisheye curve theta_d(theta) still increases.

    Beyond it, different directions map to the same pixel; projection marks such points invalid.
    """
    d = _pad_dist(_as_torch(dist), "fisheye")
    grid = torch.linspace(0.0, math.pi, _MONOTONIC_SAMPLES, dtype=d.dtype, device=d.device)
    slope = _fisheye_dtheta_d(grid, d)
    out = _first_non_increasing(slope, grid, math.pi)
    return out if isinstance(dist, torch.Tensor) else out.numpy()


@torch.no_grad()
def pinhole_max_radius(dist) -> torch.Tensor | np.ndarray:
    """Largest undistorted radius r = |(x/z, y/z)| where the radial curve r * radial(r) still increases."""
    d = _pad_dist(_as_torch(dist), "pinhole")
    r = torch.linspace(0.0, _PINHOLE_MAX_RADIUS, _MONOTONIC_SAMPLES, dtype=d.dtype, device=d.device)
    r2 = r * r
    slope = _pinhole_radial(r2, d) + 2 * r2 * _pinhole_radial_slope(r2, d)
    out = _first_non_increasing(slope, r, _PINHOLE_MAX_RADIUS)
    return out if isinstance(dist, torch.Tensor) else out.numpy()


# --------------------------------------------------------------------------------------------
# Projection
# --------------------------------------------------------------------------------------------


def _apply_K(xd: torch.Tensor, yd: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Normalised distorted coords (...,N) -> pixels (...,N,2)."""
    u = K[..., 0, 0:1] * xd + K[..., 0, 1:2] * yd + K[..., 0, 2:3]
    v = K[..., 1, 1:2] * yd + K[..., 1, 2:3]
    return torch.stack([u, v], dim=-1)


def _remove_K(pixels: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels (...,N,2) -> normalised distorted coords (xd, yd), each (...,N)."""
    yd = (pixels[..., 1] - K[..., 1, 2:3]) / K[..., 1, 1:2]
    xd = (pixels[..., 0] - K[..., 0, 2:3] - K[..., 0, 1:2] * yd) / K[..., 0, 0:1]
    return xd, yd


def _distort_pinhole(x: torch.Tensor, y: torch.Tensor, d: torch.Tensor):
    """Radial-tangential distortion of normalised coords (...,N); d (...,5)."""
    r2 = x * x + y * y
    radial = _pinhole_radial(r2, d)
    p1, p2 = d[..., 2:3], d[..., 3:4]
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def _project_pinhole(points: torch.Tensor, K: torch.Tensor, d: torch.Tensor):
    """Pinhole projection of (...,N,3) -> pixels (...,N,2), valid (...,N)."""
    X, Y, Z = points.unbind(-1)
    eps = torch.finfo(points.dtype).tiny ** 0.5
    in_front = Z > eps
    Z_safe = torch.where(in_front, Z, torch.ones_like(Z))
    x, y = X / Z_safe, Y / Z_safe
    r_max = pinhole_max_radius(d.detach())
    valid = in_front & (x.detach() ** 2 + y.detach() ** 2 < r_max.unsqueeze(-1) ** 2)
    xd, yd = _distort_pinhole(x, y, d)
    return _apply_K(xd, yd, K), valid


def _project_fisheye(points: torch.Tensor, K: torch.Tensor, d: torch.Tensor):
    """Fisheye projection of (...,N,3) -> pixels (...,N,2), valid (...,N)."""
    X, Y, Z = points.unbind(-1)
    rho2 = X * X + Y * Y
    eps2 = torch.finfo(points.dtype).eps ** 2
    off_axis = rho2 > eps2 * (Z * Z)
    rho = torch.sqrt(torch.where(off_axis, rho2, torch.ones_like(rho2)))
    theta = torch.atan2(rho, Z)
    theta_d = _fisheye_theta_d(theta, d)
    # Near the axis theta_d / rho -> 1 / Z (theta ~ rho / Z, theta_d ~ theta).
    Z_safe = torch.where(Z.abs() > 0, Z, torch.ones_like(Z))
    scale = torch.where(off_axis, theta_d / rho, 1.0 / Z_safe)
    theta_max = fisheye_max_theta(d.detach())
    on_axis_front = (~off_axis) & (Z > 0)
    valid = (off_axis & (theta.detach() < theta_max.unsqueeze(-1))) | on_axis_front
    return _apply_K(X * scale, Y * scale, K), valid


def project(points_cam, K, dist, model: str, return_valid: bool = False):
    """Project camera-frame points to pixels.

    Args:
        points_cam: (...,3) points in the camera frame, metres (numpy or torch).
        K: (3,3) intrinsics (or (B,3,3) with points (B,N,3)).
        dist: (n,) distortion coefficients (or (B,n)); see module docstring.
        model: ``"pinhole"`` or ``"fisheye"``.
        return_valid: also return a bool mask (...,) of points that project meaningfully:
            pinhole -- in front of the camera (z > 0) and inside the monotonic range of the
            distortion; fisheye -- off-axis angle below :func:`fisheye_max_theta`.

    Returns:
        pixels (...,2) ``(u, v)`` in OpenCV pixel coordinates, a tensor if any input is one,
        else numpy; invalid points are NaN. With ``return_valid``, ``(pixels, valid)``.
    """
    is_numpy = not _any_torch(points_cam, K, dist)
    points, K_t, d_t = _prepare(points_cam, K, dist, model)
    if points.shape[-1] != 3:
        raise EgorelightError(f"points must be (...,3), got {tuple(points.shape)}")
    batch_shape = points.shape[:-1]
    flat = _flatten_for_params(points, K_t)
    project_fn = _project_pinhole if model == "pinhole" else _project_fisheye
    pixels, valid = project_fn(flat, K_t, d_t)
    pixels = torch.where(valid.unsqueeze(-1), pixels, torch.full_like(pixels, float("nan")))
    pixels = pixels.reshape(*batch_shape, 2)
    valid = valid.reshape(batch_shape)
    if is_numpy:
        pixels = pixels.numpy().astype(_result_numpy_dtype(points_cam), copy=False)
        valid = valid.numpy()
    return (pixels, valid) if return_valid else pixels


def _flatten_for_params(values: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Reshape (...,c) values to (B...,N,c) matching K's batch dims (...,3,3).

    With a single K, everything becomes (N,c); with K (B,3,3), values (B,...,c) -> (B,N,c).
    """
    n_batch = K.dim() - 2
    if values.dim() - 1 < n_batch:
        raise EgorelightError("K has more batch dimensions than the points/pixels")
    lead = values.shape[:n_batch]
    return values.reshape(*lead, -1, values.shape[-1])


# --------------------------------------------------------------------------------------------
# Unprojection
# --------------------------------------------------------------------------------------------


def _newton_tolerance(dtype: torch.dtype) -> float:
    """Residual (normalised image units) below which Newton iterations stop."""
    return 1e-14 if dtype == torch.float64 else 1e-7


def _undistort_pinhole(xd: torch.Tensor, yd: torch.Tensor, d: torch.Tensor):
    """Invert radial-tangential distortion by Newton's method; d (...,5).

    Iterates without gradients, then takes one differentiable Newton step from the converged
    point, which gives exactly the implicit-function gradient.
    """

    def residual_and_jacobian(x, y):
        r2 = x * x + y * y
        radial = _pinhole_radial(r2, d)
        slope = _pinhole_radial_slope(r2, d)
        p1, p2 = d[..., 2:3], d[..., 3:4]
        fx, fy = _distort_pinhole(x, y, d)
        j11 = radial + 2 * x * x * slope + 2 * p1 * y + 6 * p2 * x
        j12 = 2 * x * y * slope + 2 * p1 * x + 2 * p2 * y
        j22 = radial + 2 * y * y * slope + 6 * p1 * y + 2 * p2 * x
        return fx - xd, fy - yd, j11, j12, j12, j22

    def newton_step(x, y):
        ex, ey, a, b, c, e = residual_and_jacobian(x, y)
        det = a * e - b * c
        det = torch.where(det.abs() > 1e-30, det, torch.full_like(det, 1e-30))
        return x - (e * ex - b * ey) / det, y - (a * ey - c * ex) / det, ex, ey

    tol = _newton_tolerance(xd.dtype)
    with torch.no_grad():
        x, y = xd.detach().clone(), yd.detach().clone()
        for _ in range(_MAX_NEWTON_ITERATIONS):
            x_new, y_new, ex, ey = newton_step(x, y)
            x_new = torch.nan_to_num(x_new, nan=0.0, posinf=0.0, neginf=0.0)
            y_new = torch.nan_to_num(y_new, nan=0.0, posinf=0.0, neginf=0.0)
            x, y = x_new, y_new
            if _max_abs(ex, ey) < tol:
                break
        ex, ey, *_ = residual_and_jacobian(x, y)
        converged = torch.maximum(ex.abs(), ey.abs()) < max(tol * 1e3, 1e-9)
    x, y, _, _ = newton_step(x, y)
    return x, y, converged


def _max_abs(a: torch.Tensor, b: torch.Tensor) -> float:
    """max(|a|, |b|) over all elements (0 when empty)."""
    if a.numel() == 0:
        return 0.0
    return float(torch.maximum(a.abs(), b.abs()).max())


def _fisheye_theta_from_theta_d(theta_d: torch.Tensor, d: torch.Tensor, theta_max: torch.Tensor):
    """Solve theta_d(theta) = theta_d for theta in [0, theta_max] by Newton's method; d (...,4)."""
    tol = _newton_tolerance(theta_d.dtype)
    with torch.no_grad():
        td = theta_d.detach()
        theta = torch.minimum(td.clone(), theta_max)
        for _ in range(_MAX_NEWTON_ITERATIONS):
            err = _fisheye_theta_d(theta, d) - td
            slope = _fisheye_dtheta_d(theta, d).clamp_min(1e-12)
            theta = torch.clamp(theta - err / slope, min=torch.zeros_like(theta), max=theta_max)
            if err.numel() == 0 or float(err.abs().max()) < tol:
                break
        err = _fisheye_theta_d(theta, d) - td
        converged = err.abs() < max(tol * 1e3, 1e-9)
    # One differentiable Newton step (implicit gradient).
    theta = theta - (_fisheye_theta_d(theta, d) - theta_d) / _fisheye_dtheta_d(theta, d)
    return theta, converged


def _unproject_pinhole(pixels: torch.Tensor, K: torch.Tensor, d: torch.Tensor):
    """Pixels (...,N,2) -> unit directions (...,N,3), valid (...,N)."""
    xd, yd = _remove_K(pixels, K)
    x, y, converged = _undistort_pinhole(xd, yd, d)
    r_max = pinhole_max_radius(d.detach()).unsqueeze(-1)
    valid = converged & (x.detach() ** 2 + y.detach() ** 2 < r_max**2)
    rays = torch.stack([x, y, torch.ones_like(x)], dim=-1)
    return rays / torch.linalg.vector_norm(rays, dim=-1, keepdim=True), valid


def _unproject_fisheye(pixels: torch.Tensor, K: torch.Tensor, d: torch.Tensor):
    """Pixels (...,N,2) -> unit directions (...,N,3), valid (...,N)."""
    xd, yd = _remove_K(pixels, K)
    rho_d2 = xd * xd + yd * yd
    eps2 = torch.finfo(pixels.dtype).eps ** 2
    off_axis = rho_d2 > eps2
    rho_d = torch.sqrt(torch.where(off_axis, rho_d2, torch.ones_like(rho_d2)))
    theta_d = torch.where(off_axis, rho_d, torch.zeros_like(rho_d))
    theta_max = fisheye_max_theta(d.detach()).unsqueeze(-1)
    theta, converged = _fisheye_theta_from_theta_d(theta_d, d, theta_max)
    # sin(theta) / rho_d -> 1 on the axis (theta ~ theta_d = rho_d).
    sin_over_rho = torch.where(off_axis, torch.sin(theta) / rho_d, torch.ones_like(rho_d))
    rays = torch.stack([xd * sin_over_rho, yd * sin_over_rho, torch.cos(theta)], dim=-1)
    valid = converged & (theta.detach() < theta_max)
    return rays, valid


def unproject_to_rays(pixels, K, dist, model: str, return_valid: bool = False):
    """Unit ray directions in the camera frame through pixel coordinates.

    Inverse distortion is solved by Newton's method (to ~1e-14 in float64); fisheye rays may
    point more than 90 degrees off-axis (z < 0) up to :func:`fisheye_max_theta`.

    Args:
        pixels: (...,2) ``(u, v)`` OpenCV pixel coordinates (numpy or torch).
        K: (3,3) intrinsics (or (B,3,3) with pixels (B,N,2)).
        dist: (n,) distortion coefficients (or (B,n)).
        model: ``"pinhole"`` or ``"fisheye"``.
        return_valid: also return a bool mask (...,) of pixels whose ray exists (distortion
            inverted inside its monotonic range; fisheye pixels outside the image circle the
            lens can produce are invalid).

    Returns:
        (...,3) unit directions (camera frame), a tensor if any input is one, else numpy; with
        ``return_valid``, ``(directions, valid)``. Invalid rays are still finite.
    """
    is_numpy = not _any_torch(pixels, K, dist)
    pix, K_t, d_t = _prepare(pixels, K, dist, model)
    if pix.shape[-1] != 2:
        raise EgorelightError(f"pixels must be (...,2), got {tuple(pix.shape)}")
    batch_shape = pix.shape[:-1]
    flat = _flatten_for_params(pix, K_t)
    unproject_fn = _unproject_pinhole if model == "pinhole" else _unproject_fisheye
    rays, valid = unproject_fn(flat, K_t, d_t)
    rays = rays.reshape(*batch_shape, 3)
    valid = valid.reshape(batch_shape)
    if is_numpy:
        rays = rays.numpy().astype(_result_numpy_dtype(pixels), copy=False)
        valid = valid.numpy()
    return (rays, valid) if return_valid else rays


# --------------------------------------------------------------------------------------------
# Camera-level helpers
# --------------------------------------------------------------------------------------------


def pixel_grid(width: int, height: int) -> np.ndarray:
    """(H,W,2) float64 pixel-centre coordinates ``(u, v) = (column, row)`` (OpenCV: centres are integers)."""
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    return np.stack([u, v], axis=-1)


def project_world(camera: Camera, points_world, return_valid: bool = False):
    """Project world points (...,3) into ``camera``: pixels (...,2) (and the validity mask)."""
    points_cam = world_to_camera(camera, points_world)
    return project(points_cam, camera.K, camera.dist, camera.model, return_valid=return_valid)


def camera_rays_world(camera: Camera, pixels=None):
    """World-space rays through pixels of ``camera`` (numpy).

    Args:
        camera: the camera.
        pixels: (...,2) pixel coordinates; default the full :func:`pixel_grid` (H,W,2).

    Returns:
        origins (...,3) (the camera centre, broadcast), unit directions (...,3), valid (...,) bool.
    """
    if pixels is None:
        pixels = pixel_grid(camera.width, camera.height)
    dirs_cam, valid = unproject_to_rays(np.asarray(pixels, dtype=np.float64), camera.K, camera.dist,
                                        camera.model, return_valid=True)
    T_world_from_cam = camera.T_world_from_cam
    dirs_world = dirs_cam @ T_world_from_cam[:3, :3].T
    origins = np.broadcast_to(T_world_from_cam[:3, 3], dirs_world.shape)
    return origins, dirs_world, valid
