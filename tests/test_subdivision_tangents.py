"""Loop subdivision and UV tangent frames / tangent-space normal maps."""

from __future__ import annotations

import numpy as np
import trimesh

from egorelight_cli.geometry.subdivision import loop_subdivide, unique_edges
from egorelight_cli.geometry.tangents import (
    face_uv_tangents,
    tangent_space_from_world,
    world_from_tangent_space,
)
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.shading import Material, render_view
from egorelight_cli.geometry.cameras import Camera, look_at


def _grid(n: int = 4):
    xs = np.linspace(0, 1, n + 1)
    xx, yy = np.meshgrid(xs, xs, indexing="xy")
    vertices = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], 1)
    idx = np.arange(xx.size).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return vertices, faces, vertices[faces][..., :2]


def test_loop_subdivision_counts_uvs_and_attributes():
    vertices, faces, uvs = _grid()
    sub = loop_subdivide(vertices, faces, uvs)
    edges, _ = unique_edges(faces)
    assert sub.faces.shape == (4 * len(faces), 3)
    assert len(sub.vertices) == len(vertices) + len(edges)
    # a flat open patch stays flat; its border stays put; UVs are the (x, y) of the corners
    assert np.abs(sub.vertices[:, 2]).max() == 0
    np.testing.assert_allclose(sub.face_uvs, sub.vertices[sub.faces][..., :2], atol=1e-12)
    # attributes extend by averaging the edge endpoints
    np.testing.assert_allclose(sub.extend(vertices), 0.5 * (sub.extend(vertices) + sub.extend(vertices)))
    np.testing.assert_allclose(sub.extend(vertices)[len(vertices):], vertices[edges].mean(1))
    assert np.all(sub.parent_face == np.repeat(np.arange(len(faces)), 4))


def test_loop_subdivision_of_a_closed_mesh_matches_trimesh():
    """On a closed mesh the rules are Loop's: the same vertex positions as trimesh's implementation."""
    sphere = trimesh.creation.icosphere(subdivisions=1)
    ours = loop_subdivide(sphere.vertices, sphere.faces)
    v, f = trimesh.remesh.subdivide_loop(sphere.vertices, sphere.faces)
    # compare as point sets (vertex order differs)
    d = np.linalg.norm(ours.vertices[:, None] - v[None], axis=-1).min(1)
    assert d.max() < 1e-9 and len(v) == len(ours.vertices) and len(f) == len(ours.faces)
    assert trimesh.Trimesh(ours.vertices, ours.faces).is_watertight


def test_tangent_space_round_trip_and_rigid_invariance():
    rng = np.random.default_rng(0)
    vertices, faces, uvs = _grid(3)
    vertices = vertices + 0.05 * rng.normal(size=vertices.shape)
    m = rng.normal(size=(len(faces), 3)) * [0.3, 0.3, 0.0] + [0, 0, 1]
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    n = np.cross(*(vertices[faces[:, k]] - vertices[faces[:, 0]] for k in (1, 2)))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tangent, sign = face_uv_tangents(vertices, faces, uvs)
    world = world_from_tangent_space(m, n, tangent, sign)
    np.testing.assert_allclose(tangent_space_from_world(world, n, tangent, sign), m, atol=1e-12)
    # rotating the mesh rotates the detail normals with it
    R = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    tangent_r, sign_r = face_uv_tangents(vertices @ R.T, faces, uvs)
    np.testing.assert_allclose(world_from_tangent_space(m, n @ R.T, tangent_r, sign_r), world @ R.T, atol=1e-12)
    # dP/du of the unit grid is the x axis
    t0, _ = face_uv_tangents(_grid(3)[0], faces, uvs)
    np.testing.assert_allclose(t0, np.tile([1.0, 0, 0], (len(faces), 1)), atol=1e-12)


def test_render_applies_a_normal_map_like_tilting_the_surface():
    """A constant tangent-space tilt on a flat quad shades exactly like the quad tilted by that angle
    (Lambert, one distant-ish light straight above)."""
    vertices, faces, uvs = _grid(2)
    vertices = vertices - [0.5, 0.5, 0.0]
    stage = LightStage(positions=np.array([[0.0, 0.0, 50.0]]), rgb_gain=np.ones((1, 3)), radius=50.0,
                       centre=(0.0, 0.0, 0.0))
    K = np.array([[200.0, 0, 31.5], [0, 200.0, 31.5], [0, 0, 1]])
    cam = Camera("pinhole", K, np.zeros(5), 64, 64, look_at(np.array([0.0, 0.0, 3.0]), np.zeros(3)), name="c")
    angle = np.radians(30)
    tilt = np.zeros((8, 8, 3), np.float32)
    tilt[...] = [np.sin(angle), 0.0, np.cos(angle)]
    flat = render_view(vertices, faces, uvs, Material(albedo=0.5), cam, stage, np.ones((1, 3)), exact_lights=1)
    bumped = render_view(vertices, faces, uvs, Material(albedo=0.5, normal_map=tilt), cam, stage, np.ones((1, 3)),
                         exact_lights=1)
    inside = flat.mask & bumped.mask
    ratio = bumped.radiance[inside][:, 0] / flat.radiance[inside][:, 0]
    to_light = stage.positions[0] - flat.raster.points[inside]
    to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
    tilted = np.array([np.sin(angle), 0.0, np.cos(angle)])
    np.testing.assert_allclose(ratio, (to_light @ tilted) / to_light[:, 2], rtol=1e-4)
    np.testing.assert_allclose(bumped.normal[inside], np.tile([np.sin(angle), 0, np.cos(angle)], (inside.sum(), 1)),
                               atol=1e-5)
