"""Egocentric depth (paper Sec. "Egocentric Depth Estimator"): the two down-facing fisheye
images of a frame -> metric depth per view -> one fused world point cloud of P points with
normals.

* **Supervision** (``train egodepth``): the multi-view reconstruction ``recon/<frame>.ply``
  (NeuS2 in the paper) ray-cast into each ego camera posed by the calibration
  (``T_world_from_cam = H inv(Pi)``) gives a metric range map. The reconstruction also holds
  the headset's outer shell, which the ego cameras see at a few centimetres: hits nearer than
  ``train.near_m`` are not body, and pixels where that happens in at least
  ``train.self_occlusion_fraction`` of the training frames form a per-camera *self-occlusion
  mask* (stored in the model, applied at inference). Back-facing hits (rays leaving the
  reconstruction from inside) are not supervised either.
* **Network** (:class:`~egorelight_cli.nn.depth_net.DepthNet`): shared by both views; trained
  with L1 on log range over the supervised pixels plus a body-mask BCE, with the paper's colour
  jitter and random crops; optional Depth-Anything-V2 prior (``--backbone``). With
  ``net.stereo_input`` (the default) it also takes SGBM's range on the rigid down-facing pair
  (:class:`SGBMDepth`, computed on the un-jittered pair) and corrects it: stereo is metric and
  lighting-independent where the body is textured, the image fills in where it has nothing.
* **Inference**: range where the body probability exceeds ``predict.mask_threshold`` and (with
  ``net.uncertainty``) the predicted error scale is below ``predict.max_uncertainty``, outside the
  self-occlusion mask, beyond ``predict.min_range_m``, minus depth-discontinuity pixels;
  ``--method sgbm`` uses OpenCV SGBM on the rectified fisheye pair instead
  (:mod:`egorelight_cli.geometry.fisheye_stereo`).
* **Point cloud**: per view ``z = (K Pi H)^-1 d`` (:func:`~egorelight_cli.geometry.depth.unproject_depth`),
  both views fused, P points sampled uniformly, Hoppe normals (KD-tree PCA) oriented towards
  the camera that saw each point; fewer than P points are padded and flagged invalid.
* **Metrics** (capture with ``groundtruth/``): range AbsRel and RMSE (cm) inside the body mask
  (the true body mesh ray-cast into the ego view; where the frame has a reconstruction, only
  pixels where it agrees within ``eval.occluder_margin_m``: elsewhere the headset, which is not
  in the body mesh, hides the body), coverage of that mask, and the point-to-surface
  distance (cm) of the fused points to the true mesh's outer surface (``point_to_surface_cm``:
  the points->true direction only, a partial view has no completeness; any topology of the
  truth); for the network and, with ``eval.compare_sgbm``, for SGBM on the same frames, with
  each one's AbsRel also on the pixels both cover (``depth_absrel_common``, the like-for-like
  comparison, since each method's own AbsRel is over the pixels it chose to keep).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from egorelight_cli import console
from egorelight_cli.errors import EgorelightError
from egorelight_cli.sharding import evenly_spaced, split_frames
from egorelight_cli.geometry.cameras import Camera, invert_rigid, transform_points
from egorelight_cli.geometry.depth import camera_ray_map, depth_edges, range_to_depth, render_depth, unproject_depth
from egorelight_cli.geometry.pointcloud_ops import fixed_size_cloud, fuse_views
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.io.calibration import posed_ego_camera
from egorelight_cli.structures.calibration import Calibration
from egorelight_cli.io.capture import Capture, SequenceInfo
from egorelight_cli.nn.depth_net import DepthNet

METHODS = ("net", "sgbm")
#: the body-mask threshold of a model trained without validation frames
DEFAULT_MASK_THRESHOLD = 0.5
MODEL_STAGE = "egodepth"


# ------------------------------------------------------------------------------------ views
@dataclass(frozen=True, eq=False)
class EgoView:
    """One ego camera at one master-clock frame.

    Attributes:
        role: camera role.
        frame_id: studio (master-clock) frame id (wild: ego id).
        camera: intrinsics with the pose ``T_cam_from_world = inv(H inv(Pi))``.
        image: (H,W,3) uint8 sRGB.
    """

    role: str
    frame_id: int
    camera: Camera
    image: np.ndarray


def load_view(capture: Capture, calibration: Calibration, sequence: SequenceInfo, role: str, frame_id: int) -> EgoView:
    """Camera and image of ``role`` at master-clock ``frame_id`` (image ``frame + stream_offset``)."""
    camera = posed_ego_camera(capture, calibration, role, sequence.name, frame_id)
    image = sequence.read_ego_image(role, calibration.ego_frame_id(sequence.name, frame_id))
    if image.shape[:2] != (camera.height, camera.width):
        raise EgorelightError(f"ego image of {role} is {image.shape[1]}x{image.shape[0]}, the camera is "
                              f"{camera.width}x{camera.height}", sequence.ego_image_path(role, calibration.ego_frame_id(
                                  sequence.name, frame_id)))
    return EgoView(role, int(frame_id), camera, image)


def check_roles(capture: Capture, sequence: SequenceInfo, roles: Sequence[str]) -> None:
    sequence.require_stream("ego")
    for role in roles:
        capture.ego_camera(role)
        if role not in sequence.ego_roles:
            raise EgorelightError(f"sequence {sequence.name!r} has no ego stream {role!r}", sequence.root / "sequence.json")


def usable_frames(calibration: Calibration, sequence: SequenceInfo, roles: Sequence[str],
                  announce: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Content frames (master clock) whose ego images exist, and for each whether the calibration
    has a valid head pose there. Frames without ego images are dropped (said once when ``announce``)."""
    if sequence.name not in calibration.head_poses:
        raise EgorelightError(f"calibration has no head poses for sequence {sequence.name!r}", calibration.source)
    poses = calibration.head_poses[sequence.name]
    candidates = sequence.content_frame_ids  # wild (no studio stream): its ego ids, offset 0
    frames, posed = [], []
    for f in candidates:
        ego = calibration.ego_frame_id(sequence.name, int(f))
        if all(sequence.ego_image_path(r, ego).exists() for r in roles):
            frames.append(int(f))
            posed.append(poses.valid_pose(int(f)) is not None)
    if not frames:
        raise EgorelightError(f"sequence {sequence.name!r} has no content frame with ego images of "
                              f"{', '.join(roles)}", sequence.root)
    if not any(posed):  # every point would be dropped: the trouble is upstream, say so here
        raise EgorelightError(f"no frame of sequence {sequence.name!r} with ego images has a valid head pose",
                              calibration.source)
    if announce and len(frames) < len(candidates):
        console.info(f"egodepth: {len(candidates) - len(frames)} of {len(candidates)} content frames of "
                     f"{sequence.name!r} lack ego images of {', '.join(roles)} and are left out")
    return np.array(frames, np.int64), np.array(posed, bool)


