"""Analytic Jacobians of keypoint positions with respect to skeleton DoFs, and the skeleton
structure inverse kinematics needs (root chain, ancestors, DoF observability).

For a keypoint ``P`` attached to joint ``j`` (``P = G_j @ offset``) and a joint ``a`` on the path
from the root to ``j`` (``a`` itself included), with ``G_a = G_parent @ translate(o_a) @
motion_a(q_a)``:

* revolute ``a``: ``dP/dq_a = (R_a axis_a) x (P - p_a)`` — the world axis (``R_a axis_a`` equals
  ``R_parent axis_a``, a rotation leaves its own axis fixed) crossed with the lever from the
  joint origin ``p_a`` (a rotation does not move its own origin);
* prismatic ``a``: ``dP/dq_a = R_a axis_a`` (``R_a = R_parent``; the axis is not normalised, as
  in DDC).

DoFs drive joints linearly (``q = theta @ dof_joint_weights``), so ``dP/dtheta_d = sum_a
W[d, a] dP/dq_a``. Everything is batched over frames in torch (float64 recommended).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from egorelight_cli.geometry.rotations import axis_angle_rotation
from egorelight_cli.structures.skeleton import PRISMATIC, REVOLUTE, Skeleton


def ancestor_matrix(parents: np.ndarray) -> np.ndarray:
    """(J,J) bool: ``A[j, a]`` is True when ``a`` is ``j`` or one of its ancestors."""
    parents = np.asarray(parents)
    A = np.zeros((len(parents), len(parents)), dtype=bool)
    for j, p in enumerate(parents):
        if p >= 0:
            A[j] = A[p]
        A[j, j] = True
    return A


def root_chain_joints(skeleton: Skeleton) -> np.ndarray:
    """(J,) bool: the global-pose chain at the root.

    The chain starts at the first root joint and follows only children while the path so far
    is a single-child chain of at most 3 prismatic and 3 revolute joints (DDC: ``Root_tx ty tz
    ry rz rx``). It stops before a joint that would exceed either count or where the tree
    branches (the joint with several children is the last member).
    """
    parents = skeleton.parents
    children: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            children[p].append(j)
    chain = np.zeros(len(parents), dtype=bool)
    roots = np.nonzero(parents < 0)[0]
    if len(roots) == 0:
        return chain
    counts = {PRISMATIC: 0, REVOLUTE: 0}
    j = int(roots[0])
    while True:
        kind = int(skeleton.joint_types[j])
        if counts[kind] >= 3:
            break
        counts[kind] += 1
        chain[j] = True
        if len(children[j]) != 1:
            break
        j = children[j][0]
    return chain


def dof_influence(skeleton: Skeleton, keypoint_joints: np.ndarray, keypoint_offsets: np.ndarray) -> np.ndarray:
    """(K,D) bool: structurally, may DoF ``d`` move keypoint ``k``?

    True when ``d`` drives a joint on the keypoint's root path that moves it: any prismatic joint
    on the path, a revolute proper ancestor, or the keypoint's own revolute joint when the
    keypoint has a non-zero offset from it.
    """
    A = ancestor_matrix(skeleton.parents)
    keypoint_joints = np.asarray(keypoint_joints)
    moves = A[keypoint_joints].copy()  # (K,J)
    own = np.linalg.norm(np.asarray(keypoint_offsets), axis=1) < 1e-12
    revolute_own = own & (skeleton.joint_types[keypoint_joints] == REVOLUTE)
    moves[np.nonzero(revolute_own)[0], keypoint_joints[revolute_own]] = False
    drives = skeleton.dof_joint_weights != 0  # (D,J)
    return (moves.astype(np.int64) @ drives.T.astype(np.int64)) > 0


class SubsetKinematics:
    """Forward kinematics of only the joints some keypoints need (their root paths), level by
    level: every joint of tree depth d is composed with its parent (depth d-1) in one batched
    product, so a pass costs ~depth operations instead of one per joint. Rotations and
    translations are kept apart (``R`` (T,S,3,3), ``t`` (T,S,3)). Differentiable (no in-place).
    """

    def __init__(self, skeleton: Skeleton, keypoint_joints: np.ndarray):
        keypoint_joints = np.asarray(keypoint_joints, dtype=np.int64)
        A = ancestor_matrix(skeleton.parents)
        needed = A[keypoint_joints].any(axis=0) if len(keypoint_joints) else np.zeros(skeleton.num_joints, bool)
        self.joints = np.nonzero(needed)[0]  # subset, parents before children
        position = np.full(skeleton.num_joints, -1)
        position[self.joints] = np.arange(len(self.joints))
        self.position = position  # skeleton joint -> subset index
        depth = A.sum(axis=1)[self.joints] - 1  # number of proper ancestors
        self.levels: list[tuple[torch.Tensor, torch.Tensor]] = []  # (subset joints, parent index in previous level)
        order = []
        previous = np.zeros(0, np.int64)
        for d in range(int(depth.max(initial=-1)) + 1):
            members = np.nonzero(depth == d)[0]
            parent_sub = position[skeleton.parents[self.joints[members]]] if d else np.zeros(0, np.int64)
            parent_in_level = np.searchsorted(previous, parent_sub) if d else np.zeros(0, np.int64)
            self.levels.append((torch.as_tensor(members), torch.as_tensor(parent_in_level)))
            order.append(members)
            previous = members
        order = np.concatenate(order) if order else np.zeros(0, np.int64)
        self.unsort = torch.as_tensor(np.argsort(order))  # level-concatenated -> subset order
        self.weights = skeleton.dof_joint_weights[:, self.joints]  # (D,S)
        self.axes = skeleton.axes[self.joints]
        self.offsets = skeleton.offsets[self.joints]
        self.revolute = torch.as_tensor(skeleton.joint_types[self.joints] == REVOLUTE)
        self.skeleton = skeleton
        self._tensors: dict = {}

    def _as(self, name: str, dtype: torch.dtype, device) -> torch.Tensor:
        key = (name, dtype, str(device))
        if key not in self._tensors:
            self._tensors[key] = torch.as_tensor(getattr(self, name), dtype=dtype, device=device)
        return self._tensors[key]

    def __call__(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``R`` (T,S,3,3) and ``t`` (T,S,3) of the subset joints for DoF values (T,D)."""
        dtype, device = theta.dtype, theta.device
        if not len(self.joints):
            T = theta.shape[0]
            return theta.new_zeros((T, 0, 3, 3)), theta.new_zeros((T, 0, 3))
        params = theta @ self._as("weights", dtype, device)  # (T,S)
        revolute = self.revolute.to(device)
        angle = torch.where(revolute, params, torch.zeros_like(params))
        axes = self._as("axes", dtype, device)
        R_local = axis_angle_rotation(axes, angle)
        slide = torch.where(revolute, torch.zeros_like(params), params)
        t_local = self._as("offsets", dtype, device) + axes * slide[..., None]
        Rs, ts = [], []
        for d, (members, parent) in enumerate(self.levels):
            R_l, t_l = R_local[:, members], t_local[:, members]
            if d == 0:
                Rs.append(R_l)
                ts.append(t_l)
                continue
            R_p, t_p = Rs[-1][:, parent], ts[-1][:, parent]
            Rs.append(R_p @ R_l)
            ts.append((R_p @ t_l[..., None])[..., 0] + t_p)
        R = torch.cat(Rs, dim=1)[:, self.unsort]
        t = torch.cat(ts, dim=1)[:, self.unsort]
        return R, t


