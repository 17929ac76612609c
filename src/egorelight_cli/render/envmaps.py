"""HDR environment maps: seeded procedural maps, disjoint train/test/wild sets, and user files.

Every map is an (H, 2H, 3) float32 array of linear RGB radiance in the equirect convention of
:mod:`egorelight_cli.geometry.equirect` (row 0 = +Y up). Scale: a clear sky of radiance ~0.3-1
with a sun giving ~2-10 units of irradiance at normal incidence, rooms and studios in
comparable ranges, so ``LightStage.envmap_to_intensities`` of any map gives lighting conditions
of similar overall brightness (irradiance ~1-10 on an upward surface).

Kinds (:func:`make_envmap`), each deterministic in ``(kind, seed, height)``:

* ``sky``: sky gradient (zenith to horizon colour, turbidity), circumsolar glow, a sun disc,
  soft clouds, textured ground lit by sun and sky;
* ``indoor``: a box room around the viewer with coloured walls, a textured floor, ceiling lamps
  (bright discs) and windows showing a bright outdoor view; walls shaded by lamps and windows;
* ``studio``: a dark background with a few coloured soft-box area lights.

Maps are rendered at 2x resolution and area-averaged (solid-angle weighted) down, and the sun's
energy is normalised so its irradiance does not depend on the resolution even when the disc is
smaller than a texel.

Sets (:func:`envmap_set`): ``train``, ``test`` and ``wild`` maps come from different seed streams
(``numpy.random.SeedSequence(seed, spawn_key=(purpose, i))``), so the sets are disjoint by
construction for a given base seed. User ``.exr`` / ``.hdr`` maps load with :func:`load_envmap`.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.equirect import (
    check_envmap,
    equirect_directions,
    equirect_solid_angles,
)

ENVMAP_KINDS = ("sky", "indoor", "studio")
PURPOSES = ("train", "test", "wild")
#: Kinds cycled through by each purpose's set (in-the-wild maps are real places: no studios).
PURPOSE_KINDS = {"train": ENVMAP_KINDS, "test": ENVMAP_KINDS, "wild": ("sky", "indoor")}
_PURPOSE_CODE = {"train": 1, "test": 2, "wild": 3}
_KIND_CODE = {"sky": 11, "indoor": 12, "studio": 13}
_SUPERSAMPLE = 2


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _direction(elevation: float, azimuth: float) -> np.ndarray:
    """Unit direction at ``elevation`` (from the horizontal, radians) and equirect azimuth (from -Z towards +X)."""
    c = math.cos(elevation)
    return np.array([c * math.sin(azimuth), math.sin(elevation), -c * math.cos(azimuth)])


def _smoothstep(edge0, edge1, x):
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _lobes(dirs: np.ndarray, rng: np.random.Generator, count: int, kappa: tuple[float, float],
           min_elevation: float = -math.pi / 2) -> np.ndarray:
    """Smooth random field on the sphere in [0, 1]: a normalised sum of von Mises-Fisher lobes."""
    field = np.zeros(dirs.shape[:-1])
    for _ in range(count):
        centre = _direction(rng.uniform(min_elevation, math.pi / 2), rng.uniform(-math.pi, math.pi))
        k = rng.uniform(*kappa)
        field += rng.uniform(0.3, 1.0) * np.exp(k * (dirs @ centre - 1.0))
    return field / max(float(field.max()), 1e-12)


def _random_colour(rng: np.random.Generator, saturation: tuple[float, float], value: float = 1.0,
                   hue: tuple[float, float] = (0.0, 1.0)) -> np.ndarray:
    h = rng.uniform(*hue) % 1.0
    return np.array(colorsys.hsv_to_rgb(h, rng.uniform(*saturation), value))


def _downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Solid-angle-weighted area average of an equirect map by an integer factor."""
    if factor == 1:
        return image
    H, W = image.shape[:2]
    weights = equirect_solid_angles(H, W)[..., None]
    h, w = H // factor, W // factor
    num = (image * weights).reshape(h, factor, w, factor, -1).sum(axis=(1, 3))
    den = weights.reshape(h, factor, w, factor, 1).sum(axis=(1, 3))
    return num / den


