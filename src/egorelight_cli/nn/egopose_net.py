"""EgoPoseNet: stereo down-facing fisheye images + head pose -> 57 world keypoints.

The paper's egocentric pose estimator is FRAME (CVPR 2025) adapted to the studio HMD
(``../shared/notes/egopose_frame.md``). This network keeps FRAME's structure at a size that
trains on a CPU:

1. **Shared encoder** (:class:`ViewEncoder`): two stride-2 convolutions then a small
   :class:`~egorelight_cli.nn.unet.UNet` body, applied to each fisheye view; features at 1/4
   of the input resolution.
2. **Stereo head**: the two views' features are concatenated along channels and a 1x1
   convolution predicts, per view and per joint, a 2D heatmap logit map and a depth map.
3. **Soft-argmax**: expected heatmap position -> pixel ``(u, v)`` in the *original* image;
   range = heatmap-weighted mean of ``r0 * exp(depth)`` (``r0``: per view/joint mean range of
   the training data, a buffer), metres along the ray.
4. **Fisheye unprojection** (:func:`unproject_keypoints`, the OpenCV fisheye model of
   :mod:`egorelight_cli.geometry.cameras`, differentiable): ``p_cam = ray(u, v) * range``.
5. **Into the HMD frame** with the hand-eye ``T_hmd_from_cam = inv(Pi)``, **view fusion**: a
   per-joint learned convex weight of the two views (a left-hand joint is seen better by the
   left camera).
6. **Temporal module** (:class:`TemporalRefiner`): the fused keypoints of a window of frames
   ending at the current one, each moved into the *heading frame* of the current frame (FRAME's
   floor-aligned frame: origin at the HMD, +Y world up, X the HMD's right axis levelled), a
   1D convolution over time predicts a residual for the current frame; then back to the world
   with the head pose ``H = T_world_from_hmd``.
7. **Pose prior** (ours, for tiny per-person training sets): per joint, a blend with the
   training mean pose in the heading frame, ``a_j * x + (1 - a_j) * prior``; ``a_j`` is fitted
   on held-out training frames (1 = no prior). Joints the down-facing cameras cannot see
   (legs hidden by the torso) can lean on the prior, visible hands need not.

Units: metres, OpenCV camera frames, world +Y up. Shapes use B frames, V = 2 views, J = 57
joints, W window frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from egorelight_cli.geometry.cameras import project, unproject_to_rays
from egorelight_cli.geometry.rotations import invert_rigid, transform_points
from egorelight_cli.nn.unet import UNet, group_norm

WORLD_UP = (0.0, 1.0, 0.0)


# ------------------------------------------------------------------------------- rig geometry
@dataclass(frozen=True)
class RigGeometry:
    """The fisheye views the network looks through (float32 tensors).

    Attributes:
        K: (V,3,3) intrinsics of the original images, pixels.
        dist: (V,4) OpenCV fisheye k1..k4.
        width, height: original image size, pixels (all views alike).
        T_hmd_from_cam: (V,4,4) inverse hand-eye transforms ``inv(Pi)``, metres.
    """

    K: torch.Tensor
    dist: torch.Tensor
    width: int
    height: int
    T_hmd_from_cam: torch.Tensor

    @property
    def T_cam_from_hmd(self) -> torch.Tensor:
        return torch.linalg.inv(self.T_hmd_from_cam)


def transform(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply (...,4,4) transforms to (...,N,3) points (T broadcast over N)."""
    return transform_points(T[..., None, :, :], points)


