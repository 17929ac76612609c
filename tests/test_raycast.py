"""Embree ray casting against an icosphere agrees with the analytic sphere."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.raycast import RayCaster

RADIUS = 0.7
CENTRE = np.array([0.1, -0.2, 0.3])


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    mesh.apply_translation(CENTRE)
    return mesh, RayCaster(mesh.vertices, mesh.faces)


def _tessellation_gap(mesh) -> float:
    """Largest distance between the sphere and the inscribed polyhedron (at face centroids)."""
    return float(RADIUS - np.linalg.norm(mesh.triangles_center - CENTRE, axis=1).min())


def _analytic_entry(origins: np.ndarray, dirs: np.ndarray):
    """Ray-sphere entry distance (inf where missed) and impact parameter of unit rays."""
    to_centre = CENTRE - origins
    along = np.einsum("ij,ij->i", to_centre, dirs)
    miss2 = np.einsum("ij,ij->i", to_centre, to_centre) - along**2
    half_chord = np.sqrt(np.clip(RADIUS**2 - miss2, 0, None))
    t = np.where(miss2 < RADIUS**2, along - half_chord, np.inf)
    return t, np.sqrt(miss2)


def _rays_towards_sphere(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    origins = CENTRE + rng.normal(size=(n, 3)) * 0.2 + np.array([0.0, 0.0, -3.0])
    targets = CENTRE + rng.uniform(-1.2, 1.2, size=(n, 3)) * RADIUS
    dirs = targets - origins
    return origins, dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def test_first_hit_matches_analytic_sphere(sphere):
    mesh, caster = sphere
    origins, dirs = _rays_towards_sphere(20000)
    hits = caster.first_hit(origins, dirs)
    t_true, impact = _analytic_entry(origins, dirs)
    gap = _tessellation_gap(mesh)
    assert 0 < gap < 2e-3

    clear_hit = impact < RADIUS - 0.01
    clear_miss = impact > RADIUS + 1e-6
    assert clear_hit.sum() > 5000 and clear_miss.sum() > 2000
    assert hits.hit[clear_hit].all() and not hits.hit[clear_miss].any()
    assert (hits.face_id[~hits.hit] == -1).all() and np.isinf(hits.distance[~hits.hit]).all()

    # Distance error along the ray is the radial gap divided by the cosine of incidence.
    points_true = origins + t_true[:, None] * dirs
    cos_incidence = np.abs(np.einsum("ij,ij->i", (points_true - CENTRE) / RADIUS, dirs))
    steep = clear_hit & (cos_incidence > 0.3)
    err = hits.distance[steep] - t_true[steep]
    assert (err > -1e-5).all()  # the polyhedron lies inside the sphere
    assert (err < gap / cos_incidence[steep] + 1e-5).all()


def test_barycentrics_reconstruct_hit_points(sphere):
    mesh, caster = sphere
    origins, dirs = _rays_towards_sphere(3000, seed=1)
    hits = caster.first_hit(origins, dirs)
    h = hits.hit
    assert np.allclose(hits.barycentrics[h].sum(axis=1), 1, atol=1e-5)
    assert (hits.barycentrics[h] > -1e-5).all()
    from_barycentrics = np.einsum("nkc,nk->nc", mesh.vertices[mesh.faces[hits.face_id[h]]], hits.barycentrics[h])
    from_distance = origins[h] + hits.distance[h, None] * dirs[h]
    assert np.abs(from_barycentrics - from_distance).max() < 1e-5


def test_leading_dims_broadcasting_and_unnormalised_dirs(sphere):
    _, caster = sphere
    origin = CENTRE + [0.0, 0.0, -2.0]
    dirs = np.zeros((2, 3, 3))
    dirs[..., 2] = 5.0  # not unit length: distances are still metres
    dirs[1, :, 0] = 10.0  # misses
    hits = caster.first_hit(origin, dirs)
    assert hits.hit.shape == (2, 3) and hits.barycentrics.shape == (2, 3, 3)
    assert hits.hit[0].all() and not hits.hit[1].any()
    assert np.allclose(hits.distance[0], 2.0 - RADIUS, atol=2e-3)
    assert caster.occluded(origin, dirs, max_dist=2.0 - RADIUS + 0.01)[0].all()
    assert not caster.occluded(origin, dirs, max_dist=2.0 - RADIUS - 0.01).any()


def test_occlusion_true_false_and_max_dist(sphere):
    _, caster = sphere
    origin = CENTRE + np.array([0.0, 0.0, -3.0])
    towards = np.array([0.0, 0.0, 1.0])
    away = np.array([0.0, 0.0, -1.0])
    entry = 3.0 - RADIUS
    assert caster.occluded(origin, towards).item()
    assert not caster.occluded(origin, away).item()
    assert caster.occluded(origin, towards, max_dist=entry + 0.01).item()
    assert not caster.occluded(origin, towards, max_dist=entry - 0.01).item()
    # A light between the point and the sphere is not shadowed by the sphere.
    assert not caster.occluded(origin, towards, max_dist=1.0).item()
    # Per-ray max_dist and near offset (shadow ray leaving the surface itself).
    max_dist = np.array([entry - 0.01, entry + 0.01, 10.0])
    assert caster.occluded(np.broadcast_to(origin, (3, 3)), towards, max_dist=max_dist).tolist() == [False, True, True]
    surface_point = CENTRE + [0.0, 0.0, -RADIUS]
    outward = np.array([0.0, 0.0, -1.0])
    assert not caster.occluded(surface_point, outward, near=1e-4).item()
    assert caster.occluded(surface_point, -outward, near=1e-4).item()  # through the body


def test_occluded_agrees_with_first_hit_strategy(sphere):
    _, caster = sphere
    origins, dirs = _rays_towards_sphere(5000, seed=2)
    max_dist = np.random.default_rng(2).uniform(1.0, 4.0, size=5000)
    any_hit = caster.occluded(origins, dirs, max_dist=max_dist)
    closest = caster.first_hit(origins, dirs)
    assert np.array_equal(any_hit, closest.distance < max_dist)
    assert np.array_equal(any_hit, caster.occluded_by_first_hit(origins, dirs, max_dist=max_dist))


def test_bad_meshes_and_rays_raise():
    with pytest.raises(EgorelightError):
        RayCaster(np.zeros((3, 2)), np.array([[0, 1, 2]]))
    with pytest.raises(EgorelightError):
        RayCaster(np.zeros((3, 3)), np.array([[0, 1, 3]]))
    caster = RayCaster(np.eye(3), np.array([[0, 1, 2]]))
    with pytest.raises(EgorelightError):
        caster.first_hit(np.zeros(3), np.zeros(3))
    with pytest.raises(EgorelightError):
        caster.occluded(np.zeros((2, 3)), np.ones((3, 3)))
