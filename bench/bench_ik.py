"""Benchmark: the ``ik`` solvers, ``lm`` (ours) against ``lbfgs`` (the paper's baseline).

Both solve the same 1000-frame sequence (30 fps) from the same noisy keypoints with the same
energy, stages, initial guess and the ``cpu`` preset config (the demo's): per solver, milliseconds
per frame, total seconds, MPJPE (cm) against the noisy input and against the noise-free truth,
and the speed ratio. Characters: the shipped default (motion: the synthetic capture's motion
library: walking, waving, boxing, ...) and, when ``../shared`` is present, the public DDC example
(107 DoFs; smooth random motion within its limits, fingers opening and closing independently in
joint-angle space, outside the default hand subspace). ``hand_prior`` scores the hands from
noise-free keypoints with the default model, the pre-fix uncapped prior and a model trained on
the motion's first half (issue 21). Noise: Gaussian, 2 cm per coordinate on body
keypoints and 1 cm on hand keypoints (egocentric detectors are at ~4-5 cm MPJPE, paper Tab. 3).

Goal (issue 7): ``lm`` at least 20x faster than ``lbfgs`` with equal or lower MPJPE, and under
5 ms per frame on 2 CPU cores. ``BENCH_IK_LBFGS_FRAMES`` (default 1000) times LBFGS on a prefix
only, reported per frame. Because 100 LBFGS iterations per stage stop far from the optimum of the
temporally coupled energy, LBFGS also runs with 300 and 1000 iterations per stage on the first
200 frames (``BENCH_IK_LONGER_LBFGS``, empty to skip): time and MPJPE there show what equal
accuracy would cost it. Run ``python bench/bench_ik.py``; it prints a JSON dict.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from egorelight_cli.config import resolve_config
from egorelight_cli.io.character import load_default_character
from egorelight_cli.io.keypoints import Keypoints
from egorelight_cli.stages.ik import (IKSettings, classify_dofs, clamp_to_limits, default_ik_model, fit_metrics,
                                      fitted_keypoints, solve_ik)
from egorelight_cli.stages.ik_model import finger_of, train_ik_model
from egorelight_cli.structures.keypoints import BODY_SLICE

FRAMES = 1000
FPS = 30.0
LBFGS_FRAMES = int(os.environ.get("BENCH_IK_LBFGS_FRAMES", FRAMES))
ACCURACY_FRAMES = 200  # prefix on which LBFGS also runs with more iterations per stage
LONGER_LBFGS = tuple(int(n) for n in os.environ.get("BENCH_IK_LONGER_LBFGS", "300,1000").split(",") if n)
BODY_NOISE_M = 0.02
HAND_NOISE_M = 0.01
DDC_CHARACTER = Path(__file__).resolve().parents[2] / "shared" / "data" / "ddc_example" / "ddc.character"


def library_motion(character) -> np.ndarray:
    """The synthetic capture's scripted motions (default character DoF names)."""
    from egorelight_cli.synth.motions import SCRIPTED, Segment, compose_motion

    return compose_motion(character, [Segment(m, 5.0) for m in SCRIPTED], FPS, FRAMES, seed=0)


def random_motion(character, model, seed: int = 0) -> np.ndarray:
    """Smooth motion for any character: every body DoF a sinusoid over a quarter of its range,
    fingers from :func:`finger_motion`, walking forward while turning; clipped to the limits."""
    sk = character.skeleton
    groups = classify_dofs(character)
    rng = np.random.default_rng(seed)
    t = np.arange(FRAMES) / FPS
    theta = np.repeat(model.theta_bar[None], FRAMES, axis=0)
    for d in groups.body:
        lo, hi = np.clip(sk.dof_limits[d], -1.0, 1.0)
        theta[:, d] = 0.5 * (lo + hi) + 0.25 * (hi - lo) * np.sin(2 * np.pi * rng.uniform(0.2, 0.7) * t + rng.uniform(0, 6))
    theta = finger_motion(character, theta, seed + 1)
    root = groups.root
    theta[:, root[0]] += 0.3 * np.sin(0.2 * t)
    theta[:, root[2]] += 0.5 * t
    theta[:, root[3]] += 0.4 * t / np.abs(sk.dof_joint_weights[root[3]]).max()
    theta[:, groups.fixed] = character.rest_theta[groups.fixed]
    return clamp_to_limits(theta, sk.dof_limits, np.setdiff1d(np.arange(sk.num_dofs), groups.fixed))


