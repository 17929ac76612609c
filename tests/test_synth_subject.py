"""The simulated subject is not the pipeline's character: own body, rig, garments, detail and scan."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorelight_cli.config import resolve_config
from egorelight_cli.geometry.embedded_graph import pose_character
from egorelight_cli.geometry.pointcloud_ops import SurfaceDistance
from egorelight_cli.geometry.skeleton import keypoint_positions
from egorelight_cli.io.exr import read_exr
from egorelight_cli.io.meshes import read_mesh
from egorelight_cli.io.npz import read_npz
from egorelight_cli.synth.appearance import CLOTH_MATERIALS
from egorelight_cli.synth.scan import scan_subject
from egorelight_cli.synth.subject import SubjectParams, make_subject, make_subject_body, pose_lbs


@pytest.fixture(scope="module")
def synth_cfg():
    return resolve_config("synth", "tiny")


@pytest.fixture(scope="module")
def subject(character, synth_cfg):
    return make_subject(character, synth_cfg, seed=3)


def test_body_is_finer_with_its_own_proportions_rig_and_weights(character, subject):
    body = subject.body
    assert body.num_vertices > 3 * character.num_vertices
    # plain LBS reproduces the rest surface at the rigging pose
    np.testing.assert_allclose(pose_lbs(body, body.rest_theta[None])[0], body.vertices, atol=1e-9)
    rest = torch.as_tensor(character.rest_theta)
    moved = np.linalg.norm(keypoint_positions(rest, body).numpy() - keypoint_positions(rest, character).numpy(), axis=1)
    assert np.median(moved) > 0.01  # its own joints: centimetres away from the template's
    original = body.skin_weights[: character.num_vertices]  # subdivision keeps the template's vertices first
    assert np.abs(original - character.skin_weights).sum(1).mean() > 0.05  # L1 per vertex, max 2
    other, _, _ = make_subject_body(character, SubjectParams(), seed=4)
    assert np.abs(other.vertices - body.vertices).max() > 0.01


def test_garments_are_separate_eased_surfaces_sewn_at_their_openings(subject):
    clothing = subject.clothing
    gap = np.linalg.norm(clothing.rest - subject.body.vertices[clothing.body_vertex], axis=1)
    inside = clothing.cloth_weight == 1
    assert np.median(gap[inside]) > 0.005 and gap[inside].max() < 0.03
    np.testing.assert_allclose(gap[clothing.cloth_weight == 0], 0.0, atol=1e-12)
    # the outer surface: open body faces + garment faces, no body face under a garment
    assert subject.garment_faces.sum() == len(clothing.faces)
    assert len(subject.faces) == (~clothing.covered_faces).sum() + len(clothing.faces)
    theta = np.repeat(subject.body.rest_theta[None], 3, 0)
    pose_part, random_part = clothing.deform(theta, 10.0, seed=1)
    posed = subject.pose(theta, pose_part + random_part)
    assert posed.shape == (3, subject.num_vertices, 3) and np.isfinite(posed).all()


def test_detail_normal_map_tilts_cloth_and_skin(tiny_capture):
    maps = read_exr(tiny_capture / "groundtruth" / "appearance.exr")
    detail, material = maps.layer("detail"), maps.layer("material")[..., 0]
    tilt = np.degrees(np.arccos(np.clip(detail[..., 2], -1, 1)))
    cloth = np.isin(material, CLOTH_MATERIALS)
    assert 4 < tilt[cloth].mean() < 25
    np.testing.assert_allclose(np.linalg.norm(detail, axis=-1), 1.0, atol=2e-3)


def test_scan_has_its_own_tessellation_and_lies_on_the_rest_surface(subject, synth_cfg):
    v, f = scan_subject(subject, synth_cfg.scan, seed=3)
    assert len(v) != subject.num_vertices
    d = SurfaceDistance(subject.rest_vertices(), subject.faces)(v)
    assert np.mean(d) < 0.003 and np.percentile(d, 99) < 0.01


def test_the_in_model_shortcut_is_gone(character, tiny_capture):
    """The pipeline's character posed with the TRUE motion (its own DQS, no clothing model) is
    centimetres from the true surface (it was 0.27 cm when the subject was the character)."""
    arrays, _ = read_npz(tiny_capture / "groundtruth" / "test" / "meshes.npz")
    assert arrays["vertices"].shape[1] != character.num_vertices
    posed = pose_character(character, torch.as_tensor(arrays["theta"].astype(np.float64)), skinning="dqs").numpy()
    to_truth = [SurfaceDistance(arrays["vertices"][t].astype(np.float64), arrays["faces"])(posed[t]).mean()
                for t in range(len(posed))]
    assert np.mean(to_truth) > 0.01


def test_capture_writes_the_scan_as_an_input(tiny_capture):
    v, f = read_mesh(tiny_capture / "scan" / "scan.ply")
    assert len(f) > 1000 and v[:, 1].max() > 1.4


def test_subdivision_vertices_take_their_light_visibility_from_their_parents(subject):
    """Tracing only the previous level's vertices (about a third of the outer surface, plus the
    boundary pairs where two parents disagree) gives nearly the same per-vertex visibility, and an
    image as close to exact per-pixel shadows (measured: 0.12% vs 0.07% mean relative error)."""
    from egorelight_cli.geometry.cameras import Camera, look_at
    from egorelight_cli.geometry.normals import vertex_normals
    from egorelight_cli.geometry.raycast import RayCaster
    from egorelight_cli.render.lightstage import LightStage
    from egorelight_cli.render.shading import Material, render_view, vertex_light_visibility
    from egorelight_cli.synth.sensors import proxied_visibility

    parents = subject.visibility_parents
    traced = parents[:, 0] == np.arange(len(parents))
    assert 0.2 < traced.mean() < 0.5
    vertices = subject.rest_vertices()
    stage = LightStage.dome(num_lights=60)
    caster = RayCaster(vertices, subject.faces)
    normals = vertex_normals(vertices, subject.faces)
    full = vertex_light_visibility(vertices, subject.faces, stage, caster=caster, normals=normals)
    proxy = proxied_visibility(vertices, normals, parents, stage, caster)
    assert (full == proxy).mean() > 0.95  # they differ at shadow boundaries, where the renderer traces exactly
    K = np.array([[300.0, 0, 79.5], [0, 300.0, 119.5], [0, 0, 1]])
    camera = Camera("pinhole", K, np.zeros(5), 160, 240, look_at(np.array([0.4, 1.0, -2.5]), np.array([0, 0.9, 0])))
    light = stage.flat(1.0)
    images = [render_view(vertices, subject.faces, None, Material(albedo=0.5), camera, stage, light, caster=caster,
                          vertex_visibility=v, normals=normals, exact_lights=0).radiance for v in (None, full, proxy)]
    exact = images[0]
    error_full, error_proxy = (np.abs(image - exact).mean() / exact.mean() for image in images[1:])
    assert error_proxy < 0.01 and error_proxy < 2.5 * error_full