# ------------------------------------------------------------------------------ supervision
@dataclass(frozen=True, eq=False)
class TrainingView:
    """One supervised view: image (H,W,3) uint8, range (H,W) float32 metres, supervised (H,W)
    bool, near (H,W) bool (reconstruction hit closer than ``near_m``: the headset), and the stereo
    range (H,W) float32 metres (0 = none) when the network takes one."""

    role: str
    sequence: str
    frame_id: int
    image: np.ndarray
    range: np.ndarray
    supervised: np.ndarray
    near: np.ndarray
    stereo: np.ndarray | None = None


def supervision(capture: Capture, calibration: Calibration, sequences: Sequence[SequenceInfo], roles: Sequence[str],
                near_m: float, max_frames: int = 0, stereo=None, validation_frames: int = 0,
                part: str = "training") -> list[TrainingView]:
    """Render every available reconstruction into the ego views (see the module docstring).

    ``stereo``: None, or a callable (the frame's :class:`EgoView` list -> range map by role, e.g.
    :class:`SGBMDepth` bound to its settings) whose output each view keeps as its stereo input.
    ``part``: ``training`` or ``validation``, the frames of :func:`split_frames` (per sequence);
    validation may be empty."""
    if part not in ("training", "validation"):
        raise ValueError(f"part must be training or validation, got {part!r}")
    from egorelight_cli.io.meshes import read_mesh

    views: list[TrainingView] = []
    for sequence in sequences:
        check_roles(capture, sequence, roles)
        # training and validation views are two calls over the same frames: say what is left out once
        frames, posed = usable_frames(calibration, sequence, roles, announce=part == "training")
        frames = [f for f, ok in zip(frames, posed) if ok and sequence.recon_path(f).exists()]
        training, validation = split_frames(frames, max_frames, validation_frames)
        for f in (training if part == "training" else validation):
            vertices, faces = read_mesh(sequence.recon_path(f))
            caster = RayCaster(vertices, faces)
            frame_views = [load_view(capture, calibration, sequence, role, f) for role in roles]
            stereo_ranges = stereo(frame_views) if stereo is not None else {}
            for view in frame_views:
                rendered = render_depth(view.camera, caster)
                near = rendered.hit & (rendered.range < near_m)
                supervised = rendered.hit & rendered.front_facing & ~near
                views.append(TrainingView(view.role, sequence.name, f, view.image, rendered.range, supervised, near,
                                          stereo_ranges.get(view.role)))
    if not views and part == "training":
        names = ", ".join(s.name for s in sequences)
        raise EgorelightError(f"no training frame: sequences {names} have no reconstruction (recon/) at a posed "
                              "frame with ego images")
    return views


