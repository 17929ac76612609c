"""Ray-traced lightstage shading against analytic radiometry: planes, spheres, shadows, linearity."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import (
    Camera,
    camera_rays_world,
    look_at,
    project_world,
)
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.io.character import load_default_character
from egorelight_cli.render.envmaps import make_envmap
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.shading import (
    Material,
    light_visibility,
    render_view,
    shade,
    vertex_light_visibility,
)

TOP = 0  # the default dome's light nearest the zenith


@pytest.fixture(scope="module")
def stage() -> LightStage:
    return LightStage.dome()


def _grid_plane(half: float, cells: int, y: float = 0.0):
    """Upward-facing square grid in the plane y (vertices, faces, face UVs with u ~ x, v ~ z)."""
    s = np.linspace(-half, half, cells + 1)
    x, z = np.meshgrid(s, s, indexing="xy")
    vertices = np.stack([x.ravel(), np.full(x.size, y), z.ravel()], axis=1)
    faces = []
    for i in range(cells):
        for j in range(cells):
            a = i * (cells + 1) + j
            b, c, d = a + 1, a + cells + 1, a + cells + 2
            faces += [[a, c, b], [b, c, d]]  # counter-clockwise seen from +Y
    faces = np.array(faces)
    uv = np.stack([(vertices[:, 0] + half) / (2 * half), (vertices[:, 2] + half) / (2 * half)], axis=1)
    return vertices, faces, uv[faces]


def _pinhole(eye, target, size: int = 96, focal: float = 80.0, up=(0.0, 1.0, 0.0)) -> Camera:
    K = [[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]]
    return Camera("pinhole", K, np.zeros(5), size, size, look_at(eye, target, up))


def _lambert_radiance(stage: LightStage, intensities, points, normals, albedo) -> np.ndarray:
    """albedo / pi * E, with E = J cos / d^2 summed over the lights (no shadows)."""
    J = stage.point_intensities(intensities)
    to_light = stage.positions[None] - points[:, None]
    d2 = np.sum(to_light ** 2, axis=-1)
    cos = np.clip(np.einsum("nlc,nc->nl", to_light, normals) / np.sqrt(d2), 0.0, None)
    return np.asarray(albedo) / math.pi * np.einsum("nl,lc->nc", cos / d2, J)


def test_plane_pixels_equal_lambert_shading(stage):
    vertices, faces, face_uvs = _grid_plane(1.0, 4)
    camera = _pinhole((0.3, 1.6, 0.4), (0.0, 0.0, 0.0))
    intensities = stage.olat(TOP, (1.0, 2.0, 0.5))
    albedo = np.array([0.7, 0.5, 0.3])
    result = render_view(vertices, faces, face_uvs, Material(albedo=albedo), camera, stage, intensities)
    mask = result.mask
    assert mask.mean() > 0.5
    # analytic ray-plane intersection, independent of the rasteriser
    origins, dirs, _ = camera_rays_world(camera)
    t = -origins[..., 1] / dirs[..., 1]
    points = (origins + t[..., None] * dirs)[mask]
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    expected = _lambert_radiance(stage, intensities, points, normals, albedo)
    np.testing.assert_allclose(result.radiance[mask], expected, rtol=2e-4)
    np.testing.assert_allclose(result.depth[mask], (t * (dirs @ camera.T_cam_from_world[2, :3]))[mask], rtol=1e-4)
    assert (result.radiance[~mask] == 0).all() and (result.face_id[~mask] == -1).all()
    np.testing.assert_allclose(result.albedo[mask], np.broadcast_to(albedo, (mask.sum(), 3)), rtol=1e-6)


def test_sphere_pixels_equal_lambert_shading(stage):
    centre, radius = np.array([0.0, 1.0, 0.0]), 0.4
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    vertices = sphere.vertices + centre
    camera = _pinhole(centre + [0.4, 0.5, 1.9], centre, size=128, focal=160.0)
    light = int(np.argmax(stage.directions @ _unit([0.8, 0.7, 0.6])))  # lights the camera's side, obliquely
    intensities = stage.olat(light, 3.0)
    result = render_view(vertices, sphere.faces, None, Material(albedo=0.8), camera, stage, intensities)
    origins, dirs, _ = camera_rays_world(camera)
    oc = origins - centre
    b = np.sum(oc * dirs, axis=-1)
    disc = b * b - (np.sum(oc * oc, axis=-1) - radius ** 2)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    points = origins + t[..., None] * dirs
    normals = (points - centre) / radius
    to_light = stage.positions[light] - points
    cos_light = np.sum(normals * to_light, axis=-1) / np.linalg.norm(to_light, axis=-1)
    cos_view = -np.sum(normals * dirs, axis=-1)
    interior = hit & result.mask & (cos_light > 0.15) & (cos_view > 0.3)
    assert interior.sum() > 1000
    expected = _lambert_radiance(stage, intensities, points[interior], normals[interior], 0.8)
    rel = np.abs(result.radiance[interior] - expected) / expected
    assert np.median(rel) < 2e-3 and rel.max() < 0.02  # facet normals: ~0.2 deg, near the terminator
    # the unlit side is black: no ambient term, no light leaking around the terminator
    dark = hit & result.mask & (cos_light < -0.1)
    assert dark.sum() > 200 and (result.radiance[dark] == 0).all()


def _blocked(points: np.ndarray, light: np.ndarray, height: float, half: float, margin: float) -> tuple:
    """(in shadow, lit) masks of plane points under a square blocker (|x|,|z| < half at y = height)."""
    t = (height - points[:, 1]) / (light[1] - points[:, 1])
    crossing = points + t[:, None] * (light - points)
    reach = np.maximum(np.abs(crossing[:, 0]), np.abs(crossing[:, 2]))
    between = (t > 0) & (t < 1)
    return between & (reach < half - margin), ~between | (reach > half + margin)


@pytest.mark.parametrize("mode", ["exact", "vertex", "vertex_no_exact_lights"])
def test_occluded_points_are_black(stage, mode):
    floor_v, floor_f, _ = _grid_plane(1.2, 12)
    block_v, block_f, _ = _grid_plane(0.15, 1, y=0.8)
    vertices = np.concatenate([floor_v, block_v])
    faces = np.concatenate([floor_f, block_f + len(floor_v)])
    camera = _pinhole((0.0, 0.6, 1.6), (0.0, 0.0, 0.0), size=128, focal=90.0)
    intensities = stage.olat(TOP, 1.0)
    caster = RayCaster(vertices, faces)
    kwargs = {}
    if mode != "exact":
        kwargs["vertex_visibility"] = vertex_light_visibility(vertices, faces, stage, caster=caster)
        kwargs["exact_lights"] = 8 if mode == "vertex" else 0
    result = render_view(vertices, faces, None, Material(albedo=0.5), camera, stage, intensities, caster=caster,
                         **kwargs)
    on_floor = result.mask & (result.raster.points[..., 1] < 1e-4)
    points = result.raster.points[on_floor].astype(np.float64)
    shadow, lit = _blocked(points, stage.positions[TOP], 0.8, 0.15, margin=0.01)
    assert shadow.sum() > 100 and lit.sum() > 1000
    radiance = result.radiance[on_floor]
    assert (radiance[shadow] == 0).all()
    expected = _lambert_radiance(stage, intensities, points[lit], np.tile([0.0, 1.0, 0.0], (lit.sum(), 1)), 0.5)
    np.testing.assert_allclose(radiance[lit], expected, rtol=2e-4)


def test_light_visibility_against_a_blocker(stage):
    floor_v, floor_f, _ = _grid_plane(1.2, 2)
    block_v, block_f, _ = _grid_plane(0.15, 1, y=0.8)
    caster = RayCaster(np.concatenate([floor_v, block_v]), np.concatenate([floor_f, block_f + len(floor_v)]))
    points = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, -0.1], [1.0, 0.0, 1.0]])
    visible = light_visibility(caster, points, np.tile([0.0, 1.0, 0.0], (3, 1)), stage)
    assert visible.shape == (3, 331)
    for point, row in zip(points, visible):
        # every light of the default dome is above the floor; only the blocker can hide it
        through_blocker = []
        for light in stage.positions:
            shadow, lit = _blocked(point[None], light, 0.8, 0.15, margin=1e-3)
            through_blocker.append(bool(shadow[0]) if (shadow | lit)[0] else None)
        decided = np.array([b is not None for b in through_blocker])
        expected = np.array([not b for b in through_blocker if b is not None])
        np.testing.assert_array_equal(row[decided], expected)
    assert not visible[0, TOP] and visible[2, TOP]


def test_rendering_is_linear_in_light_intensity(stage):
    character = load_default_character()
    camera = _pinhole((0.4, 1.2, 2.4), (0.0, 0.9, 0.0), size=64, focal=60.0)
    material = Material(albedo=np.full((8, 8, 3), 0.6, np.float32), specular=0.2, roughness=0.4)
    caster = RayCaster(character.vertices, character.faces)

    def render(intensities):
        return render_view(character.vertices, character.faces, character.face_uvs, material, camera, stage,
                           intensities, caster=caster).radiance

    one, two = stage.olat(TOP, (1.0, 0.5, 2.0)), stage.olat(120, 0.7)
    both = render(one + two)
    np.testing.assert_allclose(both, render(one) + render(two), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(render(2.0 * one), 2.0 * render(one), rtol=1e-6, atol=1e-8)
    assert both.max() > 0


def test_hybrid_vertex_visibility_is_close_to_exact(stage):
    character = load_default_character()
    camera = _pinhole((0.3, 1.0, 1.8), (0.0, 0.9, 0.0), size=128, focal=110.0)
    caster = RayCaster(character.vertices, character.faces)
    intensities = stage.envmap_to_intensities(make_envmap("sky", 1, 32))
    visibility = vertex_light_visibility(character.vertices, character.faces, stage, caster=caster)
    assert visibility.shape == (len(character.vertices), 331)
    material = Material(albedo=0.6)
    exact = render_view(character.vertices, character.faces, None, material, camera, stage, intensities, caster=caster)
    hybrid = render_view(character.vertices, character.faces, None, material, camera, stage, intensities,
                         caster=caster, vertex_visibility=visibility)
    assert hybrid.shadow_rays < exact.shadow_rays / 4
    mask = exact.mask
    rel = np.abs(hybrid.radiance[mask] - exact.radiance[mask]).sum(-1) / exact.radiance[mask].sum(-1)
    print(f"hybrid vs exact visibility: median {np.median(rel):.2e}, p99 {np.percentile(rel, 99):.3f}, "
          f"rays {hybrid.shadow_rays} vs {exact.shadow_rays}")
    assert np.median(rel) < 1e-3 and np.percentile(rel, 99) < 0.05


def test_fisheye_pixels_land_where_the_camera_projects(stage):
    K = [[85.0, 0, 127.5], [0, 85.0, 127.5], [0, 0, 1]]
    T = look_at((0.0, 1.6, 0.0), (0.0, 0.0, 0.3), up=(0.0, 0.0, -1.0))
    camera = Camera("fisheye", K, [0.02, -0.01, 0.003, -0.001], 256, 256, T)
    # a small sphere ~60 degrees off the optical axis
    axis = T[2, :3]
    side = T[0, :3]
    target = camera.centre_world + 0.6 * (math.cos(math.radians(60)) * axis + math.sin(math.radians(60)) * side)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.02)
    result = render_view(sphere.vertices + target, sphere.faces, None, Material(albedo=1.0), camera, stage,
                         stage.flat(1.0))
    assert result.radiance[result.mask].min() > 0
    rows, cols = np.nonzero(result.mask)
    centroid = np.array([cols.mean(), rows.mean()])
    expected = project_world(camera, target[None])[0]
    assert np.linalg.norm(centroid - expected) < 0.3
    assert 20 < result.mask.sum() < 400


def test_textures_are_looked_up_at_the_pixel_uvs(stage):
    vertices, faces, face_uvs = _grid_plane(1.0, 2)
    texture = np.zeros((16, 16, 3), np.float32)
    texture[:8] = [0.8, 0.1, 0.1]  # top rows = v > 0.5 = +z half of the plane
    texture[8:] = [0.1, 0.1, 0.8]
    camera = _pinhole((0.0, 2.0, 0.01), (0.0, 0.0, 0.0), size=64, focal=40.0, up=(0.0, 0.0, -1.0))
    result = render_view(vertices, faces, face_uvs, Material(albedo=texture), camera, stage, stage.flat(1.0),
                         background=(0.1, 0.2, 0.3))
    z = result.raster.points[..., 2]
    plus, minus = result.mask & (z > 0.2), result.mask & (z < -0.2)
    np.testing.assert_allclose(result.albedo[plus], np.broadcast_to([0.8, 0.1, 0.1], (plus.sum(), 3)), atol=1e-5)
    np.testing.assert_allclose(result.albedo[minus], np.broadcast_to([0.1, 0.1, 0.8], (minus.sum(), 3)), atol=1e-5)
    np.testing.assert_allclose(result.radiance[result.mask],
                               result.albedo[result.mask] / math.pi * result.irradiance[result.mask], rtol=1e-5)
    np.testing.assert_allclose(result.radiance[~result.mask], np.broadcast_to([0.1, 0.2, 0.3], ((~result.mask).sum(), 3)))
    as_dict = render_view(vertices, faces, face_uvs, {"albedo": texture}, camera, stage, stage.flat(1.0),
                          background=(0.1, 0.2, 0.3))
    np.testing.assert_array_equal(as_dict.radiance, result.radiance)
    with pytest.raises(EgorelightError, match="UVs"):
        render_view(vertices, faces, None, Material(albedo=texture), camera, stage, stage.flat(1.0))


def test_white_furnace_and_specular_energy():
    """Uniform radiance 1 from a full sphere of lights: Lambert albedo 1 reflects 1; the lobe at most 1."""
    stage = LightStage.dome(num_lights=3000, radius=100.0, min_elevation_deg=-90.0, centre=(0.0, 0.0, 0.0))
    point, up = np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]])
    lambert = shade(point, up, up, 1.0, None, stage, stage.flat(1.0))
    np.testing.assert_allclose(lambert, 1.0, rtol=0.01)
    for roughness in (0.3, 0.5, 0.8):
        view = np.array([[0.0, 1.0, 0.0]])
        lobe = shade(point, up, view, 0.0, (1.0, roughness), stage, stage.flat(1.0))
        assert 0.97 < lobe[0, 0] < 1.01, (roughness, lobe)  # normalised at normal incidence
        oblique = shade(point, up, _unit([0.8, 0.6, 0.0])[None], 0.0, (1.0, roughness), stage, stage.flat(1.0))
        assert 0.1 < oblique[0, 0] < 1.0  # Blinn-Phong loses energy at grazing views, never gains
    # specular radiance peaks in the mirror direction of a single light
    single = stage.olat(int(np.argmax(stage.directions @ _unit([0.5, 1.0, 0.0]))), 1.0)
    views = np.array([_unit([-0.5, 1.0, 0.0]), _unit([0.5, 1.0, 0.0]), _unit([0.0, 1.0, 0.5])])
    spec = shade(np.zeros((3, 3)), np.tile(up, (3, 1)), views, 0.0, (1.0, 0.3), stage, single)
    assert spec[0, 0] > 10 * spec[1, 0] and spec[0, 0] > 10 * spec[2, 0]


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def test_bad_inputs(stage):
    vertices, faces, _ = _grid_plane(1.0, 1)
    camera = _pinhole((0.0, 2.0, 0.5), (0.0, 0.0, 0.0))
    with pytest.raises(EgorelightError):
        render_view(vertices, faces, None, Material(), camera, stage, np.ones((10, 3)))
    with pytest.raises(EgorelightError):
        render_view(vertices, faces, None, Material(), camera, stage, stage.flat(1.0),
                    vertex_visibility=np.ones((3, 331), bool))
    with pytest.raises(EgorelightError):
        shade(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3)), 0.5, np.ones((2, 7)), stage, stage.flat(1.0))


def test_facing_visibility_skips_lights_behind_and_matches_the_full_trace(stage):
    """Only lights in front of a point's tangent plane are traced; those agree with the full trace,
    and on a closed convex surface the full trace already finds every light behind occluded."""
    import trimesh

    from egorelight_cli.render.shading import facing_light_visibility

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    vertices = sphere.vertices + stage.centre
    caster = RayCaster(vertices, sphere.faces)
    full = light_visibility(caster, vertices, sphere.vertex_normals, stage)
    facing = facing_light_visibility(caster, vertices, sphere.vertex_normals, stage)
    front = sphere.vertex_normals @ stage.positions.T - np.sum(sphere.vertex_normals * vertices, 1, keepdims=True) > 0
    np.testing.assert_array_equal(facing[front], full[front])
    assert not facing[~front].any() and not full[~front].any() and facing[front].mean() > 0.9
