"""GeoLift scoring: the truth at the surface a mesh shows (closest point) and at the texel's own UV."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from egorelight_cli.io.npz import write_npz
from egorelight_cli.render.raster import rasterize_uv, texel_centres_uv
from egorelight_cli.render.uv_features import texel_surface
from egorelight_cli.stages.geolift_eval import GeoLiftScores, GeoLiftTruth

TRUTH_RESOLUTION = 64


def _truth_maps(uv: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A truth that differs from place to place: the texture is (u, v, 0.5); the normals are tilted
    by a function of UV."""
    tilted = normals + 0.3 * np.stack([np.sin(10 * uv[:, 0]), np.cos(10 * uv[:, 1]), 0 * uv[:, 0]], -1)
    tilted /= np.linalg.norm(tilted, axis=1, keepdims=True)
    return tilted, np.concatenate([uv, np.full((len(uv), 1), 0.5)], axis=1)


@pytest.fixture(scope="module")
def truth_capture(character, tmp_path_factory):
    """A stand-in capture whose ``groundtruth/seq`` holds the character itself (frame 7) as the
    true surface, with UV truth maps made by :func:`_truth_maps`."""
    root = tmp_path_factory.mktemp("gt")
    folder = root / "groundtruth" / "seq"
    folder.mkdir(parents=True)
    raster = rasterize_uv(character.face_uvs, TRUTH_RESOLUTION, conservative=False)
    surface = texel_surface(raster, character.vertices, character.faces)
    normals, texture = _truth_maps(texel_centres_uv(raster.resolution)[raster.coverage], surface.normals)
    write_npz(folder / "uv_truth.npz", {"normals": normals[None].astype(np.float16),
                                        "flat_texture": texture[None].astype(np.float16),
                                        "coverage": raster.coverage, "frame_ids": np.array([7])}, {"kind": "test", "version": 1})
    write_npz(folder / "meshes.npz", {"vertices": character.vertices[None].astype(np.float32),
                                      "faces": character.faces, "face_uvs": character.face_uvs.astype(np.float32),
                                      "frame_ids": np.array([7])}, {"kind": "test", "version": 1})

    def groundtruth_file(sequence, name):
        path = root / "groundtruth" / sequence / name
        return path if path.is_file() else None

    return SimpleNamespace(root=root, groundtruth_file=groundtruth_file, groundtruth_root=lambda: root / "groundtruth")


def test_truth_at_the_surface_is_the_truth_at_the_closest_points_uv(truth_capture, character):
    raster = rasterize_uv(character.face_uvs, 32)
    truth = GeoLiftTruth(truth_capture, "seq", raster)
    assert truth.available and truth.has(7) and not truth.has(8)
    surface = texel_surface(raster, character.vertices, character.faces)
    keep = truth.faithful
    assert keep.mean() > 0.5 and not keep.all()  # the conservative pass moved some texels
    # texels on the true surface: distance 0, texture = their own UV (up to the truth's texel size)
    normals, texture, distance = truth.at_surface(7, surface.points)
    assert np.median(distance) < 1e-6 and distance.max() < 2e-3  # (closest-face candidates by sampling)
    own_uv = texel_centres_uv(raster.resolution)[raster.coverage]
    np.testing.assert_allclose(texture[keep, :2], own_uv[keep], atol=1.5 / TRUTH_RESOLUTION)
    # lifted 5 mm off the surface: the same points of the truth, 5 mm away
    lifted = truth.at_surface(7, surface.points + 0.005 * surface.normals)
    assert abs(np.median(lifted[2]) - 0.005) < 2e-4 and lifted[2].max() < 0.0052  # (curved: <= 5 mm)
    assert np.mean(np.abs(lifted[1][keep] - texture[keep]).max(axis=1) < 1.5 / TRUTH_RESOLUTION) > 0.95
    # the material comparison agrees where the texel lies where its UV says
    _, uv_texture, valid = truth.frame(7)
    assert valid.mean() > 0.4
    np.testing.assert_allclose(uv_texture[valid, :2], own_uv[valid], atol=1.5 / TRUTH_RESOLUTION)
    assert truth.at_surface(8, surface.points) is None


def test_scores_put_the_prediction_next_to_its_baselines(truth_capture, character):
    raster = rasterize_uv(character.face_uvs, 32)
    truth = GeoLiftTruth(truth_capture, "seq", raster)
    surface = texel_surface(raster, character.vertices, character.faces)
    true_normals, true_texture, _ = truth.at_surface(7, surface.points)

    def as_map(values):
        out = np.zeros(raster.resolution + (3,), np.float32)
        out[raster.coverage] = values
        return np.moveaxis(out, -1, 0)

    coarse = as_map(surface.normals)
    scores = GeoLiftScores()
    scores.add(truth, 7, surface.points, as_map(true_normals), coarse, as_map(true_texture), as_map(true_texture * 0))
    metrics = scores.metrics()
    assert metrics["normal_deg"] < 0.05 < metrics["normal_deg_coarse"]
    assert metrics["texture_l1"] < 1e-3 < metrics["texture_l1_mean_texture"]
    assert metrics["surface_distance_median_mm"] < 1e-3
    assert metrics["normal_deg_uv"] < metrics["normal_deg_uv_coarse"]
