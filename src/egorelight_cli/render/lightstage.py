"""The lightstage: L point lights on a dome, lighting conditions, and environment map -> lights (S(E)).

Geometry. Lights sit at ``positions`` (L,3), metres, around a dome ``centre`` (default
(0, 1, 0), about chest height of a standing subject; world +Y up). :func:`dome_positions`
places them near-uniformly (a Fibonacci spiral) on the part of a sphere of ``radius`` above
``min_elevation_deg`` (elevation from the horizontal plane through the centre). Each light owns
the *solid-angle cell* of the unit directions from the centre that are closer to its own
direction than to any other light's (spherical Voronoi cell; :meth:`LightStage.cell_solid_angles`,
steradians, summing to 4 pi -- the cells of the lowest ring reach down to the nadir and so also
stand for the floor region, where a dome has no lights).

Units and semantics. A *lighting condition* ``I`` is an (L,3) float array of linear RGB
*radiance-like* values: light ``l`` stands for a patch of environment of radiance ``I_l`` over its
cell. It emits ``I_l * rgb_gain_l`` and is rendered as a point light that gives a surface point
``x`` with unit normal ``n`` the irradiance

    E_l(x) = I_l * gain_l * Omega_l * (R_l / |x - p_l|)^2 * max(0, n . w_l) * V_l(x)

with ``Omega_l`` its cell's solid angle, ``R_l = |p_l - centre|``, ``w_l`` the unit direction from
``x`` to ``p_l`` and ``V_l`` the binary visibility (shadow ray). Equivalently it is a point light of
radiant intensity ``J_l = I_l gain_l Omega_l R_l^2`` (:meth:`LightStage.point_intensities`, W/sr-like
units if ``I`` is in W/(sr m^2)). At the dome centre an environment map ``E`` and its light
intensities ``S(E)`` (:meth:`LightStage.envmap_to_intensities`) give the same irradiance up to
the discretisation into L directions. ``flat(1)`` is the lighting of a uniform white environment
of radiance 1 (irradiance pi on any upward surface at the centre); ``olat(l, c)`` is light ``l``
alone at radiance ``c``.

``rig/lights.json`` (:meth:`LightStage.to_json`): ``{"positions": (L,3) metres, "rgb_gain": (L,3),
"centre": (3,) metres, "radius": metres, "num_lights": L, "units": {...}}``. A file with only
positions and gains (a real capture) loads too: the centre and radius are then fitted to the
positions (least-squares sphere).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import SphericalVoronoi, cKDTree

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.equirect import (
    check_envmap,
    equirect_directions,
    equirect_solid_angles,
    sample_equirect,
    yaw_rotation,
)

DEFAULT_NUM_LIGHTS = 331
DEFAULT_RADIUS = 1.8
DEFAULT_CENTRE = (0.0, 1.0, 0.0)
DEFAULT_MIN_ELEVATION_DEG = -30.0
LIGHTS_JSON_KIND = "egorelight/lights"
LIGHTS_JSON_VERSION = 1


def dome_positions(num_lights: int = DEFAULT_NUM_LIGHTS, radius: float = DEFAULT_RADIUS,
                   min_elevation_deg: float = DEFAULT_MIN_ELEVATION_DEG,
                   centre=DEFAULT_CENTRE) -> np.ndarray:
    """(L,3) float64 near-uniform light positions (metres) on the sphere cap above ``min_elevation_deg``.

    A Fibonacci spiral restricted to the cap: heights uniform in ``sin(elevation)`` (equal
    areas), azimuths advancing by the golden angle. The first light is nearest the zenith.
    """
    num_lights = int(num_lights)
    if num_lights < 4:
        raise EgorelightError(f"a dome needs at least 4 lights, got {num_lights}")
    if not radius > 0:
        raise EgorelightError(f"dome radius must be positive, got {radius}")
    if not -90.0 <= min_elevation_deg < 90.0:
        raise EgorelightError(f"min_elevation_deg must be in [-90, 90), got {min_elevation_deg}")
    lowest = math.sin(math.radians(min_elevation_deg))
    k = np.arange(num_lights) + 0.5
    height = 1.0 - (1.0 - lowest) * k / num_lights
    ring = np.sqrt(np.clip(1.0 - height * height, 0.0, None))
    azimuth = math.pi * (3.0 - math.sqrt(5.0)) * k
    unit = np.stack([ring * np.sin(azimuth), height, -ring * np.cos(azimuth)], axis=-1)
    return np.asarray(centre, dtype=np.float64) + float(radius) * unit


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere (centre (3,), radius) through points (N,3), N >= 4 not coplanar."""
    points = np.asarray(points, dtype=np.float64)
    A = np.concatenate([2.0 * points, np.ones((len(points), 1))], axis=1)
    b = np.sum(points * points, axis=1)
    solution, *_ = np.linalg.lstsq(A, b, rcond=None)
    centre = solution[:3]
    radius = math.sqrt(max(float(solution[3] + centre @ centre), 0.0))
    return centre, radius


