"""Depth-conditioned animatable avatar (paper Sec. "Depth-conditioned Animatable Avatar" and the
supplement's "Details about Depth-conditioned Animatable Avatar").

From skeleton motion ``theta`` and the egocentric point cloud ``z``, AnimationNet regresses the
embedded-graph rotations/translations ``alpha, beta`` and per-vertex offsets ``o``; the
character model poses them with DQS: ``V = W(E(V_bar, alpha, beta, o), K(theta))``.

Per frame t the network input is a UV map (``uv_resolution`` square) with channels

* rest position (3) and rest normal (3) of the template (constant);
* ``Theta``: positions and normals of the skinned template at t and t-1 in the root frame of t (12);
* ``xi / eps_d`` (3) and the ``xi`` mask (1): the depth encoding (zero without depth).

With ``net.depth_skip`` (ours) the sampled ``xi`` channels are also added to the offsets with
a learned gain, and with ``net.depth_node_skip`` (ours) their mean over the observed texels
around each graph node to its translation with another (see :mod:`egorelight_cli.nn.animation_net`).

Training (``train animate``) minimises the supplement's loss against the multi-view
reconstruction of each frame::

    w_eg chamf(V_EG, recon) + w_delta chamf(V_Delta, recon) + w_arap ARAP(graph)
        + w_spatial smooth(o) + w_iso iso(o)

with normal-filtered Chamfer pairs (:mod:`egorelight_cli.nn.mesh_losses`). ``xi`` is dropped
(set to zero) for a random ``depth_dropout`` fraction of the samples, so one network also
works without depth (the ``--no-depth`` ablation); the paper's depth-agnostic student is the
same network fine-tuned with ``xi = 0`` on the flat-lit frames of ``relight_train``
(``train animate --no-depth --init MODEL``). With ``train.validation_frames`` (ours) frames are set
aside and the model keeps the weights that score best on them (model selection; the paper trains a
fixed schedule).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial

import numpy as np
import torch
from scipy.spatial import cKDTree

from egorelight_cli import console
from egorelight_cli.config import Config, setting, settings_from_config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.depth_encoding import SkinnedTemplate, encode_depth, skinned_template
from egorelight_cli.geometry.embedded_graph import embedded_deformation, mesh_edges, node_positions, pose_through_graph
from egorelight_cli.geometry.normals import vertex_normals
from egorelight_cli.geometry.skeleton import bone_transforms
from egorelight_cli.geometry.uv_signals import UVLayout, canonical_signal, motion_signal, root_transforms
from egorelight_cli.structures.mesh_sequence import MeshSequence
from egorelight_cli.nn.animation_net import AnimationNet
from egorelight_cli.nn.mesh_losses import filtered_chamfer, graph_arap, offset_isometry, offset_smoothness
from egorelight_cli.structures.character import Character

ANIMATE_MODEL_TYPE = "animate"
#: UV input channels: rest (6) + Theta (12) + xi (3) + xi mask (1).
IN_CHANNELS = 22
XI_CHANNELS = slice(18, 22)


# ------------------------------------------------------------------------------ settings
_net = partial(setting, "animate")  # every default lives in stages/animate.yaml


@dataclass(frozen=True)
class NetSettings:
    """Architecture (``net.*``; stored in the model artifact)."""

    uv_resolution: int = _net("net.uv_resolution")
    base_channels: int = _net("net.base_channels")
    levels: int = _net("net.levels")
    node_level_downsample: int = _net("net.node_level_downsample")
    hidden: int = _net("net.hidden")
    rotation_scale: float = _net("net.rotation_scale")
    translation_scale: float = _net("net.translation_scale")
    offset_scale: float = _net("net.offset_scale")
    depth_skip: bool = _net("net.depth_skip")
    depth_node_skip: bool = _net("net.depth_node_skip")

    @classmethod
    def from_config(cls, cfg: Config) -> "NetSettings":
        return settings_from_config(cls, cfg)

    @classmethod
    def from_architecture(cls, architecture: dict) -> "NetSettings":
        """The settings a model artifact stored (models written before the node skip have none)."""
        return cls(**{"depth_node_skip": False, **architecture})

    def build_net(self) -> AnimationNet:
        """A fresh AnimationNet of this architecture."""
        skip = (XI_CHANNELS.start, XI_CHANNELS.start + 3) if self.depth_skip else None
        node_skip = XI_CHANNELS.start + 3 if self.depth_skip and self.depth_node_skip else None
        return AnimationNet(IN_CHANNELS, self.base_channels, self.levels, self.node_level_downsample, self.hidden,
                            self.rotation_scale, self.translation_scale, self.offset_scale, skip, node_skip)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class DepthSettings:
    """Depth encoding thresholds (``depth.*``)."""

    eps_d: float = _net("depth.eps_d")
    eps_n: float = _net("depth.eps_n")

    @classmethod
    def from_config(cls, cfg: Config) -> "DepthSettings":
        return settings_from_config(cls, cfg)


@dataclass(frozen=True)
class TrainSettings:
    """``train.*``."""

    steps: int = _net("train.steps")
    finetune_steps: int | None = _net("train.finetune_steps")
    validation_frames: int = _net("train.validation_frames")
    validate_every: int = _net("train.validate_every")
    batch: int = _net("train.batch")
    lr: float = _net("train.lr")
    depth_dropout: float = _net("train.depth_dropout")
    target_points: int = _net("train.target_points")
    weights: dict = _net("train.weights")
    min_normal_dot: float = _net("train.min_normal_dot")
    max_distance: float = _net("train.max_distance")
    point_to_plane: bool = _net("train.point_to_plane")
    log_every: int = _net("train.log_every")
    seed: int = _net("seed", 0)

    @classmethod
    def from_config(cls, cfg: Config) -> "TrainSettings":
        return settings_from_config(cls, cfg)

    def starting_from_a_model(self) -> "TrainSettings":
        """These settings for a run that starts from a trained model (``--init``): ``finetune_steps``
        steps when set, else ``steps``."""
        if self.finetune_steps is None:
            return self
        return replace(self, steps=int(self.finetune_steps))


# ---------------------------------------------------------------------------- the model
class AnimationModel:
    """AnimationNet bound to a character: UV inputs from motion + clouds, and posing."""

    def __init__(self, character: Character, net_settings: NetSettings, depth: DepthSettings,
                 net: AnimationNet | None = None, device: torch.device | str = "cpu"):
        self.character = character
        self.settings = net_settings
        self.depth = depth
        self.device = torch.device(device)
        self.layout = UVLayout.build(character, net_settings.uv_resolution)
        self.net = (net or net_settings.build_net()).to(self.device)
        self.node_uv = torch.as_tensor(self.layout.node_uv, device=self.device)
        self.vertex_uv = torch.as_tensor(self.layout.vertex_uv, device=self.device)
        self.rest = torch.as_tensor(character.vertices, dtype=torch.float32, device=self.device)
        self.canonical_uv = self.layout.to_uv(canonical_signal(character))  # (6,R,R)
        self.mesh_edges = torch.as_tensor(mesh_edges(character.faces), device=self.device)
        self.graph_edges = torch.as_tensor(character.graph.edges, device=self.device)

    # ------------------------------------------------------------------ inputs
    def uv_inputs(self, theta: np.ndarray, previous: np.ndarray, clouds: list | None,
                  template: SkinnedTemplate | None = None) -> tuple[torch.Tensor, np.ndarray, SkinnedTemplate]:
        """UV input maps for every frame.

        Args:
            theta: (T,D) DoFs.
            previous: (T,) index of each frame's previous frame (itself for the first).
            clouds: per frame ``(points, normals)`` or None; None overall = no depth (xi = 0).
            template: the skinned template of ``theta`` if already computed.
        Returns:
            ``(inputs (T,22,R,R) float32 CPU, xi mask (T,V) bool, template)``.
        """
        template = template or skinned_template(self.character, theta)
        theta_signal = motion_signal(self.character, template.vertices, root_transforms(self.character, theta), previous)
        T, V = theta_signal.shape[:2]
        if clouds is None:
            xi, mask = np.zeros((T, V, 3), np.float32), np.zeros((T, V), bool)
        else:
            xi, mask = encode_depth(template, clouds, self.depth.eps_d, self.depth.eps_n)
        per_vertex = np.concatenate([theta_signal, xi / self.depth.eps_d, mask[..., None].astype(np.float32)], -1)
        dynamic = self.layout.to_uv(per_vertex)
        inputs = torch.cat([self.canonical_uv.expand(T, -1, -1, -1), dynamic], 1)
        return inputs, mask, template

    # ------------------------------------------------------------------ posing
    def pose(self, theta: torch.Tensor, alpha: torch.Tensor, beta: torch.Tensor, offsets: torch.Tensor | None):
        """``V = W(E(V_bar, alpha, beta, o), K(theta))`` (graph posing with DQS).

        Args:
            theta: (B,D); alpha, beta: (B,N,3); offsets: (B,V,3) or None.
        Returns:
            ``(posed (B,V,3), canonical (B,V,3) after E without offsets)``.
        """
        canonical = embedded_deformation(self.rest, self.character.graph, alpha, beta)
        full = canonical if offsets is None else canonical + offsets
        bone_T = bone_transforms(theta.to(torch.float32), self.character)
        posed = pose_through_graph(full, bone_T, self.character.skin_weights, self.character.graph, "dqs")
        return posed, canonical

    def predict(self, inputs: torch.Tensor, theta: np.ndarray, chunk: int = 8) -> dict[str, np.ndarray]:
        """Run the network and pose every frame; returns vertices (T,V,3), alpha, beta, offsets."""
        out = {"vertices": [], "eg_rotation": [], "eg_translation": [], "offsets": []}
        self.net.eval()
        with torch.no_grad():
            for start in range(0, len(inputs), chunk):
                x = inputs[start:start + chunk].to(self.device)
                th = torch.as_tensor(np.asarray(theta[start:start + chunk]), dtype=torch.float32, device=self.device)
                alpha, beta, off = self.net(x, self.node_uv, self.vertex_uv)
                posed, _ = self.pose(th, alpha, beta, off)
                for name, value in zip(out, (posed, alpha, beta, off)):
                    out[name].append(value.cpu().numpy())
        return {k: np.concatenate(v).astype(np.float32) for k, v in out.items()}

    def mesh_sequence(self, inputs: torch.Tensor, theta: np.ndarray, frame_ids: np.ndarray,
                      fps: float | None) -> MeshSequence:
        p = self.predict(inputs, theta)
        return MeshSequence(p["vertices"], self.character.faces, theta, p["eg_rotation"], p["eg_translation"],
                            p["offsets"], frame_ids, fps)


def previous_rows(frame_ids: np.ndarray) -> np.ndarray:
    """(T,) row of each frame's predecessor (frame id - 1) when present, else the frame itself."""
    frame_ids = np.asarray(frame_ids, np.int64)
    lookup = {int(f): i for i, f in enumerate(frame_ids)}
    return np.array([lookup.get(int(f) - 1, i) for i, f in enumerate(frame_ids)], np.int64)


