"""The character's mesh fitted to a surface, per frame: a multi-view reconstruction or the truth.

The appearance stages need meshes in the character's topology. This module deforms the animate
prediction of each frame towards a target surface with the same parameterisation the network
drives (embedded-graph rotations ``alpha`` and translations ``beta``, per-vertex canonical offsets
``o``, posed by the frame's motion) and the same loss it is trained with
(:func:`~egorelight_cli.stages.animate.deformation_loss`: normal-filtered Chamfer plus the ARAP,
smoothness and isometry terms). Two targets:

* ``animate --fit-recon``: the capture's multi-view reconstruction (``recon/``), what a lightstage
  records beside its images. Tracked meshes refined onto it are GeoLift's training geometry (the
  student alone sits ~0.7 cm off on ``relight_train``; relight keeps the student's own, see the
  Makefile's ``meshes_recon``).
* ``animate --fit-truth`` (evaluation only; issue 18's "with ground-truth meshes" relight row): a
  simulated capture's true outer surface (:func:`~egorelight_cli.stages.animate_eval.outer_faces`).
  The truth has its own topology (garment sheets over a body of another tessellation), so it
  cannot be handed to the appearance stages as it is; what is left between the fitted meshes and
  the truth is what the character's topology and the regularisers cannot follow, and relit renders
  from them isolate the appearance model from tracking error. Nothing on a stage's input path
  reads ``capture/groundtruth/<seq>/meshes.npz``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np
import torch
from scipy.spatial import cKDTree

from egorelight_cli import console
from egorelight_cli.config import Config, setting, settings_from_config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import transform_points
from egorelight_cli.io.capture import SequenceInfo, read_reconstructions
from egorelight_cli.structures.mesh_sequence import MeshSequence, SurfaceSequence

_fit = partial(setting, "animate")


@dataclass(frozen=True)
class FitSettings:
    """``fit.*``: Adam on the deformation parameters (in network output units) of a chunk of
    frames at a time."""

    steps: int = _fit("fit.steps")
    recon_steps: int = _fit("fit.recon_steps")  # ``steps`` of ``--fit-recon`` (``steps``: ``--fit-truth``)
    lr: float = _fit("fit.lr")
    chunk: int = _fit("fit.chunk")
    target_points: int = _fit("fit.target_points")

    @classmethod
    def from_config(cls, cfg: Config) -> "FitSettings":
        return settings_from_config(cls, cfg)


def recon_targets(sequence: SequenceInfo, frame_ids: np.ndarray, count: int,
                  seed: int = 0) -> dict[int, tuple[torch.Tensor, torch.Tensor]]:
    """Frame id -> ``(points (M,3), unit normals (M,3))`` float32: up to ``count`` vertices of the
    multi-view reconstruction of each frame of ``frame_ids`` that has one in ``sequence`` (the
    reconstructions lie in the studio world, the frame of the motions the stages estimate)."""
    from egorelight_cli.stages.animate import surface_target

    rng = np.random.default_rng(seed)
    return {fid: surface_target(v, f, count, rng)
            for fid, (v, f) in sorted(read_reconstructions(sequence, frame_ids).items())}


def require_reconstructions(sequence: SequenceInfo, capture_path) -> None:
    """A one-line error unless ``sequence`` has a multi-view reconstruction of at least one frame
    (``--fit-recon`` of ``animate`` and ``ik``)."""
    if not any(sequence.recon_path(int(f)).is_file() for f in sequence.frame_ids):
        raise EgorelightError(f"--fit-recon needs multi-view reconstructions of sequence {sequence.name!r} "
                              "(sequences/<seq>/recon/), which this capture does not have", capture_path)


def require_targets(targets: dict, frame_ids: np.ndarray, option: str, sequence: str, surface: str) -> None:
    """A one-line error when no frame of ``frame_ids`` (T,) found a target (``targets`` empty):
    ``option`` (``--fit-recon``) was given another sequence's motion, most likely."""
    if not targets:
        raise EgorelightError(f"{option}: no frame of the motion ({len(frame_ids)} frames, ids {int(frame_ids[0])}-"
                              f"{int(frame_ids[-1])}) has a target in sequence {sequence!r} ({surface}); is --seq the "
                              "motion's sequence?")