def finger_motion(character, theta: np.ndarray, seed: int = 1) -> np.ndarray:
    """``theta`` (T,D) with its finger DoFs replaced by hands that open and close: each finger's
    curl is half a shared grasp and half its own sinusoid, each curl joint turning up to 60-90
    degrees of *joint* rotation (DoF value x joint weight) towards its flexion side; spread DoFs
    swing +-10 degrees. Fingers move independently, so the motion leaves the default model's
    coupled hand subspace (the IK's hand prior has to be learned or be right about the anatomy)."""
    sk = character.skeleton
    rng = np.random.default_rng(seed)
    t = np.arange(len(theta)) / FPS
    theta = np.array(theta, dtype=np.float64)
    for index in classify_dofs(character).hands.values():
        grasp = 0.5 + 0.5 * np.sin(2 * np.pi * 0.25 * t + rng.uniform(0, 6))
        curl = {f: np.clip(0.5 * grasp + 0.25 + 0.25 * np.sin(2 * np.pi * rng.uniform(0.3, 0.8) * t + rng.uniform(0, 6)), 0, 1)
                for f in ("Thumb", "Index", "Middle", "Ring", "Pinky")}
        for d in index:
            weight = np.abs(sk.dof_joint_weights[d]).max()
            lo, hi = sk.dof_limits[d]
            rest = np.clip(character.rest_theta[d], lo, hi)
            finger, is_curl = finger_of(character, int(d))
            if is_curl:
                flexion_side = -1.0 if rest - lo >= hi - rest else 1.0
                theta[:, d] = rest + flexion_side * np.radians(rng.uniform(60, 90)) * curl[finger] / weight
            else:
                theta[:, d] = rest + np.radians(10) * np.sin(2 * np.pi * rng.uniform(0.2, 0.5) * t + rng.uniform(0, 6)) / weight
            theta[:, d] = np.clip(theta[:, d], lo, hi)
    return theta


def noisy_keypoints(character, theta: np.ndarray, seed: int = 1) -> tuple[Keypoints, np.ndarray]:
    clean = fitted_keypoints(character, theta)
    sigma = np.full(clean.shape[1], HAND_NOISE_M)
    sigma[BODY_SLICE] = BODY_NOISE_M
    noisy = clean + np.random.default_rng(seed).normal(size=clean.shape) * sigma[None, :, None]
    return Keypoints(noisy, np.ones(clean.shape[:2]), np.arange(len(theta)), character.keypoint_names, FPS), clean


def solve(character, keypoints: Keypoints, clean: np.ndarray, model, settings: IKSettings) -> dict:
    started = time.perf_counter()
    result = solve_ik(character, keypoints, model, settings)
    seconds = time.perf_counter() - started
    metrics = fit_metrics(result)
    truth = np.linalg.norm(result.fitted_keypoints - clean, axis=-1)
    return {
        "frames": len(keypoints.frame_ids),
        "total_s": round(seconds, 3),
        "ms_per_frame": round(1000 * seconds / len(keypoints.frame_ids), 3),
        "mpjpe_input_cm": round(metrics["mpjpe_input_all_cm"], 3),
        "mpjpe_gt_cm": round(100 * float(truth.mean()), 3),
        "mpjpe_gt_body_cm": round(100 * float(truth[:, BODY_SLICE].mean()), 3),
        "mpjpe_gt_hands_cm": round(100 * float(truth[:, BODY_SLICE.stop:].mean()), 3),
        "stages": {s.name: {"iterations": s.iterations, "evaluations": s.evaluations, "seconds": round(s.seconds, 3)}
                   for s in result.stages},
    }