def _as_rgb(intensity, name: str) -> np.ndarray:
    """A scalar or (3,) intensity as a (3,) float64 RGB vector."""
    try:
        rgb = np.array(np.broadcast_to(np.asarray(intensity, dtype=np.float64), (3,)))
    except (TypeError, ValueError):
        rgb = None
    if rgb is None or not np.isfinite(rgb).all() or (rgb < 0).any():
        raise EgorelightError(f"{name} must be a finite non-negative scalar or RGB triple, got {intensity!r}")
    return rgb


@dataclass(eq=False)
class LightStage:
    """L point lights on a dome (see the module docstring for units).

    Attributes:
        positions: (L,3) float64 light positions, metres, world frame.
        rgb_gain: (L,3) float64 per-light linear RGB gain (calibration; 1 = nominal).
        radius: dome radius, metres (informational; the per-light ``R_l`` is measured).
        centre: (3,) dome centre, metres.
    """

    positions: np.ndarray
    rgb_gain: np.ndarray
    radius: float = DEFAULT_RADIUS
    centre: np.ndarray = field(default_factory=lambda: np.array(DEFAULT_CENTRE))
    _assignments: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        positions = np.array(self.positions, dtype=np.float64)
        gain = np.array(self.rgb_gain, dtype=np.float64)
        centre = np.array(self.centre, dtype=np.float64).reshape(-1)
        if positions.ndim != 2 or positions.shape[1] != 3 or len(positions) < 1:
            raise EgorelightError(f"light positions must be (L,3), got {positions.shape}")
        if gain.shape != positions.shape:
            raise EgorelightError(f"light rgb_gain must be {positions.shape}, got {gain.shape}")
        if centre.shape != (3,):
            raise EgorelightError(f"dome centre must be (3,), got {centre.shape}")
        if not (np.isfinite(positions).all() and np.isfinite(gain).all() and np.isfinite(centre).all()):
            raise EgorelightError("light positions, gains and centre must be finite")
        if (gain < 0).any():
            raise EgorelightError("light rgb_gain must be non-negative")
        offsets = positions - centre
        distances = np.linalg.norm(offsets, axis=1)
        if not (distances > 1e-6).all():
            raise EgorelightError("every light must be away from the dome centre")
        self.positions, self.rgb_gain, self.centre = positions, gain, centre
        self.radius = float(self.radius)
        self._distances = distances
        self._directions = offsets / distances[:, None]
        self._solid_angles: np.ndarray | None = None

    # ---------------------------------------------------------------- construction / io

    @classmethod
    def dome(cls, num_lights: int = DEFAULT_NUM_LIGHTS, radius: float = DEFAULT_RADIUS,
             min_elevation_deg: float = DEFAULT_MIN_ELEVATION_DEG, centre=DEFAULT_CENTRE,
             rgb_gain=None) -> LightStage:
        """The default simulated lightstage: :func:`dome_positions` with unit (or given) gains."""
        positions = dome_positions(num_lights, radius, min_elevation_deg, centre)
        gain = np.ones_like(positions) if rgb_gain is None else np.broadcast_to(rgb_gain, positions.shape)
        return cls(positions=positions, rgb_gain=gain, radius=radius, centre=np.asarray(centre, np.float64))

    def to_json(self) -> dict[str, Any]:
        """JSON-able dict for ``rig/lights.json`` (positions, rgb_gain, centre, radius)."""
        return {
            "kind": LIGHTS_JSON_KIND,
            "version": LIGHTS_JSON_VERSION,
            "num_lights": self.num_lights,
            "units": {"positions": "m", "centre": "m", "radius": "m", "rgb_gain": "linear"},
            "centre": self.centre.tolist(),
            "radius": self.radius,
            "positions": self.positions.tolist(),
            "rgb_gain": self.rgb_gain.tolist(),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any] | str | Path) -> LightStage:
        """From a :meth:`to_json` dict or a ``lights.json`` path; centre/radius fitted when absent."""
        path = None
        if isinstance(data, (str, Path)):
            path = Path(data)
            try:
                data = json.loads(path.read_text())
            except FileNotFoundError:
                raise EgorelightError("lights file not found", path) from None
            except (OSError, ValueError) as error:
                raise EgorelightError(f"cannot read lights JSON ({error})", path) from None
        if not isinstance(data, Mapping) or "positions" not in data:
            raise EgorelightError("lights JSON lacks 'positions'", path)
        try:
            positions = np.asarray(data["positions"], dtype=np.float64)
            gain = np.asarray(data.get("rgb_gain", np.ones_like(positions)), dtype=np.float64)
            if "centre" in data:
                centre = np.asarray(data["centre"], dtype=np.float64)
                radius = float(data.get("radius", np.median(np.linalg.norm(positions - centre, axis=1))))
            else:
                centre, radius = fit_sphere(positions)
                radius = float(data.get("radius", radius))
            return cls(positions=positions, rgb_gain=gain, radius=radius, centre=centre)
        except EgorelightError as error:
            raise EgorelightError(error.message, path) from None
        except (TypeError, ValueError) as error:
            raise EgorelightError(f"malformed lights JSON ({error})", path) from None

    def write_json(self, path: str | Path) -> None:
        """Write :meth:`to_json` to ``path`` (indented)."""
        Path(path).write_text(json.dumps(self.to_json(), indent=1) + "\n")

    # ---------------------------------------------------------------- derived quantities

    @property
    def num_lights(self) -> int:
        return len(self.positions)

    @property
    def directions(self) -> np.ndarray:
        """(L,3) unit directions from the dome centre to the lights."""
        return self._directions

    @property
    def distances(self) -> np.ndarray:
        """(L,) distances R_l from the dome centre to the lights, metres."""
        return self._distances

    def cell_solid_angles(self) -> np.ndarray:
        """(L,) solid angle (sr) of each light's spherical Voronoi cell; sums to 4 pi."""
        if self._solid_angles is None:
            if self.num_lights < 4:
                self._solid_angles = np.full(self.num_lights, 4.0 * math.pi / self.num_lights)
            else:
                try:
                    voronoi = SphericalVoronoi(self._directions, radius=1.0, center=np.zeros(3))
                    areas = voronoi.calculate_areas()
                except (ValueError, RuntimeError) as error:
                    raise EgorelightError(f"cannot build the lights' solid-angle cells ({error}); "
                                          "are two light directions identical?") from None
                self._solid_angles = np.asarray(areas, dtype=np.float64)
        return self._solid_angles

    def point_intensities(self, intensities: np.ndarray) -> np.ndarray:
        """(L,3) radiant intensity J_l = I_l gain_l Omega_l R_l^2 of the equivalent point lights.

        The irradiance at ``x`` is ``J_l max(0, n . w_l) V / |x - p_l|^2``.
        """
        intensities = self.check_intensities(intensities)
        scale = self.cell_solid_angles() * self._distances ** 2
        return intensities * self.rgb_gain * scale[:, None]

    def check_intensities(self, intensities) -> np.ndarray:
        """Validate a lighting condition: (L,3) finite, non-negative; returned as float64."""
        intensities = np.asarray(intensities, dtype=np.float64)
        if intensities.shape != (self.num_lights, 3):
            raise EgorelightError(f"a lighting condition must be ({self.num_lights},3), got {intensities.shape}")
        if not np.isfinite(intensities).all() or (intensities < 0).any():
            raise EgorelightError("light intensities must be finite and non-negative")
        return intensities

    # ---------------------------------------------------------------- lighting conditions

    def olat(self, index: int, intensity=1.0) -> np.ndarray:
        """(L,3) one-light-at-a-time condition: light ``index`` at ``intensity`` (scalar or RGB), others off."""
        index = int(index)
        if not 0 <= index < self.num_lights:
            raise EgorelightError(f"OLAT light index {index} outside [0, {self.num_lights})")
        out = np.zeros((self.num_lights, 3))
        out[index] = _as_rgb(intensity, "OLAT intensity")
        return out

    def flat(self, intensity=1.0) -> np.ndarray:
        """(L,3) all lights at ``intensity`` (scalar or RGB): a uniform environment of that radiance."""
        return np.tile(_as_rgb(intensity, "flat intensity"), (self.num_lights, 1))

    def _texel_assignment(self, height: int, width: int, yaw_deg: float) -> np.ndarray:
        """(H*W,) index of the light whose (yaw-rotated) direction is nearest each texel's direction."""
        key = (height, width, round(float(yaw_deg) % 360.0, 9))
        if key not in self._assignments:
            # Lights of the map rotated by yaw sit, in the unrotated map, at R_y(yaw)^T w_l.
            light_dirs = self._directions @ yaw_rotation(yaw_deg)
            texel_dirs = equirect_directions(height, width).reshape(-1, 3)
            _, nearest = cKDTree(light_dirs).query(texel_dirs)
            if len(self._assignments) > 16:
                self._assignments.clear()
            self._assignments[key] = nearest
        return self._assignments[key]

    def envmap_to_intensities(self, envmap: np.ndarray, yaw_deg: float = 0.0) -> np.ndarray:
        """The paper's S(E): (L,3) mean radiance of an equirect map (H,2H,3) over each light's cell.

        Every texel goes to the light whose direction is nearest to it; a light's intensity is
        the solid-angle-weighted mean of its texels. Lights whose cell holds no texel centre
        (maps coarser than the dome) take the map's bilinear sample in their direction.
        ``yaw_deg`` gives the intensities of ``rotate_envmap(envmap, yaw_deg)`` without resampling
        the map. Assignments are cached per map size and yaw.
        """
        envmap = check_envmap(envmap)
        if envmap.shape[2] != 3:
            raise EgorelightError(f"environment map must have 3 channels, got {envmap.shape[2]}")
        if not np.isfinite(envmap).all():
            raise EgorelightError("environment map contains NaN or infinity")
        height, width = envmap.shape[:2]
        nearest = self._texel_assignment(height, width, yaw_deg)
        weights = equirect_solid_angles(height, width).reshape(-1)
        texels = envmap.reshape(-1, 3).astype(np.float64)
        total_weight = np.bincount(nearest, weights=weights, minlength=self.num_lights)
        sums = np.stack([np.bincount(nearest, weights=weights * texels[:, c], minlength=self.num_lights)
                         for c in range(3)], axis=-1)
        out = np.zeros((self.num_lights, 3))
        filled = total_weight > 0
        out[filled] = sums[filled] / total_weight[filled, None]
        if not filled.all():
            light_dirs = self._directions[~filled] @ yaw_rotation(yaw_deg)
            out[~filled] = sample_equirect(envmap, light_dirs)
        return out

    def transfer(self, points: np.ndarray, normals: np.ndarray, visibility: np.ndarray | None = None) -> np.ndarray:
        """(N,L) float64 per-light geometry ``G_l(x) = V_l max(0, n.w_l) Omega_l R_l^2 / |x - p_l|^2``.

        The irradiance is ``E(x) = sum_l G_l(x) gain_l I_l``; ``visibility`` (N,L) bool/float,
        default all visible. Points (N,3) metres, unit normals (N,3).
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        if visibility is not None and np.shape(visibility) != (len(points), self.num_lights):
            raise EgorelightError(f"visibility must be ({len(points)},{self.num_lights}), got {np.shape(visibility)}")
        to_light = self.positions[None] - points[:, None]
        d2 = np.einsum("nlc,nlc->nl", to_light, to_light)
        cos = np.clip(np.einsum("nlc,nc->nl", to_light, normals) / np.sqrt(d2), 0.0, None)
        out = cos * (self.cell_solid_angles() * self._distances ** 2) / d2
        if visibility is not None:
            out *= np.asarray(visibility, dtype=np.float64)
        return out

    def irradiance(self, points: np.ndarray, normals: np.ndarray, intensities: np.ndarray,
                   visibility: np.ndarray | None = None) -> np.ndarray:
        """(N,3) irradiance E(x) = sum_l E_l(x) at points (N,3) with unit normals (N,3).

        ``visibility`` (N,L) bool/float, default all visible. Mostly for tests and checks; the
        renderer (``render/shading.py``) evaluates the same formula in chunks.
        """
        radiance = self.check_intensities(intensities) * self.rgb_gain
        return self.transfer(points, normals, visibility) @ radiance
