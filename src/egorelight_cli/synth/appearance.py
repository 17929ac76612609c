"""The subject's appearance: procedural UV albedo, specular and roughness maps.

Built on the character's own UV layout (:func:`~egorelight_cli.render.raster.rasterize_uv` gives
each texel its face, :func:`~egorelight_cli.render.raster.texels_to_surface` its rest-pose 3D
point), so patterns are defined in 3D and stay continuous across UV seams. Each texel takes the
segmentation label of its face (LIP labels of the default character: hair, upper clothes,
pants, face, arms, legs, shoes); characters without those labels get a uniform skin-and-cloth
split by height.

Materials (spatially varying, the paper's diffuse + specular separation needs both):

* skin (face, arms, legs): a seeded skin tone with soft 3D variation; glossy (ks ~0.045,
  roughness ~0.38);
* hair: dark, streaky; moderately glossy;
* shirt (upper clothes): a seeded pattern (stripes, checks or dots) in two colours; matte cloth;
* trousers: the **shiny garment** (a coated/leather-like fabric: ks ~0.12, roughness ~0.28);
* shoes: dark with a light sole; semi-glossy.

Texels outside every UV island are filled with their nearest island texel (dilation), so
bilinear lookups near seams stay on the right material.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from egorelight_cli.render.raster import UVRaster, rasterize_uv, texels_to_surface
from egorelight_cli.structures.character import Character

#: Material classes of texels.
SKIN, HAIR, SHIRT, TROUSERS, SHOES = 0, 1, 2, 3, 4
MATERIAL_NAMES = {SKIN: "skin", HAIR: "hair", SHIRT: "shirt", TROUSERS: "trousers", SHOES: "shoes"}
#: LIP segmentation label -> material class (default character).
LABEL_MATERIAL = {2: HAIR, 5: SHIRT, 9: TROUSERS, 13: SKIN, 14: SKIN, 15: SKIN, 16: SKIN, 17: SKIN,
                  18: SHOES, 19: SHOES}
#: Clothing materials (where the cloth simulation moves the surface).
CLOTH_MATERIALS = (SHIRT, TROUSERS)
#: (specular albedo, roughness) per material.
SPECULAR = {SKIN: (0.045, 0.38), HAIR: (0.06, 0.45), SHIRT: (0.012, 0.9), TROUSERS: (0.12, 0.28),
            SHOES: (0.08, 0.35)}
SKIN_TONES = ((0.61, 0.42, 0.33), (0.50, 0.32, 0.23), (0.36, 0.22, 0.15), (0.22, 0.13, 0.08), (0.68, 0.50, 0.40))


@dataclass(frozen=True, eq=False)
class Appearance:
    """UV maps of the subject (row 0 is v = 1, the UV convention of ``render/raster.py``).

    Attributes:
        albedo: (R,R,3) float32 linear diffuse albedo.
        specular: (R,R,1) float32 specular albedo ks.
        roughness: (R,R,1) float32 roughness in (0,1].
        material: (R,R) int8 material class per texel (see :data:`MATERIAL_NAMES`).
        coverage: (R,R) bool, texels inside a UV island.
        description: what the seed chose (skin tone, colours, shirt pattern).
        normal_map: (R,R,3) float32 tangent-space detail normals (:mod:`egorelight_cli.synth.detail`)
            or None.
    """

    albedo: np.ndarray
    specular: np.ndarray
    roughness: np.ndarray
    material: np.ndarray
    coverage: np.ndarray
    description: dict
    normal_map: np.ndarray | None = None


def vertex_materials(character: Character) -> np.ndarray:
    """(V,) int material class per vertex from the segmentation labels (height split otherwise)."""
    labels = character.segmentation
    known = np.isin(labels, list(LABEL_MATERIAL))
    if known.mean() > 0.9:
        lookup = np.full(int(labels.max()) + 1, SKIN, dtype=np.int64)
        for label, material in LABEL_MATERIAL.items():
            if label < len(lookup):
                lookup[label] = material
        return lookup[labels]
    y = character.vertices[:, 1]
    lo, hi = float(y.min()), float(y.max())
    rel = (y - lo) / max(hi - lo, 1e-6)
    out = np.full(len(y), SKIN, dtype=np.int64)
    out[(rel > 0.47) & (rel < 0.82)] = SHIRT
    out[(rel > 0.05) & (rel <= 0.47)] = TROUSERS
    out[rel <= 0.05] = SHOES
    return out


def value_noise(points: np.ndarray, scale: float, rng: np.random.Generator, octaves: int = 3) -> np.ndarray:
    """Smooth 3D noise in about [-1, 1] at (N,3) points: a sum of random plane waves per octave."""
    out = np.zeros(len(points))
    amplitude, total = 1.0, 0.0
    for octave in range(octaves):
        freq = (2 ** octave) / scale
        for _ in range(6):
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            out += amplitude * np.sin(2 * np.pi * freq * points @ direction + rng.uniform(0, 2 * np.pi))
        total += 6 * amplitude
        amplitude *= 0.5
    return out / np.sqrt(total)


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(h % 1.0, s, v))


def _dilate(values: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """Fill texels outside the islands with the nearest covered texel's value."""
    if coverage.all():
        return values
    _, (rows, cols) = ndimage.distance_transform_edt(~coverage, return_indices=True)
    return values[rows, cols]


