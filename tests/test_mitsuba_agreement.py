"""Independent check of the renderer against Mitsuba 3 (test-only dependency ``mitsuba==3.9.1``).

The default character at rest, diffuse with a constant albedo, lit by three lightstage lights,
rendered by our ``render_view`` (exact per-pixel shadow rays) and by Mitsuba's ``direct``
integrator with point emitters of radiant intensity ``J_l = I_l gain_l Omega_l R_l^2`` (the
lightstage convention) and a perspective sensor matching our pinhole camera. Mitsuba's camera
looks along +Z with +X to the image *left* and +Y up, so its ``to_world`` is our
``T_world_from_cam`` with the x and y axes flipped; ``fov`` is the vertical field of view.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from egorelight_cli.geometry.cameras import Camera, look_at
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.io.character import load_default_character
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import vertex_normals
from egorelight_cli.render.shading import Material, render_view

mi = pytest.importorskip("mitsuba")

ALBEDO = 0.6
SIZE = 192
SPP = 64


def _write_ply(path, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> None:
    """Binary little-endian PLY with per-vertex normals (so both renderers shade with the same normals)."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vertex_data = np.concatenate([vertices, normals], axis=1).astype("<f4")
    face_data = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face_data["n"] = 3
    face_data["i"] = faces
    with open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(vertex_data.tobytes())
        handle.write(face_data.tobytes())


def _mitsuba_render(camera: Camera, ply_path, stage: LightStage, intensities: np.ndarray) -> np.ndarray:
    """Sum of one Mitsuba render per lit light (one emitter per scene: no light-selection noise)."""
    mi.set_variant("scalar_rgb")
    to_world = camera.T_world_from_cam @ np.diag([-1.0, -1.0, 1.0, 1.0])
    fov_y = math.degrees(2.0 * math.atan(0.5 * camera.height / camera.K[1, 1]))
    scene = {
        "type": "scene",
        "integrator": {"type": "direct"},
        "sensor": {
            "type": "perspective",
            "fov": fov_y,
            "fov_axis": "y",
            "to_world": mi.ScalarTransform4f(to_world.tolist()),
            "film": {"type": "hdrfilm", "width": camera.width, "height": camera.height,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": SPP},
        },
        "character": {
            "type": "ply",
            "filename": str(ply_path),
            "face_normals": False,
            "bsdf": {"type": "twosided", "material": {"type": "diffuse",
                                                       "reflectance": {"type": "rgb", "value": [ALBEDO] * 3}}},
        },
    }
    J = stage.point_intensities(intensities)
    total = np.zeros((camera.height, camera.width, 3))
    for index in np.flatnonzero(J.any(axis=1)):
        scene["light"] = {"type": "point", "position": stage.positions[index].tolist(),
                          "intensity": {"type": "rgb", "value": J[index].tolist()}}
        total += np.array(mi.render(mi.load_dict(scene), seed=int(index)), dtype=np.float64)[..., :3]
    return total


def test_diffuse_render_agrees_with_mitsuba(tmp_path, record_property):
    character = load_default_character()
    vertices, faces = character.vertices, character.faces
    normals = vertex_normals(vertices, faces)
    stage = LightStage.dome()
    # three lights (the character faces -Z): high front, side, low back rim, with different colours
    picks = [np.argmax(stage.directions @ (d / np.linalg.norm(d)))
             for d in ([-0.5, 0.8, -0.6], [1.0, 0.2, -0.3], [0.4, -0.2, 1.0])]
    intensities = stage.olat(picks[0], (4.0, 3.5, 3.0)) + stage.olat(picks[1], (1.0, 1.5, 2.5)) + \
        stage.olat(picks[2], 2.0)
    K = [[270.0, 0.0, (SIZE - 1) / 2], [0.0, 270.0, (SIZE - 1) / 2], [0.0, 0.0, 1.0]]
    camera = Camera("pinhole", K, np.zeros(5), SIZE, SIZE, look_at((0.8, 1.2, -2.5), (0.0, 0.88, 0.0)))

    ours = render_view(vertices, faces, None, Material(albedo=ALBEDO), camera, stage, intensities,
                       caster=RayCaster(vertices, faces), normals=normals)
    ply = tmp_path / "character.ply"
    _write_ply(ply, vertices, normals, faces)
    theirs = _mitsuba_render(camera, ply, stage, intensities)

    # Mitsuba averages each pixel's footprint (box filter), we sample its centre: compare away from
    # silhouettes and from depth steps (a limb in front of the body), where footprints mix surfaces
    both = ndimage.binary_erosion(ours.mask & (theirs.sum(-1) > 0), iterations=2)
    depth_step = ndimage.maximum_filter(ours.depth, 3) - ndimage.minimum_filter(ours.depth, 3) > 0.05
    level = np.percentile(ours.radiance[both].sum(-1), 99)
    compare = both & ~depth_step & (ours.radiance.sum(-1) > 0.02 * level)
    assert compare.sum() > 3000
    rel = np.abs(ours.radiance[compare] - theirs[compare]).sum(-1) / theirs[compare].sum(-1)
    median, p90 = float(np.median(rel)), float(np.percentile(rel, 90))
    mean_ratio = float(ours.radiance[compare].sum() / theirs[compare].sum())
    print(f"\nMitsuba 3 agreement over {compare.sum()} pixels: median relative error {median:.4f}, "
          f"p90 {p90:.4f}, total radiance ratio ours/mitsuba {mean_ratio:.4f}")
    record_property("mitsuba_median_relative_error", median)
    record_property("mitsuba_p90_relative_error", p90)
    assert median < 0.02
    assert abs(mean_ratio - 1.0) < 0.02
    # shadows agree: pixels black in ours are (nearly) black in Mitsuba's render
    shadowed = both & (ours.radiance.sum(-1) == 0)
    if shadowed.sum() > 50:
        assert np.median(theirs[shadowed].sum(-1)) < 0.02 * level
