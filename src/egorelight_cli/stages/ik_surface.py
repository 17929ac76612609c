"""Skeleton motion refined onto a surface: ``ik --fit-recon`` (ours; issue 21).

The IK of markerless-mocap keypoints returns the DoFs that put the *character's* keypoints on the
detected ones. Where the character's keypoints sit a centimetre or more from where the studio's
detector places the subject's (a fitted template never matches a person exactly), those DoFs pose
the character's *surface* off the subject's even with perfect keypoints. A lightstage records a
multi-view reconstruction beside its images; this module moves each frame's DoFs so that the
character, posed by skinning alone (no embedded graph, no offsets), lies on that reconstruction:

    min_theta  chamf(W(V_bar, K(theta)), recon)

with the normal-filtered, point-to-plane Chamfer that ``train animate`` uses
(:func:`~egorelight_cli.nn.mesh_losses.filtered_chamfer`), Adam from the IK solution on the root
and body DoFs and (``surface_fit.head``) the neck and head DoFs no keypoint sees, which the
reconstruction does (the fingers keep the IK's hand-PCA pose: at a reconstruction's resolution a
finger is a few samples), the result clamped to the DoF limits. A frame without a reconstruction
keeps its IK DoFs.

What it is for: ``train animate`` learns the clothing's deformation from pairs (motion,
reconstruction); under a motion fitted this way the skinned character already lies on the
reconstruction, so the network also sees motions whose skinning needs no correction. Measured on
the cpu capture's ``ego_train`` (136 frames, 128 with a reconstruction): skinned Chamfer to the
reconstruction 1.39 cm under the mocap IK, 0.53 after the fit (on every 4th of those frames 1.37 ->
0.52, and 0.68 under the simulator's own DoFs); body DoFs 6.8 -> 4.6 deg and the root 2.2 -> 1.0 cm
off the simulator's (``gt_dof_error_body_deg``, ``gt_root_translation_error_cm``). The head
(issue 21's twenty-ninth session, ``ego_train``): Chamfer 0.528 -> 0.515 cm; as the reference of
``ik --hmd-reference`` the headset's mounting then spreads 2.4 deg over the frames instead of 3.9,
and the avatar retrained on such motions scores `test` 2.302 -> 2.288 cm P2S under the estimated
motion, 0.755 -> 0.729 under the IK of the true keypoints (its neck/head DoFs do move away from
the simulator's: 0.73 -> 2.78 deg, the template's head is not the subject's).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np
import torch
from scipy.spatial import cKDTree

from egorelight_cli import console
from egorelight_cli.config import check_settings, setting, settings_from_config
from egorelight_cli.geometry.embedded_graph import pose_character
from egorelight_cli.geometry.normals import vertex_normals
from egorelight_cli.nn.mesh_losses import filtered_chamfer
from egorelight_cli.structures.character import Character

_key = partial(setting, "ik")


@dataclass(frozen=True)
class SurfaceFitSettings:
    """``surface_fit.*`` of ``stages/ik.yaml``."""

    steps: int = _key("surface_fit.steps")
    lr: float = _key("surface_fit.lr")
    chunk: int = _key("surface_fit.chunk")
    target_points: int = _key("surface_fit.target_points")
    min_normal_dot: float = _key("surface_fit.min_normal_dot")
    max_distance: float = _key("surface_fit.max_distance")
    head: bool = _key("surface_fit.head")

    def __post_init__(self) -> None:
        check_settings(self)

    @classmethod
    def from_config(cls, cfg) -> "SurfaceFitSettings":
        return settings_from_config(cls, cfg)


def surface_fit_dofs(character: Character, head: bool = True) -> np.ndarray:
    """(D,) bool: the DoFs :func:`fit_motion_to_surface` moves: root and body, and with ``head``
    the neck and head DoFs no keypoint sees (:func:`~egorelight_cli.stages.ik_head.head_chain`; the
    reconstruction does see the face and hair); not the fingers, jaw, toes or fixed DoFs."""
    from egorelight_cli.stages.ik_head import head_chain
    from egorelight_cli.stages.ik_model import classify_dofs

    groups = classify_dofs(character)
    free = np.zeros(character.skeleton.num_dofs, bool)
    free[groups.root] = True
    free[groups.body] = True
    if head and len(groups.unobservable):
        free[head_chain(character).dofs] = True
    return free


def skinned_chamfer_cm(character: Character, theta: torch.Tensor, targets: list, trees: list,
                       settings: SurfaceFitSettings) -> torch.Tensor:
    """(B,) normal-filtered point-to-plane Chamfer (cm) of the character skinned by ``theta`` (B,D)
    to ``targets``: per sample ``(points (M,3), unit normals (M,3))`` metres, with their KD-trees."""
    vertices = pose_character(character, theta)
    normals = vertex_normals(vertices, character.faces)
    return torch.stack([filtered_chamfer(vertices[b], normals[b], points, point_normals, trees[b],
                                         settings.min_normal_dot, settings.max_distance, point_to_plane=True)
                        for b, (points, point_normals) in enumerate(targets)])


def fit_motion_to_surface(character: Character, theta: np.ndarray, frame_ids: np.ndarray,
                          targets: dict[int, tuple[torch.Tensor, torch.Tensor]],
                          settings: SurfaceFitSettings) -> tuple[np.ndarray, dict]:
    """Each frame's DoFs moved so that the skinned character lies on its target surface.

    Args:
        theta: (T,D) the starting motion (the IK solution), radians / metres.
        frame_ids: (T,) its frame ids.
        targets: frame id -> (points (M,3), unit normals (M,3)) float32 tensors, metres, in the
            motion's world (:func:`~egorelight_cli.stages.animate_fit.recon_targets`).
    Returns:
        ``(theta (T,D) float64, {"surface_fit_frames", "surface_fit_chamfer_cm_before",
        "surface_fit_chamfer_cm_after"})``; frames without a target keep their DoFs.
    """
    theta = np.asarray(theta, np.float64).copy()
    rows = [r for r, f in enumerate(np.asarray(frame_ids)) if int(f) in targets]
    moved = surface_fit_dofs(character, settings.head)
    free = torch.as_tensor(moved, dtype=torch.float32)
    low, high = character.skeleton.dof_limits[moved].T
    before, after = [], []
    for start in range(0, len(rows), max(1, settings.chunk)):
        chunk = rows[start:start + settings.chunk]
        pairs = [targets[int(frame_ids[r])] for r in chunk]
        trees = [cKDTree(points.numpy().astype(np.float64)) for points, _ in pairs]
        theta0 = torch.as_tensor(theta[chunk], dtype=torch.float32)
        step = torch.zeros_like(theta0, requires_grad=True)
        optimizer = torch.optim.Adam([step], lr=settings.lr)

        def chamfer() -> torch.Tensor:
            return skinned_chamfer_cm(character, theta0 + step * free, pairs, trees, settings)

        for iteration in range(settings.steps):
            optimizer.zero_grad()
            value = chamfer()
            if iteration == 0:
                before.append(value.detach().numpy())
            value.mean().backward()
            optimizer.step()
        with torch.no_grad():
            fitted = theta[chunk]  # the DoFs it does not move keep their values exactly
            fitted[:, moved] = np.clip((theta0 + step * free).numpy()[:, moved].astype(np.float64), low, high)
            after.append(skinned_chamfer_cm(character, torch.as_tensor(fitted, dtype=torch.float32), pairs, trees,
                                            settings).numpy())
        theta[chunk] = fitted
        console.info(f"ik: fitted {start + len(chunk)} of {len(rows)} frames to the surface")

    def mean(values: list) -> float | None:
        return float(np.concatenate(values).mean()) if values else None

    return theta, {"surface_fit_frames": len(rows), "surface_fit_chamfer_cm_before": mean(before),
                   "surface_fit_chamfer_cm_after": mean(after)}


def with_theta(character: Character, result, theta: np.ndarray, xyz: np.ndarray | None):
    """``result`` (an :class:`~egorelight_cli.stages.ik_solvers.IKResult`) with ``theta`` (T,D) in place
    of its DoFs: fitted keypoints recomputed, residuals against the input keypoints ``xyz`` (T,K,3)
    metres where ``result`` had one (all NaN without keypoints)."""
    from dataclasses import replace

    from egorelight_cli.stages.ik_eval import fitted_keypoints

    fitted = fitted_keypoints(character, theta)
    residual = np.full(fitted.shape[:2], np.nan)
    if xyz is not None:
        residual = np.where(np.isnan(result.residual_m), np.nan, np.linalg.norm(fitted - xyz, axis=-1))
    return replace(result, theta=np.asarray(theta, np.float64), fitted_keypoints=fitted, residual_m=residual)
