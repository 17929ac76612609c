"""Benchmark: the egodepth stage per frame (two down-facing fisheye views).

* ``depth_net_<preset>_ms_per_frame``: the depth network's forward pass on both views of one
  frame (one batch of 2; with the stereo input it also needs the SGBM below), with the ``cpu`` preset network on 256x256 views (the demo capture)
  and the ``paper`` preset network on 512x512 views; paper: 87.7 ms per frame on a GPU for its
  Depth-Anything-V2 fine-tune;
* ``sgbm_ms_per_frame``: SGBM on the rectified pair (rectification maps are built once per sequence) (both reference views) + mapping back, 256x256;
* ``unproject_normals_ms_per_frame``: unprojection of both depth maps (256x256), fusion,
  sampling to P = 20,000 and Hoppe normals (k = 16) with orientation.

Inputs are synthetic (a torso-sized ellipsoid 5 cm below two fisheye cameras, ~17% of each view), so the benchmark
needs no capture. ``BENCH_EGODEPTH_REPEATS`` (default 5) sets the timed repetitions (best is
reported). Run ``python bench/bench_egodepth.py``; it prints a JSON dict.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np
import torch
import trimesh

from egorelight_cli.config import resolve_config
from egorelight_cli.geometry.cameras import Camera, look_at
from egorelight_cli.geometry.depth import camera_ray_map, render_depth
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.nn.depth_net import DepthNet
from egorelight_cli.stages.egodepth import EgoView, frame_pointcloud
from egorelight_cli.runtime import resolve_device

REPEATS = int(os.environ.get("BENCH_EGODEPTH_REPEATS", 5))


def _best_ms(fn, repeats: int = REPEATS) -> float:
    fn()  # warm-up
    best = np.inf
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - started)
    return round(best * 1000, 2)


def _cameras(size: int) -> dict:
    f = size / 3.48  # ~200 degree lens like the synthetic HMD's (f = 27.6 px at 96 px)
    K = [[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]]
    dist = [0.014, -0.004, 0.0007, 0.0]
    return {"left": Camera("fisheye", K, dist, size, size, look_at([-0.06, 0, 0], [-0.03, -1, 0.4]), "down_left"),
            "right": Camera("fisheye", K, dist, size, size, look_at([0.06, 0, 0], [0.03, -1, 0.4]), "down_right")}


def _body():
    body = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    body.apply_scale([0.3, 0.45, 0.25])
    body.apply_translation([0.0, -0.5, 0.1])
    return RayCaster(body.vertices, body.faces)


def _network_ms(preset: str, size: int, device: torch.device) -> float:
    cfg = resolve_config("egodepth", preset)
    model = DepthNet.from_config(cfg.net).to(device).eval()
    image = torch.rand(2, 3, size, size, device=device)
    rays = torch.rand(2, 3, size, size, device=device)
    stereo = torch.rand(2, 1, size, size, device=device) if model.stereo_input else None

    def forward():
        with torch.no_grad():
            model(image, rays, None, stereo)
        if device.type == "cuda":
            torch.cuda.synchronize()

    return _best_ms(forward, max(1, REPEATS if preset == "cpu" or device.type == "cuda" else 2))


def run() -> dict:
    device = resolve_device("auto")
    results = {"device": str(device)}
    results["depth_net_cpu_preset_256px_ms_per_frame"] = _network_ms("cpu", 256, device)
    results["depth_net_paper_preset_512px_ms_per_frame"] = _network_ms("paper", 512, device)
    results["paper_depth_ms_per_frame_gpu"] = 87.7

    cameras = _cameras(256)
    caster = _body()
    ray_maps, views, ranges = {}, [], {}
    for camera in cameras.values():
        rendered = render_depth(camera, caster)
        ray_maps[camera.name] = camera_ray_map(camera)
        ranges[camera.name] = rendered.range
        views.append(EgoView(camera.name, 0, camera, np.zeros((256, 256, 3), np.uint8)))
    rng = np.random.default_rng(0)
    results["unproject_normals_ms_per_frame"] = _best_ms(
        lambda: frame_pointcloud(views, ranges, ray_maps, 20000, 16, rng))
    points = frame_pointcloud(views, ranges, ray_maps, 20000, 16, rng)[2]
    results["fused_valid_points"] = int(points.sum())

    from egorelight_cli.geometry.fisheye_stereo import rectify_pair, stereo_ranges
    from egorelight_cli.geometry.cameras import invert_rigid

    texture = (np.random.default_rng(1).uniform(0, 255, (256, 256, 3))).astype(np.uint8)
    images = {"left": texture, "right": np.roll(texture, 4, axis=1)}
    T_right_from_left = cameras["right"].T_cam_from_world @ invert_rigid(cameras["left"].T_cam_from_world)
    pair = rectify_pair(cameras["left"], cameras["right"], T_right_from_left, 384, 384, 130.0)  # once per sequence

    def sgbm():
        stereo_ranges(pair, cameras, images, 0.1, 5)

    results["sgbm_ms_per_frame"] = _best_ms(sgbm, max(1, REPEATS // 2))
    return results


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
