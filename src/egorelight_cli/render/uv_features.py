"""Per-texel lighting features of a tracked mesh (paper Sec. "Diffuse and Specular Separation").

Shared by ``geolift``, ``relight`` and ``envmap``. For the texels of a UV layout (``UVRaster``)
and one posed mesh:

* :func:`texel_surface` -- the surface point ``p'`` of every texel and the coarse normal ``n̄``
  (barycentric interpolation of the mesh's vertex normals), with the coverage mask;
  :func:`texel_tangent_frames` -- the UV tangent frame around ``n̄`` (for tangent-space normals);
* :func:`texel_visibility` -- Eq. ``optix``: a shadow ray from ``p' + delta n̄`` to every
  lightstage light, against the tracked mesh (Embree), ``delta = SHADOW_EPS``;
* :func:`light_transfer` -- the per-light geometry term ``G_l = V_l max(0, n.w_l) Omega_l R_l^2 / d_l^2``
  (for the normal ``n`` of choice, GeoLift's lifted one in the paper). With it

  - the flat-lit shadow map ``rho = sum_l G_l / pi`` (:func:`shadow_map`; 1 for an unoccluded
    surface at the dome centre lit from its whole hemisphere, less where shadowed), and
  - the HDR irradiance map ``chi = sum_l G_l gain_l I_l`` (:func:`irradiance_map`), which is
    exactly the irradiance :meth:`LightStage.irradiance` and the renderer's shading compute
    (the paper's ``sum 1 e (n.w)`` up to per-light constants, which this keeps physical);

* :func:`select_rays` -- the top-``r`` lights of each texel by the Blinn-Phong importance
  ``max(0, n.h)^alpha G_l |gain_l I_l|`` for a camera centre (``h`` the half vector), and
  :func:`ray_encoding` -- the paper's 6-D ``psi = (n.w, n.v, n.h, G_l gain_l I_l)``.

Features are computed for the covered texels only, as flat (N,...) arrays in row-major texel
order (``coverage`` selects them). Everything that depends on the light intensities is a torch
function of them, so gradients reach an environment map through :class:`~egorelight_cli.render.lighting.EnvmapPooling`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.geometry.tangents import face_uv_tangents, tangent_frames
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import UVRaster, texels_to_surface, vertex_normals
from egorelight_cli.render.shading import SHADOW_EPS, facing_light_visibility

DEFAULT_SHININESS = 32.0  # alpha of the importance score (the paper leaves it open: only the order matters)
_CHUNK_TEXELS = 8192


@dataclass(frozen=True, eq=False)
class TexelSurface:
    """The covered texels of one posed mesh.

    Attributes:
        coverage: (H,W) bool texels that sample the surface.
        points: (N,3) float64 surface points ``p'`` of the covered texels (row-major order), metres.
        normals: (N,3) float64 unit coarse normals ``n̄``.
    """

    coverage: np.ndarray
    points: np.ndarray
    normals: np.ndarray

    def to_map(self, values, fill: float = 0.0) -> np.ndarray:
        """Scatter per-texel values (N,...) back to a UV map (H,W,...)."""
        return texel_map(self.coverage, values, fill)


def texel_map(coverage: np.ndarray, values, fill: float = 0.0) -> np.ndarray:
    """Per covered texel values (N,...) (row-major order) -> a UV map (H,W,...) filled elsewhere."""
    values = np.asarray(values)
    out = np.full(coverage.shape + values.shape[1:], fill, dtype=values.dtype)
    out[coverage] = values
    return out


def texel_surface(uv_raster: UVRaster, vertices: np.ndarray, faces: np.ndarray) -> TexelSurface:
    """Texel points and coarse normals of a mesh (V,3) posed in the layout's topology."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    coverage = uv_raster.coverage
    points = texels_to_surface(uv_raster, vertices, faces)[coverage].astype(np.float64)
    normals = texels_to_surface(uv_raster, vertex_normals(vertices, faces), faces)[coverage].astype(np.float64)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    if np.any(length < 1e-12):
        raise EgorelightError("the mesh has texels with a zero normal (degenerate faces)")
    return TexelSurface(coverage=coverage, points=points, normals=normals / length)


def texel_tangent_frames(uv_raster: UVRaster, vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray,
                         surface: TexelSurface) -> tuple[np.ndarray, np.ndarray]:
    """(t, b) (N,3) float64 orthonormal UV tangent frames of the covered texels around ``surface.normals``
    (:mod:`~egorelight_cli.geometry.tangents`: a tangent-space normal ``m`` means ``m_t t + m_b b + m_n n``)."""
    face_id = uv_raster.face_id[uv_raster.coverage]
    faces = np.asarray(faces, dtype=np.int64)[face_id]
    tangent, sign = face_uv_tangents(np.asarray(vertices, np.float64), faces, np.asarray(face_uvs)[face_id])
    return tangent_frames(surface.normals, tangent, sign)


