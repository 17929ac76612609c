"""EWA projection of 3D Gaussians into a camera, and the per-pixel opacity of a splat.

Shared by the fast rasteriser (``render/gaussians.py``) and the dense reference
(``render/gaussians_reference.py``), so both composite exactly the same splats.

Maths (3DGS, Kerbl et al. 2023, Eq. 5; Zwicker et al. 2002):

* camera-frame mean ``p = R_cw mu + t_cw``; 2D mean ``project(p)`` with the camera's actual
  model (pinhole with radial-tangential distortion, or OpenCV fisheye, also past 90 degrees);
* 2D covariance ``Sigma' = J R_cw Sigma R_cw^T J^T + eps2d I`` with ``J = d pixel / d p`` the
  Jacobian of that projection (``geometry/projection_jacobian.py``); ``eps2d`` (pixels^2, 3DGS
  and gsplat use 0.3) is a low-pass filter that keeps every splat at least ~a pixel wide;
* opacity at pixel ``x``: ``alpha = min(ALPHA_MAX, o exp(-0.5 d^T Sigma'^-1 d))``, ``d = x - mean``,
  set to 0 below ``ALPHA_MIN`` (1/255, as 3DGS);
* the sort key ("depth") is the camera-frame ``z`` for a pinhole and the distance from the
  camera centre for a fisheye (whose rays can point sideways or backwards, where ``z`` is not an
  order along the ray);
* a pinhole camera culls the Gaussians whose centre lies outside its field of view widened by
  ``FOV_MARGIN`` (3DGS's 1.3 tan(fov/2) limit): its distortion polynomial describes the lens only
  near the image, and far off-axis (x/z ~ 10) the projection and its Jacobian grow without bound,
  turning a centimetre Gaussian beside the camera into a splat over the whole image. A fisheye's
  projection stays bounded up to its valid angle and needs no such cut.

Pixel ``(row i, column j)`` has its centre at ``(u, v) = (j, i)`` (DESIGN Sec. 4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from egorelight_cli.geometry.cameras import Camera, project, unproject_to_rays
from egorelight_cli.geometry.projection_jacobian import projection_jacobian
from egorelight_cli.structures.gaussians import GaussianSet

ALPHA_MIN = 1.0 / 255.0  # splats fainter than this at a pixel are skipped (3DGS)
ALPHA_MAX = 0.99  # a single splat never makes a pixel fully opaque (3DGS), so T stays > 0
EPS2D = 0.3  # pixels^2 added to every 2D covariance (3DGS / gsplat default)
NEAR_M = 0.01  # Gaussians closer to the camera centre than this are culled
FOV_MARGIN = 0.3  # pinhole: centres beyond the image's x/z, y/z range widened by this share of it are culled
_BOX_MARGIN = 1e-4


@dataclass(frozen=True)
class ProjectedGaussians:
    """The visible subset of a :class:`GaussianSet`, projected into one camera.

    Attributes:
        index: (M,) int64 indices of the visible Gaussians in the input set, sorted front to
            back (stable: ties keep the input order).
        means2d: (M,2) pixel centres ``(u, v)``.
        conics: (M,3) ``(a, b, c)`` of the inverse 2D covariance ``[[a, b], [b, c]]``, 1/px^2.
        depths: (M,) sort key, metres (pinhole: z; fisheye: distance to the camera centre).
        opacities: (M,) peak opacities.
        bbox: (M,4) int64 inclusive pixel box ``(u0, v0, u1, v1)`` clipped to the image,
            outside which the splat's opacity is below ``ALPHA_MIN`` (empty when u1 < u0).
        width, height: image size in pixels.
    """

    index: torch.Tensor
    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    opacities: torch.Tensor
    bbox: torch.Tensor
    width: int
    height: int


def camera_tensors(camera: Camera, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(T_cam_from_world (4,4), K (3,3), dist (n,)) of ``camera`` as tensors like ``like``."""
    def as_tensor(array):
        return torch.tensor(np.array(array), dtype=like.dtype, device=like.device)

    return as_tensor(camera.T_cam_from_world), as_tensor(camera.K), as_tensor(camera.dist)