def heading_frame(T_world_from_hmd: torch.Tensor) -> torch.Tensor:
    """(...,4,4) ``T_world_from_heading``: origin at the HMD, Y = world up, X = the HMD's right
    axis projected onto the floor (robust to looking down), Z = X x Y (backwards, like the HMD)."""
    up = torch.tensor(WORLD_UP, dtype=T_world_from_hmd.dtype, device=T_world_from_hmd.device)
    right = T_world_from_hmd[..., :3, 0]
    right = right - (right @ up)[..., None] * up
    right = right / torch.linalg.vector_norm(right, dim=-1, keepdim=True).clamp_min(1e-6)
    up_b = up.expand_as(right)
    back = torch.linalg.cross(right, up_b, dim=-1)
    T = torch.zeros_like(T_world_from_hmd)
    T[..., :3, 0], T[..., :3, 1], T[..., :3, 2] = right, up_b, back
    T[..., :3, 3] = T_world_from_hmd[..., :3, 3]
    T[..., 3, 3] = 1
    return T


def unproject_keypoints(pixels: torch.Tensor, ranges: torch.Tensor, rig: RigGeometry) -> torch.Tensor:
    """Camera-frame points from fisheye pixels and ranges (distance along the ray).

    Args:
        pixels: (B,V,J,2) ``(u, v)`` in each view's original image.
        ranges: (B,V,J) metres.
    Returns:
        (B,V,J,3) points in each camera's frame.
    """
    B, V, J, _ = pixels.shape
    flat = pixels.permute(1, 0, 2, 3).reshape(V, B * J, 2)
    rays = unproject_to_rays(flat, rig.K.to(pixels), rig.dist.to(pixels), "fisheye")
    rays = rays.reshape(V, B, J, 3).permute(1, 0, 2, 3)
    return rays * ranges.unsqueeze(-1)


