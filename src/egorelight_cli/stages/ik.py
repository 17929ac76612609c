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
"""

from __future__ import annotations

import copy
import math
import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse
import torch
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.linalg.blas import dsbmv

from egorelight_cli import console
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.ik_jacobian import KeypointJacobian, dof_influence, root_chain_joints
from egorelight_cli.geometry.rigid import project_to_rotation
from egorelight_cli.geometry.rotations import axis_angle_rotation
from egorelight_cli.geometry.skeleton import forward_kinematics
from egorelight_cli.io.keypoints import Keypoints
from egorelight_cli.io.motion import Motion
from egorelight_cli.runtime import blas_threads
from egorelight_cli.stages.ik_robust import check_keypoint_units, distant_keypoints, huber_factors, residual_outliers
from egorelight_cli.stages.ik_settings import IKSettings
from egorelight_cli.structures.character import Character
from egorelight_cli.structures.keypoints import BODY_SLICE, LEFT_HAND_SLICE, RIGHT_HAND_SLICE
from egorelight_cli.structures.skeleton import PRISMATIC, REVOLUTE

SIDES = ("Left", "Right")
FINGER_JOINT = re.compile(r"^(Left|Right)Hand(Thumb|Index|Middle|Ring|Pinky)")
CURL_JOINT = re.compile(r"^(Left|Right)Hand(Thumb|Index|Middle|Ring|Pinky)\d$")
DTYPE = torch.float64
JACOBIAN_DTYPE = torch.float32


# ---------------------------------------------------------------------------------- DoF classes
@dataclass(frozen=True, eq=False)
class DofGroups:
    """DoF indices per class (see the module docstring)."""

    root: np.ndarray
    body: np.ndarray
    hands: dict[str, np.ndarray]
    fixed: np.ndarray
    unobservable: np.ndarray

    def summary(self) -> dict[str, int]:
        return {"root": len(self.root), "body": len(self.body),
                **{f"hand_{s.lower()}": len(v) for s, v in self.hands.items()},
                "fixed": len(self.fixed), "unobservable": len(self.unobservable)}


def classify_dofs(character: Character) -> DofGroups:
    """Split the character's DoFs into root, body, per-hand, fixed and unobservable ones."""
    sk = character.skeleton
    chain = root_chain_joints(sk)
    observable = dof_influence(sk, character.keypoint_joints, character.keypoint_offsets).any(axis=0)
    groups: dict[str, list[int]] = {"root": [], "body": [], "Left": [], "Right": [], "fixed": [], "unobservable": []}
    for d in range(sk.num_dofs):
        joints = np.nonzero(sk.dof_joint_weights[d])[0]
        names = [sk.joint_names[j] for j in joints]
        sides = {m.group(1) for m in map(FINGER_JOINT.match, names) if m}
        if len(joints) == 0:
            groups["fixed"].append(d)
        elif chain[joints].all():
            groups["root"].append(d)
        elif (sk.joint_types[joints] == PRISMATIC).all():
            groups["fixed"].append(d)
        elif (len(sides) == 1 and all(FINGER_JOINT.match(n) for n in names)
              and (sk.joint_types[joints] == REVOLUTE).all()):
            groups[sides.pop()].append(d)
        elif not observable[d]:
            groups["unobservable"].append(d)
        else:
            groups["body"].append(d)
    arr = lambda key: np.array(groups[key], dtype=np.int64)  # noqa: E731
    return DofGroups(root=arr("root"), body=arr("body"), hands={s: arr(s) for s in SIDES if groups[s]},
                     fixed=arr("fixed"), unobservable=arr("unobservable"))