def compare(name: str, character, theta_fn) -> dict:
    config = resolve_config("ik", "cpu")
    lm = IKSettings.from_config(config)
    lbfgs = IKSettings(**{**lm.__dict__, "solver": "lbfgs"})
    model = default_ik_model(character, lm)
    theta = theta_fn(character, model)
    keypoints, clean = noisy_keypoints(character, theta)
    input_error = 100 * float(np.linalg.norm(keypoints.xyz - clean, axis=-1).mean())
    out = {"character": name, "dofs": character.skeleton.num_dofs, "input_mpjpe_gt_cm": round(input_error, 3),
           "lm": solve(character, keypoints, clean, model, lm)}
    n = min(LBFGS_FRAMES, len(theta))
    out["lbfgs"] = solve(character, keypoints.select(slice(0, n)), clean[:n], model, lbfgs)
    if n < len(theta):
        out["lbfgs"]["note"] = f"timed on the first {n} frames; per-frame numbers are comparable"
    out["speed_ratio"] = round(out["lbfgs"]["ms_per_frame"] / out["lm"]["ms_per_frame"], 2)
    out["goal_20x"] = out["speed_ratio"] >= 20
    out["goal_under_5ms"] = out["lm"]["ms_per_frame"] < 5
    out["goal_equal_or_lower_mpjpe"] = out["lm"]["mpjpe_gt_cm"] <= out["lbfgs"]["mpjpe_gt_cm"]
    # LBFGS with more iterations per stage, on a prefix: what it costs to get near lm's accuracy
    m = min(ACCURACY_FRAMES, len(theta))
    out["lm_prefix"] = solve(character, keypoints.select(slice(0, m)), clean[:m], model, lm)
    out["lbfgs_longer"] = {}
    for iterations in LONGER_LBFGS:
        longer = IKSettings(**{**lbfgs.__dict__, "lbfgs_iterations": iterations})
        row = solve(character, keypoints.select(slice(0, m)), clean[:m], model, longer)
        row.pop("stages")
        row["time_ratio_to_lm"] = round(row["ms_per_frame"] / out["lm_prefix"]["ms_per_frame"], 1)
        out["lbfgs_longer"][f"{iterations}_iterations"] = row
    out["lm_prefix"].pop("stages")
    return out


def hand_prior(character, theta: np.ndarray, settings: IKSettings) -> dict:
    """Hands MPJPE (cm) on the second half of ``theta`` from its noise-free keypoints, for the
    default model, the default model without the flexion cap (before issue 21: finger DoFs curled
    to their limits whatever their joint weight) and a model trained on the first half."""
    half = len(theta) // 2
    clean = fitted_keypoints(character, theta[half:])
    keypoints = Keypoints(clean, np.ones(clean.shape[:2]), np.arange(len(clean)), character.keypoint_names, FPS)
    uncapped = IKSettings(**{**settings.__dict__, "hand_max_flexion_deg": 1e6})
    models = {"default": default_ik_model(character, settings), "default_uncapped": default_ik_model(character, uncapped),
              "trained_first_half": train_ik_model(character, [theta[:half]], settings)}
    out = {"frames": len(clean)}
    for name, model in models.items():
        result = solve_ik(character, keypoints, model, settings)
        error = np.linalg.norm(result.fitted_keypoints - clean, axis=-1)[:, BODY_SLICE.stop:]
        hands = next(s for s in result.stages if s.name == "hands")
        out[name] = {"mpjpe_hands_cm": round(100 * float(error.mean()), 3),
                     "max_hand_error_cm": round(100 * float(error.max()), 2),
                     "hands_stage_iterations": hands.iterations}
    out["lm_frame_iterations"] = settings.lm_frame_iterations  # the sweeps' cap (coarse and fine passes each)
    return out


def run() -> dict:
    results = {"torch_threads": torch.get_num_threads(), "frames": FRAMES,
               "noise_m": {"body": BODY_NOISE_M, "hands": HAND_NOISE_M}}
    character = load_default_character()
    try:
        library_motion(character)
        motion_fn = lambda c, m: library_motion(c)  # noqa: E731
    except Exception:  # the synth library is optional for this benchmark
        motion_fn = random_motion
    results["default"] = compare("default", character, motion_fn)
    config_settings = IKSettings.from_config(resolve_config("ik", "cpu"))
    results["default"]["hand_prior"] = hand_prior(
        character, finger_motion(character, motion_fn(character, default_ik_model(character))), config_settings)
    if DDC_CHARACTER.is_file():
        from egorelight_cli.stages.character_commands import load_character

        ddc, _ = load_character(DDC_CHARACTER)
        results["ddc_example"] = compare("ddc_example", ddc, random_motion)
        results["ddc_example"]["hand_prior"] = hand_prior(ddc, random_motion(ddc, default_ik_model(ddc, config_settings)),
                                                          config_settings)
    else:
        results["ddc_example"] = {"skipped": "../shared/data/ddc_example is not available"}
    return results


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