def self_occlusion_masks(views: Sequence[TrainingView], fraction: float) -> dict[str, np.ndarray]:
    """Per role (H,W) bool: pixels where the reconstruction shows the headset itself in at least
    ``fraction`` of the training frames."""
    masks = {}
    for role in sorted({v.role for v in views}):
        near = np.stack([v.near for v in views if v.role == role])
        masks[role] = near.mean(axis=0) >= fraction
    return masks


# --------------------------------------------------------------------------------- training
@dataclass(frozen=True)
class TrainSettings:
    steps: int
    batch: int
    crop: int
    lr: float
    w_depth: float
    w_mask: float
    jitter: dict
    log_every: int
    checkpoint_every: int
    seed: int

    @classmethod
    def from_config(cls, cfg) -> "TrainSettings":
        t = cfg.train
        return cls(int(t.steps), int(t.batch), int(t.crop), float(t.lr), float(t.loss.depth), float(t.loss.mask),
                   dict(t.jitter.to_dict()), int(t.log_every), int(t.checkpoint_every), int(cfg.seed))


def _tensors(views: Sequence[TrainingView], ray_maps: dict, self_masks: dict) -> dict[str, torch.Tensor]:
    """Stacked training tensors: image (N,3,H,W) [0,1], rays (N,3,H,W), log range (N,1,H,W),
    supervised (N,1,H,W), weight of the mask loss (N,1,H,W) (inside the lens, outside the
    self-occlusion mask), and the stereo range (N,1,H,W) metres when the views have one."""
    images = np.stack([v.image for v in views]).astype(np.float32) / 255.0
    rays = np.stack([ray_maps[v.role][0] for v in views]).astype(np.float32)
    inside = np.stack([ray_maps[v.role][1] & ~self_masks[v.role] for v in views])
    supervised = np.stack([v.supervised for v in views]) & inside
    log_range = np.log(np.where(supervised, np.stack([v.range for v in views]), 1.0))
    tensors = {
        "image": torch.from_numpy(images).permute(0, 3, 1, 2).contiguous(),
        "rays": torch.from_numpy(rays).permute(0, 3, 1, 2).contiguous(),
        "log_range": torch.from_numpy(log_range.astype(np.float32))[:, None],
        "supervised": torch.from_numpy(supervised)[:, None],
        "inside": torch.from_numpy(inside)[:, None],
    }
    if views[0].stereo is not None:
        tensors["stereo"] = torch.from_numpy(np.stack([v.stereo for v in views]).astype(np.float32))[:, None]
    return tensors