def _disc(dirs: np.ndarray, centre: np.ndarray, radius: float, softness: float) -> np.ndarray:
    """Soft-edged disc of angular ``radius`` (radians) around ``centre``: 1 inside, 0 outside."""
    angle = np.arccos(np.clip(dirs @ centre, -1.0, 1.0))
    return 1.0 - _smoothstep(radius - softness, radius + softness, angle)


# --------------------------------------------------------------------------------------------
# Kinds
# --------------------------------------------------------------------------------------------


def _outdoor_view(dirs: np.ndarray, rng: np.random.Generator, scale: float) -> np.ndarray:
    """A sun-less daylight view (sky gradient over a ground) for windows: (...,3) radiance."""
    up = dirs[..., 1:2]
    zenith = np.array([0.35, 0.55, 1.0]) * rng.uniform(0.7, 1.0)
    horizon = np.array([0.9, 0.93, 1.0])
    sky = zenith + (horizon - zenith) * (1.0 - np.clip(up, 0.0, 1.0)) ** 3
    ground = _random_colour(rng, (0.2, 0.5), 0.5, hue=(0.15, 0.4))  # greenish/grey scenery
    return scale * np.where(up > 0, sky, ground * (0.6 + 0.4 * (1.0 + up)))


def _sky(dirs: np.ndarray, rng: np.random.Generator, solid_angles: np.ndarray) -> np.ndarray:
    up = dirs[..., 1]
    turbidity = rng.uniform(0.0, 1.0)
    sun_dir = _direction(math.radians(rng.uniform(8.0, 75.0)), rng.uniform(-math.pi, math.pi))
    sun_elev_sin = float(sun_dir[1])
    brightness = rng.uniform(0.5, 1.0)

    zenith = np.array([0.18, 0.35, 0.85]) * (1.0 - 0.5 * turbidity) + 0.5 * turbidity * np.array([0.55, 0.6, 0.7])
    horizon = np.array([0.85, 0.88, 0.95]) * rng.uniform(0.8, 1.1)
    if sun_elev_sin < math.sin(math.radians(20.0)):  # low sun: warm horizon
        horizon = horizon * np.array([1.15, 0.95, 0.75])
    t = (1.0 - np.clip(up, 0.0, 1.0))[..., None] ** 3
    sky = zenith + (horizon - zenith) * t
    cos_sun = np.clip(dirs @ sun_dir, -1.0, 1.0)
    sun_colour = np.array([1.0, 0.95, 0.85]) if sun_elev_sin > 0.35 else np.array([1.0, 0.8, 0.55])
    glow = (0.6 + 1.2 * turbidity) * np.exp((cos_sun - 1.0) / 0.04) + 0.25 * np.exp((cos_sun - 1.0) / 0.5)
    sky = brightness * (sky + glow[..., None] * sun_colour)

    cover = rng.uniform(0.0, 0.7)
    clouds = _lobes(dirs, rng, int(rng.integers(6, 20)), (8.0, 60.0), min_elevation=math.radians(5.0))
    clouds = _smoothstep(1.0 - cover, 1.0 - cover + 0.35, clouds) * (cover > 0.05)
    clouds = clouds * _smoothstep(-0.02, 0.08, up)
    cloud_colour = brightness * rng.uniform(0.6, 1.1) * np.array([0.95, 0.95, 1.0])
    sky = sky * (1.0 - clouds[..., None]) + clouds[..., None] * cloud_colour

    # Sun disc, energy-normalised: its irradiance at normal incidence is `sun_irradiance`
    # whatever the map resolution (the disc is widened to at least ~1.5 texels).
    texel = math.pi / dirs.shape[0]
    radius = max(math.radians(0.27), 1.5 * texel)
    disc = _disc(dirs, sun_dir, radius, 0.5 * texel)
    sun_cloud = float(np.sum(clouds * disc * solid_angles) / max(np.sum(disc * solid_angles), 1e-12))
    sun_irradiance = rng.uniform(2.0, 10.0) * (1.0 - 0.6 * turbidity) * (1.0 - 0.85 * sun_cloud)
    sun = disc * (sun_irradiance / max(float(np.sum(disc * solid_angles)), 1e-12))

    ground_albedo = _random_colour(rng, (0.2, 0.6), rng.uniform(0.15, 0.35), hue=(0.05, 0.35))
    texture = 0.7 + 0.6 * _lobes(dirs, rng, 24, (20.0, 200.0), min_elevation=-math.pi / 2)
    ground_irradiance = sun_irradiance * sun_elev_sin + math.pi * 0.5 * float(np.mean(sky[up > 0]))
    ground = ground_albedo * texture[..., None] * ground_irradiance / math.pi
    haze = _smoothstep(-0.15, 0.0, up)[..., None]
    ground = ground * (1.0 - haze) + haze * horizon * brightness
    return np.where(up[..., None] > 0, sky, ground) + sun[..., None] * sun_colour