def texel_visibility(vertices: np.ndarray, faces: np.ndarray, surface: TexelSurface, lightstage: LightStage,
                     delta: float = SHADOW_EPS, caster: RayCaster | None = None) -> np.ndarray:
    """(N,L) bool: the light is visible from ``p' + delta n̄`` (Eq. ``optix``), occluders = the mesh itself;
    lights behind the texel's tangent plane are not visible (no ray cast)."""
    if caster is None:
        caster = RayCaster(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64))
    return facing_light_visibility(caster, surface.points, surface.normals, lightstage, eps=delta)


def light_transfer(points: np.ndarray, normals: np.ndarray, lightstage: LightStage,
                   visibility: np.ndarray | None = None) -> torch.Tensor:
    """(N,L) float32 ``G_l = V_l max(0, n.w_l) Omega_l R_l^2 / d_l^2`` (:meth:`LightStage.transfer`, chunked).

    Args:
        points: (N,3) metres. normals: (N,3) unit (coarse or lifted). visibility: (N,L) or None.
    """
    out = np.empty((len(points), lightstage.num_lights), dtype=np.float32)
    for start in range(0, len(points), _CHUNK_TEXELS):
        rows = slice(start, start + _CHUNK_TEXELS)
        out[rows] = lightstage.transfer(points[rows], normals[rows], None if visibility is None else visibility[rows])
    return torch.from_numpy(out)


@dataclass(frozen=True, eq=False)
class TexelLighting:
    """The view-independent lighting geometry of one posed mesh's texels.

    Attributes:
        surface: texel points and coarse normals (:func:`texel_surface`).
        normals: (N,3) float64 unit shading normals the transfer was computed with.
        transfer: (N,L) float32 per-light transfer ``G`` with the mesh's own shadows.
    """

    surface: TexelSurface
    normals: np.ndarray
    transfer: torch.Tensor


def texel_lighting(raster: UVRaster, vertices: np.ndarray, faces: np.ndarray, lightstage: LightStage,
                   normals: np.ndarray | None = None, delta: float = SHADOW_EPS,
                   surface: TexelSurface | None = None) -> TexelLighting:
    """Texel surface, visibility (shadow rays leave along the coarse normals) and transfer ``G``.

    ``normals`` (N,3), e.g. GeoLift's lifted ones, shade the texels; they are renormalised, and
    rows shorter than 0.5 (texels the map does not cover) and ``None`` use the coarse normals.
    ``surface``: :func:`texel_surface` of these vertices when the caller already has it.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    surface = texel_surface(raster, vertices, faces) if surface is None else surface
    shading = surface.normals
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        shading = np.where(length > 0.5, normals / np.maximum(length, 1e-12), surface.normals)
    visibility = texel_visibility(vertices, faces, surface, lightstage, delta)
    return TexelLighting(surface, shading, light_transfer(surface.points, shading, lightstage, visibility))


def shadow_map(transfer: torch.Tensor) -> torch.Tensor:
    """Flat-lit shadow map ``rho`` (N,): ``sum_l G_l / pi``."""
    return transfer.sum(dim=1) / math.pi


def light_radiance(lightstage: LightStage, intensities) -> torch.Tensor:
    """(L,3) emitted radiance ``gain_l I_l`` (torch, differentiable in ``intensities``)."""
    intensities = torch.as_tensor(intensities)
    if tuple(intensities.shape) != (lightstage.num_lights, 3):
        raise EgorelightError(f"a lighting condition must be ({lightstage.num_lights},3), got {tuple(intensities.shape)}")
    return intensities * torch.as_tensor(lightstage.rgb_gain, dtype=intensities.dtype)


def irradiance_map(transfer: torch.Tensor, lightstage: LightStage, intensities) -> torch.Tensor:
    """HDR irradiance ``chi`` (N,3) = ``G @ (gain I)``: the renderer's irradiance for the same lights."""
    radiance = light_radiance(lightstage, intensities)
    return transfer.to(radiance.dtype) @ radiance