def depth_losses(model: DepthNet, batch: dict[str, torch.Tensor], prior: torch.Tensor | None = None) -> dict:
    """L1 on log range over supervised pixels and the body-mask BCE inside the lens; for a network
    with the uncertainty, ``depth`` adds the Laplace negative log-likelihood |e|/b + log b of the
    *detached* error, so the scale learns to predict the error while the range and the mask train
    as without it (the coupled likelihood down-weights hard pixels and starved the mask: on the
    tiny capture its training IoU fell from 0.8 to 0.2)."""
    log_range, logit, log_scale = model(batch["image"], batch["rays"], prior, batch.get("stereo"))
    sup = batch["supervised"].float()
    inside = batch["inside"].float()
    error = (log_range - batch["log_range"]).abs()
    count = sup.sum().clamp_min(1.0)
    l_l1 = (error * sup).sum() / count
    bce = torch.nn.functional.binary_cross_entropy_with_logits(logit, sup, reduction="none")
    l_mask = (bce * inside).sum() / inside.sum().clamp_min(1.0)
    out = {"depth_l1_log": l_l1, "depth": l_l1, "mask_bce": l_mask}
    if log_scale is not None:
        nll = error.detach() * torch.exp(-log_scale) + log_scale
        out["scale_nll"] = (nll * sup).sum() / count
        out["depth"] = l_l1 + out["scale_nll"]
    return out