def _box_hit(dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Exit point (...,3) of rays from the origin through an axis-aligned box around it, and the axis hit (...)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_axes = np.where(dirs > 0, hi / dirs, np.where(dirs < 0, lo / dirs, np.inf))
    axis = np.argmin(t_axes, axis=-1)
    t = np.take_along_axis(t_axes, axis[..., None], axis=-1)
    return dirs * t, axis


def _indoor(dirs: np.ndarray, rng: np.random.Generator, solid_angles: np.ndarray) -> np.ndarray:
    width, depth = rng.uniform(3.0, 8.0, size=2)
    ceiling = rng.uniform(2.4, 3.5)
    eye_height = rng.uniform(1.0, 1.7)
    offset = rng.uniform(-0.3, 0.3, size=2) * np.array([width, depth])
    lo = np.array([-width / 2 - offset[0], -eye_height, -depth / 2 - offset[1]])
    hi = np.array([width / 2 - offset[0], ceiling - eye_height, depth / 2 - offset[1]])
    points, axis = _box_hit(dirs, lo, hi)
    is_floor = (axis == 1) & (dirs[..., 1] < 0)
    is_ceiling = (axis == 1) & (dirs[..., 1] > 0)
    is_wall = axis != 1

    wall_albedo = _random_colour(rng, (0.05, 0.35), rng.uniform(0.5, 0.85))
    floor_albedo = _random_colour(rng, (0.3, 0.6), rng.uniform(0.15, 0.4), hue=(0.02, 0.12))
    ceiling_albedo = np.full(3, rng.uniform(0.7, 0.9))
    albedo = np.where(is_floor[..., None], floor_albedo, np.where(is_ceiling[..., None], ceiling_albedo, wall_albedo))
    if rng.uniform() < 0.6:  # wood planks
        planks = 0.8 + 0.2 * np.sin(points[..., 0] * rng.uniform(8.0, 20.0) + 3.0 * np.sin(points[..., 2] * 2.0))
        albedo = np.where(is_floor[..., None], albedo * planks[..., None], albedo)
    for _ in range(int(rng.integers(2, 6))):  # pictures, shelves, furniture fronts on the walls
        centre = rng.uniform(lo, hi)
        size = rng.uniform(0.3, 1.5, size=3)
        inside = np.all(np.abs(points - centre) < size / 2, axis=-1) & is_wall
        albedo = np.where(inside[..., None], _random_colour(rng, (0.1, 0.8), rng.uniform(0.1, 0.8)), albedo)

    # Ceiling lamps: downward cosine emitters, drawn as bright discs on the ceiling.
    colour_temp = _random_colour(rng, (0.05, 0.35), 1.0, hue=(0.06, 0.12))
    n_x, n_z = int(rng.integers(1, 4)), int(rng.integers(1, 4))
    lamp_radius = rng.uniform(0.08, 0.25)
    lamp_radiance = rng.uniform(20.0, 60.0) * (0.12 / lamp_radius) ** 2
    irradiance = np.zeros(dirs.shape[:-1] + (3,))
    emission = np.zeros_like(irradiance)
    lamp_power = lamp_radiance * math.pi * lamp_radius ** 2  # radiant intensity along the axis
    # Inward (towards the viewer) unit normal of the wall, floor or ceiling each texel sees.
    normal = -np.eye(3)[axis] * np.sign(np.take_along_axis(dirs, axis[..., None], -1))

    def cos_towards(to_point: np.ndarray, d2: np.ndarray) -> np.ndarray:
        """Cosine at the texel's surface of the direction back towards a source at ``point - to_point``."""
        return np.clip(-np.sum(normal * to_point, axis=-1) / np.sqrt(d2), 0.0, 1.0)

    for i in range(n_x):
        for k in range(n_z):
            lamp = np.array([lo[0] + (i + 0.5) * (hi[0] - lo[0]) / n_x, hi[1],
                             lo[2] + (k + 0.5) * (hi[2] - lo[2]) / n_z])
            on_lamp = is_ceiling & (np.linalg.norm((points - lamp)[..., [0, 2]], axis=-1) < lamp_radius)
            emission += on_lamp[..., None] * lamp_radiance * colour_temp
            to_point = points - lamp
            d2 = np.maximum(np.sum(to_point ** 2, axis=-1), 0.05)
            cos_lamp = np.clip(-to_point[..., 1] / np.sqrt(d2), 0.0, 1.0)
            irradiance += (lamp_power * cos_lamp * cos_towards(to_point, d2) / d2)[..., None] * colour_temp

    # Windows: bright rectangles on walls showing an outdoor view; they also light the room.
    outdoor_scale = rng.uniform(2.0, 10.0)
    for _ in range(int(rng.integers(0, 4))):
        wall_axis = int(rng.choice([0, 2]))
        side = hi if rng.uniform() < 0.5 else lo
        along = 2 - wall_axis
        half_w = rng.uniform(0.4, 1.3)
        centre_along = rng.uniform(lo[along] + half_w + 0.1, hi[along] - half_w - 0.1) if \
            hi[along] - lo[along] > 2 * half_w + 0.3 else 0.5 * (lo[along] + hi[along])
        sill, top = lo[1] + rng.uniform(0.6, 1.0), min(hi[1] - 0.2, lo[1] + rng.uniform(1.9, 2.4))
        on_window = (axis == wall_axis) & (np.abs(points[..., wall_axis] - side[wall_axis]) < 1e-6) & \
            (np.abs(points[..., along] - centre_along) < half_w) & (points[..., 1] > sill) & (points[..., 1] < top)
        emission = np.where(on_window[..., None], _outdoor_view(dirs, rng, outdoor_scale), emission)
        albedo = np.where(on_window[..., None], 0.0, albedo)
        window_centre = np.zeros(3)
        window_centre[wall_axis], window_centre[along], window_centre[1] = side[wall_axis], centre_along, 0.5 * (sill + top)
        area = 2 * half_w * (top - sill)
        to_point = points - window_centre
        d2 = np.maximum(np.sum(to_point ** 2, axis=-1), 0.3)
        inward = -np.sign(side[wall_axis]) * np.eye(3)[wall_axis]
        cos_window = np.clip(to_point @ inward / np.sqrt(d2), 0.0, 1.0)
        cos_surface = cos_towards(to_point, d2)
        irradiance += (0.8 * outdoor_scale * area * cos_window * cos_surface / d2)[..., None] * np.array([0.85, 0.9, 1.0])

    ambient = 0.25 * float(np.mean(irradiance))  # one bounce, roughly
    diffuse = albedo * (irradiance + ambient) / math.pi
    return diffuse + emission


def _studio(dirs: np.ndarray, rng: np.random.Generator, solid_angles: np.ndarray) -> np.ndarray:
    up = dirs[..., 1:2]
    base = rng.uniform(0.003, 0.03)
    out = base * (0.6 + 0.4 * np.clip(up + 0.5, 0.0, 1.5)) * np.ones(3)
    out = np.where(up < -0.3, base * 1.5 * _random_colour(rng, (0.0, 0.2)), out)  # floor
    count = int(rng.integers(2, 6))
    for light in range(count):
        elevation = math.radians(rng.uniform(10.0, 60.0) if light == 0 else rng.uniform(-15.0, 75.0))
        centre = _direction(elevation, rng.uniform(-math.pi, math.pi))
        tangent = _unit(np.cross(centre, [0.0, 1.0, 0.0]) + 1e-9)
        bitangent = np.cross(tangent, centre)
        half_a, half_b = np.radians(rng.uniform(4.0, 18.0, size=2))
        power = 4.0 + 8.0 * rng.uniform() if rng.uniform() < 0.5 else 2.0
        a = (dirs @ tangent) / half_a
        b = (dirs @ bitangent) / half_b
        shape = (np.abs(a) ** 4 + np.abs(b) ** 4) ** 0.25
        box = (1.0 - _smoothstep(0.85, 1.15, shape)) * (dirs @ centre > 0)
        saturation = (0.0, 0.15) if light == 0 else (0.3, 1.0)
        colour = _random_colour(rng, saturation)
        irradiance = rng.uniform(1.0, 4.0) * (power / 6.0)
        box_solid_angle = max(float(np.sum(box * solid_angles)), 1e-9)
        out = out + (box * irradiance / box_solid_angle)[..., None] * colour
    return out


_GENERATORS = {"sky": _sky, "indoor": _indoor, "studio": _studio}


# --------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------


def make_envmap(kind: str, seed: int, height: int = 64) -> np.ndarray:
    """A procedural HDR environment map: (height, 2*height, 3) float32 linear radiance, >= 0.

    Args:
        kind: ``"sky"``, ``"indoor"`` or ``"studio"`` (see the module docstring).
        seed: any non-negative integer; the map is a deterministic function of (kind, seed, height)
            (different heights give the same scene at different resolutions).
        height: rows (the width is twice that), >= 4.
    """
    if kind not in _GENERATORS:
        raise EgorelightError(f"unknown environment map kind {kind!r}; expected one of {', '.join(ENVMAP_KINDS)}")
    height = int(height)
    if height < 4:
        raise EgorelightError(f"environment map height must be at least 4, got {height}")
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(_KIND_CODE[kind],)))
    H, W = _SUPERSAMPLE * height, 2 * _SUPERSAMPLE * height
    dirs = equirect_directions(H, W)
    image = _GENERATORS[kind](dirs, rng, equirect_solid_angles(H, W))
    image = _downsample(np.maximum(image, 0.0), _SUPERSAMPLE)
    return np.ascontiguousarray(image, dtype=np.float32)


