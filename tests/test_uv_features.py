"""Per-texel lighting features: rho, chi, visibility, top-r rays and psi against the renderer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import rasterize_uv
from egorelight_cli.render.shading import light_visibility, shade
from egorelight_cli.render.uv_features import (
    TexelSurface,
    irradiance_map,
    light_transfer,
    ray_encoding,
    select_rays,
    shadow_map,
    texel_surface,
    texel_visibility,
)


@pytest.fixture(scope="module")
def stage() -> LightStage:
    stage = LightStage.dome(num_lights=100)
    gains = np.random.default_rng(0).uniform(0.8, 1.2, size=(100, 3))
    return LightStage(positions=stage.positions, rgb_gain=gains, centre=stage.centre, radius=stage.radius)


def _lighting(stage: LightStage, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 2.0, size=(stage.num_lights, 3))


def _renderer_irradiance(stage, points, normals, intensities, visibility) -> np.ndarray:
    view = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    return shade(points, normals, view, 0.5, None, stage, intensities, visibility, components=True).irradiance


def test_chi_and_rho_on_a_sphere_match_the_renderer(stage):
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    vertices = sphere.vertices + stage.centre
    points, normals = vertices, sphere.vertex_normals
    visibility = light_visibility(RayCaster(vertices, sphere.faces), points, normals, stage)
    assert 0.2 < visibility.mean() < 0.8  # the sphere shadows itself
    intensities = _lighting(stage)
    transfer = light_transfer(points, normals, stage, visibility)
    chi = irradiance_map(transfer, stage, torch.from_numpy(intensities))
    np.testing.assert_allclose(chi.numpy(), _renderer_irradiance(stage, points, normals, intensities, visibility),
                               rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(chi.numpy(), stage.irradiance(points, normals, intensities, visibility), rtol=1e-5)
    # rho is the irradiance of a uniform white dome (unit gains) over pi
    white = LightStage(positions=stage.positions, rgb_gain=np.ones((stage.num_lights, 3)), centre=stage.centre,
                       radius=stage.radius)
    expected_rho = white.irradiance(points, normals, white.flat(1.0), visibility)[:, 0] / math.pi
    np.testing.assert_allclose(shadow_map(transfer).numpy(), expected_rho, rtol=1e-5)


def test_rho_of_an_unoccluded_upward_point_at_the_centre_is_one(stage):
    rho = shadow_map(light_transfer(stage.centre[None], np.array([[0.0, 1.0, 0.0]]), stage))
    assert float(rho) == pytest.approx(1.0, abs=0.03)  # the dome's discretisation of the hemisphere


def test_texel_features_on_the_character_match_the_renderer(character, stage):
    raster = rasterize_uv(character.face_uvs, 24)
    vertices = character.vertices
    surface = texel_surface(raster, vertices, character.faces)
    assert len(surface.points) == raster.coverage.sum() > 100
    # texel points lie on their faces' planes; coarse normals are unit and face like the faces
    face = raster.face_id[raster.coverage]
    face_normals = trimesh.Trimesh(vertices, character.faces, process=False).face_normals[face]
    offsets = surface.points - vertices[character.faces[face, 0]]
    assert np.abs(np.sum(offsets * face_normals, axis=1)).max() < 1e-5
    np.testing.assert_allclose(np.linalg.norm(surface.normals, axis=1), 1.0, atol=1e-9)
    assert np.median(np.sum(face_normals * surface.normals, axis=1)) > 0.95
    visibility = texel_visibility(vertices, character.faces, surface, stage)
    intensities = _lighting(stage, 2)
    chi = irradiance_map(light_transfer(surface.points, surface.normals, stage, visibility), stage, intensities)
    np.testing.assert_allclose(chi.numpy(), _renderer_irradiance(stage, surface.points, surface.normals,
                                                                intensities, visibility), rtol=1e-4, atol=1e-5)
    assert surface.to_map(chi.numpy()).shape == (24, 24, 3)


def test_visibility_of_a_texel_under_an_occluder(stage):
    floor = trimesh.creation.box(extents=(2.0, 0.02, 2.0))
    floor.apply_translation([0.0, stage.centre[1] - 0.5, 0.0])
    roof = trimesh.creation.box(extents=(0.3, 0.02, 0.3))
    roof.apply_translation([0.0, stage.centre[1] - 0.2, 0.0])
    scene = trimesh.util.concatenate([floor, roof])
    top = stage.centre[1] - 0.49
    surface = TexelSurface(coverage=np.ones((1, 2), bool), points=np.array([[0.0, top, 0.0], [0.8, top, 0.0]]),
                           normals=np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]]))
    visibility = texel_visibility(scene.vertices, scene.faces, surface, stage)
    to_light = stage.positions - surface.points[0]
    elevation = np.degrees(np.arcsin(to_light[:, 1] / np.linalg.norm(to_light, axis=1)))
    overhead = elevation > 60  # behind the roof (0.3 m wide, 0.3 m above the texel: < 27 degrees off vertical)
    grazing = (elevation > 5) & (elevation < 30)
    assert overhead.any() and grazing.any()
    assert not visibility[0, overhead].any()
    assert visibility[0, grazing].all()
    assert visibility[1, elevation > 60].mean() > 0.5  # the texel out from under the roof sees the sky
    assert not visibility[0, to_light[:, 1] < 0].any()  # lights below the floor's top face are hidden


def test_top_r_picks_the_lights_in_the_specular_lobe(stage):
    point = stage.centre[None] + [0.0, 0.0, 0.0]
    normal = np.array([[0.0, 1.0, 0.0]])
    target = int(np.argmax(stage.directions[:, 1] * (stage.directions[:, 1] < 0.8)))  # a high light, off the pole
    w = stage.directions[target]
    camera = point[0] + 2.0 * np.array([-w[0], w[1], -w[2]])  # the mirror direction about the normal
    intensities = np.ones((stage.num_lights, 3))
    transfer = light_transfer(point, normal, stage)
    index, valid = select_rays(point, normal, transfer, stage, intensities, camera, r=8, shininess=200.0)
    assert int(index[0, 0]) == target and valid.all()
    # the order is by the half-vector cosine: a plain reference
    v = (camera - point[0]) / np.linalg.norm(camera - point[0])
    to_light = stage.positions - point[0]
    w_all = to_light / np.linalg.norm(to_light, axis=1, keepdims=True)
    h = (w_all + v) / np.linalg.norm(w_all + v, axis=1, keepdims=True)
    score = np.clip(h[:, 1], 0, None) ** 200.0 * transfer[0].numpy() * np.linalg.norm(stage.rgb_gain, axis=1)
    np.testing.assert_array_equal(index[0].numpy(), np.argsort(-score, kind="stable")[:8])
    # lights below the horizon have no importance: asking for all of them leaves invalid slots
    index, valid = select_rays(point, normal, transfer, stage, intensities, camera, r=stage.num_lights)
    below = (stage.positions[:, 1] - point[0, 1]) <= 0
    assert (~valid).sum() == below.sum() and set(index[0, ~valid[0]].tolist()) == set(np.flatnonzero(below))


def test_psi_sums_to_chi_and_is_differentiable_in_the_lights(stage):
    rng = np.random.default_rng(4)
    points = stage.centre + rng.normal(scale=0.2, size=(30, 3))
    normals = rng.normal(size=(30, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    camera = stage.centre + np.array([0.0, 0.5, 2.0])
    # facing the camera, every light in front of a texel has n.h > 0 and so a non-zero importance
    normals *= np.sign(np.sum(normals * (camera - points), axis=1, keepdims=True))
    transfer = light_transfer(points, normals, stage)
    intensities = torch.tensor(_lighting(stage, 5), requires_grad=True)
    index, valid = select_rays(points, normals, transfer, stage, intensities, camera, r=stage.num_lights)
    psi = ray_encoding(points, normals, transfer, stage, intensities, camera, index, valid)
    assert psi.shape == (30, stage.num_lights, 6)
    chi = irradiance_map(transfer, stage, intensities)
    torch.testing.assert_close(psi[..., 3:].sum(1), chi.to(psi.dtype), rtol=1e-5, atol=1e-6)
    assert (psi[..., 0][valid] > 0).all()  # n.w > 0 for every selected light
    assert torch.all(psi[~valid] == 0)
    grad = torch.autograd.grad(psi[..., 3:].sum(), intensities)[0]
    expected = (transfer.double().sum(0)[:, None] * torch.from_numpy(stage.rgb_gain))
    torch.testing.assert_close(grad, expected, rtol=1e-5, atol=1e-6)
