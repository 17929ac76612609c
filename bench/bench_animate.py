"""Benchmark: ``animate`` inference speed on the CPU, with and without depth.

Per configuration (the ``cpu`` preset's 64x64 UV / 16 channels, and the paper's 128x128 / 32
channels), frames per second of the whole feed-forward inference (skinning the template, the
motion signal Theta, the depth encoding xi, UV rasterisation, AnimationNet, posing with the
character model) over a 60-frame motion of the synthetic capture's motion library, with a
20,000-point cloud per frame (the skinned template's front half plus 3 mm noise; the network is
untrained, which does not change its cost). The paper reports 46 FPS with depth and 76 without
on a GPU. Run ``python bench/bench_animate.py``; it prints a JSON dict.
"""

from __future__ import annotations

import json
import time

import numpy as np
import torch

from egorelight_cli.io.character import load_default_character
from egorelight_cli.stages.animate import AnimationModel, DepthSettings, NetSettings, previous_rows

FRAMES = 60
FPS = 30.0
CLOUD_POINTS = 20000
CONFIGS = {"cpu_preset_uv64": NetSettings(uv_resolution=64, base_channels=16),
           "paper_uv128": NetSettings(uv_resolution=128, base_channels=32)}


def _motion(character) -> np.ndarray:
    from egorelight_cli.synth.motions import SCRIPTED, Segment, compose_motion

    return compose_motion(character, [Segment(m, 1.0) for m in SCRIPTED[:3]], FPS, FRAMES, seed=0)


def _clouds(character, theta: np.ndarray) -> list:
    from egorelight_cli.geometry.depth_encoding import skinned_template

    rng = np.random.default_rng(0)
    template = skinned_template(character, theta)
    clouds = []
    for v, n in zip(template.vertices, template.normals):
        front = np.flatnonzero(n[:, 2] < 0)
        pick = rng.choice(front, CLOUD_POINTS, replace=True)
        clouds.append((v[pick] + 0.003 * rng.normal(size=(CLOUD_POINTS, 3)), n[pick]))
    return clouds


def run() -> dict:
    torch.manual_seed(0)
    character = load_default_character()
    theta = _motion(character)
    frame_ids = np.arange(len(theta))
    clouds = _clouds(character, theta)
    out: dict = {"frames": len(theta), "cloud_points": CLOUD_POINTS, "torch_threads": torch.get_num_threads()}
    for name, settings in CONFIGS.items():
        model = AnimationModel(character, settings, DepthSettings())  # UV layout built (and cached) here
        for label, cl in (("with_depth", clouds), ("no_depth", None)):
            started = time.perf_counter()
            inputs, _, _ = model.uv_inputs(theta, previous_rows(frame_ids), cl)
            encoded = time.perf_counter()
            model.predict(inputs, theta)
            done = time.perf_counter()
            out[f"{name}_{label}_fps"] = round(len(theta) / (done - started), 2)
            out[f"{name}_{label}_encode_ms_per_frame"] = round(1000 * (encoded - started) / len(theta), 2)
            out[f"{name}_{label}_network_pose_ms_per_frame"] = round(1000 * (done - encoded) / len(theta), 2)
    out["paper_gpu_fps_with_depth"] = 46
    out["paper_gpu_fps_no_depth"] = 76
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=1))