# ------------------------------------------------------------------------------- training
@dataclass
class TrainingData:
    """Precomputed training samples (one per frame with a reconstruction and motion).

    Attributes:
        inputs: (S,22,R,R) UV inputs.
        theta: (S,D) float32.
        targets: list of (points (M,3), normals (M,3)) float32 tensors, reconstruction samples.
        trees: KD-trees of the target points.
        frame_ids: (S,) studio frame ids.
    """

    inputs: torch.Tensor
    theta: torch.Tensor
    targets: list
    trees: list
    frame_ids: np.ndarray

    @classmethod
    def concatenate(cls, parts: list["TrainingData"]) -> "TrainingData":
        """The samples of several sets in one (e.g. the same frames under two motions)."""
        if len(parts) == 1:
            return parts[0]
        return cls(torch.cat([p.inputs for p in parts]), torch.cat([p.theta for p in parts]),
                   [t for p in parts for t in p.targets], [t for p in parts for t in p.trees],
                   np.concatenate([p.frame_ids for p in parts]))


def surface_target(vertices: np.ndarray, faces: np.ndarray, count: int,
                   rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to ``count`` vertices (M,3) of a surface ``vertices`` (V,3), ``faces`` (F,3) with their unit
    normals (M,3), float32 tensors in the vertices' units; only vertices that ``faces`` use (a stray
    vertex has no normal)."""
    vertices = np.asarray(vertices, np.float64)
    used = np.unique(faces)
    normals = vertex_normals(vertices, faces)[used]
    keep = np.arange(len(used)) if len(used) <= count else rng.choice(len(used), count, replace=False)
    return (torch.as_tensor(vertices[used][keep], dtype=torch.float32),
            torch.as_tensor(normals[keep], dtype=torch.float32))


def animation_loss(model: AnimationModel, x: torch.Tensor, theta: torch.Tensor, targets: list, trees: list,
                   settings: TrainSettings) -> dict[str, torch.Tensor]:
    """The supplement's loss for one batch; returns every term and their weighted sum ``loss``."""
    alpha, beta, off = model.net(x, model.node_uv, model.vertex_uv)
    return deformation_loss(model, theta, alpha, beta, off, targets, trees, settings)


