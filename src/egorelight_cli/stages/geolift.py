"""GeoLift (paper Sec. "Geometry Lifting"): the tracked mesh sequence -> UV normals and flat-lit texture.

Training (``train geolift``) uses the flat-lit frames of the relit training sequence, seen by the
studio cameras, with the tracked (student) meshes of those frames. The mesh is an input, not a
variable, so the differentiable renderer ``D(V, x)`` is a precomputed raster (which UV each pixel
sees) followed by a bilinear lookup of the predicted UV map (:func:`~egorelight_cli.nn.unet.sample_feature_map`).
Losses per view (``../shared/notes/appearance.md`` Sec. 1.2, text/supplement pairing):

* ``rgb``: L1 between the rendered texture ``D(V, a)`` and the flat-lit image;
* ``normal``: L1 between the rendered normals ``D(V, n)`` and the multi-view reconstruction's
  normals (``recon/``, the paper's NeuS2), world frame;
* ``detail``: the paper's perceptual loss (x80, VGG) against the screen-space normal estimates
  (``normals/``, the paper's Sapiens). Without VGG weights the substitute is an L1 between the
  *differences of neighbouring pixels* of the rendered and the estimated normals: it asks for the
  estimate's local structure (folds, edges) without enforcing its absolute values, which is what
  the paper uses the perceptual loss for. Weight ``train.weights.detail``;
* ``screen`` (ours, off by default): L1 between the rendered normals and the screen-space
  estimates themselves. Measured on the cpu demo it does not help: the estimates and the
  reconstruction are image-aligned, the tracked mesh slides along the surface by centimetres.

Baselines (what GeoLift must beat, paper Tab. 4 "w/o GeoLiftingNet"): the coarse normals of the
tracked mesh, and the mean texture (per texel, the mean of the flat-lit pixels that saw it over
all training views).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from egorelight_cli import console
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.io.capture import Capture, SequenceInfo, read_reconstructions
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.io.exr import read_exr
from egorelight_cli.io.images import read_image
from egorelight_cli.structures.mesh_sequence import MeshSequence
from egorelight_cli.nn.geolift_net import HISTORY, GeoLiftNet
from egorelight_cli.nn.distributed import rank_share
from egorelight_cli.nn.training import train
from egorelight_cli.nn.unet import sample_feature_map
from egorelight_cli.render.raster import UVRaster, rasterize, uv_to_texel_coords
from egorelight_cli.render.uv_features import texel_surface, texel_tangent_frames

MODEL_STAGE = "geolift"
LOSSES = ("rgb", "normal", "screen", "detail")


@dataclass(frozen=True)
class TrainSettings:
    """``train.*`` of ``stages/geolift.yaml``."""

    steps: int
    lr: float
    views_per_step: int
    weights: dict
    log_every: int
    seed: int
    checkpoint_every: int = 200

    @classmethod
    def from_config(cls, cfg: Config) -> "TrainSettings":
        t = cfg.train
        weights = {k: float(t.weights[k]) for k in LOSSES}
        # value ranges: the checks of stages/geolift.yaml
        return cls(int(t.steps), float(t.lr), int(t.views_per_step), weights, int(t.log_every), int(cfg.seed),
                   int(t.checkpoint_every))


# --------------------------------------------------------------------------------------------
# UV-space inputs
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CoarseMaps:
    """The tracked mesh sequence in UV space (0 off the layout).

    Attributes:
        normals: (T,3,H,W) float32 world-space coarse normals ``n̄``.
        frames: (T,6,H,W) float32 the UV tangent frame ``(t, b)`` around them (world space).
    """

    normals: np.ndarray
    frames: np.ndarray


def coarse_maps(raster: UVRaster, vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray) -> CoarseMaps:
    """:class:`CoarseMaps` of a mesh sequence (T,V,3) in the layout ``raster`` of ``face_uvs``."""
    normals = np.zeros((len(vertices), 3) + raster.resolution, np.float32)
    frames = np.zeros((len(vertices), 6) + raster.resolution, np.float32)
    for t, frame in enumerate(vertices):
        surface = texel_surface(raster, frame, faces)
        tangent, bitangent = texel_tangent_frames(raster, frame, faces, face_uvs, surface)
        normals[t] = np.moveaxis(surface.to_map(surface.normals.astype(np.float32)), -1, 0)
        frames[t] = np.moveaxis(surface.to_map(np.concatenate([tangent, bitangent], 1).astype(np.float32)), -1, 0)
    return CoarseMaps(normals, frames)


def stacked_input(normal_maps: np.ndarray, index: int, first: int = 0) -> np.ndarray:
    """(9,H,W) the coarse normals of frames ``index - 2, index - 1, index``, clamped at ``first``
    (the index of the sequence's first frame when several sequences are stacked)."""
    picks = [max(index - k, first) for k in reversed(range(HISTORY))]
    return np.concatenate([normal_maps[i] for i in picks], axis=0)


# --------------------------------------------------------------------------------------------
# Training views: what each (frame, studio camera) supervises
# --------------------------------------------------------------------------------------------


@dataclass
class TrainView:
    """The pixels of one (frame, camera) that see the tracked mesh inside the subject mask.

    Attributes:
        index: the frame's index in the (stacked) mesh sequences.
        uv: (P,2) float32 UV the tracked mesh shows at each pixel.
        colour: (P,3) float32 flat-lit image (linear radiance).
        recon_normal: (P,3) float32 world normal of the reconstruction; recon_valid (P,) bool.
        screen_normal: (P,3) float32 world normal estimate (``normals/``); screen_valid (P,) bool.
        right, down: (P,) int64 index of the right / lower neighbour pixel in this view, -1 if none.
        first: the index of its sequence's first frame (the temporal stack stops there).
    """

    index: int
    uv: np.ndarray
    colour: np.ndarray
    recon_normal: np.ndarray
    recon_valid: np.ndarray
    screen_normal: np.ndarray
    screen_valid: np.ndarray
    right: np.ndarray
    down: np.ndarray
    first: int = 0


def _neighbours(selected: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For a pixel mask (H,W): index of each selected pixel's right and lower selected neighbour, or -1."""
    index = np.full(selected.shape, -1, np.int64)
    index[selected] = np.arange(int(selected.sum()))
    right = np.full_like(index, -1)
    right[:, :-1] = index[:, 1:]
    down = np.full_like(index, -1)
    down[:-1] = index[1:]
    return right[selected], down[selected]


def _camera_to_world(normals_cam: np.ndarray, camera: Camera) -> np.ndarray:
    return normals_cam @ camera.T_cam_from_world[:3, :3]  # R^T n for row vectors


def build_views(capture: Capture, sequence: SequenceInfo, meshes: MeshSequence, faces: np.ndarray,
                face_uvs: np.ndarray, frame_ids: np.ndarray, cameras: list[str], offset: int = 0) -> list[TrainView]:
    """Training views of the mesh frames ``frame_ids`` seen by the studio ``cameras``; ``offset``
    is where this sequence's frames start in the stacked normal maps."""
    recon = read_reconstructions(sequence, frame_ids)
    views = []
    for frame_id in console.progress(frame_ids, total=len(frame_ids), desc="geolift views"):
        if int(frame_id) not in recon:
            continue
        index = meshes.index_of(int(frame_id))
        recon_vertices, recon_faces = recon[int(frame_id)]
        caster = RayCaster(meshes.vertices[index].astype(np.float64), faces)
        for name in cameras:
            camera = capture.studio_cameras[name]
            mesh = rasterize(meshes.vertices[index], faces, camera, face_uvs=face_uvs, caster=caster)
            mask_path = sequence.mask_path(name, int(frame_id))
            subject = read_image(mask_path)
            if subject.shape[:2] != (camera.height, camera.width):
                raise EgorelightError(f"mask is {subject.shape[1]}x{subject.shape[0]}, camera {name!r} is "
                                      f"{camera.width}x{camera.height}", mask_path)
            selected = mesh.mask & (subject.reshape(camera.height, camera.width, -1)[..., 0] > 127)
            if not selected.any():
                continue
            image = read_exr(sequence.studio_image_path(name, int(frame_id))).layer("", ("R", "G", "B"))
            truth = rasterize(recon_vertices, recon_faces, camera)
            screen_path = sequence.normals_path(name, int(frame_id))
            screen = read_exr(screen_path).layer("normal") if screen_path.is_file() else np.zeros_like(image)
            screen_world = _camera_to_world(screen[selected], camera)
            right, down = _neighbours(selected)
            views.append(TrainView(
                index=offset + index, first=offset, uv=mesh.uv[selected].astype(np.float32), colour=image[selected].astype(np.float32),
                recon_normal=truth.normal[selected].astype(np.float32), recon_valid=truth.mask[selected],
                screen_normal=screen_world.astype(np.float32),
                screen_valid=np.linalg.norm(screen_world, axis=1) > 0.5, right=right, down=down))
    if not views:
        raise EgorelightError(f"no flat-lit frame of sequence {sequence.name!r} has a reconstruction and a "
                              "studio view of the meshes", sequence.root)
    return views


def mean_texture(views: list[TrainView], resolution: tuple[int, int]) -> np.ndarray:
    """(3,H,W) per-texel mean of the flat-lit pixels that saw each texel (unseen texels: the global mean)."""
    height, width = resolution
    sums = np.zeros((height * width, 3))
    counts = np.zeros(height * width)
    for view in views:
        xy = np.rint(uv_to_texel_coords(view.uv, resolution)).astype(np.int64)
        texel = np.clip(xy[:, 1], 0, height - 1) * width + np.clip(xy[:, 0], 0, width - 1)
        np.add.at(sums, texel, view.colour)
        np.add.at(counts, texel, 1.0)
    overall = np.concatenate([v.colour for v in views]).mean(axis=0)
    texture = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], overall)
    return np.moveaxis(texture.reshape(height, width, 3), -1, 0).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Losses and training