def project_keypoints(points_cam: torch.Tensor, rig: RigGeometry) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,V,J,3) camera-frame points -> pixels (B,V,J,2) (NaN where invalid) and a mask of
    points that project inside the image."""
    B, V, J, _ = points_cam.shape
    flat = points_cam.permute(1, 0, 2, 3).reshape(V, B * J, 3)
    pixels, valid = project(flat, rig.K.to(points_cam), rig.dist.to(points_cam), "fisheye", return_valid=True)
    pixels = pixels.reshape(V, B, J, 2).permute(1, 0, 2, 3)
    valid = valid.reshape(V, B, J).permute(1, 0, 2)
    inside = valid & (pixels[..., 0] >= -0.5) & (pixels[..., 0] <= rig.width - 0.5) \
        & (pixels[..., 1] >= -0.5) & (pixels[..., 1] <= rig.height - 0.5)
    return pixels, inside


# ------------------------------------------------------------------------------------ modules
class ViewEncoder(nn.Module):
    """(N,3,H,W) images in [0,1] -> (N,C,H/4,W/4) features (two stride-2 convs + a UNet body)."""

    def __init__(self, channels: int = 32, levels: int = 2):
        super().__init__()
        half = max(channels // 2, 4)
        self.stem = nn.Sequential(
            nn.Conv2d(3, half, 3, stride=2, padding=1), group_norm(half), nn.SiLU(),
            nn.Conv2d(half, channels, 3, stride=2, padding=1), group_norm(channels), nn.SiLU())
        self.body = UNet(channels, channels, base_channels=channels, levels=levels)
        self.out_channels = channels

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.body.decoder_features(self.stem(images * 2 - 1))[-1]


class TemporalRefiner(nn.Module):
    """Residual 1D convolution over a window of fused keypoints in the current heading frame.

    forward: (B,W,J,3) (last = current frame) -> (B,J,3) refined current frame. The last layer
    starts at zero, so an untrained refiner is the identity.
    """

    def __init__(self, num_joints: int, window: int, hidden: int = 128):
        super().__init__()
        self.window = window
        channels = num_joints * 3
        layers: list[nn.Module] = [nn.Conv1d(channels, hidden, 1), nn.SiLU()]
        if window > 1:
            layers += [nn.Conv1d(hidden, hidden, min(3, window)), nn.SiLU()]
        self.net = nn.Sequential(*layers)
        self.out = nn.Linear(hidden, channels)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, window_points: torch.Tensor) -> torch.Tensor:
        B, W, J, _ = window_points.shape
        x = window_points.reshape(B, W, J * 3).transpose(1, 2)  # (B,3J,W)
        h = self.net(x).mean(dim=-1)
        return window_points[:, -1] + self.out(h).reshape(B, J, 3)


class EgoPoseNet(nn.Module):
    """The whole estimator (see the module docstring).

    Args:
        num_joints: J (57).
        channels: encoder width.
        levels: UNet depth of the encoder body.
        window: frames seen by the temporal module (1 = none).
        temporal_hidden: temporal module width.
        num_views: V (2).
        tied: pairs of joints that are one point (the body wrist and the hand wrist): each view's
            estimates of a pair are averaged.
    """

    def __init__(self, num_joints: int = 57, channels: int = 32, levels: int = 2, window: int = 5,
                 temporal_hidden: int = 128, num_views: int = 2, tied: list | tuple = ()):
        super().__init__()
        self.num_joints, self.num_views = num_joints, num_views
        self.tied = [(int(a), int(b)) for a, b in tied]
        self.encoder = ViewEncoder(channels, levels)
        self.head = nn.Conv2d(channels * num_views, num_views * num_joints * 2, 1)
        self.log_temperature = nn.Parameter(torch.zeros(()))
        self.view_logits = nn.Parameter(torch.zeros(num_views, num_joints))
        self.register_buffer("log_range0", torch.zeros(num_views, num_joints))
        # pose prior in the heading frame and each joint's trust in the estimate over it (1: no prior)
        self.register_buffer("prior_heading", torch.zeros(num_joints, 3))
        self.register_buffer("prior_blend", torch.ones(num_joints))
        self.temporal = TemporalRefiner(num_joints, window, temporal_hidden)

    @property
    def window(self) -> int:
        return self.temporal.window

    # -- per frame --------------------------------------------------------------------------
    def heatmaps(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B,V,3,H,W) -> heatmap logits and depth maps, each (B,V,J,h,w)."""
        B, V = images.shape[:2]
        features = self.encoder(images.flatten(0, 1))
        h, w = features.shape[-2:]
        stereo = features.reshape(B, V * features.shape[1], h, w)
        out = self.head(stereo).reshape(B, V, 2, self.num_joints, h, w)
        return out[:, :, 0], out[:, :, 1]

    def soft_argmax(self, logits: torch.Tensor, depth: torch.Tensor, width: int, height: int):
        """Pixels (B,V,J,2) in an original ``width`` x ``height`` image, ranges (B,V,J) metres and
        the heatmap peak probability (B,V,J)."""
        h, w = logits.shape[-2:]
        prob = torch.softmax(logits.flatten(-2) * self.log_temperature.exp(), dim=-1).reshape(logits.shape)
        xs = (torch.arange(w, dtype=prob.dtype, device=prob.device) + 0.5) * (width / w) - 0.5
        ys = (torch.arange(h, dtype=prob.dtype, device=prob.device) + 0.5) * (height / h) - 0.5
        u = (prob.sum(-2) * xs).sum(-1)
        v = (prob.sum(-1) * ys).sum(-1)
        log_range = (prob * depth).sum((-2, -1)) + self.log_range0
        return torch.stack([u, v], dim=-1), log_range.exp(), prob.flatten(-2).amax(-1)

    def forward_frames(self, images: torch.Tensor, rig: RigGeometry) -> dict[str, torch.Tensor]:
        """Per-frame estimate of (B,V,3,H,W) image pairs.

        Returns a dict: ``pixels`` (B,V,J,2), ``ranges`` (B,V,J), ``peak`` (B,V,J), ``points_cam``
        (B,V,J,3), ``points_hmd`` (B,V,J,3) per view, ``fused_hmd`` (B,J,3), ``disagreement``
        (B,J) distance between the two views' estimates, metres.
        """
        logits, depth = self.heatmaps(images)
        pixels, ranges, peak = self.soft_argmax(logits, depth, rig.width, rig.height)
        points_cam = unproject_keypoints(pixels, ranges, rig)
        points_hmd = transform(rig.T_hmd_from_cam.to(points_cam)[None], points_cam)
        if self.tied:
            a, b = (torch.tensor(ids) for ids in zip(*self.tied))
            mean = (points_hmd[:, :, a] + points_hmd[:, :, b]) / 2
            points_hmd = points_hmd.index_copy(2, a, mean).index_copy(2, b, mean)
        weights = torch.softmax(self.view_logits, dim=0)  # (V,J)
        fused = (points_hmd * weights[None, :, :, None]).sum(1)
        spread = torch.linalg.vector_norm(points_hmd - fused[:, None], dim=-1).amax(1) * 2
        return {"pixels": pixels, "ranges": ranges, "peak": peak, "points_cam": points_cam,
                "points_hmd": points_hmd, "fused_hmd": fused, "disagreement": spread}

    # -- temporal ---------------------------------------------------------------------------
    def refine(self, fused_world: torch.Tensor, T_world_from_hmd: torch.Tensor) -> torch.Tensor:
        """Temporal refinement of window sequences.

        Args:
            fused_world: (B,W,J,3) per-frame fused keypoints, world metres; last = current.
            T_world_from_hmd: (B,4,4) head pose of the current frame.
        Returns:
            (B,J,3) world keypoints of the current frame: the temporal module's output blended
            per joint with the pose prior, ``a * x + (1 - a) * prior`` in the heading frame.
        """
        T_world_from_heading = heading_frame(T_world_from_hmd)
        local = transform(invert_rigid(T_world_from_heading)[:, None], fused_world)
        blend = self.prior_blend[:, None]
        refined = blend * self.temporal(local) + (1 - blend) * self.prior_heading
        return transform(T_world_from_heading, refined)


