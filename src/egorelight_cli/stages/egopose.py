"""Egocentric pose estimation (paper Sec. "Egocentric Pose Estimator"): the stereo down-facing
fisheye images of the HMD and its head pose -> 57 world keypoints per frame.

The network is :class:`~egorelight_cli.nn.egopose_net.EgoPoseNet` (FRAME adapted). This module
holds what is around it, callable without the CLI:

* :func:`load_frames`: the two down-facing views of a sequence at the network's input size,
  their head poses (``H = T_world_from_hmd`` from the calibration; for ``wild`` without aligned
  poses, the capture's own tracker poses) and which frames are usable.
* :func:`train_egopose`: per-person training on an ``ego_train``-purpose sequence supervised by its
  markerless mocap (content frames only: the prefix is the sync flash code). Phase 1 fits the
  per-frame network with losses on the 2D heatmap positions (mocap projected into each view), the
  ranges, each view's 3D keypoints and the fused 3D keypoints; hand joints are re-weighted
  (``train.hand_weight``). Colour jitter in brightness, contrast, saturation and hue
  (``train.colour_jitter``) is the paper's key finding: it is what makes the estimator survive the
  unseen test lighting. A smooth random gain field per view (``train.jitter.shading``, not in the
  paper) re-shades the flat-lit training images as if lit from one side, and random texture replaces
  the lightstage dome behind the body (``train.augment.background``, not in the paper;
  :mod:`egorelight_cli.stages.egopose_augment`) so another room's floor is no surprise. Phase 2
  fits the temporal module on windows of the frozen per-frame estimates of several augmented copies
  of the training frames (plus noise). Both phases checkpoint and resume
  (:func:`egorelight_cli.nn.training.train`). The last ``train.validation_fraction`` of the frames
  (a contiguous block, so no near-duplicates of training frames) is held out: its first half fits,
  per joint, how much to trust the estimate over the training mean pose (``train.prior_blend``),
  its second half gives the validation MPJPE against the mocap, before and after the blend (never
  scored on the frames it was fit on). With ~30 training frames the network memorises the legs,
  which the down-facing cameras barely see behind the torso; the blend moves them towards the mean
  pose and keeps the hands.
* :func:`predict`: per-frame estimates, temporal refinement, confidences (agreement of the two
  views); frames whose head pose is flagged invalid get NaN and confidence 0, never invented.
* :func:`keypoint_metrics`: MPJPE (cm) of body (15) and hand (42) keypoints against ground truth.
* :func:`preview_image`: predicted (red) and ground-truth (green) keypoints drawn on the ego images.

Frame ids are studio (master-clock) ids; the ego image of frame ``f`` is ego frame
``f + stream_offset``. ``wild`` has no studio stream: ego ids, offset 0.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from egorelight_cli import console
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.sharding import evenly_spaced
from egorelight_cli.geometry.mpjpe import mpjpe_cm
from egorelight_cli.geometry.rotations import invert_rigid
from egorelight_cli.structures.calibration import Calibration, HeadPoses
from egorelight_cli.io.capture import Capture, SequenceInfo
from egorelight_cli.structures.keypoints import Keypoints
from egorelight_cli.stages.egopose_augment import jitter_images, keep_masks, occlude_and_noise, swap_background
from egorelight_cli.nn.egopose_net import (EgoPoseNet, RigGeometry, heading_frame, project_keypoints,
                                           range_log_init, transform, windows)
from egorelight_cli.structures.keypoints import BODY_SLICE, HANDS_SLICE, KEYPOINT_NAMES, NUM_KEYPOINTS

EGOPOSE_MODEL_TYPE = "egopose"
DOWN_ROLES = ("down_left", "down_right")


# ----------------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class EgoPoseSettings:
    """The resolved ``stages/egopose.yaml`` (see the comments there)."""

    cfg: Config

    @property
    def net(self) -> Config:
        return self.cfg.net

    @property
    def train(self) -> Config:
        return self.cfg.train

    def architecture(self) -> dict:
        net = self.net
        return {"num_joints": NUM_KEYPOINTS, "channels": int(net.channels), "levels": int(net.levels),
                "window": int(net.window), "temporal_hidden": int(net.temporal_hidden), "num_views": len(DOWN_ROLES),
                "tied": [list(pair) for pair in tied_keypoints()]}

    def joint_weights(self) -> torch.Tensor:
        """(J,) loss weight per keypoint: 1 for body, ``train.hand_weight`` for hand joints."""
        weights = torch.ones(NUM_KEYPOINTS)
        weights[HANDS_SLICE] = float(self.train.hand_weight)
        return weights / weights.mean()


def tied_keypoints() -> list[tuple[int, int]]:
    """Keypoint index pairs that are one point: each body wrist and its hand's wrist."""
    return [(KEYPOINT_NAMES.index(f"{side}Hand"), KEYPOINT_NAMES.index(f"{side}HandWrist")) for side in ("Left", "Right")]