def deformation_loss(model: AnimationModel, theta: torch.Tensor, alpha: torch.Tensor, beta: torch.Tensor,
                     off: torch.Tensor, targets: list, trees: list, settings: TrainSettings) -> dict[str, torch.Tensor]:
    """The supplement's loss of given deformations: theta (B,D), alpha / beta (B,N,3) rad / m, off
    (B,V,3) m against per-sample targets ``(points, normals)`` and their KD-trees; every term and
    their weighted sum ``loss``."""
    B = theta.shape[0]
    both, canonical = model.pose(torch.cat([theta, theta]), torch.cat([alpha, alpha]), torch.cat([beta, beta]),
                                 torch.cat([torch.zeros_like(off), off]))
    v_eg, v_delta = both[:B], both[B:]
    n_eg = vertex_normals(v_eg, model.character.faces)
    n_delta = vertex_normals(v_delta, model.character.faces)
    chamf_eg, chamf_delta = [], []
    for b in range(B):
        tp, tn = targets[b]
        for out, v, n in ((chamf_eg, v_eg[b], n_eg[b]), (chamf_delta, v_delta[b], n_delta[b])):
            out.append(filtered_chamfer(v, n, tp, tn, trees[b], settings.min_normal_dot, settings.max_distance,
                                        settings.point_to_plane))
    g = node_positions(model.rest, model.character.graph)
    terms = {
        "chamfer_eg_cm": torch.stack(chamf_eg).mean(),
        "chamfer_delta_cm": torch.stack(chamf_delta).mean(),
        "arap": graph_arap(g, alpha, beta, model.graph_edges),
        "spatial": offset_smoothness(off, model.mesh_edges),
        "iso": offset_isometry(canonical[:B], off, model.mesh_edges),
    }
    w = settings.weights
    terms["loss"] = (w["eg"] * terms["chamfer_eg_cm"] + w["delta"] * terms["chamfer_delta_cm"] + w["arap"] * terms["arap"]
                     + w["spatial"] * terms["spatial"] + w["iso"] * terms["iso"])
    return terms


