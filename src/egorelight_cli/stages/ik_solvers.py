"""The IK solvers (see :mod:`egorelight_cli.stages.ik`): one hierarchical stage as a least-squares
problem over the whole sequence (:class:`_StageProblem`), banded Levenberg-Marquardt with
Gauss-Seidel warm start, and the LBFGS baseline; the result types."""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import torch
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.linalg.blas import dsbmv

from egorelight_cli import console
from egorelight_cli.geometry.ik_jacobian import KeypointJacobian, dof_influence
from egorelight_cli.structures.motion import Motion
from egorelight_cli.runtime import blas_threads
from egorelight_cli.stages.ik_robust import huber_factors
from egorelight_cli.stages.ik_settings import IKSettings
from egorelight_cli.structures.character import Character

DTYPE = torch.float64
JACOBIAN_DTYPE = torch.float32


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