@dataclass(frozen=True)
class EnvmapSpec:
    """One map of a set: its name (``<purpose>_<index>_<kind>``), kind, seed and purpose."""

    name: str
    kind: str
    seed: int
    purpose: str


def envmap_specs(purpose: str, count: int, seed: int = 0, kinds: tuple[str, ...] | None = None) -> list[EnvmapSpec]:
    """The (name, kind, seed) of the ``count`` maps of a purpose's set; kinds cycle through ``kinds``.

    Seeds come from ``SeedSequence(seed, spawn_key=(purpose, index))``: the ``train``, ``test``
    and ``wild`` streams of one base seed never share a map.
    """
    if purpose not in PURPOSES:
        raise EgorelightError(f"unknown environment map purpose {purpose!r}; expected one of {', '.join(PURPOSES)}")
    if int(count) < 0:
        raise EgorelightError(f"environment map count must be >= 0, got {count}")
    kinds = tuple(kinds) if kinds else PURPOSE_KINDS[purpose]
    for kind in kinds:
        if kind not in _GENERATORS:
            raise EgorelightError(f"unknown environment map kind {kind!r}")
    specs = []
    for index in range(int(count)):
        sequence = np.random.SeedSequence(int(seed), spawn_key=(_PURPOSE_CODE[purpose], index))
        child = int(sequence.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))
        kind = kinds[index % len(kinds)]
        specs.append(EnvmapSpec(name=f"{purpose}_{index:03d}_{kind}", kind=kind, seed=child, purpose=purpose))
    return specs