def input_size(width: int, height: int, size: int) -> tuple[int, int]:
    """Network input (width, height): ``size`` wide, aspect kept, both multiples of 4."""
    w = max(4, int(size) // 4 * 4)
    h = max(4, int(round(size * height / width / 4)) * 4)
    return w, h


# -------------------------------------------------------------------------------------- frames
@dataclass
class EgoFrames:
    """The down-facing views of one sequence, as the network reads them.

    Attributes:
        sequence: sequence name.
        frame_ids: (T,) int64 master-clock ids (wild: ego ids).
        ego_ids: (T,) int64 ego frame ids.
        images: (T,V,3,h,w) uint8 tensor at the network input size.
        T_world_from_hmd: (T,4,4) float64 (identity where invalid).
        valid: (T,) bool head pose valid.
        content: (T,) bool after the sync prefix (wild: all).
        head_pose_source: ``calibration`` or ``tracker``.
        fps: frame rate of the sequence.
    """

    sequence: str
    frame_ids: np.ndarray
    ego_ids: np.ndarray
    images: torch.Tensor
    T_world_from_hmd: np.ndarray
    valid: np.ndarray
    content: np.ndarray
    head_pose_source: str = "calibration"
    fps: float | None = None

    @property
    def usable(self) -> np.ndarray:
        """Frames the temporal module may look at: valid head pose and content."""
        return self.valid & self.content

    def select(self, rows: np.ndarray) -> "EgoFrames":
        return EgoFrames(self.sequence, self.frame_ids[rows], self.ego_ids[rows], self.images[torch.as_tensor(rows)],
                         self.T_world_from_hmd[rows], self.valid[rows], self.content[rows], self.head_pose_source,
                         self.fps)


def check_down_cameras(capture: Capture, calibration: Calibration) -> None:
    """Both down-facing cameras must be fisheye, of one size, and hand-eye calibrated."""
    sizes = set()
    for role in DOWN_ROLES:
        camera = capture.ego_camera(role)
        if camera.model != "fisheye":
            raise EgorelightError(f"egopose expects fisheye down-facing cameras; {role} is {camera.model}",
                                  capture.root / "rig" / "hmd.json")
        sizes.add((camera.width, camera.height))
        if role not in calibration.ego_cameras:
            raise EgorelightError(f"calibration has no hand-eye transform for {role}", calibration.source)
    if len(sizes) != 1:
        raise EgorelightError(f"down-facing cameras differ in size: {sorted(sizes)}", capture.root / "rig" / "hmd.json")


def rig_geometry(capture: Capture, calibration: Calibration) -> RigGeometry:
    """The two down-facing views: intrinsics from the capture rig, hand-eye from calibration."""
    check_down_cameras(capture, calibration)
    cams = [capture.ego_camera(r) for r in DOWN_ROLES]
    dist = np.zeros((len(cams), 4))
    for i, cam in enumerate(cams):
        dist[i, :cam.dist.size] = cam.dist
    T_hmd_from_cam = np.stack([np.linalg.inv(calibration.ego_cameras[r].T_cam_from_hmd) for r in DOWN_ROLES])
    return RigGeometry(torch.tensor(np.stack([c.K for c in cams]), dtype=torch.float32),
                       torch.tensor(dist, dtype=torch.float32), cams[0].width, cams[0].height,
                       torch.tensor(T_hmd_from_cam, dtype=torch.float32))


def head_poses_for(capture: Capture, calibration: Calibration, info: SequenceInfo) -> tuple[HeadPoses, str]:
    """The sequence's head poses: the calibration's, else (sequences with a tracker stream,
    i.e. ``wild``) the capture's own ``head_pose.npz`` in the tracker's world frame."""
    if info.name in calibration.head_poses:
        return calibration.head_poses[info.name], "calibration"
    if info.streams.get("head_pose") and info.head_pose_path().is_file():
        from egorelight_cli.io.tracker import tracker_head_poses

        console.info(f"egopose: calibration has no head poses for {info.name!r}; using the capture's tracker poses")
        return tracker_head_poses(info), "tracker"
    raise EgorelightError(f"calibration has no head poses for sequence {info.name!r} "
                          f"(has {', '.join(sorted(calibration.head_poses)) or 'none'}); run calibrate on it",
                          calibration.source)


def frame_table(capture: Capture, calibration: Calibration, sequence: str, only_content: bool = False) -> EgoFrames:
    """The frames :func:`load_frames` reads (ids, head poses, flags), without their images
    (``images`` is an empty (T,0) tensor): cheap, for choosing shards and preview frames."""
    info = capture.sequence(sequence)
    info.require_stream("ego")
    missing = [r for r in DOWN_ROLES if r not in info.ego_roles]
    if missing:
        raise EgorelightError(f"sequence {sequence!r} has no {', '.join(missing)} ego stream", info.root / "sequence.json")
    if len(info.frame_ids):
        if sequence not in calibration.stream_offsets:
            raise EgorelightError(f"calibration has no stream offset for sequence {sequence!r}", calibration.source)
        ids = info.frame_ids
        offset = int(calibration.stream_offsets[sequence])
        content_ids = info.content_frame_ids
    else:
        ids, offset = info.ego_frame_ids, 0
        content_ids = info.content_frame_ids if len(info.content_frame_ids) else ids
    ego_ids = ids + offset
    keep = np.isin(ego_ids, info.ego_frame_ids)
    if only_content:
        keep &= np.isin(ids, content_ids)
    ids, ego_ids = ids[keep], ego_ids[keep]
    if len(ids) == 0:
        raise EgorelightError(f"sequence {sequence!r} has no frames with ego images", info.root / "sequence.json")
    poses, source = head_poses_for(capture, calibration, info)
    lookup = {int(f): i for i, f in enumerate(poses.frame_ids)}
    T = np.tile(np.eye(4), (len(ids), 1, 1))
    valid = np.zeros(len(ids), bool)
    for row, frame in enumerate(ids):
        i = lookup.get(int(frame))
        if i is not None and poses.valid[i]:
            T[row], valid[row] = poses.T_world_from_hmd[i], True
    if not valid.any():  # every keypoint would be NaN: the trouble is upstream, say so here
        raise EgorelightError(f"no frame of sequence {sequence!r} with ego images has a valid head pose ({source})",
                              calibration.source if source == "calibration" else info.head_pose_path())
    fps = float(info.doc["fps"]) if info.doc.get("fps") else None
    return EgoFrames(sequence, ids, ego_ids, torch.empty((len(ids), 0), dtype=torch.uint8), T, valid,
                     np.isin(ids, content_ids), source, fps)


def load_frames(capture: Capture, calibration: Calibration, sequence: str, size: int,
                only_content: bool = False, rows: slice | None = None) -> EgoFrames:
    """Read the down-facing views of ``sequence`` at input width ``size`` (see :class:`EgoFrames`).

    Frames without an ego image of either view are left out; ``only_content`` keeps only the
    frames after the sync prefix; ``rows`` reads only those rows of :func:`frame_table`."""
    table = frame_table(capture, calibration, sequence, only_content)
    if rows is not None:
        table = table.select(np.arange(len(table.frame_ids))[rows])
    info = capture.sequence(sequence)
    camera = capture.ego_camera(DOWN_ROLES[0])
    w, h = input_size(camera.width, camera.height, size)
    images = np.empty((len(table.frame_ids), len(DOWN_ROLES), 3, h, w), np.uint8)
    for row, ego in enumerate(table.ego_ids):
        for v, role in enumerate(DOWN_ROLES):
            image = info.read_ego_image(role, int(ego))
            images[row, v] = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA).transpose(2, 0, 1)
    return dataclasses.replace(table, images=torch.from_numpy(images))


