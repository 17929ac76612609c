"""Sub-mesh surface detail: a tangent-space normal map of the subject (bump mapping).

What GeoLift must recover beyond the tracked mesh: structure finer than any mesh the pipeline
fits, seen only in shading. A height field ``h`` (metres) is defined in 3D on the rest surface per
material, at wavelengths the studio cameras resolve (1.5-4 cm):

* shirt: ribbing, a sine along a seeded direction (wavelength ~1.8 cm, amplitude ~0.7 mm);
* trousers: a twill of two crossing sines (~2.5 cm, ~1 mm);
* skin: soft bumps (3D value noise, ~3 cm, ~0.4 mm); hair: strands (~1.2 cm, ~0.3 mm);
* shoes: smooth.

Each texel's rest normal ``n`` is tilted by the surface gradient of ``h`` (``n' = normalize(n -
grad_s h)``, gradient by central differences in 3D) and stored in the texel face's tangent frame
(:mod:`egorelight_cli.geometry.tangents`), so the renderer applies it to the posed surface.
Slopes are 0.1-0.3 (about 6-17 degrees).
"""

from __future__ import annotations

import numpy as np

from egorelight_cli.geometry.normals import vertex_normals
from egorelight_cli.geometry.tangents import face_uv_tangents, tangent_space_from_world
from egorelight_cli.render.raster import UVRaster, texels_to_surface
from egorelight_cli.synth.appearance import HAIR, SHIRT, SHOES, SKIN, TROUSERS, value_noise

_EPS_M = 5e-4


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def material_heights(rng: np.random.Generator) -> dict:
    """Material -> height function ``h(points (N,3)) -> (N,)`` metres (seeded)."""
    rib = _unit(rng.normal(size=3) * [0.3, 1.0, 0.3])
    twill_a, twill_b = _unit(rng.normal(size=3)), _unit(rng.normal(size=3))
    strand = _unit(rng.normal(size=3) * [1.0, 0.2, 1.0])
    rib_l, twill_l = rng.uniform(0.015, 0.021), rng.uniform(0.022, 0.03)
    skin_rng = np.random.default_rng(rng.integers(1 << 31))
    # value_noise draws its waves from the generator on every call: freeze one draw per material.
    skin_seed = int(skin_rng.integers(1 << 31))

    def skin(p):
        return 0.0004 * value_noise(p, 0.03, np.random.default_rng(skin_seed), octaves=2)

    return {
        SHIRT: lambda p: 0.0007 * np.sin(2 * np.pi * p @ rib / rib_l),
        TROUSERS: lambda p: 0.0006 * (np.sin(2 * np.pi * p @ twill_a / twill_l) + np.sin(2 * np.pi * p @ twill_b / twill_l)),
        SKIN: skin,
        HAIR: lambda p: 0.0003 * np.sin(2 * np.pi * p @ strand / 0.012),
        SHOES: lambda p: np.zeros(len(p)),
    }


def detail_normal_map(raster: UVRaster, vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray,
                      material: np.ndarray, seed: int) -> np.ndarray:
    """(H,W,3) float32 tangent-space normal map of the detail, (0,0,1) outside the UV islands.

    Args:
        raster: UV raster of ``face_uvs`` at the map's resolution.
        vertices: (V,3) rest surface; faces (F,3); face_uvs (F,3,2).
        material: (H,W) material class per texel (:mod:`egorelight_cli.synth.appearance`).
        seed: detail seed.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xDE7]))
    heights = material_heights(rng)
    covered = raster.coverage
    points = texels_to_surface(raster, vertices, faces)[covered].astype(np.float64)
    fid = raster.face_id[covered]
    bary = raster.barycentrics[covered].astype(np.float64)
    n = np.einsum("pkc,pk->pc", vertex_normals(vertices, faces)[faces[fid]], bary)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    mat = material[covered]
    grad = np.zeros_like(points)
    for cls, h in heights.items():
        rows = np.flatnonzero(mat == cls)
        if rows.size == 0:
            continue
        for axis in range(3):
            step = np.zeros(3)
            step[axis] = _EPS_M
            grad[rows, axis] = (h(points[rows] + step) - h(points[rows] - step)) / (2 * _EPS_M)
    surface_grad = grad - np.sum(grad * n, axis=1, keepdims=True) * n
    tilted = n - surface_grad
    tilted /= np.linalg.norm(tilted, axis=1, keepdims=True)
    tangent, sign = face_uv_tangents(vertices, faces, face_uvs)
    out = np.zeros(raster.face_id.shape + (3,), np.float32)
    out[..., 2] = 1.0
    out[covered] = tangent_space_from_world(tilted, n, tangent[fid], sign[fid])
    return out
