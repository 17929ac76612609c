"""Ground-truth shading under the lightstage: ray-traced direct light with shadow rays (Embree).

Radiometry (see :mod:`egorelight_cli.render.lightstage` for the light model). A surface point
``x`` with unit shading normal ``n``, seen from direction ``v`` (unit, from ``x`` towards the
camera), under a lighting condition ``I`` (L,3) reflects the radiance

    L_o(x, v) = sum_l  f(x, w_l, v) * E_l(x),
    E_l(x)    = J_l * max(0, n . w_l) * V_l(x) / |p_l - x|^2,     J_l = I_l gain_l Omega_l R_l^2,

with ``w_l`` the unit direction to light ``l`` and ``V_l`` its binary visibility (a shadow ray:
self-occlusion of the mesh). The BRDF is Lambert plus a normalised Blinn-Phong lobe:

    f = albedo / pi  +  ks * c(s) * max(0, n . h)^s,    h = (w_l + v) / |w_l + v|,
    c(s) = (s + 2) (s + 4) / (8 pi (2^(-s/2) + s)),

``albedo`` (3,) the diffuse reflectance (linear RGB in [0,1]), ``ks`` the specular albedo (grey
or RGB) and ``s`` the Blinn-Phong exponent from a roughness ``r`` in (0, 1]: ``alpha = r^2``,
``s = 2 / alpha^2 - 2`` (Walter et al.'s Beckmann-equivalent mapping, clamped to [1, 10^4]). The
factor ``c(s)`` (Giesen's exact Blinn-Phong normalisation; ~(s + 8) / (8 pi) for large s) makes the
cosine-weighted lobe integrate to at most one (one at normal incidence), so the material is
energy-conserving when ``albedo + ks <= 1`` per channel. Everything is linear in ``I`` (no
clamping), in float32, with no interreflections.

Visibility. :func:`light_visibility` casts one shadow ray per (point, light) pair from the
point offset by ``eps`` along its normal towards the light's side (pixels: the geometric face
normal; vertices: the vertex normal), with ``max_dist`` the distance to the light (Embree any-hit). :func:`render_view` either traces that exactly for every visible
pixel and lit light (``vertex_visibility=None``; ~N_pixels x L rays), or reuses a per-vertex
(V,L) visibility computed once per frame and shared by all cameras
(:func:`vertex_light_visibility`; lights behind a vertex's tangent plane are not traced: they
cannot light it). Per-vertex visibility interpolated over a face is only
trusted where the face's three vertices agree; pixels on faces whose vertices disagree (shadow
boundaries), and all pixels for the ``exact_lights`` strongest lights (OLAT, a sun), get exact
per-pixel shadow rays. The remaining error is a shadow smaller than one triangle (e.g. a thin
strap shadowing the middle of a face whose corners all see the light) under a weak light; the
saving is typically 5-20x fewer rays.

Materials (:class:`Material`) hold per-texel maps (H_t,W_t,C) sampled bilinearly at the
rasterised UVs (``cv2.remap``; UV convention of :mod:`egorelight_cli.render.raster`: row 0 is
v = 1), per-point arrays (N,C) for :func:`shade`, or constants. Textures should be dilated past
their UV islands by the producer: bilinear lookups near seams read neighbouring texels.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.geometry.tangents import face_uv_tangents, world_from_tangent_space
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import (
    RasterResult,
    rasterize,
    uv_to_texel_coords,
    vertex_normals,
)
from egorelight_cli.runtime import single_torch_thread

#: Offset (metres) of shadow-ray origins from the surface, along the normal towards the light.
SHADOW_EPS = 1e-3
#: Blinn-Phong exponents are clamped to this range.
MAX_SHININESS = 1e4
MIN_ROUGHNESS = 0.05
#: Pixels shaded per chunk (memory ~ chunk x lights x 40 bytes).
_CHUNK_PIXELS = 4096
#: Shadow rays per Embree call in :func:`light_visibility`.
_CHUNK_RAYS = 1 << 20
_REMAP_COLUMNS = 1024  # cv2.remap maps must stay below SHRT_MAX rows and columns


# --------------------------------------------------------------------------------------------
# Materials
# --------------------------------------------------------------------------------------------


def roughness_to_shininess(roughness) -> np.ndarray:
    """Blinn-Phong exponent ``s = 2 / alpha^2 - 2`` with ``alpha = roughness^2``, clamped to [1, 1e4]."""
    r = np.clip(np.asarray(roughness, dtype=np.float32), MIN_ROUGHNESS, 1.0)
    alpha2 = (r * r) ** 2
    return np.clip(2.0 / alpha2 - 2.0, 1.0, MAX_SHININESS).astype(np.float32)


def _sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a UV texture (Ht,Wt[,C]) at UVs (N,2) -> (N,C) float32 (row 0 is v = 1)."""
    texture = np.asarray(texture, dtype=np.float32)
    if texture.ndim == 2:
        texture = texture[..., None]
    channels = texture.shape[2]
    n = len(uv)
    if n == 0:
        return np.zeros((0, channels), np.float32)
    coords = uv_to_texel_coords(uv, texture.shape[:2]).astype(np.float32)
    rows = -(-n // _REMAP_COLUMNS)
    maps = np.full((rows * _REMAP_COLUMNS, 2), -1.0, np.float32)
    maps[:n] = coords
    maps = maps.reshape(rows, _REMAP_COLUMNS, 2)
    out = np.empty((rows, _REMAP_COLUMNS, channels), np.float32)
    for start in range(0, channels, 4):  # cv2.remap takes at most 4 channels
        part = np.ascontiguousarray(texture[..., start:start + 4])
        sampled = cv2.remap(part, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out[..., start:start + 4] = sampled.reshape(rows, _REMAP_COLUMNS, -1)
    return out.reshape(-1, channels)[:n]


def _resolve(value, uv: np.ndarray | None, n: int, channels: int, name: str) -> np.ndarray:
    """A material field as per-point (n, channels) float32: texture, per-point array or constant."""
    array = np.asarray(value, dtype=np.float32)
    if array.ndim == 3:
        if uv is None:
            raise EgorelightError(f"material {name} is a texture but the mesh has no UVs")
        array = _sample_texture(array, uv)
    elif array.ndim <= 1:
        array = np.broadcast_to(array.reshape(1, -1), (n, array.size if array.ndim else 1))
    if array.ndim != 2 or array.shape[0] != n or array.shape[1] not in (1, channels):
        raise EgorelightError(f"material {name} must be a texture, ({n},{channels}) or a constant, got {np.shape(value)}")
    return np.ascontiguousarray(np.broadcast_to(array, (n, channels)), dtype=np.float32)


@dataclass(eq=False)
class Material:
    """Surface reflectance; each field is a UV texture (H_t,W_t,C) (always 3-D, C = 1 allowed),
    per-point (N,C) or a constant (scalar or (C,)).

    Attributes:
        albedo: diffuse reflectance, linear RGB in [0,1] (C = 3, or 1 for grey).
        specular: specular albedo ks, grey (C = 1) or RGB; 0 disables the lobe.
        roughness: in (0, 1] (C = 1); mapped to a Blinn-Phong exponent by :func:`roughness_to_shininess`.
        normal_map: None, or a (H_t,W_t,3) tangent-space normal texture (``(0,0,1)``: no detail;
            see :mod:`egorelight_cli.geometry.tangents`) that tilts the shading normals.
    """

    albedo: np.ndarray | float = 0.5
    specular: np.ndarray | float = 0.0
    roughness: np.ndarray | float = 0.5
    normal_map: np.ndarray | None = None

    def at(self, uv: np.ndarray | None, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-point (albedo (n,3), ks (n,3), shininess (n,)) at UVs (n,2) (None: constants/per-point only)."""
        albedo = _resolve(self.albedo, uv, n, 3, "albedo")
        ks = _resolve(self.specular, uv, n, 3, "specular")
        shininess = roughness_to_shininess(_resolve(self.roughness, uv, n, 1, "roughness")[:, 0])
        return albedo, ks, shininess

    def detail_normals(self, normals: np.ndarray, uv: np.ndarray | None, face_id: np.ndarray, vertices: np.ndarray,
                       faces: np.ndarray, face_uvs: np.ndarray | None) -> np.ndarray:
        """(n,3) shading normals tilted by the normal map (unchanged without one or without UVs).

        Args:
            normals: (n,3) unit interpolated normals at the points; uv (n,2) their UVs.
            face_id: (n,) face of each point; vertices (V,3), faces (F,3), face_uvs (F,3,2) the mesh.
        """
        if self.normal_map is None or uv is None or face_uvs is None or len(normals) == 0:
            return normals
        # tangent frames of the faces hit only (not of the whole mesh, once per camera)
        tangent, sign = face_uv_tangents(vertices, np.asarray(faces)[face_id], np.asarray(face_uvs)[face_id])
        tilted = world_from_tangent_space(_sample_texture(self.normal_map, uv), normals, tangent, sign)
        return tilted.astype(np.float32)


# --------------------------------------------------------------------------------------------
# Visibility
# --------------------------------------------------------------------------------------------


def _row_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products (n,) of (n,3) arrays, element-wise (faster than a reduce over axis 3)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _shadow_rays(points: np.ndarray, offset_normals: np.ndarray, light_positions: np.ndarray, eps: float):
    """Origins (n,3), unit directions (n,3) and distances (n,) of shadow rays, one per row (float32).

    The origin is the point moved by ``eps`` along its normal, on the side facing the light.
    """
    eps = np.float32(eps)
    side = np.where(_row_dot(light_positions - points, offset_normals) < 0, -eps, eps)
    origins = points + side[:, None] * offset_normals
    dirs = light_positions - origins
    distance = np.sqrt(_row_dot(dirs, dirs))
    dirs /= distance[:, None]
    return origins, dirs, distance


def trace_pairs(caster: RayCaster, points: np.ndarray, offset_normals: np.ndarray, light_positions: np.ndarray,
                point_index: np.ndarray, light_index: np.ndarray, eps: float = SHADOW_EPS) -> np.ndarray:
    """Visibility (P,) bool of (point, light) pairs, in chunks of shadow rays."""
    points = np.asarray(points, dtype=np.float32)
    offset_normals = np.asarray(offset_normals, dtype=np.float32)
    light_positions = np.asarray(light_positions, dtype=np.float32)
    visible = np.empty(len(point_index), dtype=bool)
    for start in range(0, len(point_index), _CHUNK_RAYS):
        p = point_index[start:start + _CHUNK_RAYS]
        l = light_index[start:start + _CHUNK_RAYS]
        origins, dirs, distance = _shadow_rays(points[p], offset_normals[p], light_positions[l], eps)
        visible[start:start + len(p)] = ~caster.occluded(origins, dirs, max_dist=np.maximum(distance - eps, 2 * eps))
    return visible


def light_visibility(caster: RayCaster, points: np.ndarray, normals: np.ndarray, lightstage: LightStage,
                     eps: float = SHADOW_EPS, lights: np.ndarray | None = None) -> np.ndarray:
    """(N,L) bool: True where the segment from each point to each light is free of the mesh.

    Args:
        caster: Embree scene of the (posed) mesh.
        points: (N,3) surface points, metres.
        normals: (N,3) unit normals used to offset ray origins by ``eps`` towards the light's side
            (a light behind the surface is then usually occluded by the surface itself).
        lightstage: the lights.
        eps: origin offset, metres.
        lights: optional light indices (M,); the result is then (N,M).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if normals.shape != points.shape:
        raise EgorelightError(f"points {points.shape} and normals {normals.shape} differ")
    light_ids = np.arange(lightstage.num_lights) if lights is None else np.asarray(lights, dtype=np.int64)
    n, m = len(points), len(light_ids)
    point_index = np.repeat(np.arange(n), m)
    light_index = np.tile(np.arange(m), n)
    visible = trace_pairs(caster, points, normals, lightstage.positions[light_ids], point_index, light_index, eps)
    return visible.reshape(n, m)


def lights_in_front(points: np.ndarray, normals: np.ndarray, lightstage: LightStage) -> np.ndarray:
    """(N,L) bool: light in front of each point's tangent plane (``n . (x_l - p) > 0``)."""
    return normals @ lightstage.positions.T - np.sum(normals * points, axis=1, keepdims=True) > 0


def facing_light_visibility(caster: RayCaster, points: np.ndarray, normals: np.ndarray, lightstage: LightStage,
                            eps: float = SHADOW_EPS) -> np.ndarray:
    """(N,L) bool like :func:`light_visibility`, but lights behind a point's tangent plane (which
    cannot light it) are False without casting a ray: about half the rays."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if normals.shape != points.shape:
        raise EgorelightError(f"points {points.shape} and normals {normals.shape} differ")
    facing = lights_in_front(points, normals, lightstage)
    point_index, light_index = np.nonzero(facing)
    visible = np.zeros(facing.shape, dtype=bool)
    visible[point_index, light_index] = trace_pairs(caster, points, normals, lightstage.positions, point_index,
                                                     light_index, eps)
    return visible


def vertex_light_visibility(vertices: np.ndarray, faces: np.ndarray, lightstage: LightStage,
                            caster: RayCaster | None = None, normals: np.ndarray | None = None,
                            eps: float = SHADOW_EPS) -> np.ndarray:
    """(V,L) bool light visibility at the vertices of a posed mesh (once per frame, shared by all cameras).

    Normals default to the area-weighted vertex normals (as :func:`render_view` uses). Lights
    behind a vertex's tangent plane are not visible (no ray is cast: they cannot light it).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    if caster is None:
        caster = RayCaster(vertices, faces)
    if normals is None:
        normals = vertex_normals(vertices, np.asarray(faces, dtype=np.int64))
    return facing_light_visibility(caster, vertices, normals, lightstage, eps=eps)


# --------------------------------------------------------------------------------------------
# Shading
# --------------------------------------------------------------------------------------------


class ShadingComponents(NamedTuple):
    """Per-point shading, all (N,3) float32 linear RGB.

    Attributes:
        radiance: total outgoing radiance, diffuse + specular.
        diffuse: albedo / pi * irradiance.
        specular: the Blinn-Phong lobe's radiance.
        irradiance: sum of the lights' irradiance E_l (the paper's diffuse shading map chi).
    """

    radiance: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    irradiance: np.ndarray


def _light_geometry(points: np.ndarray, normals: np.ndarray, light_positions: np.ndarray):
    """Unit directions to the lights as components (3 x (n,La)), 1/d^2 (n,La) and clamped cosines (n,La).

    float32, structure-of-arrays, element-wise numpy only (no BLAS: see the note on OpenBLAS
    threads in geometry/raycast.py).
    """
    p = points.astype(np.float32)
    q = light_positions.astype(np.float32)
    n = normals.astype(np.float32)
    dirs = [q[None, :, k] - p[:, k, None] for k in range(3)]
    inv_d2 = dirs[0] * dirs[0]
    inv_d2 += dirs[1] * dirs[1]
    inv_d2 += dirs[2] * dirs[2]
    np.reciprocal(inv_d2, out=inv_d2)
    inv_d = np.sqrt(inv_d2)
    cos = np.zeros_like(inv_d2)
    for k in range(3):
        dirs[k] *= inv_d
        cos += dirs[k] * n[:, k, None]
    np.maximum(cos, 0.0, out=cos)
    return dirs, inv_d2, cos


def _lobe_normalisation(s: np.ndarray) -> np.ndarray:
    """Blinn-Phong normalisation c(s) = (s + 2)(s + 4) / (8 pi (2^(-s/2) + s)) (float32)."""
    return ((s + 2.0) * (s + 4.0) / (np.float32(8.0 * math.pi) * (np.exp2(-0.5 * s) + s))).astype(np.float32)


def _shade_chunk(dirs, inv_d2, cos, visibility, normals, view_dirs, albedo, ks, shininess, J):
    """Irradiance, diffuse and specular radiance (n,3) of one chunk; see the module docstring."""
    weight = cos * inv_d2
    if visibility is not None:
        weight *= visibility
    irradiance = np.einsum("nl,lc->nc", weight, J)
    diffuse = albedo * irradiance * np.float32(1.0 / math.pi)
    specular = np.zeros_like(diffuse)
    shiny = np.flatnonzero(np.any(ks > 0, axis=1))
    if shiny.size:
        every = shiny.size == len(ks)
        pick = (lambda a: a) if every else (lambda a: a[shiny])
        half = [pick(dirs[k]) + view_dirs[shiny, k, None] for k in range(3)]
        n = normals[shiny]
        inv_norm = half[0] * half[0] + half[1] * half[1] + half[2] * half[2]
        np.maximum(inv_norm, 1e-24, out=inv_norm)
        inv_norm = 1.0 / np.sqrt(inv_norm)
        n_dot_h = half[0] * n[:, 0, None] + half[1] * n[:, 1, None] + half[2] * n[:, 2, None]
        n_dot_h *= inv_norm
        np.maximum(n_dot_h, 0.0, out=n_dot_h)
        s = shininess[shiny, None]
        lobe = np.power(n_dot_h, s, out=n_dot_h)
        lobe *= _lobe_normalisation(s)
        lobe *= pick(weight)
        specular[shiny] = ks[shiny] * np.einsum("nl,lc->nc", lobe, J)
    return irradiance, diffuse, specular


def _spec_arrays(spec, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(ks (n,3), shininess (n,)) from shade()'s ``spec`` argument."""
    if spec is None:
        return np.zeros((n, 3), np.float32), np.ones(n, np.float32)
    if isinstance(spec, Material):
        _, ks, shininess = spec.at(None, n)
        return ks, shininess
    if isinstance(spec, tuple):
        ks, roughness = spec
        return _resolve(ks, None, n, 3, "specular"), roughness_to_shininess(_resolve(roughness, None, n, 1, "roughness")[:, 0])
    spec = np.asarray(spec, dtype=np.float32)
    if spec.shape == (n, 2):
        return _resolve(spec[:, :1], None, n, 3, "specular"), roughness_to_shininess(spec[:, 1])
    if spec.shape == (n, 4):
        return np.ascontiguousarray(spec[:, :3]), roughness_to_shininess(spec[:, 3])
    raise EgorelightError(f"spec must be None, (ks, roughness), ({n},2) or ({n},4), got {spec.shape}")


def _active_lights(lightstage: LightStage, intensities) -> tuple[np.ndarray, np.ndarray]:
    """Indices of lights that emit anything and their point intensities J (La,3) float32."""
    J = lightstage.point_intensities(intensities)
    active = np.flatnonzero(np.any(J > 0, axis=1))
    return active, np.ascontiguousarray(J[active], dtype=np.float32)


def shade(points: np.ndarray, normals: np.ndarray, view_dirs: np.ndarray, albedo: np.ndarray, spec,
          lightstage: LightStage, intensities: np.ndarray, visibility: np.ndarray | None = None,
          components: bool = False):
    """Outgoing radiance of surface points under a lighting condition (see the module docstring).

    Args:
        points: (N,3) world points, metres.
        normals: (N,3) unit shading normals.
        view_dirs: (N,3) unit directions from the points towards the viewer.
        albedo: (N,3) (or (3,) / scalar) diffuse reflectance, linear RGB.
        spec: specular parameters: None (Lambert only), a tuple ``(ks, roughness)`` of per-point or
            constant values, an (N,2) array ``[ks, roughness]``, an (N,4) array
            ``[ks_r, ks_g, ks_b, roughness]``, or a per-point :class:`Material`.
        lightstage: the lights.
        intensities: (L,3) lighting condition (radiance-like, linear RGB).
        visibility: (N,L) bool/float light visibility (:func:`light_visibility`); None = all visible.
        components: return :class:`ShadingComponents` instead of the radiance alone.

    Returns:
        (N,3) float32 radiance (linear in ``intensities``), or :class:`ShadingComponents`.
    """
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    n = len(points)
    normals = np.asarray(normals, dtype=np.float32).reshape(n, 3)
    view_dirs = np.asarray(view_dirs, dtype=np.float32).reshape(n, 3)
    albedo = _resolve(albedo, None, n, 3, "albedo")
    ks, shininess = _spec_arrays(spec, n)
    active, J = _active_lights(lightstage, intensities)
    if visibility is not None:
        visibility = np.asarray(visibility)
        if visibility.shape != (n, lightstage.num_lights):
            raise EgorelightError(f"visibility must be ({n},{lightstage.num_lights}), got {visibility.shape}")
    out = [np.zeros((n, 3), np.float32) for _ in range(4)]
    light_positions = lightstage.positions[active]
    for start in range(0, n if active.size else 0, _CHUNK_PIXELS):
        rows = slice(start, min(start + _CHUNK_PIXELS, n))
        dirs, inv_d2, cos = _light_geometry(points[rows], normals[rows], light_positions)
        vis = None if visibility is None else visibility[rows][:, active].astype(np.float32)
        irradiance, diffuse, specular = _shade_chunk(dirs, inv_d2, cos, vis, normals[rows], view_dirs[rows],
                                                     albedo[rows], ks[rows], shininess[rows], J)
        out[0][rows], out[1][rows], out[2][rows], out[3][rows] = diffuse + specular, diffuse, specular, irradiance
    result = ShadingComponents(*out)
    return result if components else result.radiance


# --------------------------------------------------------------------------------------------
# Rendering a camera view
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RenderResult:
    """One camera's render; (H,W) is the camera's image size, background where ``mask`` is False.

    Attributes:
        radiance: (H,W,3) float32 linear RGB radiance (background filled in).
        mask: (H,W) bool, True where the mesh is visible.
        depth: (H,W) float32 camera-frame z of the visible surface, metres (0 on background).
        normal: (H,W,3) float32 unit world shading normals, with the normal map (0 on background).
        face_id: (H,W) int32 visible face, -1 on background.
        albedo: (H,W,3) float32 diffuse albedo seen at each pixel (0 on background).
        diffuse: (H,W,3) float32 diffuse radiance (0 on background).
        specular: (H,W,3) float32 specular radiance (0 on background).
        irradiance: (H,W,3) float32 irradiance at the surface (0 on background).
        shadow_rays: number of shadow rays traced for this view.
        raster: the underlying :class:`~egorelight_cli.render.raster.RasterResult`.
    """

    radiance: np.ndarray
    mask: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    face_id: np.ndarray
    albedo: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    irradiance: np.ndarray
    shadow_rays: int
    raster: RasterResult


def _background(background, height: int, width: int) -> np.ndarray:
    """(H,W,3) float32 background radiance from None, a scalar, an RGB triple or an image."""
    if background is None:
        return np.zeros((height, width, 3), np.float32)
    background = np.asarray(background, dtype=np.float32)
    if background.ndim == 3:
        if background.shape != (height, width, 3):
            raise EgorelightError(f"background image must be ({height},{width},3), got {background.shape}")
        return background.copy()
    try:
        return np.array(np.broadcast_to(background, (height, width, 3)), dtype=np.float32)
    except ValueError:
        raise EgorelightError(f"background must be a scalar, RGB triple or image, got shape {background.shape}") from None


def _strongest_lights(lightstage: LightStage, intensities: np.ndarray, active: np.ndarray, count: int) -> np.ndarray:
    """Positions in ``active`` of the ``count`` lights giving the most irradiance at the dome centre."""
    if count <= 0 or not active.size:
        return np.zeros(0, dtype=np.int64)
    strength = (np.asarray(intensities)[active] * lightstage.rgb_gain[active]).max(axis=1) * \
        lightstage.cell_solid_angles()[active]
    return np.argsort(-strength, kind="stable")[:count]


def render_view(vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray | None, material_textures: Material,
                camera: Camera, lightstage: LightStage, intensities: np.ndarray, caster: RayCaster | None = None,
                vertex_visibility: np.ndarray | None = None, background=None, normals: np.ndarray | None = None,
                exact_lights: int = 8, shadow_eps: float = SHADOW_EPS) -> RenderResult:
    """Render a textured mesh under the lightstage through a pinhole or fisheye camera.

    Args:
        vertices: (V,3) posed vertices, metres, world frame.
        faces: (F,3) vertex indices.
        face_uvs: (F,3,2) face-corner UVs (None when the material has no textures).
        material_textures: a :class:`Material` whose fields are UV textures or constants (or a
            dict of its fields: ``{"albedo": (Ht,Wt,3), "specular": ..., "roughness": ...}``).
        camera: the camera (``geometry.cameras.Camera``, pinhole or fisheye).
        lightstage: the lights.
        intensities: (L,3) lighting condition.
        caster: an Embree scene of this posed mesh (share it between cameras of a frame).
        vertex_visibility: (V,L) per-vertex light visibility of this posed mesh
            (:func:`vertex_light_visibility`), or None for exact per-pixel shadow rays.
        background: None (black), a scalar / RGB radiance, or an (H,W,3) radiance image.
        normals: (V,3) vertex normals; default area-weighted ones.
        exact_lights: with ``vertex_visibility``, this many strongest lights always get exact
            per-pixel shadow rays (plus every light on faces whose vertices disagree).
        shadow_eps: shadow-ray origin offset, metres.

    Returns:
        :class:`RenderResult`.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    intensities = lightstage.check_intensities(intensities)
    if isinstance(material_textures, Mapping):
        material_textures = Material(**material_textures)
    if caster is None:
        caster = RayCaster(vertices, faces)
    if normals is None:
        normals = vertex_normals(vertices, faces)
    if vertex_visibility is not None:
        vertex_visibility = np.asarray(vertex_visibility, dtype=bool)
        if vertex_visibility.shape != (len(vertices), lightstage.num_lights):
            raise EgorelightError(f"vertex visibility must be ({len(vertices)},{lightstage.num_lights}), "
                                  f"got {vertex_visibility.shape}")
    with single_torch_thread():
        raster = rasterize(vertices, faces, camera, face_uvs=face_uvs, normals=normals, caster=caster)
    mask = raster.mask
    H, W = mask.shape
    n = int(mask.sum())
    points = raster.points[mask]
    face_id = raster.face_id[mask]
    shading_normals = material_textures.detail_normals(raster.normal[mask], None if raster.uv is None else raster.uv[mask],
                                                       face_id, vertices, faces, face_uvs)
    offset_normals = raster.face_normal[mask]
    view_dirs = camera.centre_world.astype(np.float32) - points
    view_dirs /= np.sqrt(np.sum(view_dirs * view_dirs, axis=-1, keepdims=True))
    albedo, ks, shininess = material_textures.at(None if raster.uv is None else raster.uv[mask], n)

    active, J = _active_lights(lightstage, intensities)
    light_positions = lightstage.positions[active]
    exact = np.zeros(len(active), dtype=bool)
    exact[_strongest_lights(lightstage, intensities, active, exact_lights)] = True
    corner_vis = None if vertex_visibility is None else vertex_visibility[:, active]

    outputs = [np.zeros((n, 3), np.float32) for _ in range(3)]
    rays = 0
    for start in range(0, n if active.size else 0, _CHUNK_PIXELS):
        rows = slice(start, min(start + _CHUNK_PIXELS, n))
        dirs, inv_d2, cos = _light_geometry(points[rows], shading_normals[rows], light_positions)
        lit = cos > 0
        if corner_vis is None:
            need = lit
            vis = np.zeros(lit.shape, np.float32)
        else:
            corners = corner_vis[faces[face_id[rows]]]  # (n,3,La) bool
            agree = corners.all(axis=1) | ~corners.any(axis=1)
            vis = corners[:, 0].astype(np.float32)
            need = lit & (~agree | exact[None, :])
        p, l = np.nonzero(need)
        if p.size:
            vis[p, l] = trace_pairs(caster, points[rows], offset_normals[rows], light_positions, p, l, shadow_eps)
            rays += int(p.size)
        irradiance, diffuse, specular = _shade_chunk(dirs, inv_d2, cos, vis, shading_normals[rows], view_dirs[rows],
                                                     albedo[rows], ks[rows], shininess[rows], J)
        outputs[0][rows], outputs[1][rows], outputs[2][rows] = irradiance, diffuse, specular

    def image(values: np.ndarray) -> np.ndarray:
        out = np.zeros((H, W, 3), np.float32)
        out[mask] = values
        return out

    irradiance, diffuse, specular = (image(v) for v in outputs)
    radiance = _background(background, H, W)
    radiance[mask] = diffuse[mask] + specular[mask]
    return RenderResult(radiance=radiance, mask=mask, depth=raster.depth, normal=image(shading_normals),
                        face_id=raster.face_id, albedo=image(albedo), diffuse=diffuse, specular=specular,
                        irradiance=irradiance, shadow_rays=rays, raster=raster)
