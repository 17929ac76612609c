"""Benchmark: relight ms per frame (one view) -- ray features, the two networks, splatting.

The default character at rest under a flat dome (100 lights), one 240x320 studio view, at the cpu
(UV 64, r 16) and paper (UV 512, r 32) settings: the top-r rays + psi for the camera at the
attention level, DiffuseNet + SpecularNet forward, and the Gaussian render (forward). The paper
reports 100 ms/frame on an RTX 4090 for the whole relighting step.
"""

from __future__ import annotations

import json

import numpy as np
import torch

from egorelight_cli.geometry.cameras import Camera, look_at
from egorelight_cli.io.character import load_default_character
from egorelight_cli.render.gaussians import render_gaussians
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import rasterize_uv
from egorelight_cli.render.uv_features import light_transfer, shadow_map, texel_surface, texel_visibility
from egorelight_cli.render.uv_gaussians import texel_gaussians
from egorelight_cli.stages import relight as rl
from timing import best_time

SETTINGS = {"cpu": dict(uv=64, base=16, levels=3, level=1, rays=16, repeats=3),
            "paper": dict(uv=512, base=32, levels=4, level=2, rays=32, repeats=1)}


def run() -> dict:
    character = load_default_character()
    vertices, faces = character.vertices.astype(np.float64), character.faces
    stage = LightStage.dome(num_lights=100)
    camera = Camera("pinhole", [[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]], np.zeros(5), 320, 240,
                    look_at((0.0, 1.0, -2.6), (0.0, 0.9, 0.0)))
    results = {"threads": torch.get_num_threads(), "image": "240x320"}
    for name, s in SETTINGS.items():
        raster = rasterize_uv(character.face_uvs, s["uv"])
        surface = texel_surface(raster, vertices, faces)
        transfer = light_transfer(surface.points, surface.normals, stage,
                                  texel_visibility(vertices, faces, surface, stage))
        intensities = stage.flat(1.0)
        maps = {"albedo": surface.to_map(np.full((len(surface.points), 3), 0.5, np.float32)),
                "shadow": surface.to_map(shadow_map(transfer).numpy()[:, None].astype(np.float32)),
                "normal": surface.to_map(surface.normals.astype(np.float32)),
                "diffuse": surface.to_map((transfer.numpy() @ stage.rgb_gain).astype(np.float32))}
        frame = rl.frame_inputs(raster, maps, vertices, faces, character.face_uvs, intensities,
                                np.zeros(len(vertices), bool))
        model = rl.RelightModel(s["base"], s["levels"], s["level"], s["rays"]).eval()
        low = rl.low_resolution_raster(character.face_uvs, s["uv"], s["level"])
        rays_s, (rays, valid) = best_time(lambda: rl.camera_rays(rl.ray_lighting(frame, low, faces, stage),
                                                                intensities, camera.centre_world, stage, s["rays"]),
                                          s["repeats"], warmup=True)
        coverage = torch.from_numpy(raster.coverage)
        with torch.no_grad():
            nets_s, (raw, spec) = best_time(lambda: (model.diffuse(frame.maps[None])[0],
                                                  model.specular(frame.maps[None, :7], rays[None], valid[None])[0]),
                                    s["repeats"], warmup=True)
            texel_raw = raw.permute(1, 2, 0)[coverage]
            gaussians, _ = texel_gaussians(frame.points, frame.footprint, texel_raw, frame.lambert)
            splat_s, _ = best_time(lambda: render_gaussians(gaussians, camera, passes={"d": frame.lambert}),
                                   s["repeats"], warmup=True)
        results.update({f"{name}_texels": int(coverage.sum()), f"{name}_rays_ms": round(1000 * rays_s, 1),
                        f"{name}_networks_ms": round(1000 * nets_s, 1), f"{name}_splatting_ms": round(1000 * splat_s, 1),
                        f"{name}_total_ms": round(1000 * (rays_s + nets_s + splat_s), 1)})
    results["paper_reference_ms_per_frame_rtx4090"] = 100.0
    return results


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