def envmap_set(purpose: str, count: int, seed: int = 0, height: int = 64,
               kinds: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """``count`` procedural maps for ``purpose`` (``train``, ``test`` or ``wild``): name -> (H,2H,3) float32.

    Sets of different purposes are disjoint by construction (see :func:`envmap_specs`).
    """
    return {spec.name: make_envmap(spec.kind, spec.seed, height)
            for spec in envmap_specs(purpose, count, seed, kinds)}


def surface_detail(height: int, seed: int, strength: float = 0.5) -> np.ndarray:
    """A multiplicative texture of the surroundings' fine structure: (height, 2*height) float32 > 0.

    Real places are full of small things (posters, windows, bricks, leaves) that the procedural
    maps, made for lighting, leave out. This is ``exp(strength * (patches + noise))``: a few
    hundred rectangles of random brightness (sharp corners for feature detectors) over
    multi-octave value noise, both zero-mean, then scaled so the solid-angle weighted mean is 1
    (multiplying a map by it keeps the map's irradiance). Deterministic in ``(height, seed)``.
    """
    height = int(height)
    if height < 4:
        raise EgorelightError(f"detail texture height must be at least 4, got {height}")
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0xDE7,)))
    H, W = height, 2 * height
    log = np.zeros((H, W), np.float64)
    for cells in (8, 16, 32, 64, 128):  # value noise: bicubic-upsampled random grids
        grid = rng.normal(size=(cells, 2 * cells))
        log += cv2.resize(grid, (W, H), interpolation=cv2.INTER_CUBIC) * (0.6 * 8 / cells) ** 0.5
    patches = np.zeros((H, W), np.float64)
    for _ in range(int(1.2 * height)):  # rectangles 0.5-6 degrees across, wrapping in azimuth
        h = max(1, int(H * rng.uniform(0.5, 6.0) / 180.0))
        w = max(1, int(W * rng.uniform(0.5, 6.0) / 360.0))
        row, col = int(rng.integers(0, H - h + 1)), int(rng.integers(0, W))
        cols = np.arange(col, col + w) % W
        patches[row:row + h, cols] = rng.normal(0.0, 1.0)
    factor = np.exp(float(strength) * (log - log.mean() + patches))
    weights = equirect_solid_angles(H, W)
    factor /= float((factor * weights).sum() / weights.sum())
    return np.ascontiguousarray(factor, dtype=np.float32)