def train_animation_model(model: AnimationModel, data: TrainingData, settings: TrainSettings, no_depth: bool = False,
                          checkpoint=None, validation: TrainingData | None = None) -> tuple[list[dict], dict]:
    """Optimise ``model.net`` on ``data`` (see the module docstring); returns the curve and the
    validation summary. With ``validation`` samples, the net ends with the weights whose mean
    ``chamfer_delta_cm`` on them (with depth unless ``no_depth``) was lowest, scored before the
    first step and every ``settings.validate_every`` steps."""
    from egorelight_cli.nn.distributed import rank_share
    from egorelight_cli.nn.training import BestOnValidation, train

    S = len(data.frame_ids)
    if S == 0:
        raise EgorelightError("no training frames (frames need motion and a reconstruction)")
    optimizer = torch.optim.Adam(model.net.parameters(), lr=settings.lr)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, max(settings.steps, 1), eta_min=settings.lr * 0.1)

    def step_fn(step: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng(settings.seed * 1_000_003 + step)
        rows = rng.choice(S, min(settings.batch, S), replace=False)
        x = data.inputs[rows].clone()
        drop = np.ones(len(rows), bool) if no_depth else rng.random(len(rows)) < settings.depth_dropout
        x[torch.as_tensor(drop), XI_CHANNELS] = 0.0
        x, rows = rank_share(x), rank_share(rows)  # this process's share under torchrun
        return animation_loss(model, x.to(model.device), data.theta[rows].to(model.device),
                              [data.targets[r] for r in rows], [data.trees[r] for r in rows], settings)

    selection = None
    if validation is not None and len(validation.frame_ids):
        selection = BestOnValidation(lambda: evaluate_chamfer(model, validation, settings, no_depth=no_depth),
                                     max(1, settings.validate_every))
    curve = train(model.net, optimizer, step_fn, settings.steps, checkpoint=checkpoint, log_every=settings.log_every,
                  scheduler=scheduler, desc="train animate", selection=selection)
    if selection is None:
        return curve, {"validation_samples": 0}
    return curve, {"validation_samples": int(len(validation.frame_ids)), "validation_chamfer_cm_start": selection.first,
                   "validation_chamfer_cm_best": selection.best, "best_step": selection.best_step}


def evaluate_chamfer(model: AnimationModel, data: TrainingData, settings: TrainSettings,
                     no_depth: bool = False) -> float:
    """Mean ``chamfer_delta_cm`` of the model over all samples of ``data`` (no gradients)."""
    values = []
    with torch.no_grad():
        for r in range(len(data.frame_ids)):
            x = data.inputs[r:r + 1].clone()
            if no_depth:
                x[:, XI_CHANNELS] = 0.0
            terms = animation_loss(model, x.to(model.device), data.theta[r:r + 1].to(model.device),
                                   [data.targets[r]], [data.trees[r]], settings)
            values.append(float(terms["chamfer_delta_cm"]))
    return float(np.mean(values))


def build_training_data(model: AnimationModel, theta: np.ndarray, frame_ids: np.ndarray, clouds: list | None,
                        recon: dict[int, tuple[np.ndarray, np.ndarray]], settings: TrainSettings) -> TrainingData:
    """Training samples for the frames of ``frame_ids`` that have a reconstruction.

    Args:
        theta: (T,D) motion; frame_ids (T,) its studio ids.
        clouds: per frame (points, normals) or None, or None for no depth at all.
        recon: frame id -> (vertices, faces) of the multi-view reconstruction.
    """
    rows = np.array([i for i, f in enumerate(frame_ids) if int(f) in recon], np.int64)
    if rows.size == 0:
        raise EgorelightError("no frame of the motion has a multi-view reconstruction to train on")
    console.info(f"train animate: encoding {len(frame_ids)} frames ({rows.size} with a reconstruction)")
    inputs, _, _ = model.uv_inputs(theta, previous_rows(frame_ids), clouds)
    rng = np.random.default_rng(settings.seed)
    targets, trees = [], []
    for r in rows:
        v, f = recon[int(frame_ids[r])]
        tp, tn = surface_target(v, f, settings.target_points, rng)
        targets.append((tp.to(model.device), tn.to(model.device)))
        trees.append(cKDTree(tp.numpy().astype(np.float64)))
    return TrainingData(inputs[rows], torch.as_tensor(np.asarray(theta)[rows], dtype=torch.float32), targets, trees,
                        np.asarray(frame_ids)[rows])
