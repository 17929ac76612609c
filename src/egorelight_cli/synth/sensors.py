"""Simulating the sensors of one frame with the renderer (``render/shading.py``).

Per frame: one Embree scene of the posed mesh, per-vertex light visibility once (shared by every
camera), then

* each **studio camera**: :func:`render_view` under the lightstage's lighting condition, linear
  radiance times the studio exposure (HDR; black dome interior behind the subject);
* each **ego camera** (posed by the head): :func:`render_view` of the scene over what the camera
  sees of its surroundings at infinity (in the studio: the dome's LEDs showing the current light
  pattern; in the wild: the environment map) via :func:`render_envmap_view`, then the camera's
  fixed, unknown :class:`CameraResponse` to 8-bit sRGB with noise.

Lighting in the wild uses a dense virtual dome of distant lights (the environment's S(E)).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.geometry.equirect import equirect_directions
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.render.camera_response import CameraResponse, render_envmap_view
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import vertex_normals
from egorelight_cli.render.shading import (
    RenderResult,
    render_view,
    facing_light_visibility,
    lights_in_front,
    trace_pairs,
)
from egorelight_cli.synth.scene import SceneLayout

#: Angular radius of an LED seen from the dome centre (backdrop of the ego cameras), radians.
LED_RADIUS = np.radians(3.0)
#: Radiance of the dome between the LEDs, relative to the mean light radiance.
DOME_FILL = 0.03


class DomeBackdrop:
    """What a camera near the dome centre sees around it: LED discs showing the light pattern."""

    def __init__(self, lightstage: LightStage, height: int = 64):
        dirs = equirect_directions(height).reshape(-1, 3)
        distance, nearest = cKDTree(lightstage.directions).query(dirs)
        self.shape = (height, 2 * height, 3)
        self.nearest = nearest
        self.on_led = 2 * np.arcsin(np.clip(distance / 2, 0, 1)) < LED_RADIUS
        self.gain = lightstage.rgb_gain

    def envmap(self, intensities: np.ndarray) -> np.ndarray:
        radiance = intensities * self.gain
        fill = DOME_FILL * radiance.mean(axis=0)
        out = np.where(self.on_led[:, None], radiance[self.nearest], fill[None])
        return out.reshape(self.shape).astype(np.float32)


@dataclass
class Timer:
    """Accumulated render seconds and counts per camera kind."""

    seconds: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)

    def add(self, kind: str, seconds: float) -> None:
        self.seconds[kind] = self.seconds.get(kind, 0.0) + seconds
        self.counts[kind] = self.counts.get(kind, 0) + 1

    def merge(self, other: "Timer") -> None:
        """Add ``other``'s seconds and counts (e.g. a worker process's) to these."""
        for kind, seconds in other.seconds.items():
            self.seconds[kind] = self.seconds.get(kind, 0.0) + seconds
            self.counts[kind] = self.counts.get(kind, 0) + other.counts[kind]

    def per_camera_frame(self) -> dict:
        return {k: self.seconds[k] / max(self.counts[k], 1) for k in self.seconds}


def proxied_visibility(vertices: np.ndarray, normals: np.ndarray, parents: np.ndarray, lightstage: LightStage,
                       caster: RayCaster) -> np.ndarray:
    """(V,L) per-vertex light visibility, traced (:func:`facing_light_visibility`) at the vertices
    that are their own parents; a subdivision vertex takes its parents' value where they agree and
    is traced itself where they do not (shadow boundaries).

    Args:
        vertices, normals: (V,3) posed vertices and unit vertex normals.
        parents: (V,2) visibility parents (:meth:`SceneLayout.visibility_parents`); parents are traced.
    """
    own = parents[:, 0] == np.arange(len(parents))
    traced = np.flatnonzero(own)
    visibility = np.zeros((len(vertices), lightstage.num_lights), dtype=bool)
    visibility[traced] = facing_light_visibility(caster, vertices[traced], normals[traced], lightstage)
    proxied = np.flatnonzero(~own)
    a, b = visibility[parents[proxied, 0]], visibility[parents[proxied, 1]]
    visibility[proxied] = a & b
    rows, lights = np.nonzero((a != b) & lights_in_front(vertices[proxied], normals[proxied], lightstage))
    if rows.size:
        visibility[proxied[rows], lights] = trace_pairs(caster, vertices[proxied], normals[proxied],
                                                        lightstage.positions, rows, lights)
    return visibility


@dataclass
class FrameRenderer:
    """Renders the cameras of one posed frame (see the module docstring)."""

    layout: SceneLayout
    lightstage: LightStage
    exact_lights: int
    timer: Timer

    def prepare(self, vertices: np.ndarray, intensities: np.ndarray) -> PreparedFrame:
        faces = self.layout.atlas.faces
        caster = RayCaster(vertices, faces)
        normals = vertex_normals(vertices, faces)
        start = time.perf_counter()
        if np.any(intensities > 0):
            visibility = proxied_visibility(vertices, normals, self.layout.visibility_parents, self.lightstage,
                                            caster)
        else:
            visibility = np.zeros((len(vertices), self.lightstage.num_lights), dtype=bool)
        self.timer.add("visibility", time.perf_counter() - start)
        return PreparedFrame(self, vertices, caster, normals, visibility, intensities)


@dataclass
class PreparedFrame:
    renderer: FrameRenderer
    vertices: np.ndarray
    caster: RayCaster
    normals: np.ndarray
    visibility: np.ndarray
    intensities: np.ndarray

    def render(self, camera: Camera, kind: str, background=None) -> RenderResult:
        r = self.renderer
        start = time.perf_counter()
        result = render_view(self.vertices, r.layout.atlas.faces, r.layout.atlas.face_uvs, r.layout.atlas.material,
                             camera, r.lightstage, self.intensities, caster=self.caster,
                             vertex_visibility=self.visibility, background=background, normals=self.normals,
                             exact_lights=r.exact_lights)
        r.timer.add(kind, time.perf_counter() - start)
        return result

    def render_ego(self, camera: Camera, response: CameraResponse, surroundings: np.ndarray, yaw_deg: float,
                   rng: np.random.Generator, radius_m: float | None = None, centre=None,
                   floor_y: float | None = None) -> tuple[np.ndarray, RenderResult]:
        """(uint8 sRGB image, render) of an HMD camera seeing the scene over ``surroundings`` (at
        infinity, or on a sphere of ``radius_m`` around ``centre`` above a floor at ``floor_y``: see
        :func:`render_envmap_view`)."""
        start = time.perf_counter()
        background = render_envmap_view(surroundings, camera, yaw_deg, supersample=1, radius_m=radius_m, centre=centre,
                                        floor_y=floor_y)
        self.renderer.timer.add("backdrop", time.perf_counter() - start)
        result = self.render(camera, "ego", background=background)
        return response.apply(result.radiance, rng), result