def windows(num_frames: int, window: int, available: torch.Tensor | None = None) -> torch.Tensor:
    """(T,W) row indices of the W frames ending at each frame (causal, as FRAME): positions
    before the start, or not ``available`` (T,) bool, repeat the nearest later usable one in
    the window (ultimately the current frame)."""
    offsets = torch.arange(-window + 1, 1)
    idx = (torch.arange(num_frames)[:, None] + offsets[None]).clamp_min(0)
    if available is not None:
        for col in range(window - 2, -1, -1):  # fill from the right: current frame is column W-1
            bad = ~available[idx[:, col]]
            idx[bad, col] = idx[bad, col + 1]
    return idx


def load_backbone_weights(net: EgoPoseNet, state: dict[str, torch.Tensor]) -> int:
    """Load encoder weights (keys with or without the ``encoder.`` prefix) whose shapes match;
    returns how many tensors were loaded."""
    own = net.encoder.state_dict()
    loaded = {}
    for key, value in state.items():
        name = key.removeprefix("encoder.")
        if name in own and own[name].shape == value.shape:
            loaded[name] = value
    own.update(loaded)
    net.encoder.load_state_dict(own)
    return len(loaded)


def range_log_init(ranges: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(V,J) log of the mean training range per view/joint from (N,V,J) ranges and mask."""
    weights = mask.to(ranges.dtype)
    mean = (ranges * weights).sum(0) / weights.sum(0).clamp_min(1)
    fallback = ranges[mask].mean() if mask.any() else torch.tensor(1.0)
    mean = torch.where(weights.sum(0) > 0, mean, fallback)
    return mean.clamp_min(0.05).log()


__all__ = ["EgoPoseNet", "RigGeometry", "TemporalRefiner", "ViewEncoder", "heading_frame",
           "load_backbone_weights", "project_keypoints", "range_log_init", "transform", "unproject_keypoints",
           "windows"]