def detailed_surroundings(envmap: np.ndarray, height: int, seed: int, strength: float = 0.5) -> np.ndarray:
    """What cameras see of a place whose light ``envmap`` describes: the map resized to ``height``
    rows (bilinear) times :func:`surface_detail` -> (height, 2*height, 3) float32."""
    envmap = check_envmap(envmap)
    height = int(height)
    big = cv2.resize(envmap, (2 * height, height), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(np.maximum(big, 0.0) * surface_detail(height, seed, strength)[..., None],
                                dtype=np.float32)


def load_envmap(path: str | Path, height: int | None = None) -> np.ndarray:
    """Read a user HDR map (``.exr`` RGB, or Radiance ``.hdr``) as (H,2H,3) float32 linear RGB.

    The map must be roughly 2:1 (within 5%); it is resized with ``cv2.INTER_AREA`` (or linear
    when enlarging) to ``height`` rows (default its own height) and exactly twice that width.
    Errors name the file.
    """
    path = Path(path)
    if not path.is_file():
        raise EgorelightError("environment map not found", path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        from egorelight_cli.io.exr import read_exr

        try:
            image = read_exr(path).layer("", ("R", "G", "B"))
        except EgorelightError as error:
            raise EgorelightError(error.message, path) from None
    elif suffix == ".hdr":
        from egorelight_cli.io.images import decode_image

        image = decode_image(path, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR, "Radiance HDR image")
    else:
        raise EgorelightError(f"unsupported environment map format {suffix!r} (use .exr or .hdr)", path)
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] != 3 or min(image.shape[:2]) < 2:
        raise EgorelightError(f"environment map must be an RGB image, got shape {image.shape}", path)
    if not np.isfinite(image).all():
        raise EgorelightError("environment map contains NaN or infinity", path)
    if not (image > 0).any():
        raise EgorelightError("environment map holds no light (no positive radiance)", path)
    if (image < 0).any():  # radiance is not negative: filtering ringing, clipped (said once)
        from egorelight_cli import console

        console.info(f"environment map: {int((image < 0).sum())} negative values clipped to 0 ({path})")
        image = np.maximum(image, 0.0)
    rows, cols = image.shape[:2]
    if abs(cols / rows - 2.0) > 0.1:
        raise EgorelightError(f"environment map must be equirectangular (width = 2 x height), got {cols}x{rows}", path)
    target = rows if height is None else int(height)
    if target < 2:
        raise EgorelightError(f"environment map height must be at least 2, got {target}", path)
    if (rows, cols) != (target, 2 * target):
        interpolation = cv2.INTER_AREA if target <= rows else cv2.INTER_LINEAR
        image = cv2.resize(image, (2 * target, target), interpolation=interpolation)
    return np.ascontiguousarray(image, dtype=np.float32)


def write_envmap(path: str | Path, envmap: np.ndarray) -> None:
    """Write an (H,2H,3) map as an RGB float32 EXR (``capture/envmaps/<name>.exr``)."""
    from egorelight_cli.io.exr import write_exr_layers

    write_exr_layers(path, {"": check_envmap(envmap).astype(np.float32)})
