"""Benchmark: ``egopose`` inference speed on the CPU (paper: 17.6 ms per frame on a GPU).

Times the whole estimator of :mod:`egorelight_cli.nn.egopose_net` (shared encoder over both
fisheye views, heatmaps + depth, soft-argmax, fisheye unprojection, view fusion, temporal
module) with random weights at the ``cpu`` and ``paper`` preset sizes, for 256x256 fisheye
images: milliseconds per frame online (one frame at a time, as a headset would run it) and in
batches of 16 frames (as ``egorelight egopose`` runs a recorded sequence). Image loading and
resizing are not included. Run ``python bench/bench_egopose.py``; it prints a JSON dict.
"""

from __future__ import annotations

import json
import time

import numpy as np
import torch

from egorelight_cli.config import resolve_config
from egorelight_cli.nn.egopose_net import EgoPoseNet, RigGeometry, transform, windows
from egorelight_cli.stages.egopose import EgoPoseSettings, input_size

IMAGE = 256


def rig() -> RigGeometry:
    K = np.array([[73.6, 0, 127.5], [0, 73.6, 127.5], [0, 0, 1]])
    T = np.stack([np.eye(4), np.eye(4)])
    T[:, :3, 3] = [[-0.06, 0, 0], [0.06, 0, 0]]
    return RigGeometry(torch.tensor(np.stack([K, K]), dtype=torch.float32),
                       torch.tensor([[0.014, -0.004, 0.0007, 0.0]] * 2, dtype=torch.float32), IMAGE, IMAGE,
                       torch.tensor(T, dtype=torch.float32))


def time_per_frame(net: EgoPoseNet, geometry: RigGeometry, size: int, batch: int, repeats: int) -> float:
    """Milliseconds per frame of per-frame estimation + temporal refinement."""
    w, h = input_size(IMAGE, IMAGE, size)
    images = torch.rand(batch, 2, 3, h, w)
    H = torch.eye(4).repeat(batch, 1, 1)
    idx = windows(batch, net.window)
    with torch.no_grad():
        for run in range(repeats + 1):
            if run == 1:
                started = time.perf_counter()
            fused = transform(H, net.forward_frames(images, geometry)["fused_hmd"])
            net.refine(fused[idx], H)
    return 1000 * (time.perf_counter() - started) / (repeats * batch)


def run() -> dict:
    torch.manual_seed(0)
    geometry = rig()
    results = {"torch_threads": torch.get_num_threads(), "image_px": IMAGE}
    for preset, repeats in (("cpu", 5), ("paper", 2)):
        cfg = resolve_config("egopose", preset)
        net = EgoPoseNet(**EgoPoseSettings(cfg).architecture()).eval()
        size = int(cfg.input_size)
        results[f"{preset}_input_px"] = size
        results[f"{preset}_parameters"] = sum(p.numel() for p in net.parameters())
        results[f"{preset}_online_ms_per_frame"] = round(time_per_frame(net, geometry, size, 1, repeats * 4), 2)
        results[f"{preset}_batch16_ms_per_frame"] = round(time_per_frame(net, geometry, size, 16, repeats), 2)
    results["paper_gpu_ms_per_frame"] = 17.6
    return results


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