def as_float_images(images: torch.Tensor) -> torch.Tensor:
    return images.to(torch.float32) / 255.0


# ------------------------------------------------------------------------------------ training
@dataclass
class Targets:
    """Mocap supervision of N training frames (rows of the training :class:`EgoFrames`).

    ``world`` (N,J,3), ``hmd`` (N,J,3), ``confidence`` (N,J), per view ``pixels`` (N,V,J,2) (0 where
    a keypoint does not project), ``inside`` (N,V,J) bool, ``ranges`` (N,V,J) metres and
    ``projects`` (N,V,J) bool (the keypoint has a pixel, in the image or not).
    """

    world: torch.Tensor
    hmd: torch.Tensor
    confidence: torch.Tensor
    pixels: torch.Tensor
    inside: torch.Tensor
    ranges: torch.Tensor
    projects: torch.Tensor


def make_targets(frames: EgoFrames, mocap: Keypoints, rig: RigGeometry) -> Targets:
    """Mocap keypoints of the frames into the HMD frame and each view (projection + range)."""
    rows = np.searchsorted(mocap.frame_ids, frames.frame_ids)
    rows = np.clip(rows, 0, len(mocap.frame_ids) - 1)
    if not np.array_equal(mocap.frame_ids[rows], frames.frame_ids):
        raise EgorelightError("mocap lacks some training frames")
    world = torch.tensor(np.nan_to_num(mocap.xyz[rows]), dtype=torch.float32)
    conf = torch.tensor(mocap.confidence[rows], dtype=torch.float32)
    T_hmd_from_world = invert_rigid(torch.tensor(frames.T_world_from_hmd, dtype=torch.float32))
    hmd = transform(T_hmd_from_world, world)
    cam = transform(rig.T_cam_from_hmd[None], hmd[:, None].expand(-1, rig.K.shape[0], -1, -1))
    pixels, inside = project_keypoints(cam, rig)
    inside = inside & (conf[:, None] > 0)
    return Targets(world, hmd, conf, torch.nan_to_num(pixels), inside, torch.linalg.vector_norm(cam, dim=-1),
                   torch.isfinite(pixels).all(-1))


