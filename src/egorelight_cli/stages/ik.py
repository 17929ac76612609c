"""Inverse kinematics (paper Sec. "Inverse Kinematics" and supplement "Details about Inverse
Kinematics"): 3D keypoints over a sequence -> skeleton motion ``theta`` (T,D).

Energy, minimised over the whole sequence at once::

    E = E_Data + E_Temporal + E_DoFLimit + E_Reg
    E_Data     = w_data  sum_t sum_k c_tk |K_k(theta_t) - zeta_tk|^2 / unit^2
    E_Temporal = w_temp  sum_t |2 x_t - x_{t-1} - x_{t+1}|^2      (root + body DoFs)
               + w_htemp sum_t sum_h |2 eta_h,t - eta_h,t-1 - eta_h,t+1|^2  (hand PCA coefficients)
    E_DoFLimit = w_limit sum_t sum_d max(theta_d - max_d, min_d - theta_d, 0)^2
    E_Reg      = w_reg   sum_t sum_d (theta_d - theta_bar_d)^2     (non-root DoFs)

with the paper's weights (temporal 3, hand temporal 30, reg 0.01, DoF limit 0.1; ``stages/ik.yaml``)
and per-keypoint confidences ``c`` weighting the data term. The paper writes every term with
``||.||_2``; we read them as squared norms (least squares — what LBFGS-on-MSE implementations
and any Gauss-Newton solver minimise). The data residual is measured in ``length_unit_m``
(default decimetres): the paper's weights only mean something relative to a length unit; this
one was the best round unit in a noise experiment (see ``stages/ik.yaml``).

Robustness (ours, :mod:`egorelight_cli.stages.ik_robust`; ``robust`` in ``stages/ik.yaml``): the
data term is Huber by default (``robust.loss: l2`` is the paper's squared norm): a keypoint off by
more than ``huber_delta_m`` pulls with a bounded force. Keypoints far from their frame's body
(``outlier_distance_m``), and keypoints far off a first fit (``residual_factor`` x the median
residual and ``min_residual_m``; the motion is then fitted again) are dropped and counted
(``rejected_keypoints``); keypoints spanning far more (or less) than a body are a unit error.

Hierarchy (paper): (1) global 6D pose (the root chain DoFs) against the torso keypoints with the
body at its mean pose, (2) body DoFs (with the root, by default), (3) hands, each hand's finger
DoFs constrained to ``theta_hand = mean + basis @ eta`` (PCA, 6 components by default). Hands
have no say in stages 1-2 (held at the PCA mean), the body is fixed in stage 3.

DoF classes (:func:`classify_dofs`): *root* DoFs drive only the root chain joints; *hand* DoFs
drive only revolute finger joints (``<Side>Hand{Thumb,Index,Middle,Ring,Pinky}...``) of one side;
*fixed* DoFs drive only prismatic joints outside the root chain (DDC bone-length "scale" DoFs)
or nothing, and stay at the character's ``rest_theta``; *unobservable* DoFs move no keypoint
(head, jaw, toes) and stay at ``theta_bar``; *body* DoFs are the rest.

Solvers:

* ``lm`` (default): Levenberg-Marquardt over the whole sequence. Keypoint Jacobians are analytic
  (:mod:`egorelight_cli.geometry.ik_jacobian`, float32); data, limit and regulariser couple only
  the DoFs of one frame and the temporal terms only frames t-2..t+2, so the normal equations are
  banded (bandwidth 2n for n variables per frame, frame-major ordering) and one banded Cholesky
  (LAPACK ``pbtrf`` via ``scipy.linalg.cholesky_banded``) per iteration solves them exactly.
  Each frame keeps its own damping. Far from the solution (the body stage starts from the mean
  pose) Gauss-Newton needs several damped steps per frame; a warm start does them cheaply:
  Gauss-Seidel sweeps of per-frame steps (frames t, t+3, ... at once, each kept only if it
  lowers the total energy), first on every 4th frame, then on all, before the coupled solve.
  Limits: the paper's hinge penalty plus bound constraints (variables on a limit are held,
  variables a step would carry past one are put on it and the rest re-solved).
* ``lbfgs``: the paper's baseline, ``torch.optim.LBFGS`` (strong-Wolfe line search) on the same
  energy and parametrisation, same stages, 100 iterations per stage.

Both solvers start from the same initial guess (body at ``theta_bar``, hands at the PCA mean, the
root rotation from a per-frame Kabsch fit of the torso keypoints) and both clamp the result to the
DoF limits at the end (``project_limits``).

Modules: settings :mod:`~egorelight_cli.stages.ik_settings`, DoF classes / hand PCA / model
:mod:`~egorelight_cli.stages.ik_model`, solvers :mod:`~egorelight_cli.stages.ik_solvers`, robust
data :mod:`~egorelight_cli.stages.ik_robust`, metrics :mod:`~egorelight_cli.stages.ik_eval`; this
module holds the initial guess, the hierarchical solve and retargeting, and re-exports the rest.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from egorelight_cli import console
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.ik_jacobian import dof_influence, root_chain_joints
from egorelight_cli.geometry.rigid import kabsch_rotations
from egorelight_cli.geometry.rotations import axis_angle_rotation
from egorelight_cli.geometry.skeleton import forward_kinematics
from egorelight_cli.structures.keypoints import Keypoints
from egorelight_cli.stages.ik_eval import fit_metrics, fitted_keypoints, gt_metrics, jitter_m, solve_timing
from egorelight_cli.stages.ik_model import (
    IK_MODEL_PAYLOAD, IK_MODEL_TYPE, DofGroups, HandPCA, IKModel, clamp_to_limits,
    classify_dofs, default_ik_model, fit_pca, synthetic_hand_poses, train_ik_model,
)
from egorelight_cli.stages.ik_robust import check_keypoint_units, distant_keypoints, residual_outliers
from egorelight_cli.stages.ik_settings import IKSettings
from egorelight_cli.stages.ik_solvers import IKResult, StageReport, _lbfgs, _levenberg_marquardt, _StageProblem
from egorelight_cli.structures.character import Character
from egorelight_cli.structures.keypoints import BODY_SLICE
from egorelight_cli.structures.skeleton import REVOLUTE

__all__ = [
    "IKSettings", "IKModel", "IKResult", "StageReport", "DofGroups", "HandPCA", "IK_MODEL_TYPE", "IK_MODEL_PAYLOAD",
    "classify_dofs", "clamp_to_limits", "synthetic_hand_poses", "fit_pca", "default_ik_model", "train_ik_model",
    "check_keypoints_for", "solve_ik", "fitted_keypoints", "fit_metrics", "solve_timing", "gt_metrics", "jitter_m",
    "SCALE_BONES", "fit_global_scale", "scale_keypoints",
]


# --------------------------------------------------------------------------------- root init
def _chain_rotation(theta_rot: np.ndarray, W: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation of the root chain end (N,3,3) and its derivatives (N,r,3,3) w.r.t. the root
    rotation DoFs; ``W`` (r,c) weights of those DoFs on the chain's revolute joints (in chain
    order) with ``axes`` (c,3)."""
    params = torch.as_tensor(theta_rot @ W)  # (N,c)
    Rj = axis_angle_rotation(torch.as_tensor(axes), params).numpy()  # (N,c,3,3)
    N, c = params.shape
    R = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
    world_axes = np.empty((N, c, 3))
    for j in range(c):
        world_axes[:, j] = R @ axes[j]
        R = R @ Rj[:, j]
    skew = np.zeros((N, c, 3, 3))
    ax = world_axes
    skew[..., 0, 1], skew[..., 0, 2], skew[..., 1, 2] = -ax[..., 2], ax[..., 1], -ax[..., 0]
    skew[..., 1, 0], skew[..., 2, 0], skew[..., 2, 1] = ax[..., 2], -ax[..., 1], ax[..., 0]
    dR_joint = skew @ R[:, None]  # (N,c,3,3)
    return R, np.einsum("rc,ncij->nrij", W, dR_joint)