def make_appearance(character: Character, resolution: int, seed: int, uv: UVRaster | None = None) -> Appearance:
    """Procedural albedo/specular/roughness maps of ``resolution`` texels for ``character`` (``uv``:
    its UV raster at that resolution when the caller already has one)."""
    rng = np.random.default_rng(seed)
    uv = rasterize_uv(character.face_uvs, resolution) if uv is None else uv
    coverage = uv.coverage
    points = texels_to_surface(uv, character.vertices, character.faces)[coverage].astype(np.float64)
    vmat = vertex_materials(character)
    corner_mat = vmat[character.faces[uv.face_id[coverage]]]  # (P,3)
    nearest = np.argmax(uv.barycentrics[coverage], axis=1)
    material = corner_mat[np.arange(len(corner_mat)), nearest]

    skin_tone = np.array(SKIN_TONES[int(rng.integers(len(SKIN_TONES)))]) * rng.uniform(0.92, 1.08)
    hair_colour = _hsv(rng.uniform(0.05, 0.1), rng.uniform(0.4, 0.7), rng.uniform(0.03, 0.25))
    shirt_a = _hsv(rng.uniform(0, 1), rng.uniform(0.45, 0.8), rng.uniform(0.45, 0.75))
    shirt_b = _hsv(rng.uniform(0, 1), rng.uniform(0.1, 0.4), rng.uniform(0.7, 0.9))
    trousers_colour = _hsv(rng.uniform(0, 1), rng.uniform(0.3, 0.7), rng.uniform(0.1, 0.25))
    shoe_colour = _hsv(rng.uniform(0, 1), rng.uniform(0.0, 0.3), rng.uniform(0.05, 0.15))
    pattern = str(rng.choice(["stripes", "checks", "dots"]))

    albedo = np.zeros((len(points), 3))
    noise = value_noise(points, 0.08, rng)
    fine = value_noise(points, 0.01, rng, octaves=2)
    # skin: tone with soft blotches and a slight redness variation
    m = material == SKIN
    albedo[m] = skin_tone * (1 + 0.06 * noise[m, None]) * (1 + np.array([0.04, -0.02, -0.03]) * fine[m, None])
    m = material == HAIR
    streaks = value_noise(points * np.array([4.0, 0.3, 4.0]), 0.05, rng)
    albedo[m] = hair_colour * (1 + 0.35 * streaks[m, None])
    m = material == SHIRT
    p = points[m]
    if pattern == "stripes":
        mix = (np.sin(2 * np.pi * p[:, 1] / rng.uniform(0.04, 0.08)) > 0).astype(float)
    elif pattern == "checks":
        period = rng.uniform(0.05, 0.09)
        mix = ((np.floor(p[:, 0] / period) + np.floor(p[:, 1] / period) + np.floor(p[:, 2] / period)) % 2).astype(float)
    else:
        period = rng.uniform(0.04, 0.07)
        cell = (p / period) - np.round(p / period)
        mix = (np.linalg.norm(cell, axis=1) < 0.3).astype(float)
    albedo[m] = (mix[:, None] * shirt_a + (1 - mix[:, None]) * shirt_b) * (1 + 0.05 * fine[m, None])
    m = material == TROUSERS
    albedo[m] = trousers_colour * (1 + 0.12 * noise[m, None] + 0.08 * fine[m, None])
    m = material == SHOES
    sole = points[m, 1] < 0.025
    albedo[m] = np.where(sole[:, None], np.array([0.7, 0.68, 0.62]), shoe_colour)

    R = resolution
    full = np.zeros((R, R, 3), np.float32)
    full[coverage] = np.clip(albedo, 0.01, 0.95)
    mat_map = np.full((R, R), SKIN, dtype=np.int8)
    mat_map[coverage] = material
    full = _dilate(full, coverage)
    mat_map = _dilate(mat_map, coverage)
    ks = np.array([SPECULAR[int(k)][0] for k in range(len(SPECULAR))], np.float32)[mat_map]
    rough = np.array([SPECULAR[int(k)][1] for k in range(len(SPECULAR))], np.float32)[mat_map]
    description = {"skin_tone": skin_tone.round(3).tolist(), "shirt_pattern": pattern,
                   "shirt_colours": [shirt_a.round(3).tolist(), shirt_b.round(3).tolist()],
                   "trousers_colour": trousers_colour.round(3).tolist(), "shiny_garment": "trousers",
                   "specular": {MATERIAL_NAMES[k]: {"ks": v[0], "roughness": v[1]} for k, v in SPECULAR.items()}}
    return Appearance(albedo=full.astype(np.float32), specular=ks[..., None], roughness=rough[..., None],
                      material=mat_map, coverage=coverage, description=description)