def frame_losses(out: dict[str, torch.Tensor], target: Targets, rows: torch.Tensor, rig: RigGeometry,
                 joint_weights: torch.Tensor, weights: Config) -> dict[str, torch.Tensor]:
    """Phase-1 losses (2D heatmap position, log range, per-view 3D, fused 3D) of a batch."""
    conf = target.confidence[rows] * joint_weights  # (B,J)
    norm = conf.sum().clamp_min(1e-6)
    inside = target.inside[rows].to(conf.dtype) * conf[:, None]
    pix = (out["pixels"] - target.pixels[rows]).abs().sum(-1) / max(rig.width, rig.height)
    heat = (pix * inside).sum() / inside.sum().clamp_min(1e-6)
    rng = ((out["ranges"].log() - target.ranges[rows].log()).abs() * conf[:, None]).sum() / (norm * out["ranges"].shape[1])
    view = (torch.linalg.vector_norm(out["points_hmd"] - target.hmd[rows][:, None], dim=-1) * conf[:, None]).sum() \
        / (norm * out["ranges"].shape[1])
    fused = (torch.linalg.vector_norm(out["fused_hmd"] - target.hmd[rows], dim=-1) * conf).sum() / norm
    loss = (float(weights.heatmap) * heat + float(weights.range) * rng + float(weights.view3d) * view
            + float(weights.fused3d) * fused)
    return {"loss": loss, "heatmap_px_frac": heat.detach(), "log_range": rng.detach(), "view3d_m": view.detach(),
            "fused3d_m": fused.detach()}


@dataclass
class TrainResult:
    """A trained network and what describes it."""

    net: EgoPoseNet
    curve: list[dict] = field(default_factory=list)
    mean_pose_heading: np.ndarray | None = None  # (J,3) training mean pose in the heading frame
    info: dict = field(default_factory=dict)
    frame_ids: np.ndarray | None = None  # the frames trained on (held-out ones excluded)