def sort_depth(points_cam: torch.Tensor, model: str) -> torch.Tensor:
    """(N,) front-to-back sort key of camera-frame points (N,3): z (pinhole) or range (fisheye)."""
    return points_cam[:, 2] if model == "pinhole" else torch.linalg.vector_norm(points_cam, dim=-1)


def image_tangent_bounds(camera: Camera, margin: float = FOV_MARGIN) -> tuple[float, float, float, float]:
    """``(x_lo, x_hi, y_lo, y_hi)``: the range of ``x/z`` and ``y/z`` of a pinhole camera's image (the
    undistorted rays through its border pixels' outer edges), each side widened by ``margin`` times the
    range's half-width."""
    w, h = camera.width, camera.height
    u = np.linspace(-0.5, w - 0.5, max(w, 2) + 1)
    v = np.linspace(-0.5, h - 0.5, max(h, 2) + 1)
    border = np.concatenate([np.stack([u, np.full_like(u, -0.5)], -1), np.stack([u, np.full_like(u, h - 0.5)], -1),
                             np.stack([np.full_like(v, -0.5), v], -1), np.stack([np.full_like(v, w - 0.5), v], -1)])
    rays = unproject_to_rays(border, camera.K, camera.dist, camera.model)
    x, y = rays[:, 0] / rays[:, 2], rays[:, 1] / rays[:, 2]
    x_pad, y_pad = 0.5 * margin * (x.max() - x.min()), 0.5 * margin * (y.max() - y.min())
    return float(x.min() - x_pad), float(x.max() + x_pad), float(y.min() - y_pad), float(y.max() + y_pad)


def in_field_of_view(points_cam: torch.Tensor, camera: Camera, margin: float = FOV_MARGIN) -> torch.Tensor:
    """(N,) bool: camera-frame points (N,3) inside a pinhole camera's widened field of view
    (:func:`image_tangent_bounds`; points with z <= 0 are outside); all True for a fisheye."""
    if camera.model != "pinhole":
        return torch.ones(points_cam.shape[0], dtype=torch.bool, device=points_cam.device)
    x_lo, x_hi, y_lo, y_hi = image_tangent_bounds(camera, margin)
    z = points_cam[:, 2]
    x, y = points_cam[:, 0], points_cam[:, 1]
    return (z > 0) & (x >= x_lo * z) & (x <= x_hi * z) & (y >= y_lo * z) & (y <= y_hi * z)


def _visible_index(gaussians: GaussianSet, camera: Camera, near: float) -> torch.Tensor:
    """Indices (M,) of Gaussians in front of ``camera`` that can reach ALPHA_MIN, front to back."""
    with torch.no_grad():
        T, K, dist = camera_tensors(camera, gaussians.means)
        points = gaussians.means @ T[:3, :3].T + T[:3, 3]
        _, valid = project(points, K, dist, camera.model, return_valid=True)
        depth = sort_depth(points, camera.model)
        finite = torch.isfinite(gaussians.means).all(-1) & torch.isfinite(gaussians.scales).all(-1)
        finite &= torch.isfinite(gaussians.quats).all(-1) & (gaussians.quats.abs().sum(-1) > 0)
        keep = valid & (depth > near) & (gaussians.opacities >= ALPHA_MIN) & finite
        keep &= in_field_of_view(points, camera)
        keep &= (gaussians.scales > 0).all(-1)
        index = torch.nonzero(keep).squeeze(1)
        order = torch.argsort(depth[index], stable=True)
        return index[order]


