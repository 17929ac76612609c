"""IK evaluation: FK keypoints of a motion, MPJPE against the input and against ground truth,
DoF errors, jitter."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.ik_jacobian import KeypointJacobian
from egorelight_cli.geometry.mpjpe import mean_distance_cm
from egorelight_cli.structures.keypoints import Keypoints
from egorelight_cli.structures.motion import Motion
from egorelight_cli.stages.ik_model import classify_dofs
from egorelight_cli.stages.ik_solvers import IKResult
from egorelight_cli.structures.character import Character
from egorelight_cli.structures.keypoints import BODY_SLICE, LEFT_HAND_SLICE, RIGHT_HAND_SLICE
from egorelight_cli.structures.skeleton import REVOLUTE


def fitted_keypoints(character: Character, theta: np.ndarray, chunk: int = 512) -> np.ndarray:
    """FK keypoints (T,K,3) of ``theta`` (T,D), float64."""
    plan = KeypointJacobian.build(character.skeleton, character.keypoint_joints, character.keypoint_offsets, [])
    theta = torch.as_tensor(np.asarray(theta, dtype=np.float64))
    out = [plan.positions(theta[i:i + chunk]) for i in range(0, len(theta), chunk)]
    return torch.cat(out).numpy() if out else np.zeros((0, len(character.keypoint_names), 3))


def motion_keypoints(character: Character, motion: Motion, rows=slice(None)) -> Keypoints:
    """The keypoints of ``motion``'s frames ``rows`` (confidence 1): its stored fitted keypoints,
    else FK of its theta on ``character``."""
    xyz = (motion.fitted_keypoints[rows] if motion.fitted_keypoints is not None
           else fitted_keypoints(character, motion.theta[rows].astype(np.float64)))
    return Keypoints(xyz, np.ones(xyz.shape[:2]), motion.frame_ids[rows], character.keypoint_names)


# ------------------------------------------------------------------------------------ metrics
def _mpjpe_cm(distance_m: np.ndarray, part: slice) -> float | None:
    value = mean_distance_cm(distance_m[:, part])
    return None if np.isnan(value) else value


def _part_errors(distance_m: np.ndarray, prefix: str) -> dict[str, float | None]:
    hands = np.concatenate([distance_m[:, LEFT_HAND_SLICE], distance_m[:, RIGHT_HAND_SLICE]], axis=1)
    return {f"{prefix}_body_cm": _mpjpe_cm(distance_m, BODY_SLICE),
            f"{prefix}_hands_cm": _mpjpe_cm(hands, slice(None)),
            f"{prefix}_all_cm": _mpjpe_cm(distance_m, slice(None))}


def fit_metrics(result: IKResult) -> dict:
    """MPJPE (cm) of the fitted keypoints against the input keypoints (body, hands, all; rejected
    outliers left out), the number of rejected keypoints (and of frames with one), and what each
    solver stage did (how long each took is in :func:`solve_timing`: metrics are what a re-run
    reproduces)."""
    metrics = _part_errors(result.residual_m, "mpjpe_input")
    rejected = result.rejected if result.rejected is not None else np.zeros((len(result.theta), 0), bool)
    metrics.update({"rejected_keypoints": int(rejected.sum()), "rejected_frames": int(rejected.any(axis=1).sum())})
    metrics.update({"solver": result.solver, "frames": int(len(result.theta)),
                    "stages": [{k: v for k, v in asdict(s).items() if k != "seconds"} for s in result.stages]})
    return metrics


def solve_timing(result: IKResult) -> dict:
    """The solve's wall time (s), per frame (ms) and per stage (s), for the manifest's ``timing``."""
    per_frame_ms = 1000.0 * result.seconds / max(len(result.theta), 1)
    return {"solve_s": round(result.seconds, 3), "ms_per_frame": round(per_frame_ms, 3),
            "stages_s": {s.name: round(s.seconds, 3) for s in result.stages}}


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
        if len(groups.unobservable):  # the neck and head: at the mean pose, or placed by the headset (ik_head.py)
            from egorelight_cli.stages.ik_head import head_chain

            neck_head = np.zeros(sk.num_dofs, bool)
            neck_head[head_chain(character).dofs] = True
            metrics["gt_dof_error_neck_head_deg"] = deg(neck_head & revolute)
        trans = groups.root[~revolute[groups.root]]
        if len(trans):
            metrics["gt_root_translation_error_cm"] = float(100 * np.linalg.norm(diff[:, trans], axis=1).mean())
        if gt_keypoints is None:
            gt_keypoints = motion_keypoints(character, gt_motion, theirs)
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