def train_egopose(frames: EgoFrames, mocap: Keypoints, rig: RigGeometry, settings: EgoPoseSettings,
                  checkpoint_dir=None, backbone_state: dict | None = None) -> TrainResult:
    """Train on the usable content frames of ``frames`` (see the module docstring)."""
    from egorelight_cli.nn.egopose_net import load_backbone_weights
    from egorelight_cli.nn.distributed import rank_share
    from egorelight_cli.nn.training import train

    train_cfg = settings.train
    seed = int(settings.cfg.seed) if "seed" in settings.cfg else 0
    torch.manual_seed(seed)
    rows = np.nonzero(frames.usable & np.isin(frames.frame_ids, mocap.frame_ids))[0]
    if len(rows) == 0:
        raise EgorelightError(f"no training frames: sequence {frames.sequence!r} has no content frame with a valid "
                              "head pose, both ego views and mocap")
    held_out = validation_count(len(rows), float(train_cfg.validation_fraction), int(train_cfg.min_validation_frames))
    val_rows, rows = rows[len(rows) - held_out:], rows[:len(rows) - held_out]
    rows = evenly_spaced(rows, int(train_cfg.max_frames))
    data = frames.select(rows)
    target = make_targets(data, mocap, rig)
    net = EgoPoseNet(**settings.architecture())
    net.log_range0.copy_(range_log_init(target.ranges, target.confidence[:, None].expand_as(target.ranges) > 0))
    info: dict = {"training_frames": int(len(rows)), "validation_frames": int(held_out),
                  "colour_jitter": bool(train_cfg.colour_jitter)}
    if backbone_state is not None:
        info["backbone_tensors_loaded"] = load_backbone_weights(net, backbone_state)
        if info["backbone_tensors_loaded"] == 0:
            raise EgorelightError("--backbone-weights holds no tensor that fits the egopose encoder")
    joint_weights = settings.joint_weights()
    images = as_float_images(data.images)
    keep = keep_masks(target, tuple(data.images.shape[-2:]), rig, settings)
    jitter_on = bool(train_cfg.colour_jitter)
    batch = int(train_cfg.batch)  # drawn with replacement; not clamped, so it stays divisible among torchrun ranks
    steps = int(train_cfg.steps)
    lr = float(train_cfg.lr)

    def step_fn(step: int) -> dict[str, torch.Tensor]:
        for group in optimizer.param_groups:  # step-decay schedule as a function of the step: exact on resume
            group["lr"] = lr * (0.3 ** ((step >= 0.7 * steps) + (step >= 0.9 * steps)))
        g = torch.Generator().manual_seed(seed * 1_000_003 + step)
        pick = torch.randint(len(rows), (batch,), generator=g)
        x = swap_background(images[pick], None if keep is None else keep[pick], settings, g)
        x = occlude_and_noise(jitter_images(x, settings, g, jitter_on), settings, g)
        x, pick = rank_share(x), rank_share(pick)  # this process's share of the batch (all of it without torchrun)
        return frame_losses(net.forward_frames(x, rig), target, pick, rig, joint_weights, train_cfg.weights)

    optimizer = torch.optim.Adam(net.parameters(), lr=lr)
    ckpt = None if checkpoint_dir is None else checkpoint_dir / "frame.pt"
    curve = train(net, optimizer, step_fn, steps, checkpoint=ckpt, checkpoint_every=int(train_cfg.checkpoint_every),
                  log_every=int(train_cfg.log_every), desc="egopose per-frame")
    curve += _train_temporal(net, images, keep, data, target, rig, settings, joint_weights, seed, checkpoint_dir,
                             steps)
    net.eval()
    mean_pose = to_heading(target.world, data.T_world_from_hmd, target.confidence)
    net.prior_heading.copy_(torch.as_tensor(mean_pose))
    if held_out:
        info.update(_validate(net, frames.select(val_rows), mocap, rig, settings, mean_pose))
    return TrainResult(net, curve, mean_pose, info, data.frame_ids)


def validation_count(num_frames: int, fraction: float, minimum: int) -> int:
    """Frames held out at the end of the training sequence: ``fraction`` of them, at least
    ``minimum``, and none when fewer than ``3 * minimum`` frames exist."""
    if fraction <= 0 or num_frames < 3 * minimum:
        return 0
    return max(int(round(fraction * num_frames)), minimum)


def to_heading(world: torch.Tensor, T_world_from_hmd: np.ndarray, confidence: torch.Tensor | None = None) -> np.ndarray:
    """(J,3) confidence-weighted mean over frames of (N,J,3) world keypoints, each frame moved
    into its heading frame."""
    T_heading = heading_frame(torch.tensor(T_world_from_hmd, dtype=torch.float32))
    local = transform(invert_rigid(T_heading), world.to(torch.float32))
    w = (torch.ones(local.shape[:2]) if confidence is None else confidence)[..., None]
    return ((local * w).sum(0) / w.sum(0).clamp_min(1e-6)).numpy()