def _crop(batch: dict[str, torch.Tensor], size: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """A random ``size`` square of every map. The corner is drawn over a range extended by half a
    crop on each side and clamped, so border pixels (the chin and hands of a fisheye view) are
    cropped about a third as often as central ones instead of almost never."""
    H, W = batch["image"].shape[-2:]
    if size <= 0 or size >= min(H, W):
        return batch

    def corner(extent: int) -> int:
        raw = int(torch.randint(-size // 2, extent - size + size // 2 + 1, (1,), generator=generator))
        return min(max(raw, 0), extent - size)

    y, x = corner(H), corner(W)
    return {k: v[..., y:y + size, x:x + size] for k, v in batch.items()}


def train_depth_net(views: Sequence[TrainingView], ray_maps: dict, self_masks: dict, settings: TrainSettings,
                    net_cfg, device: torch.device, checkpoint=None, prior_fn=None) -> tuple[DepthNet, list[dict]]:
    """Fit a :class:`DepthNet` to the supervised views; returns the model (eval mode, CPU) and curve."""
    from egorelight_cli.nn.augment import ColourJitter
    from egorelight_cli.nn.distributed import rank_share
    from egorelight_cli.nn.training import train

    data = _tensors(views, ray_maps, self_masks)
    if not bool(data["supervised"].any()):
        raise EgorelightError("the reconstructions cover no ego pixel: nothing to supervise the depth network with")
    priors = None
    if prior_fn is not None:
        priors = torch.cat([prior_fn(data["image"][i:i + 4]) for i in range(0, len(views), 4)])
    mean = float(data["log_range"][data["supervised"]].median())
    stereo_input = bool(net_cfg.stereo_input)
    if stereo_input != ("stereo" in data):
        raise EgorelightError("net.stereo_input and the training views disagree: give the views their stereo ranges"
                              if stereo_input else "the training views carry stereo ranges the network does not take")
    torch.manual_seed(settings.seed)
    model = DepthNet.from_config(net_cfg, 1 if priors is not None else 0, mean).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=settings.lr)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=settings.lr, total_steps=max(settings.steps, 1),
                                                    pct_start=0.1)
    jitter = ColourJitter(**settings.jitter)
    if priors is not None:
        data["prior"] = priors
    N = len(views)

    def step_fn(step: int) -> dict[str, torch.Tensor]:
        generator = torch.Generator().manual_seed(settings.seed * 100003 + step)
        index = torch.randint(0, N, (settings.batch,), generator=generator)
        batch = _crop({k: v[index] for k, v in data.items()}, settings.crop, generator)
        batch["image"] = jitter(batch["image"], generator)
        batch = {k: rank_share(v).to(device) for k, v in batch.items()}  # this process's share under torchrun
        losses = depth_losses(model, batch, batch.get("prior"))
        losses["loss"] = settings.w_depth * losses.pop("depth") + settings.w_mask * losses["mask_bce"]
        return losses

    curve = train(model, optimizer, step_fn, settings.steps, checkpoint=checkpoint,
                  checkpoint_every=settings.checkpoint_every, log_every=settings.log_every, scheduler=scheduler,
                  desc="train egodepth")
    return model.cpu().eval(), curve


@torch.no_grad()
def fit_report(model: DepthNet, views: Sequence[TrainingView], ray_maps: dict, self_masks: dict,
               prior_fn=None) -> dict:
    """How well the model fits its own training views (full images, no jitter): mean |log range
    error| over the supervised pixels for the network and for the constant training median, and
    the body-mask IoU."""
    data = _tensors(views, ray_maps, self_masks)
    net, constant, inter, union = [], [], 0, 0
    for i in range(0, len(views), 4):
        batch = {k: v[i:i + 4] for k, v in data.items()}
        prior = prior_fn(batch["image"]) if prior_fn is not None else None
        log_range, logit, _ = model(batch["image"], batch["rays"], prior, batch.get("stereo"))
        sup = batch["supervised"]
        net.append((log_range - batch["log_range"]).abs()[sup])
        constant.append((model.log_range_mean - batch["log_range"]).abs()[sup])
        body = (logit > 0) & batch["inside"]
        inter += int((body & sup).sum())
        union += int((body | sup).sum())
    return {"train_log_range_l1": float(torch.cat(net).mean()),
            "train_log_range_l1_constant_baseline": float(torch.cat(constant).mean()),
            "train_mask_iou": inter / max(union, 1)}


# -------------------------------------------------------------------------------- inference
@dataclass(frozen=True)
class PredictSettings:
    """``predict.*``; ``mask_threshold`` None: the model's own (chosen on its validation frames,
    :mod:`egorelight_cli.stages.egodepth_mask`), see :meth:`for_model`."""

    mask_threshold: float | None
    min_range_m: float
    max_range_m: float
    edge_relative_jump: float
    max_uncertainty: float

    @classmethod
    def from_config(cls, cfg) -> "PredictSettings":
        p = cfg.predict
        threshold = None if p.mask_threshold is None else float(p.mask_threshold)
        return cls(threshold, float(p.min_range_m), float(p.max_range_m), float(p.edge_relative_jump),
                   float(p.max_uncertainty))

    def for_model(self, model_threshold: float | None) -> "PredictSettings":
        """These settings with the body-mask threshold resolved: the configured one, else the
        model's (``model_threshold``), else :data:`DEFAULT_MASK_THRESHOLD` (a model trained
        without validation frames)."""
        if self.mask_threshold is not None:
            return self
        chosen = DEFAULT_MASK_THRESHOLD if model_threshold is None else float(model_threshold)
        return replace(self, mask_threshold=chosen)


def clean_range(range_map: np.ndarray, inside: np.ndarray, settings: PredictSettings) -> np.ndarray:
    """Zero out-of-bounds ranges and depth-discontinuity pixels of a (H,W) range map."""
    valid = inside & (range_map >= settings.min_range_m) & (range_map <= settings.max_range_m)
    if settings.edge_relative_jump > 0:
        valid &= ~depth_edges(range_map, valid, settings.edge_relative_jump)
    return np.where(valid, range_map, 0.0).astype(np.float32)


@torch.no_grad()
def network_maps(model: DepthNet, images: np.ndarray, rays: np.ndarray, device: torch.device, prior_fn=None,
                 stereo: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The network on N views: images (N,H,W,3) uint8, rays (N,H,W,3), stereo ranges (N,H,W) metres
    for a network with the stereo input -> range (N,H,W) metres, body probability (N,H,W) and the
    predicted Laplace scale of the log-range error (N,H,W) or None, all float32."""
    image = torch.from_numpy(images.astype(np.float32) / 255.0).permute(0, 3, 1, 2)
    ray = torch.from_numpy(rays.astype(np.float32)).permute(0, 3, 1, 2)
    prior = prior_fn(image).to(device) if prior_fn is not None else None
    stereo_maps = None
    if model.stereo_input:
        if stereo is None:
            raise EgorelightError("this egodepth network takes stereo ranges: none were given")
        stereo_maps = torch.from_numpy(stereo.astype(np.float32))[:, None].to(device)
    log_range, logit, log_scale = model(image.to(device), ray.to(device), prior, stereo_maps)
    scale = torch.exp(log_scale[:, 0]).cpu().numpy() if log_scale is not None else None
    return torch.exp(log_range[:, 0]).cpu().numpy(), torch.sigmoid(logit[:, 0]).cpu().numpy(), scale


def kept_range(range_map: np.ndarray, probability: np.ndarray, scale: np.ndarray | None, inside: np.ndarray,
               settings: PredictSettings, threshold: float) -> np.ndarray:
    """One view's (H,W) range map as inference keeps it: body probability above ``threshold``,
    predicted scale below ``settings.max_uncertainty`` (when it is on), ``inside`` (the lens minus
    the self-occlusion mask), then :func:`clean_range`; 0 = no depth."""
    keep = inside & (probability > threshold)
    if scale is not None and settings.max_uncertainty > 0:
        keep &= scale < settings.max_uncertainty
    return clean_range(range_map, keep, settings)


def predict_ranges_net(model: DepthNet, views: Sequence[EgoView], ray_maps: dict, self_masks: dict,
                       settings: PredictSettings, device: torch.device, prior_fn=None,
                       stereo: dict | None = None) -> dict[str, np.ndarray]:
    """Range maps (H,W) float32 (0 = none) of a frame's views, by role; ``stereo``: the frame's
    stereo range maps by role, for a network with the stereo input; ``settings`` with its mask
    threshold resolved (:meth:`PredictSettings.for_model`)."""
    if settings.mask_threshold is None:
        raise EgorelightError("egodepth: the body-mask threshold is unresolved (PredictSettings.for_model)")
    stereo_maps = np.stack([stereo[v.role] for v in views]) if stereo is not None else None
    ranges, probability, scale = network_maps(model, np.stack([v.image for v in views]),
                                              np.stack([ray_maps[v.role][0] for v in views]), device, prior_fn,
                                              stereo_maps)
    return {v.role: kept_range(ranges[i], probability[i], scale[i] if scale is not None else None,
                               ray_maps[v.role][1] & ~self_masks.get(v.role, False), settings,
                               settings.mask_threshold)
            for i, v in enumerate(views)}


class SGBMDepth:
    """SGBM on the rectified down-facing pair (the pair is fixed on the headset, so it is
    rectified once from the calibration's hand-eye transforms)."""

    def __init__(self, capture: Capture, calibration: Calibration, roles: Sequence[str], cfg):
        from egorelight_cli.geometry.fisheye_stereo import rectify_pair

        if len(roles) != 2:
            raise EgorelightError(f"sgbm needs exactly two ego cameras, got {', '.join(roles)}")
        self.roles = tuple(roles)
        left, right = (capture.ego_camera(r) for r in roles)
        for role in roles:
            if role not in calibration.ego_cameras:
                raise EgorelightError(f"calibration has no ego camera {role!r}", calibration.source)
        Pi_l, Pi_r = (calibration.ego_cameras[r].T_cam_from_hmd for r in roles)
        T_right_from_left = Pi_r @ invert_rigid(Pi_l)
        if T_right_from_left[0, 3] > 0:  # the reference must be the camera on the left of the baseline
            self.roles = self.roles[::-1]
            left, right = right, left
            T_right_from_left = invert_rigid(T_right_from_left)
        scale = float(cfg.sgbm.resolution_scale)
        self.cameras = {"left": left, "right": right}
        self.pair = rectify_pair(left, right, T_right_from_left, int(round(left.width * scale)),
                                 int(round(left.height * scale)), float(cfg.sgbm.fov_deg),
                                 float(cfg.sgbm.pitch_deg))
        self.min_depth = float(cfg.sgbm.min_depth_m)
        self.block = int(cfg.sgbm.block_size)

    def __call__(self, views: Sequence[EgoView], ray_maps: dict, settings: PredictSettings) -> dict[str, np.ndarray]:
        from egorelight_cli.geometry.fisheye_stereo import stereo_ranges

        by_role = {v.role: v for v in views}
        images = {"left": by_role[self.roles[0]].image, "right": by_role[self.roles[1]].image}
        ranges = stereo_ranges(self.pair, self.cameras, images, self.min_depth, self.block)
        return {self.roles[0]: clean_range(ranges["left"], ray_maps[self.roles[0]][1], settings),
                self.roles[1]: clean_range(ranges["right"], ray_maps[self.roles[1]][1], settings)}


# ------------------------------------------------------------------------------ point cloud
def frame_pointcloud(views: Sequence[EgoView], ranges: dict, ray_maps: dict, size: int, neighbours: int,
                     rng: np.random.Generator):
    """Unproject each view's range map through its posed camera, fuse, sample P, Hoppe normals.

    Returns points (P,3), normals (P,3) float32, valid (P,) bool, and the axial depth maps by role.
    """
    maps, masks, centres, depths = [], [], [], {}
    for v in views:
        depth = range_to_depth(ranges[v.role], ray_maps[v.role][0])
        depths[v.role] = depth
        points, valid = unproject_depth(v.camera, depth, rays=ray_maps[v.role])
        maps.append(points)
        masks.append(valid)
        centres.append(v.camera.centre_world)
    fused, seen_from = fuse_views(maps, masks, centres)
    points, normals, valid = fixed_size_cloud(fused, seen_from, size, neighbours, rng)
    return points, normals, valid, depths


# -------------------------------------------------------------------------------- evaluation
class GroundTruth:
    """The true body surface per frame (``groundtruth/<seq>/meshes.npz``, any topology), for
    scoring only, in the frame of ``calibration``'s head poses
    (:func:`~egorelight_cli.synth.groundtruth.T_pose_frame_from_truth_world`)."""

    def __init__(self, capture: Capture, calibration: Calibration, sequence: SequenceInfo, occluder_margin_m: float):
        from egorelight_cli.stages.animate_eval import groundtruth_meshes
        from egorelight_cli.synth.groundtruth import T_pose_frame_from_truth_world

        truth = groundtruth_meshes(capture, sequence.name)
        self.available = truth is not None
        self.sequence = sequence
        self.margin = occluder_margin_m
        if self.available:
            self.T_pose_frame_from_truth = T_pose_frame_from_truth_world(capture.groundtruth_root(), calibration,
                                                                         sequence.name)
            self.vertices = transform_points(self.T_pose_frame_from_truth, truth.vertices).astype(np.float32)
            self.faces, self.frame_ids = truth.faces, truth.frame_ids

    def has(self, frame_id: int) -> bool:
        return self.available and bool(np.any(self.frame_ids == frame_id))

    def frame(self, frame_id: int, views: Sequence[EgoView]):
        """(SurfaceDistance to the true mesh's outer surface (the points->true direction,
        :class:`~egorelight_cli.stages.animate_eval.OuterSurface`), {role: (true range (H,W),
        body mask (H,W))})."""
        from egorelight_cli.io.meshes import read_mesh
        from egorelight_cli.stages.animate_eval import OuterSurface

        i = int(np.nonzero(self.frame_ids == frame_id)[0][0])
        caster = RayCaster(self.vertices[i], self.faces)
        recon = None
        if self.sequence.recon_path(frame_id).exists():
            recon_vertices, recon_faces = read_mesh(self.sequence.recon_path(frame_id))
            recon = RayCaster(transform_points(self.T_pose_frame_from_truth, recon_vertices), recon_faces)
        maps = {}
        for v in views:
            truth = render_depth(v.camera, caster)
            mask = truth.hit
            if recon is not None:
                # The headset is not in the body mesh; where it hides the body the reconstruction
                # either shows its outer shell (nearer) or nothing/back faces (its inner side).
                seen = render_depth(v.camera, recon)
                mask &= seen.front_facing & (np.abs(seen.range - truth.range) < self.margin)
            maps[v.role] = (truth.range, mask)
        return OuterSurface(self.vertices[i], self.faces, caster=caster).distance, maps
