"""Benchmark: lightstage rendering of the default character (``render/shading.py``).

One simulated frame = per-vertex light visibility (V x 331 shadow rays, once per frame) + one
render per camera. Cameras: a 256x256 pinhole studio view of the whole body and a 256x256
fisheye ego view from the head looking down. Lighting: a sky environment map turned into 331
light intensities (every light on). Reported: seconds per frame per camera (hybrid per-vertex
visibility, and exact per-pixel shadow rays for reference), shadow rays per second.
Run ``python bench/bench_render.py``; it prints a JSON dict.
"""

from __future__ import annotations

import json
import time

import numpy as np

from egorelight_cli.geometry.cameras import Camera, look_at
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.io.character import load_default_character
from egorelight_cli.render.envmaps import make_envmap
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.shading import Material, render_view, vertex_light_visibility


def _cameras(size: int = 256) -> dict[str, Camera]:
    studio = Camera("pinhole", [[260.0, 0, (size - 1) / 2], [0, 260.0, (size - 1) / 2], [0, 0, 1]], np.zeros(5),
                    size, size, look_at((0.6, 1.1, -2.3), (0.0, 0.85, 0.0)))
    # the character faces -Z; an HMD camera in front of the face looking down at the body
    ego = Camera("fisheye", [[85.0, 0, (size - 1) / 2], [0, 85.0, (size - 1) / 2], [0, 0, 1]],
                 [0.02, -0.005, 0.0, 0.0], size, size,
                 look_at((0.04, 1.52, -0.24), (0.0, 0.8, -0.05), up=(0.0, 0.0, -1.0)))
    return {"pinhole": studio, "fisheye": ego}


def _best(fn, repeats: int) -> tuple[float, object]:
    best, result = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return best, result


def run(repeats: int = 3) -> dict:
    """Seconds per frame per camera and shadow-ray throughput."""
    character = load_default_character()
    vertices, faces = character.vertices, character.faces
    stage = LightStage.dome()
    intensities = stage.envmap_to_intensities(make_envmap("sky", 0, 64))
    material = Material(albedo=np.full((256, 256, 3), 0.6, np.float32), specular=0.04, roughness=0.5)

    build_s, caster = _best(lambda: RayCaster(vertices, faces), 1)
    visibility_s, visibility = _best(lambda: vertex_light_visibility(vertices, faces, stage, caster=caster), repeats)
    vertex_rays = visibility.size
    out = {
        "num_vertices": len(vertices),
        "num_faces": len(faces),
        "num_lights": stage.num_lights,
        "embree_build_s": build_s,
        "vertex_visibility_s": visibility_s,
        "vertex_visibility_rays": int(vertex_rays),
        "shadow_rays_per_s": vertex_rays / visibility_s,
    }
    frame_s = visibility_s
    for name, camera in _cameras().items():
        def hybrid(camera=camera):
            return render_view(vertices, faces, character.face_uvs, material, camera, stage, intensities,
                               caster=caster, vertex_visibility=visibility)

        def exact(camera=camera):
            return render_view(vertices, faces, character.face_uvs, material, camera, stage, intensities,
                               caster=caster)

        hybrid_s, result = _best(hybrid, repeats)
        exact_s, exact_result = _best(exact, 1)
        frame_s += hybrid_s
        out.update({
            f"{name}_pixels_on_body": int(result.mask.sum()),
            f"{name}_render_s": hybrid_s,
            f"{name}_shadow_rays": int(result.shadow_rays),
            f"{name}_exact_render_s": exact_s,
            f"{name}_exact_shadow_rays": int(exact_result.shadow_rays),
            f"{name}_exact_shadow_rays_per_s": exact_result.shadow_rays / exact_s,
        })
    out["frame_two_cameras_s"] = frame_s
    out["frame_per_camera_s"] = frame_s / 2
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
