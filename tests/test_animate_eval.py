"""Topology-free geometric metrics (:mod:`egorelight_cli.stages.animate_eval`): point-to-surface
distances both ways against a true surface of any tessellation, its outer part, ego visibility."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from egorelight_cli.geometry.cameras import Camera, look_at
from egorelight_cli.geometry.normals import vertex_normals
from egorelight_cli.stages.animate_eval import OuterSurface, outer_faces, score_meshes


@pytest.fixture(scope="module")
def retopologized_capture(tiny_capture, tmp_path_factory) -> Path:
    """The tiny capture with a true surface of another topology (:mod:`retopologize`)."""
    from retopologize import subdivided_truth_capture

    return subdivided_truth_capture(tiny_capture, tmp_path_factory.mktemp("retopologized") / "capture")


def _sphere(subdivisions: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(sphere.vertices), np.asarray(sphere.faces)


def _score(truth: OuterSurface, faces: np.ndarray, **predicted: np.ndarray) -> dict:
    return score_meshes({name: v[None] for name, v in predicted.items()}, faces, np.array([7]), {7: truth})


def test_a_sphere_5_mm_out_with_another_tessellation_is_half_a_centimetre_off_both_ways():
    truth = OuterSurface(*_sphere(5, 0.25))
    vertices, faces = _sphere(4, 0.255)
    score = _score(truth, faces, offset=vertices)
    assert score["eval_frames"] == 1
    # the predicted vertices lie on the sphere of 25.5 cm, the truth's faces just inside 25 cm
    assert score["offset_p2s_pred_to_true_cm"] == pytest.approx(0.5, abs=0.01)
    assert score["offset_p2s_true_to_pred_cm"] == pytest.approx(0.5, abs=0.03)
    assert score["offset_p2s_cm"] == score["offset_p2s_pred_to_true_cm"]
    assert np.isnan(score["offset_p2s_ego_visible_pred_to_true_cm"])  # no camera: nothing ego-visible
    assert np.isnan(score["offset_p2s_ego_visible_true_to_pred_cm"]) and np.isnan(score["offset_p2s_ego_visible_cm"])


def test_the_directions_differ_on_a_prediction_that_covers_half_the_truth():
    vertices, faces = _sphere(4, 0.25)
    upper = faces[(vertices[faces][:, :, 1] >= 0).all(axis=1)]
    truth = OuterSurface(vertices, faces)
    score = score_meshes({"half": vertices[None].repeat(2, axis=0)}, upper, np.array([3, 7]), {7: truth})
    assert score["eval_frames"] == 1  # frame 3 has no truth
    assert score["half_p2s_pred_to_true_cm"] < 1e-9  # every predicted vertex lies on the truth ...
    assert score["half_p2s_true_to_pred_cm"] > 5.0  # ... but the lower half of the truth is missing


def test_a_truth_of_the_characters_surface_subdivided_and_pushed_out_5_mm_scores_the_character(character):
    rest, faces = np.asarray(character.vertices, np.float64), np.asarray(character.faces)
    fine_vertices, fine_faces = trimesh.remesh.subdivide(rest, faces)
    assert len(fine_faces) == 4 * len(faces)
    # another topology, the same surface: (almost) nothing to measure
    same_surface = _score(OuterSurface(fine_vertices, fine_faces), faces, rest=rest)
    assert same_surface["rest_p2s_pred_to_true_cm"] < 0.01 and same_surface["rest_p2s_true_to_pred_cm"] < 0.01
    pushed = fine_vertices + 0.005 * vertex_normals(fine_vertices, fine_faces)
    score = _score(OuterSurface(pushed, fine_faces), faces, rest=rest)
    # 5 mm along the normals is 5 mm off the surface but in creases and at thin parts (less), and
    # at the rim of a pocket in the head that the push seals off (more)
    assert 0.45 < score["rest_p2s_pred_to_true_cm"] < 0.53
    assert 0.45 < score["rest_p2s_true_to_pred_cm"] < 0.53
    # the same topology still scores: the same push on the character's own mesh, and no push at all
    same = _score(OuterSurface(rest + 0.005 * vertex_normals(rest, faces), faces), faces, rest=rest)
    for key in ("rest_p2s_pred_to_true_cm", "rest_p2s_true_to_pred_cm"):
        assert same[key] == pytest.approx(score[key], abs=0.03)
    exact = _score(OuterSurface(rest, faces), faces, rest=rest)
    # (SurfaceDistance misses the closest face of a few points on sliver triangles by < 2 mm)
    assert exact["rest_p2s_pred_to_true_cm"] < 1e-6 and exact["rest_p2s_true_to_pred_cm"] < 1e-3


def test_skin_under_a_separate_garment_is_not_part_of_the_scored_surface():
    skin_vertices, skin_faces = _sphere(4, 0.25)
    garment_vertices, garment_faces = _sphere(4, 0.26)
    # one truth mesh: body skin plus a garment sheet over it, wound the other way round
    vertices = np.concatenate([skin_vertices, garment_vertices])
    faces = np.concatenate([skin_faces, garment_faces[:, ::-1] + len(skin_vertices)])
    outer = outer_faces(vertices, faces)
    assert not outer[:len(skin_faces)].any() and outer[len(skin_faces):].all()
    truth = OuterSurface(vertices, faces)
    fitted_vertices, fitted_faces = _sphere(3, 0.26)
    naked = _score(truth, skin_faces, naked=skin_vertices)
    clothed = _score(truth, fitted_faces, clothed=fitted_vertices)
    # a prediction of the bare body is the garment's 1 cm off, not 0 cm from the hidden skin
    assert naked["naked_p2s_pred_to_true_cm"] == pytest.approx(1.0, abs=0.01)
    assert naked["naked_p2s_true_to_pred_cm"] == pytest.approx(1.0, abs=0.01)
    assert clothed["clothed_p2s_pred_to_true_cm"] < 0.01 and clothed["clothed_p2s_true_to_pred_cm"] < 0.06


def test_the_ego_visible_scores_keep_to_what_the_camera_sees():
    vertices, faces = _sphere(5, 0.25)
    camera = Camera("pinhole", [[200.0, 0, 99.5], [0, 200.0, 99.5], [0, 0, 1]], np.zeros(5), 200, 200,
                    look_at([0.0, 1.0, 0.0], [0.0, 0.0, 0.0], up=(0.0, 0.0, -1.0)), "above")
    truth = OuterSurface(vertices, faces, [camera])
    # from 1 m the camera sees the cap above y = r^2 / 1 m: (1 - r / 1 m) / 2 of the area
    assert truth.visible_area_fraction == pytest.approx(0.375, abs=0.01)
    assert (truth.samples[truth.sample_visible, 1] > 0.05).all()
    pred_vertices, pred_faces = _sphere(4, 0.25)
    top = pred_vertices[:, 1] > 0
    pred_vertices[top] *= 0.26 / 0.25  # the upper half 1 cm out, the lower half exact
    score = _score(truth, pred_faces, top=pred_vertices)
    assert score["top_p2s_ego_visible_pred_to_true_cm"] == pytest.approx(1.0, abs=0.01)
    assert score["top_p2s_ego_visible_true_to_pred_cm"] == pytest.approx(1.0, abs=0.02)
    assert score["top_p2s_ego_visible_cm"] == score["top_p2s_ego_visible_pred_to_true_cm"]
    assert score["top_p2s_pred_to_true_cm"] == pytest.approx(top.mean(), abs=0.02)
    assert 0.3 < score["top_p2s_true_to_pred_cm"] < 0.6


def test_egodepth_scores_against_a_truth_of_another_topology(tiny_capture, retopologized_capture, oracle_calibration):
    import egorelight_cli.stages.egodepth as ed
    from egorelight_cli.io.capture import Capture

    truths, frames = [], []
    for root in (tiny_capture, retopologized_capture):
        capture = Capture(root)
        sequence = capture.sequence("test")
        frame = int(sequence.content_frame_ids[-1])
        views = [ed.load_view(capture, oracle_calibration, sequence, role, frame)
                 for role in capture.ego_cameras if role.startswith("down")]
        truths.append(ed.GroundTruth(capture, oracle_calibration, sequence, 0.05))
        frames.append(truths[-1].frame(frame, views))
    (surface, maps), (fine_surface, fine_maps) = frames
    # the subdivided truth is the same surface: the same true ranges, body masks and distances
    for role, (true_range, mask) in maps.items():
        fine_range, fine_mask = fine_maps[role]
        assert mask.sum() > 100 and np.mean(mask != fine_mask) < 1e-3
        both = mask & fine_mask
        assert np.abs(true_range[both] - fine_range[both]).max() < 1e-4
    vertices = truths[0].vertices[truths[0].frame_ids == frame][0]
    assert truths[1].vertices.shape[1] > vertices.shape[0]
    points = vertices + np.random.default_rng(0).normal(scale=0.01, size=vertices.shape)
    gap = np.abs(fine_surface(points) - surface(points))
    # the same but where a point's closest outer face borders hidden skin (outer is decided per face)
    assert np.mean(gap < 1e-6) > 0.95 and gap.max() < 0.02