def _root_rotation_dofs(R_target: np.ndarray, W: np.ndarray, axes: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Root rotation DoF values (T,r) whose chain rotation best matches ``R_target`` (T,3,3):
    Gauss-Newton on the Frobenius residual from 4 starting headings, best kept."""
    T, r = R_target.shape[0], W.shape[0]
    starts = []
    first = W[:, 0]
    for heading in (0.0, 0.5 * math.pi, math.pi, -0.5 * math.pi):
        start = np.zeros(r)
        d = int(np.abs(first).argmax())
        start[d] = heading / first[d] if first[d] != 0 else 0.0
        starts.append(start)
    q = np.repeat(np.stack(starts)[None], T, axis=0).reshape(-1, r)  # (T*4,r)
    target = np.repeat(R_target, len(starts), axis=0)
    for _ in range(iterations):
        R, dR = _chain_rotation(q, W, axes)
        res = (R - target).reshape(len(q), 9)
        J = dR.reshape(len(q), r, 9).transpose(0, 2, 1)
        H = J.transpose(0, 2, 1) @ J + 1e-9 * np.eye(r)
        q = q - np.linalg.solve(H, (J.transpose(0, 2, 1) @ res[..., None]))[..., 0]
    R, _ = _chain_rotation(q, W, axes)
    cost = ((R - target) ** 2).sum(axis=(1, 2)).reshape(T, len(starts))
    best = cost.argmin(axis=1)
    return q.reshape(T, len(starts), r)[np.arange(T), best]


def _initial_root(character: Character, groups: DofGroups, theta_init: np.ndarray, targets: np.ndarray,
                  weights: np.ndarray, torso: np.ndarray) -> np.ndarray:
    """(T,D) initial guess: ``theta_init`` with the root rotation DoFs from a per-frame Kabsch
    fit of the torso keypoints (frames with fewer than 3 take the nearest fitted frame's)."""
    sk = character.skeleton
    T = targets.shape[0]
    theta = np.repeat(theta_init[None], T, axis=0)
    chain = np.nonzero(root_chain_joints(sk))[0]
    rev = chain[sk.joint_types[chain] == REVOLUTE]
    rot_dofs = np.array([d for d in groups.root if np.any(sk.dof_joint_weights[d, rev] != 0)], dtype=np.int64)
    if len(rot_dofs) == 0 or len(rev) == 0 or len(torso) < 3:
        return theta
    G0 = forward_kinematics(torch.as_tensor(theta_init), sk)
    kp0 = torch.as_tensor(fitted_keypoints(character, theta_init[None])[0])
    end = G0[chain[-1]].numpy()
    P = (kp0.numpy()[torso] - end[:3, 3]) @ end[:3, :3]  # torso points in the chain-end frame
    w = weights[:, torso]
    valid = (w > 0).sum(axis=1) >= 3
    if not valid.any():
        return theta
    R = kabsch_rotations(P, targets[valid][:, torso], w[valid])
    q = _root_rotation_dofs(R, sk.dof_joint_weights[np.ix_(rot_dofs, rev)], sk.axes[rev])
    full = np.empty((T, len(rot_dofs)))
    idx = np.nonzero(valid)[0]
    nearest = idx[np.clip(np.searchsorted(idx, np.arange(T)), 0, len(idx) - 1)]
    prev = idx[np.clip(np.searchsorted(idx, np.arange(T)) - 1, 0, len(idx) - 1)]
    nearest = np.where(np.abs(prev - np.arange(T)) < np.abs(nearest - np.arange(T)), prev, nearest)
    full[:] = q[np.searchsorted(idx, nearest)]
    scale = np.array([np.abs(sk.dof_joint_weights[d, rev]).max() for d in rot_dofs])
    full = np.unwrap(full * scale, axis=0) / scale  # continuous angles over time
    theta[:, rot_dofs] = full
    return theta


# -------------------------------------------------------------------------------------- solve
def _data_weights(keypoints: Keypoints, settings: IKSettings) -> np.ndarray:
    conf = np.where(keypoints.confidence > settings.min_confidence, keypoints.confidence, 0.0).astype(np.float64)
    conf[~np.isfinite(keypoints.xyz).all(axis=-1)] = 0.0
    return conf


def check_keypoints_for(character: Character, keypoints: Keypoints, settings: IKSettings = IKSettings(), path=None) -> None:
    """Raise a clear error unless ``keypoints`` can drive ``character``."""
    if tuple(keypoints.names) != tuple(character.keypoint_names):
        if len(keypoints.names) != len(character.keypoint_names):
            raise EgorelightError(f"keypoints have {len(keypoints.names)} keypoints but the character has "
                                  f"{len(character.keypoint_names)}", path)
        raise EgorelightError("keypoint names differ from the character's keypoint layout", path)
    if keypoints.num_frames == 0:
        raise EgorelightError("keypoints hold no frames", path)
    weights = _data_weights(keypoints, settings)
    if not (weights > 0).any():
        raise EgorelightError("no usable keypoints: every keypoint is missing (NaN) or has confidence "
                              f"<= {settings.min_confidence}", path)
    unknown = [n for n in settings.global_keypoints if n not in character.keypoint_names]
    if unknown:
        raise EgorelightError(f"ik global_keypoints names {', '.join(map(repr, unknown))}, not a keypoint of the "
                              f"character (it has {', '.join(character.keypoint_names[:15])}, ...)")
    check_keypoint_units(keypoints.xyz, weights > 0, settings.min_span_m, settings.max_span_m, path)


def solve_ik(character: Character, keypoints: Keypoints, model: IKModel | None = None,
             settings: IKSettings = IKSettings(), keypoint_weights: np.ndarray | None = None) -> IKResult:
    """Solve the motion of ``character`` that best explains ``keypoints`` (see the module
    docstring). ``model`` defaults to :func:`default_ik_model`; ``keypoint_weights`` (K,) >= 0
    multiply each keypoint's confidence in the data term (default: all 1).

    Gross outliers (:mod:`egorelight_cli.stages.ik_robust`) are dropped: keypoints far from their
    frame's body before the fit, then keypoints far off a first fit (the motion is fitted again
    without them); ``IKResult.rejected`` marks both.
    """
    started = time.perf_counter()
    check_keypoints_for(character, keypoints, settings)
    model = (model or default_ik_model(character, settings)).check_character(character)
    xyz = keypoints.xyz.astype(np.float64)
    conf = _data_weights(keypoints, settings)
    if keypoint_weights is not None:
        conf = conf * np.asarray(keypoint_weights, np.float64)[None, :]
    rejected = distant_keypoints(xyz, conf > 0, settings.outlier_distance_m)
    conf[rejected] = 0.0
    runs = frame_runs(keypoints.frame_ids)
    theta, reports = _fit_runs(runs, character, model, xyz, conf, settings)
    fitted, residual = _fit_residuals(character, theta, xyz, conf)
    again = residual_outliers(residual, conf > 0, settings.outlier_residual_factor, settings.outlier_min_residual_m)
    if again.any():
        console.debug(f"ik: {int(again.sum())} keypoints far off the first fit dropped, fitting again")
        rejected |= again
        conf[again] = 0.0
        theta, more = _fit_runs(runs, character, model, xyz, conf, settings)
        reports += more
        fitted, residual = _fit_residuals(character, theta, xyz, conf)
    fps = keypoints.fps or settings.fps
    return IKResult(theta, keypoints.frame_ids.copy(), float(fps), fitted, residual, tuple(reports), settings.solver,
                    time.perf_counter() - started, rejected)


def _fit_residuals(character: Character, theta: np.ndarray, xyz: np.ndarray, conf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """FK keypoints (T,K,3) of ``theta`` and their distance (T,K) in metres to ``xyz``, NaN where
    ``conf`` is 0."""
    fitted = fitted_keypoints(character, theta)
    residual = np.linalg.norm(fitted - xyz, axis=-1)
    residual[conf <= 0] = np.nan
    return fitted, residual


def frame_runs(frame_ids: np.ndarray) -> list[slice]:
    """The runs of evenly spaced frames in ``frame_ids`` (T,) int: a run ends where the next frame
    lies more than 1.5 times the median step away (frames are missing there), so the temporal
    term never couples frames across a gap. One run when the ids are not increasing."""
    steps = np.diff(np.asarray(frame_ids, np.int64))
    if len(steps) == 0 or np.any(steps <= 0):
        return [slice(0, len(frame_ids))]
    breaks = np.flatnonzero(steps > 1.5 * np.median(steps)) + 1
    bounds = [0, *breaks.tolist(), len(frame_ids)]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]


def _fit_runs(runs: list[slice], character: Character, model: IKModel, xyz: np.ndarray, conf: np.ndarray,
              settings: IKSettings) -> tuple[np.ndarray, list[StageReport]]:
    """:func:`_fit` on each run of frames (:func:`frame_runs`) alone, stacked."""
    fits = [_fit(character, model, xyz[run], conf[run], settings) for run in runs]
    return np.concatenate([theta for theta, _ in fits]), [report for _, reports in fits for report in reports]


def _fit(character: Character, model: IKModel, xyz: np.ndarray, conf: np.ndarray,
         settings: IKSettings) -> tuple[np.ndarray, list[StageReport]]:
    """The hierarchical solve (module docstring): theta (T,D) fitting keypoints ``xyz`` (T,K,3)
    metres with confidences ``conf`` (T,K) (0: ignored), and the per-stage reports."""
    sk = character.skeleton
    D = sk.num_dofs
    groups = classify_dofs(character)
    targets = np.where(conf[..., None] > 0, np.nan_to_num(xyz), 0.0)
    sqrt_w = np.sqrt(settings.w_data * conf) / settings.length_unit_m
    theta_bar = model.theta_bar.copy()
    theta_init = theta_bar.copy()
    theta_init[groups.fixed] = character.rest_theta[groups.fixed]
    hands = [h for h in model.hands if len(h.dof_index)]
    for h in hands:
        theta_init[h.dof_index] = h.mean
    names = list(character.keypoint_names)
    torso = np.array([names.index(n) for n in settings.global_keypoints if n in names], dtype=np.int64)
    theta = _initial_root(character, groups, theta_init, targets, conf, torso)
    reg_index = np.concatenate([groups.body, *[h.dof_index for h in hands]]
                               + ([groups.root] if settings.regularise_root else [])).astype(np.int64)
    run = _levenberg_marquardt if settings.solver == "lm" else _lbfgs
    reports = []

    def stage(name: str, S: np.ndarray, x0: np.ndarray, base: np.ndarray, w_temporal: float, sqrt_weights: np.ndarray,
              warm_start: bool = False):
        problem = _StageProblem(name, character, S, base, x0, targets, sqrt_weights,
                                np.full(S.shape[1], w_temporal), reg_index, theta_bar, settings.w_reg,
                                settings.w_dof_limit, settings.project_limits, settings.lm_chunk_frames,
                                settings.huber_delta_m if settings.robust_loss == "huber" else None)
        problem.warm_start = warm_start
        if not len(problem.keypoints):  # nothing observed moves these DoFs: keep the initial guess
            return base + x0 @ S.T
        x, report = run(problem, settings)
        reports.append(report)
        return base + x @ S.T

    def selection(index: np.ndarray) -> np.ndarray:
        S = np.zeros((D, len(index)))
        S[index, np.arange(len(index))] = 1.0
        return S

    def split(index: np.ndarray, theta_now: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        base = theta_now.copy()
        base[:, index] = 0.0
        return theta_now[:, index].copy(), base

    # (1) global 6D pose against the torso keypoints
    if len(groups.root):
        torso_w = np.zeros_like(sqrt_w)
        torso_w[:, torso if len(torso) >= 3 else np.arange(BODY_SLICE.stop)] = 1.0
        x0, base = split(groups.root, theta)
        theta = stage("global", selection(groups.root), x0, base, settings.w_temporal, sqrt_w * torso_w)
    # (2) body (with the root), against the keypoints the finger DoFs do not move (the hands
    # are still at their mean pose; wrist and knuckles fix the hand's placement)
    body = np.concatenate([groups.root, groups.body]) if settings.body_stage_includes_root else groups.body
    if len(body):
        x0, base = split(body, theta)
        hand_dofs = np.concatenate([h.dof_index for h in hands]).astype(np.int64) if hands else np.zeros(0, np.int64)
        moved_by_fingers = dof_influence(sk, character.keypoint_joints, character.keypoint_offsets)[:, hand_dofs].any(axis=1)
        theta = stage("body", selection(body), x0, base, settings.w_temporal, sqrt_w * ~moved_by_fingers, warm_start=True)
    # (3) hands in PCA space
    if hands:
        S = np.zeros((D, sum(h.num_components for h in hands)))
        col = 0
        x0_parts = []
        for h in hands:
            S[h.dof_index, col:col + h.num_components] = h.basis
            col += h.num_components
            x0_parts.append(h.project(theta[:, h.dof_index]))
        base = theta.copy()
        for h in hands:
            base[:, h.dof_index] = h.mean
        theta = stage("hands", S, np.concatenate(x0_parts, axis=1), base, settings.w_hand_temporal, sqrt_w)
    if settings.project_limits:
        theta = clamp_to_limits(theta, sk.dof_limits, np.setdiff1d(np.arange(D), groups.fixed))
    return theta, reports


# ----------------------------------------------------------------------------- retargeting
SCALE_BONES = (("LeftUpLeg", "LeftLeg"), ("LeftLeg", "LeftFoot"), ("RightUpLeg", "RightLeg"), ("RightLeg", "RightFoot"),
               ("LeftArm", "LeftForeArm"), ("LeftForeArm", "LeftHand"), ("RightArm", "RightForeArm"),
               ("RightForeArm", "RightHand"), ("LeftUpLeg", "RightUpLeg"), ("LeftArm", "RightArm"),
               ("Neck", "LeftUpLeg"), ("Neck", "RightUpLeg"))


def fit_global_scale(character: Character, keypoints: Keypoints) -> float:
    """Scale ``s`` making ``s * keypoints`` match the character's proportions: least squares
    over the median lengths of the :data:`SCALE_BONES` both carry (1 when none)."""
    rest = fitted_keypoints(character, character.rest_theta[None])[0]
    names = list(keypoints.names)
    ours, theirs = [], []
    for a, b in SCALE_BONES:
        if a not in names or b not in names or a not in character.keypoint_names or b not in character.keypoint_names:
            continue
        ia, ib = names.index(a), names.index(b)
        ok = (keypoints.confidence[:, ia] > 0) & (keypoints.confidence[:, ib] > 0)
        if not ok.any():
            continue
        theirs.append(float(np.median(np.linalg.norm(keypoints.xyz[ok, ia] - keypoints.xyz[ok, ib], axis=-1))))
        ca, cb = character.keypoint_names.index(a), character.keypoint_names.index(b)
        ours.append(float(np.linalg.norm(rest[ca] - rest[cb])))
    theirs_a, ours_a = np.array(theirs), np.array(ours)
    denom = float((theirs_a ** 2).sum())
    return float((theirs_a * ours_a).sum() / denom) if denom > 0 else 1.0


def scale_keypoints(keypoints: Keypoints, scale: float) -> Keypoints:
    return Keypoints(keypoints.xyz * scale, keypoints.confidence, keypoints.frame_ids, keypoints.names, keypoints.fps)
