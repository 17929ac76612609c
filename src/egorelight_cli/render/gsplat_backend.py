"""gsplat (CUDA) as the accelerator of ``render/gaussians.py``.

gsplat 1.x has no CPU rasteriser (``../shared/notes/appearance.md`` Sec. 3.2), so it is used only
when the Gaussians live on a CUDA device and ``import gsplat`` works. It models a pinhole
without distortion and an equidistant fisheye (``theta_d = theta``) exactly; cameras with
distortion coefficients stay on the torch path (which also runs on CUDA). gsplat sorts by
camera-frame z and culls ``z < near``; its splat extent is 3 sigma rather than the torch path's
exact ``ALPHA_MIN`` ellipse, so the two agree to a small tolerance, not bit for bit.
"""

from __future__ import annotations

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.render.gaussians import GaussianRender, assemble_render
from egorelight_cli.structures.gaussians import GaussianSet


def available() -> bool:
    """True when CUDA is present and gsplat imports."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:  # gsplat JIT-compiles on import in some versions; any failure means "no"
        return False
    return True


def supports_camera(camera: Camera) -> bool:
    """True for cameras gsplat projects exactly: pinhole or fisheye with zero distortion, no skew."""
    return not np.any(camera.dist) and camera.K[0, 1] == 0


def usable(gaussians: GaussianSet, camera: Camera, required: bool) -> bool:
    """Whether to render with gsplat; with ``required`` a reason is raised instead of ``False``."""
    reasons = []
    if gaussians.device.type != "cuda":
        reasons.append("the Gaussians are not on a CUDA device")
    elif not available():
        reasons.append("gsplat does not import")
    if not supports_camera(camera):
        reasons.append(f"camera {camera.name!r} has distortion or skew gsplat does not model")
    if reasons and required:
        raise EgorelightError(f"cannot render with gsplat: {'; '.join(reasons)}")
    return not reasons


def render(gaussians: GaussianSet, camera: Camera, background, passes, pass_backgrounds, eps2d: float,
           near: float) -> GaussianRender:
    """Render with ``gsplat.rasterization``; the same outputs as the torch path."""
    from gsplat import rasterization

    like = gaussians.means
    T = torch.as_tensor(camera.T_cam_from_world, dtype=torch.float32, device=like.device)
    K = torch.as_tensor(camera.K, dtype=torch.float32, device=like.device)
    points = gaussians.means.float() @ T[:3, :3].T + T[:3, 3]
    depth = points[:, 2] if camera.model == "pinhole" else torch.linalg.vector_norm(points, dim=-1)
    columns = [gaussians.colours] + list((passes or {}).values()) + [depth[:, None].to(like.dtype)]
    features = torch.cat(columns, dim=1).float()
    image, alpha, _ = rasterization(
        gaussians.means.float(), gaussians.quats.float(), gaussians.scales.float(), gaussians.opacities.float(),
        features, T[None], K[None], camera.width, camera.height, near_plane=near, eps2d=eps2d,
        camera_model="pinhole" if camera.model == "pinhole" else "fisheye", render_mode="RGB",
        packed=False, sh_degree=None,
    )
    accumulated = torch.cat([image[0], alpha[0]], dim=-1).reshape(camera.width * camera.height, -1).to(like.dtype)
    return assemble_render(accumulated, gaussians, passes, background, pass_backgrounds, camera.height,
                           camera.width, backend="gsplat", device=str(like.device))
