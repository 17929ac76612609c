"""What ``train ik`` learns and how the IK sees a character: DoF classes (root, body, hands,
fixed, unobservable; see :mod:`egorelight_cli.stages.ik`), per-hand PCA of the finger DoFs and
the :class:`IKModel` (mean pose + hand PCAs) with its training."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.ik_jacobian import dof_influence, root_chain_joints
from egorelight_cli.stages.ik_settings import IKSettings
from egorelight_cli.structures.character import Character
from egorelight_cli.structures.skeleton import PRISMATIC, REVOLUTE

SIDES = ("Left", "Right")
FINGER_JOINT = re.compile(r"^(Left|Right)Hand(Thumb|Index|Middle|Ring|Pinky)")
CURL_JOINT = re.compile(r"^(Left|Right)Hand(Thumb|Index|Middle|Ring|Pinky)\d$")


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


def finger_of(character: Character, d: int) -> tuple[str, bool]:
    """(finger name, is a curl DoF) of a hand DoF, from its first driven joint's name."""
    sk = character.skeleton
    names = [sk.joint_names[j] for j in np.nonzero(sk.dof_joint_weights[d])[0]]
    finger = FINGER_JOINT.match(names[0]).group(2)
    return finger, any(CURL_JOINT.match(n) for n in names)


def synthetic_hand_poses(character: Character, dof_index: np.ndarray, num: int, rng: np.random.Generator,
                         max_flexion_rad: float) -> np.ndarray:
    """(num, m) finger poses sampled within the DoF limits with anatomical coupling.

    A latent grasp ``g ~ Beta(0.7, 0.7)`` (0 open, 1 fist) drives every finger: finger curl
    ``c_f = clip(g + 0.2 N)`` (thumb ``clip(0.6 g + 0.2 + 0.25 N)``), and each joint of the finger
    curls ``clip(c_f + 0.08 N)`` of the way from the rest value to its flexion end: the limit on
    the side with the larger range, but no further than ``max_flexion_rad`` of *joint* rotation.
    A DoF drives its joints with a weight (DDC fingers: 3), so a DoF value ``v`` turns the joint
    by ``weight * v``; limits are in DoF units and can allow far more than a finger bends (the DDC
    example's [-1.57, 0.3] are -270..+52 degrees of joint rotation). Spread/abduction DoFs are
    uniform within their limits (again capped at ``max_flexion_rad`` of joint rotation from rest),
    biased towards spreading when the hand is open. DoFs without finite limits get +-0.8 rad of
    joint motion around rest (curl DoFs then sample both directions).
    """
    sk = character.skeleton
    limits = sk.dof_limits[dof_index]
    rest = np.clip(character.rest_theta[dof_index], limits[:, 0], limits[:, 1])
    weight = np.maximum(np.array([np.abs(sk.dof_joint_weights[d]).max() for d in dof_index]), 1e-6)
    span = 0.8 / weight
    reach = max_flexion_rad / weight  # the most a finger joint turns, in DoF units
    lo = np.where(np.isfinite(limits[:, 0]), np.maximum(limits[:, 0], rest - reach), rest - span)
    hi = np.where(np.isfinite(limits[:, 1]), np.minimum(limits[:, 1], rest + reach), rest + span)
    info = [finger_of(character, int(d)) for d in dof_index]
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
    return {"hand_components": settings.hand_components, "hand_samples": settings.hand_samples,
            "hand_max_flexion_deg": settings.hand_max_flexion_deg, "seed": settings.seed}


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
        synthetic = synthetic_hand_poses(character, index, settings.hand_samples, rng,
                                         np.radians(settings.hand_max_flexion_deg))
        source = data[:, index] if len(data) >= 2 else synthetic
        mean, basis, variance = fit_pca(source, settings.hand_components, fallback=synthetic)
        total = float(np.var(source, axis=0, ddof=1).sum()) if len(source) > 1 else 0.0
        hands.append(HandPCA(side, index, mean, basis, variance, max(total, float(variance.sum()))))
        theta_bar[index] = mean
    return IKModel(tuple(sk.dof_names), theta_bar, tuple(hands), "motions" if len(data) else "default",
                   int(len(data)), _model_settings(settings))