def project_gaussians(gaussians: GaussianSet, camera: Camera, eps2d: float = EPS2D,
                      near: float = NEAR_M) -> ProjectedGaussians:
    """EWA-project ``gaussians`` into ``camera`` (differentiable w.r.t. every Gaussian parameter).

    Only the Gaussians that are in front of the camera, inside the projection's valid range and
    at least ``ALPHA_MIN`` opaque enter the differentiable computation, so culled ones get zero
    (never NaN) gradients.
    """
    index = _visible_index(gaussians, camera, near)
    visible = gaussians.subset(index)
    T, K, dist = camera_tensors(camera, gaussians.means)
    R_cw = T[:3, :3]
    points = visible.means @ R_cw.T + T[:3, 3]
    means2d = project(points, K, dist, camera.model)
    J = projection_jacobian(points, K, dist, camera.model) @ R_cw  # (M,2,3): d pixel / d world
    cov2d = J @ visible.covariances() @ J.transpose(-1, -2)
    cov_xx = cov2d[:, 0, 0] + eps2d
    cov_xy = cov2d[:, 0, 1]
    cov_yy = cov2d[:, 1, 1] + eps2d
    det = (cov_xx * cov_yy - cov_xy * cov_xy).clamp_min(torch.finfo(points.dtype).tiny)
    conics = torch.stack([cov_yy / det, -cov_xy / det, cov_xx / det], dim=-1)
    bbox = _footprint_box(means2d.detach(), cov_xx.detach(), cov_yy.detach(), visible.opacities.detach(),
                          camera.width, camera.height)
    return ProjectedGaussians(index, means2d, conics, sort_depth(points, camera.model), visible.opacities,
                              bbox, camera.width, camera.height)


def _footprint_box(means2d: torch.Tensor, cov_xx: torch.Tensor, cov_yy: torch.Tensor, opacities: torch.Tensor,
                   width: int, height: int) -> torch.Tensor:
    """Inclusive pixel box (M,4) of the ellipse where ``o exp(-q/2) >= ALPHA_MIN``.

    That ellipse is ``d^T Sigma'^-1 d <= k^2`` with ``k^2 = 2 ln(o / ALPHA_MIN)``; its axis-aligned
    half-extents are ``k sqrt(Sigma'_xx)`` and ``k sqrt(Sigma'_yy)``, so no pixel outside the
    box can pass the threshold (the box is exact, not a 3-sigma guess).
    """
    k = torch.sqrt(2.0 * torch.log((opacities / ALPHA_MIN).clamp_min(1.0)))
    # a hair wider than exact, so rounding never drops a pixel at the threshold (those inside the
    # box but under ALPHA_MIN are zeroed by splat_alpha anyway)
    half_u = k * torch.sqrt(cov_xx) * (1 + _BOX_MARGIN) + _BOX_MARGIN
    half_v = k * torch.sqrt(cov_yy) * (1 + _BOX_MARGIN) + _BOX_MARGIN
    # clamp before the integer cast: far off-screen splats must not overflow int64
    big = float(max(width, height) + 1)
    u0 = torch.ceil((means2d[:, 0] - half_u).clamp(-1.0, big)).long().clamp_min(0)
    u1 = torch.floor((means2d[:, 0] + half_u).clamp(-1.0, big)).long().clamp_max(width - 1)
    v0 = torch.ceil((means2d[:, 1] - half_v).clamp(-1.0, big)).long().clamp_min(0)
    v1 = torch.floor((means2d[:, 1] + half_v).clamp(-1.0, big)).long().clamp_max(height - 1)
    return torch.stack([u0, v0, u1, v1], dim=-1)


def splat_falloff(du: torch.Tensor, dv: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """``exp(-q/2)`` with ``q = a du^2 + 2 b du dv + c dv^2``: the splat's shape at pixel offsets (du, dv)."""
    return torch.exp(-0.5 * (a * du * du + 2.0 * b * du * dv + c * dv * dv))


def splat_alpha(offsets: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor) -> torch.Tensor:
    """Opacity of splats at pixel offsets: ``min(ALPHA_MAX, o exp(-q/2))``, 0 below ``ALPHA_MIN``.

    Args:
        offsets: (...,2) pixel minus splat centre ``(du, dv)``.
        conics: (...,3) ``(a, b, c)`` broadcastable to ``offsets[..., 0]``.
        opacities: (...) peak opacities.
    Returns:
        (...) opacities in ``{0} U [ALPHA_MIN, ALPHA_MAX]``.
    """
    a, b, c = conics.unbind(-1)
    alpha = (opacities * splat_falloff(offsets[..., 0], offsets[..., 1], a, b, c)).clamp_max(ALPHA_MAX)
    return torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