@dataclass(frozen=True, eq=False)
class KeypointJacobian:
    """Keypoint positions and their Jacobian w.r.t. a subset of DoFs, with the index structure
    precomputed once (see the module docstring for the formulas).

    Build with :meth:`build`; :meth:`positions` gives keypoints (T,K,3) of ``theta`` (T,D) (FK of
    the needed joints only); calling it gives keypoints and the Jacobian (T,K,3,n) w.r.t.
    ``theta[:, dof_index]``; :meth:`weighted_transpose` gives the Gauss-Newton layout.
    """

    kinematics: SubsetKinematics
    keypoint_joints: torch.Tensor  # (K,) subset indices
    keypoint_offsets: np.ndarray  # (K,3) float64
    dof_index: np.ndarray  # (n,)
    joints: torch.Tensor  # (U,) subset indices of joints driven by the selected DoFs that move some keypoint
    axes: np.ndarray  # (U,3)
    pair_keypoint: torch.Tensor  # (P,)
    pair_joint: torch.Tensor  # (P,) index into ``joints``
    pair_revolute: torch.Tensor  # (P,) bool
    entry_pair: torch.Tensor  # (Q,) pair of each (pair, DoF) entry
    entry_column: torch.Tensor  # (Q,) keypoint * n + column
    entry_weight: np.ndarray  # (Q,) dof_joint_weights[dof, joint]

    @classmethod
    def build(cls, skeleton: Skeleton, keypoint_joints, keypoint_offsets, dof_index) -> "KeypointJacobian":
        keypoint_joints = np.asarray(keypoint_joints, dtype=np.int64).reshape(-1)
        dof_index = np.asarray(dof_index, dtype=np.int64).reshape(-1)
        kinematics = SubsetKinematics(skeleton, keypoint_joints)
        W = skeleton.dof_joint_weights[dof_index]  # (n,J)
        driven = np.nonzero((W != 0).any(axis=0))[0]
        A = ancestor_matrix(skeleton.parents)
        on_path = A[keypoint_joints][:, driven]  # (K,U)
        used = on_path.any(axis=0)
        driven, on_path = driven[used], on_path[:, used]
        pair_k, pair_u = np.nonzero(on_path)
        n = len(dof_index)
        entries_p, entries_c, entries_w = [], [], []
        for c in range(n):
            weights = W[c, driven[pair_u]]
            hit = np.nonzero(weights != 0)[0]
            entries_p.append(hit)
            entries_c.append(pair_k[hit] * n + c)
            entries_w.append(weights[hit])
        cat = lambda parts, dtype: np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)  # noqa: E731
        return cls(
            kinematics=kinematics,
            keypoint_joints=torch.as_tensor(kinematics.position[keypoint_joints]),
            keypoint_offsets=np.asarray(keypoint_offsets, dtype=np.float64).reshape(-1, 3),
            dof_index=dof_index,
            joints=torch.as_tensor(kinematics.position[driven]),
            axes=skeleton.axes[driven],
            pair_keypoint=torch.as_tensor(pair_k),
            pair_joint=torch.as_tensor(pair_u),
            pair_revolute=torch.as_tensor(skeleton.joint_types[driven[pair_u]] == REVOLUTE),
            entry_pair=torch.as_tensor(cat(entries_p, np.int64)),
            entry_column=torch.as_tensor(cat(entries_c, np.int64)),
            entry_weight=cat(entries_w, np.float64),
        )

    @property
    def num_keypoints(self) -> int:
        return int(self.keypoint_joints.shape[0])

    def keypoints_from(self, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Keypoint positions (T,K,3) from subset transforms (see :class:`SubsetKinematics`)."""
        offsets = torch.as_tensor(self.keypoint_offsets, dtype=R.dtype, device=R.device)
        Rk = R.index_select(1, self.keypoint_joints)
        return (Rk @ offsets[..., None])[..., 0] + t.index_select(1, self.keypoint_joints)

    def positions(self, theta: torch.Tensor) -> torch.Tensor:
        """Keypoint positions (T,K,3) of DoF values ``theta`` (T,D); differentiable."""
        return self.keypoints_from(*self.kinematics(theta))

    def __call__(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Keypoints (T,K,3) and Jacobian (T,K,3,n) at ``theta`` (T,D)."""
        kp, Jt = self.weighted_transpose(theta)
        T, n, K = Jt.shape[0], len(self.dof_index), self.num_keypoints
        return kp, Jt.view(T, n, K, 3).permute(0, 2, 3, 1)

    def weighted_transpose(self, theta: torch.Tensor, weights: torch.Tensor | None = None,
                           dtype: torch.dtype | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Keypoints (T,K,3) in ``theta``'s dtype and the transposed, row-weighted Jacobian
        ``Jt[t, c, 3k + i] = weights[t, k] * dP_k,i / dtheta_c`` (T,n,3K) in ``dtype`` (default
        ``theta``'s) — the layout Gauss-Newton wants (``J^T J = Jt @ Jt^T``).

        Internally frames go last (``(pairs, 3, T)``), so every gather moves contiguous rows
        of ``T`` values instead of 3-vectors.
        """
        R, t = self.kinematics(theta)
        T = theta.shape[0]
        dtype = dtype or theta.dtype
        device = theta.device
        kp = self.keypoints_from(R, t)
        n, K = len(self.dof_index), self.num_keypoints
        out = torch.zeros(T, K * n, 3, dtype=dtype, device=device)
        if len(self.entry_pair):
            Ru = R.index_select(1, self.joints).to(dtype)  # (T,U,3,3)
            axes = torch.as_tensor(self.axes, dtype=dtype, device=device)
            axis_world = torch.einsum("tuij,uj->uit", Ru, axes).contiguous()  # (U,3,T)
            origin = t.index_select(1, self.joints).to(dtype).permute(1, 2, 0).contiguous()  # (U,3,T)
            kp_last = kp.to(dtype).permute(1, 2, 0).contiguous()  # (K,3,T)
            a = axis_world.index_select(0, self.pair_joint)  # (P,3,T)
            lever = kp_last.index_select(0, self.pair_keypoint) - origin.index_select(0, self.pair_joint)
            ax, ay, az = a.unbind(1)
            lx, ly, lz = lever.unbind(1)
            cross = torch.stack([ay * lz - az * ly, az * lx - ax * lz, ax * ly - ay * lx], dim=1)
            d = torch.where(self.pair_revolute[:, None, None], cross, a)
            scale = torch.as_tensor(self.entry_weight, dtype=dtype, device=device)[:, None].expand(-1, T)
            if weights is not None:
                entry_keypoint = self.pair_keypoint.index_select(0, self.entry_pair)
                scale = scale * weights.to(dtype).T.index_select(0, entry_keypoint)
            entries = (d.index_select(0, self.entry_pair) * scale[:, None, :]).permute(2, 0, 1)  # (T,Q,3)
            out.index_add_(1, self.entry_column, entries)
        Jt = out.view(T, K, n, 3).permute(0, 2, 1, 3).reshape(T, n, 3 * K)
        return kp, Jt


def finite_difference_jacobian(theta: np.ndarray, skeleton: Skeleton, keypoint_joints, keypoint_offsets,
                               dof_index, eps: float = 1e-6) -> np.ndarray:
    """Central-difference Jacobian (K,3,n) of keypoints at one pose ``theta`` (D,) — for tests."""
    plan = KeypointJacobian.build(skeleton, keypoint_joints, keypoint_offsets, dof_index)
    dof_index = np.asarray(dof_index).reshape(-1)
    thetas = np.repeat(np.asarray(theta, dtype=np.float64)[None], 2 * len(dof_index), axis=0)
    for c, d in enumerate(dof_index):
        thetas[2 * c, d] += eps
        thetas[2 * c + 1, d] -= eps
    kp = plan.positions(torch.as_tensor(thetas)).numpy()
    return np.stack([(kp[2 * c] - kp[2 * c + 1]) / (2 * eps) for c in range(len(dof_index))], axis=-1)