def true_targets(truth: SurfaceSequence, frame_ids: np.ndarray, count: int, T_pose_frame_from_truth: np.ndarray,
                 seed: int = 0) -> dict[int, tuple[torch.Tensor, torch.Tensor]]:
    """Frame id -> ``(points (M,3), unit normals (M,3))`` float32: up to ``count`` vertices of the
    true outer surface of each frame of ``frame_ids`` the truth has, in the frame of the meshes
    (``T_pose_frame_from_truth`` (4,4) applied)."""
    from egorelight_cli.stages.animate import surface_target
    from egorelight_cli.stages.animate_eval import outer_faces

    rng = np.random.default_rng(seed)
    out = {}
    for fid in np.asarray(frame_ids):
        if int(fid) not in truth.frame_ids:
            continue
        vertices = transform_points(T_pose_frame_from_truth, truth.vertices[truth.index_of(int(fid))].astype(np.float64))
        out[int(fid)] = surface_target(vertices, truth.faces[outer_faces(vertices, truth.faces)], count, rng)
    return out


def fit_to_surface(model, meshes: MeshSequence, targets: dict[int, tuple[torch.Tensor, torch.Tensor]],
                 train_settings, settings: FitSettings) -> tuple[MeshSequence, dict[str, float]]:
    """Each frame of ``meshes`` with a target deformed towards it (see the module docstring).

    Args:
        model: the :class:`~egorelight_cli.stages.animate.AnimationModel` (its character and output
            scales; the network is not run).
        meshes: the prediction to start from (its theta, alpha, beta, offsets).
        targets: frame id -> (points (M,3), unit normals (M,3)) in the frame of ``meshes``
            (:func:`recon_targets`, :func:`true_targets`).
        train_settings: the animate ``TrainSettings`` (loss weights, Chamfer filters).
    Returns:
        ``(fitted meshes, {"fit_frames", "fit_chamfer_cm_before", "fit_chamfer_cm_after"})``; frames
        without a target keep the prediction.
    """
    from egorelight_cli.stages.animate import deformation_loss

    scales = model.net.scales  # rotation, translation, offset
    rows = [r for r, f in enumerate(meshes.frame_ids) if int(f) in targets]
    fitted = [meshes.eg_rotation.copy(), meshes.eg_translation.copy(), meshes.offsets.copy()]
    vertices = meshes.vertices.copy()
    before, after = [], []
    for start in range(0, len(rows), max(1, settings.chunk)):
        chunk = rows[start:start + settings.chunk]
        pairs = [targets[int(meshes.frame_ids[r])] for r in chunk]
        trees = [cKDTree(p.numpy().astype(np.float64)) for p, _ in pairs]
        pairs = [(p.to(model.device), n.to(model.device)) for p, n in pairs]
        theta = torch.as_tensor(meshes.theta[chunk], dtype=torch.float32, device=model.device)
        params = [torch.tensor(value[chunk] / scale, dtype=torch.float32, device=model.device, requires_grad=True)
                  for value, scale in zip(fitted, scales)]
        optimizer = torch.optim.Adam(params, lr=settings.lr)

        def physical() -> list[torch.Tensor]:
            return [p * scale for p, scale in zip(params, scales)]

        def loss() -> dict[str, torch.Tensor]:
            return deformation_loss(model, theta, *physical(), pairs, trees, train_settings)

        for step in range(settings.steps):
            optimizer.zero_grad()
            terms = loss()
            if step == 0:
                before.append(float(terms["chamfer_delta_cm"].detach()) * len(chunk))
            terms["loss"].backward()
            optimizer.step()
        with torch.no_grad():
            after.append(float(loss()["chamfer_delta_cm"]) * len(chunk))
            deformation = physical()
            vertices[chunk] = model.pose(theta, *deformation)[0].cpu().numpy()
            for value, part in zip(fitted, deformation):
                value[chunk] = part.cpu().numpy()
        console.info(f"animate: fitted {start + len(chunk)} of {len(rows)} frames")
    result = MeshSequence(vertices, meshes.faces, meshes.theta, *fitted, meshes.frame_ids, meshes.fps,
                          meshes.ego_frame_ids)

    def mean(per_frame_sums: list[float]) -> float | None:
        return sum(per_frame_sums) / len(rows) if rows else None

    return result, {"fit_frames": len(rows), "fit_chamfer_cm_before": mean(before),
                    "fit_chamfer_cm_after": mean(after)}
