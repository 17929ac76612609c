"""Benchmark: differentiable Gaussian splatting on the CPU (``render/gaussians.py``).

Scene: N Gaussians on a 0.35 m sphere 1.2 m in front of a 240x320 pinhole camera (f = 300 px),
sized like a UV layer of an avatar (disc-shaped, standard deviation 0.6x the spacing of the
samples, 1/10 of that along the normal), random colours, opacities in [0.5, 1]. Reported per N:
forward and forward+backward seconds (best of a few runs), pairs composited, and for N = 10k the
speed-up over the dense reference (every splat against every pixel) in the same run (timed on 32
of the 240 rows and scaled: its cost per pixel is constant).
Goal (issue 16): forward+backward for 10k under 0.15 s on 2 cores, >= 20x the dense reference.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import torch

from egorelight_cli.geometry.cameras import Camera, look_at
from egorelight_cli.geometry.rotations import matrix_to_quaternion
from egorelight_cli.render.gaussians import render_gaussians
from egorelight_cli.render.gaussians_reference import render_gaussians_dense
from egorelight_cli.structures.gaussians import GaussianSet
from timing import best_time

WIDTH, HEIGHT = 320, 240


def sphere_scene(n: int, seed: int = 0, radius_m: float = 0.35) -> GaussianSet:
    """N surface-like Gaussians on a sphere at the origin (float32, requiring gradients)."""
    generator = torch.Generator().manual_seed(seed)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    i = torch.arange(n, dtype=torch.float64)
    y = 1.0 - 2.0 * (i + 0.5) / n
    ring = torch.sqrt(1.0 - y * y)
    normals = torch.stack([ring * torch.cos(golden * i), y, ring * torch.sin(golden * i)], -1)
    tangent = torch.nn.functional.normalize(torch.linalg.cross(normals, torch.tensor([[0.3, 1.0, 0.2]], dtype=torch.float64).expand(n, 3)), dim=-1)
    bitangent = torch.linalg.cross(normals, tangent)
    quats = matrix_to_quaternion(torch.stack([tangent, bitangent, normals], -1))
    spacing = radius_m * math.sqrt(4.0 * math.pi / n)
    scales = torch.tensor([0.6 * spacing, 0.6 * spacing, 0.06 * spacing], dtype=torch.float64).expand(n, 3)
    opacities = 0.5 + 0.5 * torch.rand(n, generator=generator, dtype=torch.float64)
    colours = torch.rand(n, 3, generator=generator, dtype=torch.float64)
    tensors = [radius_m * normals, quats, scales, opacities, colours]
    return GaussianSet(*(t.float().contiguous().requires_grad_(True) for t in tensors))


def bench_camera() -> Camera:
    K = [[300.0, 0.0, (WIDTH - 1) / 2], [0.0, 300.0, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]]
    return Camera("pinhole", K, np.zeros(5), WIDTH, HEIGHT, look_at((0.0, 0.1, -1.2), (0.0, 0.0, 0.0)))


def _forward_backward(render, gaussians: GaussianSet, camera: Camera):
    def step():
        out = render(gaussians, camera, background=[0.2, 0.2, 0.2])
        (out.colour.sum() + out.depth.sum()).backward()
        for tensor in gaussians.tensors():
            tensor.grad = None
    return step


def band_camera(camera: Camera, first_row: int, rows: int) -> Camera:
    """The rows ``first_row .. first_row + rows - 1`` of ``camera`` as a camera of their own."""
    K = camera.K.copy()
    K[1, 2] -= first_row
    return Camera(camera.model, K, camera.dist, camera.width, rows, camera.T_cam_from_world, camera.name)


def dense_forward_backward_s(gaussians: GaussianSet, camera: Camera, bands: int = 4, rows: int = 8) -> float:
    """Seconds for the dense reference's forward + backward over the whole image.

    Its cost is the same for every pixel (every splat against every pixel) and it needs
    H W N memory, so it runs on ``bands`` evenly spread bands of ``rows`` rows and the time is
    scaled by ``height / (bands rows)`` (3 minutes for the whole 10k image otherwise).
    """
    firsts = np.linspace(0, camera.height - rows, bands).astype(int)
    start = time.perf_counter()
    for first in firsts:
        _forward_backward(render_gaussians_dense, gaussians, band_camera(camera, int(first), rows))()
    return (time.perf_counter() - start) * camera.height / (bands * rows)


def run(repeats: int = 5) -> dict:
    camera = bench_camera()
    results = {"threads": torch.get_num_threads(), "image": f"{HEIGHT}x{WIDTH}"}
    for n in (10_000, 160_000):
        gaussians = sphere_scene(n)
        with torch.no_grad():
            out = render_gaussians(gaussians, camera)
        forward = best_time(lambda: render_gaussians(gaussians, camera), repeats)[0]
        both = best_time(_forward_backward(render_gaussians, gaussians, camera), repeats)[0]
        key = f"{n // 1000}k"
        results[f"{key}_forward_s"] = round(forward, 4)
        results[f"{key}_forward_backward_s"] = round(both, 4)
        results[f"{key}_pairs"] = out.stats.pairs
        results[f"{key}_truncated_pixels"] = out.stats.truncated_pixels
        if n == 10_000:
            dense = dense_forward_backward_s(gaussians, camera)
            results["10k_dense_forward_backward_s_scaled_from_32_rows"] = round(dense, 2)
            results["10k_speedup_over_dense"] = round(dense / both, 1)
    results["goal_10k_forward_backward_s"] = 0.15
    results["goal_speedup_over_dense"] = 20.0
    return results


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