def fit_prior_blend(pred: np.ndarray, truth: np.ndarray, prior: np.ndarray, T_world_from_hmd: np.ndarray) -> np.ndarray:
    """(J,) least-squares blend ``a`` in [0,1] of ``a * pred + (1 - a) * prior`` against ``truth``
    (pred, truth (N,J,3) world; prior (J,3) heading frame) on held-out frames."""
    T_from_world = invert_rigid(heading_frame(torch.tensor(T_world_from_hmd, dtype=torch.float32)))
    p = transform(T_from_world, torch.tensor(pred, dtype=torch.float32)).numpy() - prior
    t = transform(T_from_world, torch.tensor(truth, dtype=torch.float32)).numpy() - prior
    num = np.nansum((p * t).sum(-1), axis=0)
    den = np.nansum((p * p).sum(-1), axis=0)
    return np.clip(num / np.maximum(den, 1e-12), 0.0, 1.0).astype(np.float32)


def blend_split(num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(fit rows, report rows) of the held-out frames: the pose-prior blend is fitted on the first
    half and scored on the second (contiguous halves), never on the frames it was fitted to."""
    half = num_frames // 2
    return np.arange(half), np.arange(half, num_frames)


def _validate(net: EgoPoseNet, frames: EgoFrames, mocap: Keypoints, rig: RigGeometry, settings: EgoPoseSettings,
              mean_pose: np.ndarray) -> dict:
    """MPJPE (cm) vs the mocap on the held-out frames. With ``train.prior_blend`` the blend is
    fitted on the first half of them (:func:`blend_split`) and every ``validation_*`` metric,
    before and after the blend, is reported on the second half."""
    sigma = float(settings.cfg.confidence_sigma_m)
    fit_rows, report_rows = blend_split(len(frames.frame_ids)) if bool(settings.train.prior_blend) else \
        (np.arange(0), np.arange(len(frames.frame_ids)))
    report = frames.select(report_rows)
    before = predict(net, report, rig, sigma)
    metrics = keypoint_metrics(before.keypoints.xyz, report.frame_ids, mocap, report.usable, "validation_")
    base = keypoint_metrics(mean_pose_keypoints(mean_pose, report), report.frame_ids, mocap, report.usable,
                            "validation_mean_pose_")
    metrics.update({k: v for k, v in base.items() if not k.endswith("scored_frames")})
    if len(fit_rows):
        fit = frames.select(fit_rows)
        truth = mocap.xyz[np.searchsorted(mocap.frame_ids, fit.frame_ids)]
        blend = fit_prior_blend(predict(net, fit, rig, sigma).keypoints.xyz, truth, mean_pose, fit.T_world_from_hmd)
        net.prior_blend.copy_(torch.as_tensor(blend))
        after = predict(net, report, rig, sigma)
        blended = keypoint_metrics(after.keypoints.xyz, report.frame_ids, mocap, report.usable, "validation_blended_")
        metrics.update({k: v for k, v in blended.items() if not k.endswith("scored_frames")})
        metrics.update({"prior_blend_body_mean": round(float(blend[BODY_SLICE].mean()), 3),
                        "prior_blend_hands_mean": round(float(blend[HANDS_SLICE].mean()), 3),
                        "prior_blend_fit_frames": int(len(fit_rows))})
    return metrics


def _train_temporal(net: EgoPoseNet, images: torch.Tensor, keep: torch.Tensor | None, data: EgoFrames,
                    target: Targets, rig: RigGeometry,
                    settings: EgoPoseSettings, joint_weights: torch.Tensor, seed: int, checkpoint_dir,
                    step_offset: int) -> list[dict]:
    """Phase 2: the temporal module on windows of frozen per-frame estimates (augmented copies, the
    first one plain)."""
    from egorelight_cli.nn.distributed import rank_share
    from egorelight_cli.nn.training import train

    cfg = settings.train.temporal
    steps = int(cfg.steps)
    if net.window <= 1 or steps <= 0:
        return []
    net.eval()
    copies = []
    H = torch.tensor(data.T_world_from_hmd, dtype=torch.float32)
    with torch.no_grad():
        for copy in range(max(int(cfg.copies), 1)):
            g = torch.Generator().manual_seed(seed * 7919 + copy)
            fused = []
            for start in range(0, len(images), 8):
                x = images[start:start + 8]
                if copy > 0:
                    x = swap_background(x, None if keep is None else keep[start:start + 8], settings, g)
                x = jitter_images(x, settings, g, bool(settings.train.colour_jitter) and copy > 0)
                fused.append(net.forward_frames(x, rig)["fused_hmd"])
            copies.append(transform(H, torch.cat(fused)))
    cached = torch.stack(copies)  # (C,N,J,3) world
    idx = windows(len(images), net.window)  # training rows are consecutive usable frames
    noise = float(cfg.noise_m)
    batch = int(settings.train.batch) * 4  # drawn with replacement, like the per-frame phase's

    def step_fn(step: int) -> dict[str, torch.Tensor]:
        g = torch.Generator().manual_seed(seed * 15485863 + step)
        pick = torch.randint(len(images), (batch,), generator=g)
        which = torch.randint(cached.shape[0], (batch, net.window), generator=g)
        win = cached[which, idx[pick]]  # (B,W,J,3)
        win = win + noise * torch.randn(win.shape, generator=g)
        win, pick = rank_share(win), rank_share(pick)
        pred = net.refine(win, H[pick])
        conf = target.confidence[pick] * joint_weights
        err = (torch.linalg.vector_norm(pred - target.world[pick], dim=-1) * conf).sum() / conf.sum().clamp_min(1e-6)
        return {"loss": err}  # metres (weighted), logged as temporal_loss

    optimizer = torch.optim.Adam(net.temporal.parameters(), lr=float(cfg.lr))
    ckpt = None if checkpoint_dir is None else checkpoint_dir / "temporal.pt"
    curve = train(net.temporal, optimizer, step_fn, steps, checkpoint=ckpt,
                  checkpoint_every=int(settings.train.checkpoint_every), log_every=int(settings.train.log_every),
                  desc="egopose temporal")
    return [{"step": row["step"] + step_offset, **{f"temporal_{k}" if k == "loss" else k: v
                                                  for k, v in row.items() if k != "step"}} for row in curve]


# ---------------------------------------------------------------------------------- prediction
@dataclass
class Prediction:
    """Estimates of one sequence.

    ``keypoints``: the output (world, confidence, frame ids); ``per_frame`` (T,J,3) fused world
    keypoints before the temporal module (NaN where invalid); ``pixels`` (T,V,J,2) soft-argmax
    positions in the original images.
    """

    keypoints: Keypoints
    per_frame: np.ndarray
    pixels: np.ndarray

    def select(self, rows: np.ndarray) -> "Prediction":
        k = self.keypoints
        return Prediction(Keypoints(k.xyz[rows], k.confidence[rows], k.frame_ids[rows], k.names, k.fps),
                          self.per_frame[rows], self.pixels[rows])


def predict(net: EgoPoseNet, frames: EgoFrames, rig: RigGeometry, confidence_sigma_m: float,
            batch: int = 1) -> Prediction:
    """Keypoints for every frame of ``frames`` (see the module docstring). ``batch`` frames per
    forward pass; the default, one, makes a frame's estimate independent of its neighbours in the
    batch (the float rounding of batched convolutions differs with the batch), so that frame
    shards reproduce a single run byte for byte."""
    net.eval()
    H = torch.tensor(frames.T_world_from_hmd, dtype=torch.float32)
    fused, disagreement, pixels = [], [], []
    with torch.no_grad():
        for start in range(0, len(frames.frame_ids), batch):
            out = net.forward_frames(as_float_images(frames.images[start:start + batch]), rig)
            fused.append(out["fused_hmd"])
            disagreement.append(out["disagreement"])
            pixels.append(out["pixels"])
        fused_world = transform(H, torch.cat(fused))
        usable = torch.as_tensor(frames.usable)
        idx = windows(len(frames.frame_ids), net.window, usable)
        # one frame per call: a frame's output then does not depend on which frames share its batch
        # (float rounding of batched matmuls), so frame shards merge into the single run's bytes
        refined = torch.cat([net.refine(fused_world[idx[t:t + 1]], H[t:t + 1]) for t in range(len(idx))])
    spread = torch.cat(disagreement)
    confidence = torch.exp(-0.5 * (spread / confidence_sigma_m) ** 2).clamp(1e-3, 1.0).numpy()
    xyz = refined.numpy().astype(np.float32)
    per_frame = fused_world.numpy().astype(np.float32)
    invalid = ~frames.valid
    xyz[invalid], per_frame[invalid], confidence[invalid] = np.nan, np.nan, 0.0
    keypoints = Keypoints(xyz, confidence, frames.frame_ids, KEYPOINT_NAMES, frames.fps)
    return Prediction(keypoints, per_frame, torch.cat(pixels).numpy())


def mean_pose_keypoints(mean_pose_heading: np.ndarray, frames: EgoFrames) -> np.ndarray:
    """(T,J,3) world keypoints of the training mean pose placed at each frame's heading frame
    (the baseline a trained estimator must beat; NaN where the head pose is invalid)."""
    T_heading = heading_frame(torch.tensor(frames.T_world_from_hmd, dtype=torch.float32))
    xyz = transform(T_heading, torch.tensor(mean_pose_heading, dtype=torch.float32)[None]
                    .expand(len(frames.frame_ids), -1, -1)).numpy()
    xyz[~frames.valid] = np.nan
    return xyz


# ------------------------------------------------------------------------------------- metrics
def keypoint_metrics(pred: np.ndarray, frame_ids: np.ndarray, truth: Keypoints, rows_mask: np.ndarray,
                     prefix: str = "") -> dict[str, float]:
    """MPJPE (cm) of body, hands and all keypoints on frames ``rows_mask`` (T,) of ``pred``
    (T,J,3) that the ground truth ``truth`` also holds."""
    common, pred_rows, truth_rows = np.intersect1d(frame_ids, truth.frame_ids, return_indices=True)
    keep = rows_mask[pred_rows]
    p, t = pred[pred_rows[keep]], truth.xyz[truth_rows[keep]]
    metrics = {f"{prefix}mpjpe_body_cm": mpjpe_cm(p[:, BODY_SLICE], t[:, BODY_SLICE]),
               f"{prefix}mpjpe_hands_cm": mpjpe_cm(p[:, HANDS_SLICE], t[:, HANDS_SLICE]),
               f"{prefix}mpjpe_all_cm": mpjpe_cm(p, t)}
    metrics[f"{prefix}scored_frames"] = int(np.isfinite(p).all(axis=(1, 2)).sum()) if len(p) else 0
    return {k: (round(v, 3) if isinstance(v, float) and np.isfinite(v) else v) for k, v in metrics.items()}


def groundtruth_keypoints(capture: Capture, sequence: str, calibration: Calibration) -> Keypoints | None:
    """``groundtruth/<seq>/keypoints.npz`` of a simulated capture (evaluation only), in the frame
    of ``calibration``'s head poses of ``sequence``
    (:func:`~egorelight_cli.synth.groundtruth.T_pose_frame_from_truth_world`), else None."""
    from egorelight_cli.geometry.cameras import transform_points
    from egorelight_cli.io.keypoints import read_keypoints_npz
    from egorelight_cli.synth.groundtruth import T_pose_frame_from_truth_world

    path = capture.groundtruth_file(sequence, "keypoints.npz")
    if path is None:
        return None
    truth = read_keypoints_npz(path)
    T = T_pose_frame_from_truth_world(capture.groundtruth_root(), calibration, sequence)
    return truth if np.array_equal(T, np.eye(4)) else dataclasses.replace(truth, xyz=transform_points(T, truth.xyz))


def evaluate(prediction: Prediction, frames: EgoFrames, truth: Keypoints, mean_pose_heading: np.ndarray | None,
             prefix: str = "") -> dict:
    """Output, per-frame (no temporal module) and mean-pose-baseline MPJPE on usable frames."""
    rows = frames.usable
    ids = frames.frame_ids
    metrics = keypoint_metrics(prediction.keypoints.xyz, ids, truth, rows, prefix)
    per_frame = keypoint_metrics(prediction.per_frame, ids, truth, rows, prefix + "per_frame_")
    metrics.update({k: v for k, v in per_frame.items() if not k.endswith("scored_frames")})
    if mean_pose_heading is not None:
        base = keypoint_metrics(mean_pose_keypoints(mean_pose_heading, frames), ids, truth, rows, prefix + "mean_pose_")
        metrics.update({k: v for k, v in base.items() if not k.endswith("scored_frames")})
    return metrics
