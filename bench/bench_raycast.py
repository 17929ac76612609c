"""Benchmark: occlusion rays per second through :class:`RayCaster` vs. embreex called directly.

Both run on the same Embree scene and the same rays in the same process, so the ratio is the
overhead of our wrapper (input checks, broadcasting, normalisation, float32 conversion).
Run ``python bench/bench_raycast.py``; it prints a JSON dict.
"""

from __future__ import annotations

import json
import time

import numpy as np
import trimesh

from egorelight_cli.geometry.raycast import RayCaster


def _scene_and_rays(n_rays: int, seed: int = 0):
    """An icosphere (r = 1 m, 20480 faces) and shadow rays from points around it towards lights.

    Returns the mesh, float32 origins (N,3), float32 unit dirs (N,3), float32 distances (N,).
    """
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    rng = np.random.default_rng(seed)
    starts = rng.uniform(-2.0, 2.0, size=(n_rays, 3))
    lights = rng.normal(size=(n_rays, 3))
    lights *= 3.0 / np.linalg.norm(lights, axis=1, keepdims=True)
    seg = lights - starts
    dist = np.linalg.norm(seg, axis=1)
    return (mesh, starts.astype(np.float32), (seg / dist[:, None]).astype(np.float32),
            dist.astype(np.float32))


def _best_times(fns: dict, repeats: int) -> dict:
    """Fastest wall time (s) of each callable over ``repeats`` rounds, interleaved round by round
    so that machine load and clock drift hit every contender alike."""
    best = {name: np.inf for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            best[name] = min(best[name], time.perf_counter() - start)
    return best


def run(n_rays: int = 1_000_000, repeats: int = 7) -> dict:
    """Measure occlusion throughput (rays/s) of our API and of raw embreex on the same rays."""
    mesh, origins, dirs, dist = _scene_and_rays(n_rays)
    caster = RayCaster(mesh.vertices, mesh.faces)
    scene = caster.embree_scene

    ours = caster.occluded(origins, dirs, max_dist=dist)
    raw = scene.run(origins, dirs, dists=dist, query="OCCLUDED") != -1
    via_first_hit = caster.occluded_by_first_hit(origins, dirs, max_dist=dist)

    t = _best_times(
        {
            "raw": lambda: scene.run(origins, dirs, dists=dist, query="OCCLUDED"),
            "ours": lambda: caster.occluded(origins, dirs, max_dist=dist),
            "raw_inf": lambda: scene.run(origins, dirs, query="OCCLUDED"),
            "ours_inf": lambda: caster.occluded(origins, dirs),
            "ours_via_first_hit": lambda: caster.occluded_by_first_hit(origins, dirs, max_dist=dist),
            # embreex writes hit distances into `dists`, hence the copy (0.3 ms)
            "raw_closest": lambda: scene.run(origins, dirs, dists=dist.copy(), output=True),
            "ours_closest": lambda: caster.first_hit(origins, dirs, max_dist=dist),
        },
        repeats,
    )
    return {
        "n_rays": n_rays,
        "n_faces": int(len(mesh.faces)),
        "occluded_fraction": float(ours.mean()),
        "agree_with_raw": bool(np.array_equal(ours, raw)),
        "first_hit_strategy_agreement": float((via_first_hit == ours).mean()),
        "raw_embree_occluded_rays_per_s": n_rays / t["raw"],
        "api_occluded_rays_per_s": n_rays / t["ours"],
        "api_over_raw_time_ratio": t["ours"] / t["raw"],
        "raw_embree_occluded_unbounded_rays_per_s": n_rays / t["raw_inf"],
        "api_occluded_unbounded_rays_per_s": n_rays / t["ours_inf"],
        "api_over_raw_unbounded_time_ratio": t["ours_inf"] / t["raw_inf"],
        "api_occluded_via_first_hit_rays_per_s": n_rays / t["ours_via_first_hit"],
        "any_hit_speedup_over_first_hit": t["ours_via_first_hit"] / t["ours"],
        "raw_embree_first_hit_rays_per_s": n_rays / t["raw_closest"],
        "api_first_hit_rays_per_s": n_rays / t["ours_closest"],
        "api_over_raw_first_hit_time_ratio": t["ours_closest"] / t["raw_closest"],
    }


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