def clamp_to_limits(theta: np.ndarray, limits: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
    """``theta`` (...,D) with the DoFs in ``index`` (default all) clamped to ``limits`` (D,2)."""
    theta = np.array(theta, dtype=np.float64)
    index = np.arange(theta.shape[-1]) if index is None else np.asarray(index)
    theta[..., index] = np.clip(theta[..., index], limits[index, 0], limits[index, 1])
    return theta


# ------------------------------------------------------------------------------------ hand PCA
@dataclass(frozen=True, eq=False)
class HandPCA:
    """One hand's PCA: ``theta[dof_index] = mean + basis @ eta``.

    Attributes:
        side: ``"Left"`` or ``"Right"``.
        dof_index: (m,) the hand's DoF indices.
        mean: (m,) DoF values.
        basis: (m,k) orthonormal columns (so ``eta`` is in DoF units, radians).
        variance: (k,) variance of the training poses along each column.
        total_variance: total variance of the training poses (all directions), so
            ``variance.sum() / total_variance`` is the fraction the subspace explains.
    """

    side: str
    dof_index: np.ndarray
    mean: np.ndarray
    basis: np.ndarray
    variance: np.ndarray
    total_variance: float = 0.0

    def __post_init__(self) -> None:
        if not self.total_variance:
            object.__setattr__(self, "total_variance", float(np.sum(self.variance)))

    @property
    def num_components(self) -> int:
        return int(self.basis.shape[1])

    def project(self, theta_hand: np.ndarray) -> np.ndarray:
        """PCA coefficients (...,k) of hand DoF values (...,m)."""
        return (np.asarray(theta_hand) - self.mean) @ self.basis

    def reconstruct(self, eta: np.ndarray) -> np.ndarray:
        """Hand DoF values (...,m) of coefficients (...,k)."""
        return self.mean + np.asarray(eta) @ self.basis.T


def _finger_of(character: Character, d: int) -> tuple[str, bool]:
    """(finger name, is a curl DoF) of a hand DoF, from its first driven joint's name."""
    sk = character.skeleton
    names = [sk.joint_names[j] for j in np.nonzero(sk.dof_joint_weights[d])[0]]
    finger = FINGER_JOINT.match(names[0]).group(2)
    return finger, any(CURL_JOINT.match(n) for n in names)


def synthetic_hand_poses(character: Character, dof_index: np.ndarray, num: int, rng: np.random.Generator) -> np.ndarray:
    """(num, m) finger poses sampled within the DoF limits with anatomical coupling.

    A latent grasp ``g ~ Beta(0.7, 0.7)`` (0 open, 1 fist) drives every finger: finger curl
    ``c_f = clip(g + 0.2 N)`` (thumb ``clip(0.6 g + 0.2 + 0.25 N)``), and each joint of the finger
    curls ``clip(c_f + 0.08 N)`` of the way from the rest value to the limit on the side with the
    larger range (the flexion side). Spread/abduction DoFs are uniform within their limits,
    biased towards spreading when the hand is open. DoFs without finite limits get +-0.8 rad of
    joint motion around rest (curl DoFs then sample both directions).
    """
    sk = character.skeleton
    limits = sk.dof_limits[dof_index]
    rest = np.clip(character.rest_theta[dof_index], limits[:, 0], limits[:, 1])
    weight = np.array([np.abs(sk.dof_joint_weights[d]).max() for d in dof_index])
    span = 0.8 / np.maximum(weight, 1e-6)
    lo = np.where(np.isfinite(limits[:, 0]), limits[:, 0], rest - span)
    hi = np.where(np.isfinite(limits[:, 1]), limits[:, 1], rest + span)
    info = [_finger_of(character, int(d)) for d in dof_index]
    g = rng.beta(0.7, 0.7, size=num)
    finger_curl = {}
    for finger in ("Thumb", "Index", "Middle", "Ring", "Pinky"):
        base = 0.6 * g + 0.2 + 0.25 * rng.normal(size=num) if finger == "Thumb" else g + 0.2 * rng.normal(size=num)
        finger_curl[finger] = np.clip(base, 0, 1)
    samples = np.empty((num, len(dof_index)))
    for c, (finger, curl) in enumerate(info):
        if curl:
            amount = np.clip(finger_curl[finger] + 0.08 * rng.normal(size=num), 0, 1)
            unlimited = not (np.isfinite(limits[c]).all())
            if unlimited:
                samples[:, c] = lo[c] + amount * (hi[c] - lo[c])
            else:
                target = lo[c] if rest[c] - lo[c] >= hi[c] - rest[c] else hi[c]
                samples[:, c] = rest[c] + amount * (target - rest[c])
        else:
            u = np.clip(0.5 + 0.3 * (0.5 - g) + 0.2 * rng.normal(size=num), 0, 1)
            samples[:, c] = lo[c] + u * (hi[c] - lo[c])
    return np.clip(samples, lo, hi)


def fit_pca(samples: np.ndarray, k: int, fallback: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean (m,), basis (m,k), variance (k,)) of ``samples`` (N,m).

    When the samples span fewer than ``k`` directions (e.g. training motions with static
    hands), the basis is completed with the leading directions of ``fallback`` (N2,m) samples
    orthogonal to the span found.
    """
    samples = np.asarray(samples, dtype=np.float64)
    m = samples.shape[1]
    k = min(k, m)
    mean = samples.mean(axis=0)
    _, s, vt = np.linalg.svd(samples - mean, full_matrices=False)
    variance = s ** 2 / max(len(samples) - 1, 1)
    keep = variance > 1e-10 * max(variance.max(initial=0.0), 1e-12)
    basis, var = vt[keep][:k].T, variance[keep][:k]
    if basis.shape[1] < k and fallback is not None:
        rest = np.asarray(fallback, dtype=np.float64)
        rest = rest - rest.mean(axis=0)
        rest = rest - (rest @ basis) @ basis.T
        _, s2, vt2 = np.linalg.svd(rest, full_matrices=False)
        extra = k - basis.shape[1]
        basis = np.concatenate([basis, vt2[:extra].T], axis=1)
        var = np.concatenate([var, s2[:extra] ** 2 / max(len(rest) - 1, 1)])
    if basis.shape[1] < k:  # degenerate: complete with any orthonormal directions
        q, _ = np.linalg.qr(np.concatenate([basis, np.eye(m)], axis=1))
        extra = k - basis.shape[1]
        basis = np.concatenate([basis, q[:, basis.shape[1]:basis.shape[1] + extra]], axis=1)
        var = np.concatenate([var, np.zeros(extra)])
    signs = np.where(basis[np.abs(basis).argmax(axis=0), np.arange(basis.shape[1])] < 0, -1.0, 1.0)
    return mean, basis * signs, var


# --------------------------------------------------------------------------------------- model
IK_MODEL_TYPE = "ik"
IK_MODEL_PAYLOAD = "model.npz"


@dataclass(frozen=True, eq=False)
class IKModel:
    """What ``train ik`` learns: the mean pose ``theta_bar`` (D,) and one PCA per hand.

    ``source`` is ``"motions"`` (fitted to training motions) or ``"default"`` (``theta_bar`` =
    the character's ``rest_theta`` clamped to its limits, hands from
    :func:`synthetic_hand_poses`; ``theta_bar``'s hand DoFs are the PCA means).
    """

    dof_names: tuple[str, ...]
    theta_bar: np.ndarray
    hands: tuple[HandPCA, ...]
    source: str
    num_training_frames: int = 0
    settings: dict = field(default_factory=dict)

    def check_character(self, character: Character, path=None) -> "IKModel":
        names = tuple(character.skeleton.dof_names)
        if names != self.dof_names:
            raise EgorelightError(f"ik model was trained for a character with {len(self.dof_names)} DoFs "
                                  f"({', '.join(self.dof_names[:3])}, ...), not this one with {len(names)} "
                                  f"({', '.join(names[:3])}, ...)", path)
        return self

    def arrays(self) -> dict[str, np.ndarray]:
        arrays = {"dof_names": np.array(self.dof_names, dtype=str), "theta_bar": self.theta_bar,
                  "hand_sides": np.array([h.side for h in self.hands], dtype=str)}
        for h in self.hands:
            key = h.side.lower()
            arrays.update({f"hand_{key}_dof_index": h.dof_index, f"hand_{key}_mean": h.mean,
                           f"hand_{key}_basis": h.basis, f"hand_{key}_variance": h.variance,
                           f"hand_{key}_total_variance": np.array(h.total_variance)})
        return arrays

    def meta(self) -> dict:
        return {"model": IK_MODEL_TYPE, "source": self.source, "num_training_frames": self.num_training_frames,
                "hand_components": {h.side: h.num_components for h in self.hands}, "settings": self.settings}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], meta: Mapping) -> "IKModel":
        hands = []
        for side in (str(s) for s in arrays["hand_sides"]):
            key = side.lower()
            hands.append(HandPCA(side, np.asarray(arrays[f"hand_{key}_dof_index"], np.int64),
                                 np.asarray(arrays[f"hand_{key}_mean"], np.float64),
                                 np.asarray(arrays[f"hand_{key}_basis"], np.float64),
                                 np.asarray(arrays[f"hand_{key}_variance"], np.float64),
                                 float(arrays.get(f"hand_{key}_total_variance", 0.0))))
        return cls(tuple(str(s) for s in arrays["dof_names"]), np.asarray(arrays["theta_bar"], np.float64),
                   tuple(hands), str(meta.get("source", "?")), int(meta.get("num_training_frames", 0)),
                   dict(meta.get("settings", {})))


def _model_settings(settings: IKSettings) -> dict:
    return {"hand_components": settings.hand_components, "hand_samples": settings.hand_samples, "seed": settings.seed}


def default_ik_model(character: Character, settings: IKSettings = IKSettings()) -> IKModel:
    """The model used when no training motion exists (see :class:`IKModel`)."""
    return train_ik_model(character, [], settings)


def train_ik_model(character: Character, motions: Sequence[np.ndarray], settings: IKSettings = IKSettings()) -> IKModel:
    """Fit ``theta_bar`` and the hand PCAs to training motions (each (T_i,D)); with none, the
    default model. Hands whose training poses span fewer than ``hand_components`` directions are
    completed from synthetic poses."""
    sk = character.skeleton
    groups = classify_dofs(character)
    rng = np.random.default_rng(settings.seed)
    frames = [np.asarray(m, dtype=np.float64).reshape(-1, sk.num_dofs) for m in motions]
    data = np.concatenate(frames, axis=0) if frames else np.zeros((0, sk.num_dofs))
    if not np.isfinite(data).all():
        raise EgorelightError("training motions hold NaN/inf values")
    theta_bar = clamp_to_limits(data.mean(axis=0) if len(data) else character.rest_theta, sk.dof_limits)
    theta_bar[groups.fixed] = character.rest_theta[groups.fixed]
    hands = []
    for side, index in groups.hands.items():
        if settings.hand_components > len(index):
            raise EgorelightError(f"ik hand_pca.components is {settings.hand_components} but the character's {side} "
                                  f"hand has {len(index)} finger DoFs")
        synthetic = synthetic_hand_poses(character, index, settings.hand_samples, rng)
        source = data[:, index] if len(data) >= 2 else synthetic
        mean, basis, variance = fit_pca(source, settings.hand_components, fallback=synthetic)
        total = float(np.var(source, axis=0, ddof=1).sum()) if len(source) > 1 else 0.0
        hands.append(HandPCA(side, index, mean, basis, variance, max(total, float(variance.sum()))))
        theta_bar[index] = mean
    return IKModel(tuple(sk.dof_names), theta_bar, tuple(hands), "motions" if len(data) else "default",
                   int(len(data)), _model_settings(settings))


# ------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class StageReport:
    """What one hierarchical stage did."""

    name: str
    variables_per_frame: int
    iterations: int
    evaluations: int
    energy_start: float
    energy_end: float
    seconds: float


@dataclass(frozen=True, eq=False)
class IKResult:
    """The solved motion.

    Attributes:
        theta: (T,D) float64 DoF values.
        frame_ids: (T,) int64.
        fps: frames per second.
        fitted_keypoints: (T,K,3) FK keypoints of ``theta``, metres.
        residual_m: (T,K) distance to the input keypoints, NaN where the input had none.
        stages: per-stage reports.
        solver: ``lm`` or ``lbfgs``.
        seconds: wall time of the solve.
        rejected: (T,K) bool, keypoints dropped as gross outliers (None: no fit).
    """

    theta: np.ndarray
    frame_ids: np.ndarray
    fps: float
    fitted_keypoints: np.ndarray
    residual_m: np.ndarray
    stages: tuple[StageReport, ...]
    solver: str
    seconds: float
    rejected: np.ndarray | None = None

    def motion(self, dof_names) -> Motion:
        return Motion(self.theta, tuple(dof_names), self.frame_ids, self.fps, self.fitted_keypoints, self.residual_m)


# ----------------------------------------------------------------------------- stage problems
def _second_difference_gram(T: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Diagonals 0, 1, 2 of ``D2^T D2`` for the (T-2,T) second-difference operator."""
    if T < 3:
        return np.zeros(T), np.zeros(max(T - 1, 0)), np.zeros(max(T - 2, 0))
    D2 = scipy.sparse.diags([np.ones(T - 2), -2 * np.ones(T - 2), np.ones(T - 2)], [0, 1, 2], shape=(T - 2, T))
    P = (D2.T @ D2).todia()
    return P.diagonal(0), P.diagonal(1), P.diagonal(2)


class _StageProblem:
    """One hierarchical stage: ``theta_t = base_t + S x_t`` with x (T,n) the unknowns.

    Only keypoints that carry weight in the stage and that some stage DoF moves enter it (the
    others add a constant to the energy).
    """

    def __init__(self, name: str, character: Character, S: np.ndarray, base: np.ndarray, x0: np.ndarray,
                 targets: np.ndarray, sqrt_weights: np.ndarray, w_temporal: np.ndarray,
                 reg_index: np.ndarray, reg_target: np.ndarray, w_reg: float, w_limit: float,
                 project: bool, chunk: int, huber_delta_m: float | None = None):
        sk = character.skeleton
        self.name, self.character, self.chunk = name, character, max(int(chunk), 1)
        self.huber_delta_m = huber_delta_m  # None: squared data term; else Huber (ik_robust)
        self.S = np.asarray(S, dtype=np.float64)  # (D,n)
        self.affected = np.nonzero(np.abs(self.S).sum(axis=1) > 0)[0]
        S_aff = self.S[self.affected]
        self.is_selection = bool(np.all((S_aff == 0) | (S_aff == 1)) and np.all(S_aff.sum(axis=0) == 1)
                                 and np.all(S_aff.sum(axis=1) == 1))
        # Jacobian columns: the stage variables directly for a selection, else the affected DoFs
        columns = self.affected[S_aff.argmax(axis=0)] if self.is_selection else self.affected
        self.S_cols_t = torch.as_tensor(self.S[columns], dtype=DTYPE)  # (a,n) maps Jacobian columns to x
        moved = dof_influence(sk, character.keypoint_joints, character.keypoint_offsets)[:, self.affected].any(axis=1)
        self.keypoints = np.nonzero(moved & (np.asarray(sqrt_weights) > 0).any(axis=0))[0]
        self.jacobian = KeypointJacobian.build(sk, character.keypoint_joints[self.keypoints],
                                               character.keypoint_offsets[self.keypoints], columns)
        self.base = torch.as_tensor(base, dtype=DTYPE)
        self.x0 = np.asarray(x0, dtype=np.float64)
        self.targets = torch.as_tensor(np.nan_to_num(targets[:, self.keypoints]), dtype=DTYPE)
        self.sqrt_w = torch.as_tensor(sqrt_weights[:, self.keypoints], dtype=DTYPE)
        self.w_temporal = np.asarray(w_temporal, dtype=np.float64)
        self.reg_index = np.intersect1d(np.asarray(reg_index, dtype=np.int64), self.affected)
        self.reg_target = torch.as_tensor(np.asarray(reg_target)[self.reg_index], dtype=DTYPE)
        self.w_reg = float(w_reg) if len(self.reg_index) else 0.0
        limits = sk.dof_limits
        finite = np.isfinite(limits).any(axis=1)
        self.limit_index = self.affected[finite[self.affected]] if w_limit > 0 else np.zeros(0, np.int64)
        self.lo = torch.as_tensor(limits[self.limit_index, 0], dtype=DTYPE)
        self.hi = torch.as_tensor(limits[self.limit_index, 1], dtype=DTYPE)
        self.w_limit = float(w_limit)
        self.project = bool(project and self.is_selection)
        if self.project:
            self.x_lo = limits[columns, 0]
            self.x_hi = limits[columns, 1]
        self.S_t = torch.as_tensor(self.S, dtype=DTYPE)
        self.S_reg_t = torch.as_tensor(self.S[self.reg_index], dtype=DTYPE)
        self.S_lim_t = torch.as_tensor(self.S[self.limit_index], dtype=DTYPE)
        self.gram = _second_difference_gram(self.x0.shape[0])
        self.evaluations = 0
        self.warm_start = False  # Gauss-Seidel frame sweeps before the coupled solve (far starts)

    def restricted(self, frames: np.ndarray, temporal_scale: float = 1.0) -> "_StageProblem":
        """The same stage on a subsequence (a shallow copy), temporal weights scaled."""
        sub = copy.copy(self)
        index = torch.as_tensor(frames)
        sub.base = self.base.index_select(0, index)
        sub.targets = self.targets.index_select(0, index)
        sub.sqrt_w = self.sqrt_w.index_select(0, index)
        sub.x0 = self.x0[frames]
        sub.w_temporal = self.w_temporal * temporal_scale
        sub.gram = _second_difference_gram(len(frames))
        return sub

    @property
    def num_vars(self) -> int:
        return int(self.S.shape[1])

    def theta(self, x: torch.Tensor, rows: slice = slice(None)) -> torch.Tensor:
        return self.base[rows] + x @ self.S_t.T

    def clamp(self, x: np.ndarray) -> np.ndarray:
        return np.clip(x, self.x_lo, self.x_hi) if self.project else x

    # -- energy (torch; differentiable for LBFGS) ---------------------------------------------
    def energy(self, x: torch.Tensor) -> torch.Tensor:
        self.evaluations += 1
        theta = self.theta(x)
        diff = self.jacobian.positions(theta) - self.targets
        r2 = ((diff * self.sqrt_w[..., None]) ** 2).sum(dim=-1)
        if self.huber_delta_m is not None:
            r2 = r2 * huber_factors(_norm(diff), self.huber_delta_m)[0]
        total = r2.sum()
        if x.shape[0] >= 3:
            dx = x[2:] - 2 * x[1:-1] + x[:-2]
            total = total + (dx * dx * torch.as_tensor(self.w_temporal, dtype=x.dtype)).sum()
        if self.w_reg > 0:
            total = total + self.w_reg * ((theta[:, self.reg_index] - self.reg_target) ** 2).sum()
        if len(self.limit_index):
            total = total + self.w_limit * (self._hinge(theta) ** 2).sum()
        return total

    def _hinge(self, theta: torch.Tensor) -> torch.Tensor:
        values = theta[:, self.limit_index]
        return torch.clamp(values - self.hi, min=0) - torch.clamp(self.lo - values, min=0)

    # -- Gauss-Newton pieces (numpy) ------------------------------------------------------------
    def local_terms(self, x: np.ndarray, frames: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per frame: energy ``e_t``, ``A_t = J_t^T J_t`` (n,n) and ``g_t = J_t^T r_t`` (n,) of
        the frame-local terms (data, regulariser, limits), for ``x`` (F,n) at the frames
        ``frames`` (F,) (default all, F = T)."""
        self.evaluations += 1
        F, n = x.shape
        frames = np.arange(F) if frames is None else np.asarray(frames)
        e, A, g = np.empty(F), np.empty((F, n, n)), np.empty((F, n))
        xt = torch.as_tensor(x, dtype=DTYPE)
        for start in range(0, F, self.chunk):
            rows = slice(start, min(start + self.chunk, F))
            index = torch.as_tensor(frames[rows])
            theta = self.base.index_select(0, index) + xt[rows] @ self.S_t.T
            t = theta.shape[0]
            sw = self.sqrt_w.index_select(0, index)
            # float32 Jacobian: half the memory traffic; J^T J and J^T r to ~1e-7, plenty for a step
            kp, Jt = self.jacobian.weighted_transpose(theta.to(JACOBIAN_DTYPE), sw)  # (t,k,3), (t,a,3k)
            diff = kp.to(DTYPE) - self.targets.index_select(0, index)
            r = (diff * sw[..., None]).reshape(t, -1)
            et = (r * r).reshape(t, -1, 3).sum(dim=2)  # (t,k)
            if self.huber_delta_m is not None:  # reweighted Gauss-Newton: rows scaled by sqrt(min(1, delta/d))
                energy_factor, row_scale = huber_factors(_norm(diff), self.huber_delta_m)
                et = et * energy_factor
                if bool((row_scale < 1).any()):
                    row_scale = row_scale.repeat_interleave(3, dim=1)
                    Jt = Jt * row_scale.to(JACOBIAN_DTYPE)[:, None, :]
                    r = r * row_scale
            et = et.sum(dim=1)
            if not self.is_selection:
                Jt = self.S_cols_t.T.to(JACOBIAN_DTYPE) @ Jt
            At = (Jt @ Jt.transpose(1, 2)).to(DTYPE)
            gt = (Jt @ r.to(JACOBIAN_DTYPE)[..., None])[..., 0].to(DTYPE)
            if self.w_reg > 0:
                res = theta[:, self.reg_index] - self.reg_target
                At = At + self.w_reg * (self.S_reg_t.T @ self.S_reg_t)
                gt = gt + self.w_reg * res @ self.S_reg_t
                et = et + self.w_reg * (res * res).sum(dim=1)
            if len(self.limit_index):
                h = self._hinge(theta)
                active = (h != 0).to(DTYPE)
                At = At + self.w_limit * torch.einsum("tl,li,lj->tij", active, self.S_lim_t, self.S_lim_t)
                gt = gt + self.w_limit * h @ self.S_lim_t
                et = et + self.w_limit * (h * h).sum(dim=1)
            A[rows], g[rows], e[rows] = At.numpy(), gt.numpy(), et.numpy()
        return e, A, g

    def solve_frames(self, A: np.ndarray, g: np.ndarray, lam: np.ndarray, prescribed: np.ndarray | None) -> np.ndarray:
        """Per-frame damped Gauss-Newton steps (F,n) (batched Cholesky), no temporal coupling;
        ``prescribed`` as in :meth:`solve`."""
        F, n = g.shape
        H = torch.as_tensor(A, dtype=DTYPE).clone()
        diag = H.diagonal(dim1=1, dim2=2)
        floor = 1e-9 * diag.amax(dim=1, keepdim=True).clamp(min=1e-12) + 1e-12
        diag += torch.as_tensor(lam, dtype=DTYPE)[:, None] * diag + floor
        rhs = -torch.as_tensor(g, dtype=DTYPE)
        if prescribed is not None:
            fixed = torch.as_tensor(~np.isnan(prescribed))
            value = torch.as_tensor(np.nan_to_num(prescribed), dtype=DTYPE)
            rhs = rhs - (H @ value[..., None])[..., 0]
            H[fixed[:, :, None] | fixed[:, None, :]] = 0.0
            H.diagonal(dim1=1, dim2=2)[fixed] = 1.0
            rhs = torch.where(fixed, value, rhs)
        L, info = torch.linalg.cholesky_ex(H)
        bad = info != 0
        if bad.any():  # not positive definite (should not happen with the floor): damp harder
            H[bad] += torch.eye(n, dtype=DTYPE) * (1e-6 * H[bad].diagonal(dim1=1, dim2=2).abs().amax(dim=1) + 1e-9)[:, None, None]
            L = torch.linalg.cholesky(H)
        return torch.cholesky_solve(rhs[..., None], L)[..., 0].numpy()

    def temporal(self, x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """Temporal energy, its half-gradient ``w D2^T D2 x`` (T,n), and per frame the energy of
        the second difference centred on it (T,)."""
        T = x.shape[0]
        grad, centred = np.zeros_like(x), np.zeros(T)
        if T < 3:
            return 0.0, grad, centred
        dx = x[2:] - 2 * x[1:-1] + x[:-2]
        wdx = dx * self.w_temporal
        grad[:-2] += wdx
        grad[1:-1] -= 2 * wdx
        grad[2:] += wdx
        centred[1:-1] = (dx * wdx).sum(axis=1)
        return float(centred.sum()), grad, centred

    def temporal_change_alone(self, x: np.ndarray, step: np.ndarray) -> np.ndarray:
        """(T,) change of the temporal energy if only frame t moved by ``step[t]``."""
        T = x.shape[0]
        change = np.zeros_like(x)
        if T < 3:
            return change.sum(axis=1)
        dx = x[2:] - 2 * x[1:-1] + x[:-2]  # residual r involves frames r, r+1, r+2 with 1, -2, 1
        s = step
        change[:-2] += 2 * dx * s[:-2] + s[:-2] ** 2
        change[1:-1] += -4 * dx * s[1:-1] + 4 * s[1:-1] ** 2
        change[2:] += 2 * dx * s[2:] + s[2:] ** 2
        return (change * self.w_temporal).sum(axis=1)

    def held_at_bounds(self, x: np.ndarray, g: np.ndarray) -> np.ndarray | None:
        """(F,n) prescribed steps: 0 for variables on a limit whose descent direction leaves the
        feasible box, NaN (free) elsewhere; None when nothing is held."""
        if not self.project:
            return None
        tol = 1e-10
        held = ((x <= self.x_lo + tol) & (g > 0)) | ((x >= self.x_hi - tol) & (g < 0))
        return np.where(held, 0.0, np.nan) if held.any() else None

    def bounded_step(self, x: np.ndarray, g: np.ndarray, solve) -> np.ndarray:
        """A feasible step from ``solve(prescribed) -> delta``: variables held on their limits,
        and variables the free step would carry past a limit put exactly on it, the rest re-solved
        (projecting the free step instead can raise the model energy and stall)."""
        prescribed = self.held_at_bounds(x, g)
        delta = solve(prescribed)
        if self.project:
            target = x + delta
            crossing = (target < self.x_lo) | (target > self.x_hi)
            if crossing.any():
                fixed = np.clip(target, self.x_lo, self.x_hi) - x
                prescribed = np.where(crossing, fixed, np.nan if prescribed is None else prescribed)
                delta = solve(prescribed)
        return self.clamp(x + delta) - x

    def solve(self, A: np.ndarray, g: np.ndarray, lam: np.ndarray, prescribed: np.ndarray | None = None) -> np.ndarray:
        """Solve ``(H + diag(lam_t) diag(H)) delta = -g`` with ``H = blockdiag(A) + D2^T D2 (x)
        diag(w)`` by one banded Cholesky; ``lam`` (T,) per-frame damping; where ``prescribed``
        (T,n) is not NaN, delta takes that value and the others are solved for."""
        T, n = g.shape
        p0, p1, p2 = self.gram
        coupled = T >= 3 and np.any(self.w_temporal > 0)
        u = 2 * n if coupled else n - 1
        ab = np.zeros((u + 1, T * n))
        for d in range(n):
            ab[d].reshape(T, n)[:, :n - d] = np.diagonal(A, offset=-d, axis1=1, axis2=2)
        if coupled:
            w = self.w_temporal
            ab[0] += (p0[:, None] * w).ravel()
            ab[n].reshape(T, n)[:-1] += p1[:, None] * w
            ab[2 * n].reshape(T, n)[:-2] += p2[:, None] * w
        diag = ab[0].copy()
        ab[0] += np.repeat(lam, n) * diag + 1e-9 * max(float(diag.max(initial=0.0)), 1e-12) + 1e-12
        rhs = -g.ravel()
        if prescribed is not None:
            fixed = ~np.isnan(prescribed.ravel())
            value = np.where(fixed, prescribed.ravel(), 0.0)
            rhs = rhs - dsbmv(u, 1.0, ab, value, lower=1)
            k = np.nonzero(fixed)[0]
            ab[:, k] = 0.0  # column k: entries H[k+d, k]
            d = np.arange(1, u + 1)[:, None]
            col = k[None, :] - d  # row k: entries H[k, k-d] live at ab[d, k-d]
            valid = col >= 0
            ab[np.broadcast_to(d, col.shape)[valid], col[valid]] = 0.0
            ab[0, k] = 1.0
            rhs = np.where(fixed, value, rhs)
        with blas_threads(1):  # a chain of small BLAS calls: see runtime.blas_threads
            try:
                factor = cholesky_banded(ab, overwrite_ab=True, lower=True, check_finite=False)
            except np.linalg.LinAlgError:  # not positive definite (round-off): damp harder
                return self.solve(A, g, lam * 10.0 + 1e-6, prescribed)
            return cho_solve_banded((factor, True), rhs, check_finite=False).reshape(T, n)


def _norm(diff: torch.Tensor) -> torch.Tensor:
    """Lengths (...,) of (...,3) vectors, with a finite gradient at zero."""
    return ((diff * diff).sum(dim=-1) + 1e-24).sqrt()


def _levenberg_marquardt(problem: _StageProblem, settings: IKSettings) -> tuple[np.ndarray, StageReport]:
    """Levenberg-Marquardt over the whole sequence with per-frame damping.

    Frames are coupled only through the temporal term, so each frame keeps its own damping
    ``lam_t``. After a trial step, frame t's move is kept only if moving frame t alone lowers
    the total energy (its local terms, exact, plus the three second differences it enters,
    exact since they are quadratic); the others are put back and their damping raised. The
    merged step is accepted when the total energy went down. One hard (far, non-linear) frame
    therefore never throttles the whole sequence.
    """
    started = time.perf_counter()
    x = problem.clamp(problem.x0.copy())
    T = x.shape[0]
    e, A, gl = problem.local_terms(x)
    energy0 = float(e.sum() + problem.temporal(x)[0])
    # an energy decrease worth less than 0.1 mm on every keypoint is no progress
    per_frame_floor = max(len(problem.keypoints), 1) * (1e-4 / settings.length_unit_m) ** 2
    frame_iterations = 0
    if settings.lm_frame_iterations > 0 and problem.warm_start:
        step = settings.lm_coarse_step
        if step > 1 and T >= 4 * step:
            # coarse to fine: sweep every step-th frame first, interpolate, then sweep all frames
            coarse = np.unique(np.r_[np.arange(0, T, step), T - 1])
            sub = problem.restricted(coarse, temporal_scale=float(step) ** -4)
            xc, ec, Ac, glc = x[coarse].copy(), e[coarse].copy(), A[coarse].copy(), gl[coarse].copy()
            xc, *_ , coarse_sweeps = _frame_sweeps(sub, xc, ec, Ac, glc, settings, per_frame_floor)
            frame_iterations += coarse_sweeps
            x = problem.clamp(np.stack([np.interp(np.arange(T), coarse, xc[:, i]) for i in range(x.shape[1])], axis=1))
            e, A, gl = problem.local_terms(x)
        x, e, A, gl, sweeps = _frame_sweeps(problem, x, e, A, gl, settings, per_frame_floor)
        frame_iterations += sweeps
    Et, gt, _ = problem.temporal(x)
    energy = float(e.sum() + Et)
    lam = np.full(T, 1e-2)
    floor = T * per_frame_floor
    iterations, previous_small = 0, False
    # after warm-start sweeps (which already minimise the full energy frame by frame) only a few
    # coupled iterations are needed, for the directions the temporal term couples strongly
    max_iterations = settings.lm_polish_iterations if frame_iterations else settings.lm_iterations
    while iterations < max_iterations:
        iterations += 1
        g = gl + gt
        delta = problem.bounded_step(x, g, lambda prescribed: problem.solve(A, g, lam, prescribed))
        x_try = x + delta
        e2, A2, gl2 = problem.local_terms(x_try)
        step = x_try - x
        predicted = e + 2 * np.einsum("ti,ti->t", gl, step) + np.einsum("ti,tij,tj->t", step, A, step)
        model_error = np.abs(e2 - predicted) / (np.abs(predicted - e) + 1e-9 * (1.0 + e))
        good = model_error < 0.25
        # keep the whole step when it lowers the energy; otherwise put back the frames whose own
        # energy rose where the linear model failed (strongly non-linear frames) and retry
        rose = e2 > e + per_frame_floor
        failed = rose & (model_error > 1.0)
        worse = np.zeros(T, bool)
        Et2, gt2, _ = problem.temporal(x_try)
        energy_try = float(e2.sum() + Et2)
        if energy_try >= energy and failed.any():
            worse = failed
            x_try = np.where(worse[:, None], x, x_try)
            e2 = np.where(worse, e, e2)
            A2[worse], gl2[worse] = A[worse], gl[worse]
            Et2, gt2, _ = problem.temporal(x_try)
            energy_try = float(e2.sum() + Et2)
        console.debug(f"ik {problem.name}: iteration {iterations}, energy {energy:.6g} -> {energy_try:.6g}, "
                      f"{int(failed.sum())} frames off their linear model, {int(worse.sum())} put back")
        if energy_try < energy:
            decrease = (energy - energy_try) / max(energy, 1e-30)
            small = decrease < settings.lm_tolerance or energy - energy_try < floor
            step_size = float(np.abs(x_try - x).max())
            x, e, A, gl, Et, gt, energy = x_try, e2, A2, gl2, Et2, gt2, energy_try
            lam = np.where(failed, lam * 10.0, np.where(good, np.maximum(lam / 3.0, 1e-9), lam))
            if (small and previous_small) or step_size < 1e-10:
                break
            previous_small = small
        else:
            lam = np.where(good, lam * 2.0, lam * 10.0)
            if lam.min() > 1e8:
                break
    report = StageReport(problem.name, problem.num_vars, frame_iterations + iterations, problem.evaluations,
                         energy0, energy, time.perf_counter() - started)
    return x, report


def _frame_sweeps(problem: _StageProblem, x: np.ndarray, e: np.ndarray, A: np.ndarray, gl: np.ndarray,
                  settings: IKSettings, floor: float):
    """Warm start: block Gauss-Seidel sweeps, one Levenberg-Marquardt step per frame.

    Frames t, t+3, t+6, ... share no second difference, so moving them together changes the
    energy by exactly the sum of their single-frame changes: each colour class is stepped at
    once (each frame with the temporal term linearised around its current neighbours), and
    every frame keeps its step only if it lowers the total energy, with its own damping. Far,
    strongly non-linear frames take many small steps here while converged ones drop out and
    cost nothing; the coupled solve then starts close to its optimum.
    """
    T, n = x.shape
    lam = np.full(T, 1e-3)
    p0 = problem.gram[0]
    todo = np.ones(T, bool)
    sweeps = 0
    energy = e.sum() + problem.temporal(x)[0]
    while todo.any() and sweeps < settings.lm_frame_iterations:
        sweeps += 1
        for colour in range(3):
            frames = np.nonzero(todo & (np.arange(T) % 3 == colour))[0]
            if not len(frames):
                continue
            _, gt, _ = problem.temporal(x)
            g = gl[frames] + gt[frames]
            H = A[frames] + (p0[frames, None] * problem.w_temporal)[:, None, :] * np.eye(n)
            lam_f = lam[frames]
            delta = problem.bounded_step(x[frames], g, lambda prescribed: problem.solve_frames(H, g, lam_f, prescribed))
            x_try = x[frames] + delta
            e2, A2, gl2 = problem.local_terms(x_try, frames)
            step = np.zeros_like(x)
            step[frames] = x_try - x[frames]
            change = (e2 - e[frames]) + problem.temporal_change_alone(x, step)[frames]
            better = change < 0
            keep = frames[better]
            x[keep], e[keep], A[keep], gl[keep] = x_try[better], e2[better], A2[better], gl2[better]
            lam[keep] = np.maximum(lam[keep] / 3.0, 1e-9)
            lam[frames[~better]] *= 10.0
            small = np.abs(delta).max(axis=1) < 1e-8
            done = (better & (-change < settings.lm_tolerance * (e2 + 1e-30) + 0.1 * floor)) | small | (lam[frames] > 1e8)
            todo[frames[done]] = False
        energy_before, energy = energy, e.sum() + problem.temporal(x)[0]
        console.debug(f"ik {problem.name}: sweep {sweeps}, {int(todo.sum())} frames active, energy {energy:.6g}")
        if energy_before - energy < settings.lm_sweep_tolerance * energy:
            break  # what is left is coupled across frames: the banded solve's job
    return x, e, A, gl, sweeps


def _lbfgs(problem: _StageProblem, settings: IKSettings) -> tuple[np.ndarray, StageReport]:
    started = time.perf_counter()
    x = torch.tensor(problem.clamp(problem.x0.copy()), dtype=DTYPE, requires_grad=True)
    with torch.no_grad():
        energy0 = float(problem.energy(x))
    optimiser = torch.optim.LBFGS([x], lr=1.0, max_iter=settings.lbfgs_iterations, history_size=settings.lbfgs_history,
                                  line_search_fn="strong_wolfe")

    def closure():
        optimiser.zero_grad()
        energy = problem.energy(x)
        energy.backward()
        return energy

    optimiser.step(closure)
    iterations = int(optimiser.state[optimiser._params[0]].get("n_iter", 0))
    with torch.no_grad():
        energy = float(problem.energy(x))
    report = StageReport(problem.name, problem.num_vars, iterations, problem.evaluations, energy0, energy,
                         time.perf_counter() - started)
    return x.detach().numpy().copy(), report


# --------------------------------------------------------------------------------- root init
def _kabsch(P: np.ndarray, Q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted rotations R (T,3,3) with ``R P + t ~ Q``; P (K,3), Q (T,K,3), w (T,K)."""
    wsum = w.sum(axis=1, keepdims=True)[..., None]
    pc = (w[..., None] * P).sum(axis=1, keepdims=True) / wsum
    qc = (w[..., None] * Q).sum(axis=1, keepdims=True) / wsum
    H = np.einsum("tk,tki,tkj->tij", w, P - pc, Q - qc)
    return project_to_rotation(np.swapaxes(H, 1, 2))


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
    R = _kabsch(P, targets[valid][:, torso], w[valid])
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
             settings: IKSettings = IKSettings()) -> IKResult:
    """Solve the motion of ``character`` that best explains ``keypoints`` (see the module
    docstring). ``model`` defaults to :func:`default_ik_model`.

    Gross outliers (:mod:`egorelight_cli.stages.ik_robust`) are dropped: keypoints far from their
    frame's body before the fit, then keypoints far off a first fit (the motion is fitted again
    without them); ``IKResult.rejected`` marks both.
    """
    started = time.perf_counter()
    check_keypoints_for(character, keypoints, settings)
    model = (model or default_ik_model(character, settings)).check_character(character)
    xyz = keypoints.xyz.astype(np.float64)
    conf = _data_weights(keypoints, settings)
    rejected = distant_keypoints(xyz, conf > 0, settings.outlier_distance_m)
    conf[rejected] = 0.0
    theta, reports = _fit(character, model, xyz, conf, settings)
    fitted, residual = _fit_residuals(character, theta, xyz, conf)
    again = residual_outliers(residual, conf > 0, settings.outlier_residual_factor, settings.outlier_min_residual_m)
    if again.any():
        console.debug(f"ik: {int(again.sum())} keypoints far off the first fit dropped, fitting again")
        rejected |= again
        conf[again] = 0.0
        theta, more = _fit(character, model, xyz, conf, settings)
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


def fitted_keypoints(character: Character, theta: np.ndarray, chunk: int = 512) -> np.ndarray:
    """FK keypoints (T,K,3) of ``theta`` (T,D), float64."""
    plan = KeypointJacobian.build(character.skeleton, character.keypoint_joints, character.keypoint_offsets, [])
    theta = torch.as_tensor(np.asarray(theta, dtype=np.float64))
    out = [plan.positions(theta[i:i + chunk]) for i in range(0, len(theta), chunk)]
    return torch.cat(out).numpy() if out else np.zeros((0, len(character.keypoint_names), 3))


# ------------------------------------------------------------------------------------ metrics
def _mpjpe_cm(distance_m: np.ndarray, part: slice) -> float | None:
    values = distance_m[:, part]
    values = values[np.isfinite(values)]
    return float(100.0 * values.mean()) if values.size else None


def _part_errors(distance_m: np.ndarray, prefix: str) -> dict[str, float | None]:
    hands = np.concatenate([distance_m[:, LEFT_HAND_SLICE], distance_m[:, RIGHT_HAND_SLICE]], axis=1)
    return {f"{prefix}_body_cm": _mpjpe_cm(distance_m, BODY_SLICE),
            f"{prefix}_hands_cm": _mpjpe_cm(hands, slice(None)),
            f"{prefix}_all_cm": _mpjpe_cm(distance_m, slice(None))}


def fit_metrics(result: IKResult) -> dict:
    """MPJPE (cm) of the fitted keypoints against the input keypoints (body, hands, all; rejected
    outliers left out), the number of rejected keypoints (and of frames with one), and the
    solver's timing."""
    metrics = _part_errors(result.residual_m, "mpjpe_input")
    T = max(len(result.theta), 1)
    rejected = result.rejected if result.rejected is not None else np.zeros((len(result.theta), 0), bool)
    metrics.update({"rejected_keypoints": int(rejected.sum()), "rejected_frames": int(rejected.any(axis=1).sum())})
    metrics.update({"solver": result.solver, "frames": int(len(result.theta)), "solve_s": round(result.seconds, 3),
                    "ms_per_frame": round(1000.0 * result.seconds / T, 3),
                    "stages": [asdict(s) for s in result.stages]})
    return metrics


def gt_metrics(character: Character, result: IKResult, gt_keypoints: Keypoints | None = None,
               gt_motion: Motion | None = None) -> dict:
    """Errors against ground truth on the frames both hold: MPJPE (cm; body, hands, all) against
    ground-truth keypoints (given, or FK of the ground-truth motion) and, with a motion, mean
    absolute DoF error (degrees over revolute DoFs; cm for the root translation)."""
    metrics: dict = {}
    sk = character.skeleton
    if gt_motion is not None:
        gt_motion.check_dofs(sk.dof_names)
        ids, ours, theirs = np.intersect1d(result.frame_ids, gt_motion.frame_ids, return_indices=True)
        if len(ids) == 0:
            raise EgorelightError("ground-truth motion shares no frame id with the input")
        gt_theta = gt_motion.theta[theirs].astype(np.float64)
        diff = result.theta[ours] - gt_theta
        groups = classify_dofs(character)
        weights = np.abs(sk.dof_joint_weights).max(axis=1)
        period = 2 * np.pi / np.maximum(weights, 1e-12)
        revolute = np.array([(sk.joint_types[sk.dof_joint_weights[d] != 0] == REVOLUTE).all() for d in range(sk.num_dofs)])
        root_rot = groups.root[revolute[groups.root]]
        diff[:, root_rot] = (diff[:, root_rot] + period[root_rot] / 2) % period[root_rot] - period[root_rot] / 2
        solved = np.zeros(sk.num_dofs, bool)
        solved[np.concatenate([groups.root, groups.body, *groups.hands.values()]).astype(np.int64)] = True
        hand = np.zeros(sk.num_dofs, bool)
        for index in groups.hands.values():
            hand[index] = True
        joint_angle = np.abs(diff) * weights  # DoF error as joint motion
        deg = lambda mask: float(np.degrees(joint_angle[:, mask].mean())) if mask.any() else None  # noqa: E731
        metrics.update({"gt_dof_error_deg": deg(solved & revolute), "gt_dof_error_body_deg": deg(solved & revolute & ~hand),
                        "gt_dof_error_hands_deg": deg(solved & revolute & hand)})
        trans = groups.root[~revolute[groups.root]]
        if len(trans):
            metrics["gt_root_translation_error_cm"] = float(100 * np.linalg.norm(diff[:, trans], axis=1).mean())
        if gt_keypoints is None:
            xyz = (gt_motion.fitted_keypoints[theirs] if gt_motion.fitted_keypoints is not None
                   else fitted_keypoints(character, gt_theta))
            gt_keypoints = Keypoints(xyz, np.ones(xyz.shape[:2]), ids, character.keypoint_names)
    if gt_keypoints is not None:
        ids, ours, theirs = np.intersect1d(result.frame_ids, gt_keypoints.frame_ids, return_indices=True)
        if len(ids) == 0:
            raise EgorelightError("ground-truth keypoints share no frame id with the input")
        if len(gt_keypoints.names) != result.fitted_keypoints.shape[1]:
            raise EgorelightError(f"ground-truth keypoints have {len(gt_keypoints.names)} keypoints, expected "
                                  f"{result.fitted_keypoints.shape[1]}")
        dist = np.linalg.norm(result.fitted_keypoints[ours] - gt_keypoints.xyz[theirs], axis=-1)
        dist[gt_keypoints.confidence[theirs] <= 0] = np.nan
        metrics.update(_part_errors(dist, "gt_mpjpe"))
        metrics["gt_frames"] = int(len(ids))
    return metrics


def jitter_m(xyz: np.ndarray) -> float:
    """Mean norm of the second temporal difference of (T,K,3) positions (m per frame^2)."""
    if len(xyz) < 3:
        return 0.0
    acc = np.linalg.norm(xyz[2:] - 2 * xyz[1:-1] + xyz[:-2], axis=-1)
    return float(np.nanmean(acc))


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