def lighting_feature_maps(raster: UVRaster, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray,
                          lightstage: LightStage, intensities) -> tuple[np.ndarray, np.ndarray]:
    """UV maps ``(rho (H,W,1), chi (H,W,3))`` float32 of one posed mesh lit by ``intensities`` (L,3),
    shaded with the normal map ``normals`` (3,H,W) (GeoLift's) and the mesh's own shadows."""
    lit = texel_lighting(raster, vertices, faces, lightstage, np.moveaxis(normals, 0, -1)[raster.coverage])
    rho = shadow_map(lit.transfer).numpy()[:, None]
    chi = irradiance_map(lit.transfer, lightstage, intensities).numpy()
    return lit.surface.to_map(rho.astype(np.float32)), lit.surface.to_map(chi.astype(np.float32))


def _half_vector_cosines(points: np.ndarray, normals: np.ndarray, light_positions: np.ndarray,
                         camera_centre: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n.w`` (N,L), ``n.v`` (N,1) and ``n.h`` (N,L) for lights (L,3) seen from one camera centre.

    Written with matrix products only (no (N,L,3) arrays): with ``d = p_l - x``,
    ``n.w = (n.p_l - n.x) / |d|``, ``v.w`` likewise, ``|d|^2 = |p_l|^2 - 2 x.p_l + |x|^2`` and
    ``n.h = (n.w + n.v) / sqrt(2 + 2 v.w)``.
    """
    v = camera_centre[None] - points
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    distance = np.sqrt(np.maximum(np.sum(light_positions ** 2, axis=1)[None] - 2.0 * points @ light_positions.T
                                  + np.sum(points ** 2, axis=1, keepdims=True), 1e-24))
    cos_w = (normals @ light_positions.T - np.sum(normals * points, axis=1, keepdims=True)) / distance
    v_dot_w = (v @ light_positions.T - np.sum(v * points, axis=1, keepdims=True)) / distance
    cos_v = np.sum(normals * v, axis=1, keepdims=True)
    cos_h = (cos_w + cos_v) / np.sqrt(np.maximum(2.0 + 2.0 * v_dot_w, 1e-24))
    return cos_w, cos_v, cos_h


@torch.no_grad()
def select_rays(points: np.ndarray, normals: np.ndarray, transfer: torch.Tensor, lightstage: LightStage,
                intensities, camera_centre, r: int, shininess: float = DEFAULT_SHININESS) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``r`` most important lights of each texel for one camera.

    Importance ``max(0, n.h)^shininess G_l |gain_l I_l|`` (Blinn-Phong; ``G`` holds visibility
    and ``n.w``). Returns ``index`` (N,r) int64 sorted by decreasing importance and ``valid``
    (N,r) bool, False where fewer than ``r`` lights have non-zero importance.
    """
    if not 1 <= r <= lightstage.num_lights:
        raise EgorelightError(f"r must be in [1, {lightstage.num_lights}], got {r}")
    brightness = torch.linalg.vector_norm(light_radiance(lightstage, intensities).double(), dim=1).numpy()
    centre = np.asarray(camera_centre, dtype=np.float64).reshape(3)
    index = torch.empty((len(points), r), dtype=torch.int64)
    valid = torch.empty((len(points), r), dtype=torch.bool)
    for start in range(0, len(points), _CHUNK_TEXELS):
        rows = slice(start, start + _CHUNK_TEXELS)
        _, _, cos_h = _half_vector_cosines(points[rows], normals[rows], lightstage.positions, centre)
        importance = np.clip(cos_h, 0.0, None) ** shininess * transfer[rows].double().numpy() * brightness
        top, chosen = torch.topk(torch.from_numpy(importance), r, dim=1)
        index[rows], valid[rows] = chosen, top > 0
    return index, valid


def ray_encoding(points: np.ndarray, normals: np.ndarray, transfer: torch.Tensor, lightstage: LightStage,
                 intensities, camera_centre, index: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The paper's 6-D ray encodings ``psi`` (N,r,6): ``(n.w, n.v, n.h, G_l gain_l I_l)``, zero where not valid.

    Differentiable in ``intensities`` (the last three channels are each light's irradiance
    contribution; summed over all lights they give ``chi``).
    """
    idx = index.numpy()
    centre = np.asarray(camera_centre, dtype=np.float64).reshape(3)
    cos_w, cos_v, cos_h = _half_vector_cosines(points, normals, lightstage.positions, centre)
    cos_w, cos_h = np.take_along_axis(cos_w, idx, axis=1), np.take_along_axis(cos_h, idx, axis=1)
    angles = torch.from_numpy(np.stack([cos_w, np.broadcast_to(cos_v, cos_w.shape), cos_h], -1))
    radiance = light_radiance(lightstage, intensities)
    contribution = torch.gather(transfer, 1, index).to(radiance.dtype)[..., None] * radiance[index]
    psi = torch.cat([angles.to(radiance.dtype), contribution], dim=-1)
    return psi * valid[..., None].to(psi.dtype)