# --------------------------------------------------------------------------------------------


def _masked_l1(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    weight = valid.to(a.dtype)[:, None]
    return ((a - b).abs() * weight).sum() / (3.0 * weight.sum()).clamp_min(1.0)


def detail_loss(predicted: torch.Tensor, estimate: torch.Tensor, valid: torch.Tensor,
                neighbours: list[torch.Tensor]) -> torch.Tensor:
    """L1 between neighbouring-pixel differences of predicted and estimated normals (P,3)."""
    terms = []
    for other in neighbours:
        pair = (other >= 0) & valid & valid[other.clamp_min(0)]
        if pair.any():
            j = other[pair]
            terms.append(((predicted[pair] - predicted[j]) - (estimate[pair] - estimate[j])).abs().mean())
    return torch.stack(terms).mean() if terms else predicted.sum() * 0.0


def view_losses(normals: torch.Tensor, texture: torch.Tensor, view: TrainView) -> dict[str, torch.Tensor]:
    """The four losses of one view from the predicted maps (1,3,H,W) each."""
    uv = torch.from_numpy(view.uv)
    sampled = sample_feature_map(torch.cat([normals, texture], dim=1), uv)[0]
    rendered_normal = F.normalize(sampled[:, :3], dim=1, eps=1e-6)
    rendered_colour = sampled[:, 3:]
    ones = torch.ones(len(uv), dtype=torch.bool)
    return {
        "rgb": _masked_l1(rendered_colour, torch.from_numpy(view.colour), ones),
        "normal": _masked_l1(rendered_normal, torch.from_numpy(view.recon_normal), torch.from_numpy(view.recon_valid)),
        "screen": _masked_l1(rendered_normal, torch.from_numpy(view.screen_normal), torch.from_numpy(view.screen_valid)),
        "detail": detail_loss(rendered_normal, torch.from_numpy(view.screen_normal),
                              torch.from_numpy(view.screen_valid),
                              [torch.from_numpy(view.right), torch.from_numpy(view.down)]),
    }


def network_inputs(normal_maps: np.ndarray, starts: np.ndarray | None = None) -> torch.Tensor:
    """(T,9,H,W) temporal stacks of every frame; ``starts`` (T,) each frame's sequence start (0)."""
    starts = np.zeros(len(normal_maps), np.int64) if starts is None else starts
    return torch.from_numpy(np.stack([stacked_input(normal_maps, i, int(starts[i])) for i in range(len(normal_maps))]))


def train_geolift(views: list[TrainView], coarse: CoarseMaps, starts: np.ndarray, settings: TrainSettings, net_cfg,
                  texture_init: np.ndarray, checkpoint=None) -> tuple[GeoLiftNet, list[dict]]:
    """Fit GeoLiftingNet to the views (CPU) given every frame's coarse maps and sequence start
    (``starts`` (T,), see :func:`network_inputs`); ``texture_init`` (3,H,W) starts the texture.
    Returns the network and its training curve."""
    torch.manual_seed(settings.seed)
    model = GeoLiftNet(int(net_cfg.base_channels), int(net_cfg.levels), int(net_cfg.uv_resolution), texture_init)
    optimizer = torch.optim.Adam(model.parameters(), lr=settings.lr)
    inputs = network_inputs(coarse.normals, starts)
    frames_all = torch.from_numpy(coarse.frames)

    def step(k: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng([settings.seed, k])
        batch = [views[i] for i in rng.choice(len(views), size=min(settings.views_per_step, len(views)),
                                               replace=False)]
        batch = rank_share(batch)  # this process's share under torchrun
        frames = sorted({v.index for v in batch})
        normals, texture = model(inputs[frames], frames_all[frames])
        totals = {name: torch.zeros(()) for name in settings.weights}
        for view in batch:
            b = frames.index(view.index)
            for name, value in view_losses(normals[b:b + 1], texture[b:b + 1], view).items():
                totals[name] = totals[name] + value / len(batch)
        loss = sum(settings.weights[name] * value for name, value in totals.items())
        return {"loss": loss, **totals}

    curve = train(model, optimizer, step, settings.steps, checkpoint=checkpoint,
                  checkpoint_every=settings.checkpoint_every, log_every=settings.log_every,
                  desc="train geolift")
    return model, curve


@torch.no_grad()
def predict_maps(model: GeoLiftNet, coarse: CoarseMaps, index: int, first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(normals (3,H,W), texture (3,H,W)) float32 for frame ``index`` (sequence starting at ``first``)."""
    normals, texture = model(torch.from_numpy(stacked_input(coarse.normals, index, first))[None],
                             torch.from_numpy(coarse.frames[index])[None])
    return normals[0].numpy(), texture[0].numpy()


def fit_report(model: GeoLiftNet, views: list[TrainView], coarse: CoarseMaps, texture: np.ndarray) -> dict:
    """Training-view errors of the network next to its baselines (coarse normals, mean texture)."""
    rows = {"rgb_l1": [], "rgb_l1_mean_texture": [], "normal_deg": [], "normal_deg_coarse": []}
    baseline_texture = torch.from_numpy(texture)[None]
    for view in views:
        normals, predicted = (torch.from_numpy(m)[None]
                              for m in predict_maps(model, coarse, view.index, view.first))
        coarse_normals = torch.from_numpy(coarse.normals[view.index])[None]
        uv = torch.from_numpy(view.uv)
        colour = torch.from_numpy(view.colour)
        rows["rgb_l1"].append(float((sample_feature_map(predicted, uv)[0] - colour).abs().mean()))
        rows["rgb_l1_mean_texture"].append(float((sample_feature_map(baseline_texture, uv)[0] - colour).abs().mean()))
        if view.recon_valid.any():
            truth = view.recon_normal[view.recon_valid]
            for key, maps in (("normal_deg", normals), ("normal_deg_coarse", coarse_normals)):
                sampled = F.normalize(sample_feature_map(maps, uv)[0], dim=1).numpy()[view.recon_valid]
                rows[key].append(float(angle_deg(sampled, truth).mean()))
    return {f"train_{k}": float(np.mean(v)) if v else None for k, v in rows.items()}


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) angle in degrees between unit vectors (N,3)."""
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))
