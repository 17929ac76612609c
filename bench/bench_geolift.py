"""Benchmark: GeoLift per frame -- the lighting features and the network (``stages/geolift*.py``).

On the default character at rest, per UV resolution (64: cpu preset, 128): the coarse UV normal
map and tangent frames, texel visibility to 100 lights (cpu preset dome) by Embree, rho + chi, the top-32 ray
selection with psi for one camera, and GeoLiftingNet's forward pass (cpu preset width). Seconds
per frame, best of a few runs.
"""

from __future__ import annotations

import json

import numpy as np
import torch

from egorelight_cli.io.character import load_default_character
from egorelight_cli.nn.geolift_net import GeoLiftNet
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import rasterize_uv
from egorelight_cli.render.uv_features import (
    irradiance_map,
    light_transfer,
    ray_encoding,
    select_rays,
    shadow_map,
    texel_surface,
    texel_visibility,
)
from egorelight_cli.stages.geolift import coarse_maps, stacked_input
from timing import best_time


def _best(fn, repeats: int) -> float:
    return best_time(fn, repeats)[0]


def run(repeats: int = 3) -> dict:
    character = load_default_character()
    vertices, faces = character.vertices, character.faces
    stage = LightStage.dome(num_lights=100)
    intensities = stage.flat(1.0)
    camera_centre = np.array([0.0, 1.2, -2.5])
    results = {"threads": torch.get_num_threads(), "lights": stage.num_lights}
    for resolution in (64, 128):
        raster = rasterize_uv(character.face_uvs, resolution)
        surface = texel_surface(raster, vertices, faces)
        visibility = texel_visibility(vertices, faces, surface, stage)
        transfer = light_transfer(surface.points, surface.normals, stage, visibility)
        key = f"uv{resolution}"
        results[f"{key}_texels"] = int(raster.coverage.sum())
        results[f"{key}_normal_map_s"] = round(_best(lambda: coarse_maps(raster, vertices[None], faces,
                                                                         character.face_uvs), repeats), 4)
        results[f"{key}_visibility_s"] = round(_best(lambda: texel_visibility(vertices, faces, surface, stage), repeats), 4)
        results[f"{key}_rho_chi_s"] = round(_best(lambda: (shadow_map(light_transfer(surface.points, surface.normals,
                                                                                    stage, visibility)),
                                                          irradiance_map(transfer, stage, intensities)), repeats), 4)

        def rays():
            index, valid = select_rays(surface.points, surface.normals, transfer, stage, intensities, camera_centre, 32)
            return ray_encoding(surface.points, surface.normals, transfer, stage, intensities, camera_centre, index, valid)

        results[f"{key}_top32_psi_s"] = round(_best(rays, repeats), 4)
        coarse = coarse_maps(raster, vertices[None], faces, character.face_uvs)
        model = GeoLiftNet(base_channels=16, levels=3, uv_resolution=resolution).eval()
        batch = torch.from_numpy(stacked_input(coarse.normals, 0))[None]
        frames = torch.from_numpy(coarse.frames[:1])
        with torch.no_grad():
            results[f"{key}_network_s"] = round(_best(lambda: model(batch, frames), repeats), 4)
    return results


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
