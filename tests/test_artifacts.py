"""Manifests, schemas, cache keys and atomic output."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from egorelight_cli import config as config_module
from egorelight_cli.artifacts import (ArtifactWriter, cache_key, is_up_to_date, known_kinds, open_artifact,
                                      sha256_file, validate_manifest)
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import read_npz
from egorelight_cli.pipeline import StageRun


def write_motion(out, theta=None, inputs=(), key=None):
    theta = np.zeros((3, 5), np.float32) if theta is None else theta
    with ArtifactWriter(out, kind="motion", stage="ik", config={"x": 1}, inputs=inputs, key=key) as w:
        w.save_npz(w.out.name if w.single_file else "motion.npz", {"theta": theta}, frame_ids=[0, 1, 2],
                   units={"theta": "rad"})
        w.metrics["mpjpe_cm"] = np.float32(1.5)
        w.metrics["undefined"] = float("nan")
    return out


def test_known_kinds_cover_design():
    kinds = known_kinds()
    for kind in ("capture", "character", "calibration", "keypoints", "motion", "pointcloud", "meshes",
                 "uvmaps", "renders", "envmap", "model"):
        assert kinds[kind] == 1


def test_directory_round_trip_and_schema(tmp_path):
    out = write_motion(tmp_path / "motion")
    artifact = open_artifact(out, kind="motion", verify=True)
    m = artifact.manifest
    assert m["kind"] == "egorelight/motion" and m["version"] == 1 and m["stage"] == "ik"
    assert m["metrics"] == {"mpjpe_cm": 1.5, "undefined": None}
    (entry,) = m["outputs"]
    assert entry["name"] == "motion.npz" and entry["digest"] == sha256_file(out / "motion.npz")
    assert entry["arrays"]["theta"] == {"shape": [3, 5], "dtype": "float32"}
    arrays, meta = read_npz(artifact.output("motion.npz"))
    assert meta["kind"] == "egorelight/motion" and meta["frame_ids"] == [0, 1, 2]
    assert not list(tmp_path.glob(".*tmp-*"))


def test_single_file_has_sidecar_and_meta(tmp_path):
    out = write_motion(tmp_path / "m.npz")
    assert (tmp_path / "m.npz.json").is_file()
    artifact = open_artifact(tmp_path / "m.npz", kind="motion")
    assert artifact.single_file and artifact.path == tmp_path / "m.npz"
    _, meta = read_npz(out)
    assert meta["kind"] == "egorelight/motion"
    # the sidecar itself also opens the artifact
    assert open_artifact(tmp_path / "m.npz.json").digest == artifact.digest


def test_inputs_are_recorded_relative_and_in_cache_key(tmp_path):
    a = open_artifact(write_motion(tmp_path / "a"))
    out = write_motion(tmp_path / "sub" / "b", inputs=[a])
    entry = open_artifact(out).manifest["inputs"][0]
    assert entry["path"] == "../../a" and entry["digest"] == a.digest
    k1 = cache_key("ik", 1, {"x": 1}, [a.digest])
    assert k1 != cache_key("ik", 2, {"x": 1}, [a.digest])
    assert k1 != cache_key("ik", 1, {"x": 2}, [a.digest])
    assert k1 != cache_key("ik", 1, {"x": 1}, ["sha256:" + "0" * 64])


def test_wrong_kind_and_version_name_both_sides(tmp_path):
    out = write_motion(tmp_path / "motion")
    with pytest.raises(EgorelightError, match="expected egorelight/keypoints, found egorelight/motion"):
        open_artifact(out, kind="keypoints")
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["version"] = 7
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(EgorelightError, match="artifact is version 7, this tool .* reads version 1"):
        open_artifact(out)


def test_schema_violation_is_reported(tmp_path):
    out = write_motion(tmp_path / "motion")
    manifest = json.loads((out / "manifest.json").read_text())
    del manifest["outputs"]
    with pytest.raises(EgorelightError, match="manifest does not match"):
        validate_manifest(manifest, out)
    (out / "manifest.json").write_text("{not json")
    with pytest.raises(EgorelightError, match="not valid JSON"):
        open_artifact(out)


def test_missing_and_unfinished(tmp_path):
    with pytest.raises(EgorelightError, match="input not found"):
        open_artifact(tmp_path / "nothing")
    (tmp_path / "half").mkdir()
    with pytest.raises(EgorelightError, match="no manifest.json"):
        open_artifact(tmp_path / "half")


def test_crash_mid_write_leaves_previous_state(tmp_path):
    out = write_motion(tmp_path / "motion", theta=np.ones((3, 5), np.float32))
    before = (out / "manifest.json").read_bytes()
    with pytest.raises(RuntimeError):
        with ArtifactWriter(out, kind="motion", stage="ik", config={}) as w:
            w.save_npz("motion.npz", {"theta": np.full((3, 5), 9, np.float32)})
            raise RuntimeError("killed half-way")
    assert (out / "manifest.json").read_bytes() == before
    np.testing.assert_array_equal(read_npz(out / "motion.npz")[0]["theta"], 1.0)
    assert not list(tmp_path.glob(".*tmp-*"))
    # a fresh output killed half-way leaves no finished-looking artifact at all
    with pytest.raises(RuntimeError):
        with ArtifactWriter(tmp_path / "fresh", kind="motion", stage="ik", config={}) as w:
            w.save_npz("motion.npz", {"theta": np.zeros((1, 1), np.float32)})
            raise RuntimeError("killed")
    assert not (tmp_path / "fresh").exists()


def test_single_file_crash_between_renames_is_detected(tmp_path):
    """Simulate a kill after the payload rename but before the sidecar rename."""
    write_motion(tmp_path / "m.npz", theta=np.ones((3, 5), np.float32))
    writer = ArtifactWriter(tmp_path / "m.npz", kind="motion", stage="ik", config={})
    writer.save_npz("m.npz", {"theta": np.zeros((3, 5), np.float32)})
    os.replace(writer.path("m.npz"), tmp_path / "m.npz")  # first half of _commit_single
    writer.abort()
    with pytest.raises(EgorelightError, match="does not match its manifest digest"):
        open_artifact(tmp_path / "m.npz")


def test_stage_run_skips_when_up_to_date_and_force_reruns(tmp_path, monkeypatch):
    (tmp_path / "stages").mkdir()
    (tmp_path / "stages" / "toy.yaml").write_text(
        "stage: toy\nversion: 1\ndefaults: {scale: 2.0}\npresets: {tiny: {}, cpu: {}, paper: {}}\n")
    monkeypatch.setattr(config_module, "stages_dir", lambda: tmp_path / "stages")
    calls = []

    def write(w, cfg):
        calls.append(cfg.scale)
        w.save_npz("motion.npz", {"theta": np.full((2, 2), cfg.scale, np.float32)})

    out = tmp_path / "toy"
    StageRun("toy").produce(out, "motion", write)
    StageRun("toy").produce(out, "motion", write)
    assert calls == [2.0]
    StageRun("toy", force=True).produce(out, "motion", write)
    assert calls == [2.0, 2.0]
    StageRun("toy", sets=("scale=3",)).produce(out, "motion", write)
    assert calls == [2.0, 2.0, 3.0]
    key = open_artifact(out).manifest["cache_key"]
    assert is_up_to_date(out, key, "motion") and not is_up_to_date(out, key, "keypoints")


def test_how_often_a_run_checkpoints_is_not_part_of_its_cache_key(tmp_path, monkeypatch):
    """train.checkpoint_every changes what a run could resume from, never what it writes: another
    value finds the output up to date and is recorded in the runtime; a key beside it (log_every:
    the curve written) still re-runs; an output recorded before (the value in its config and key)
    stays up to date. (Resuming under another value: tiny_models' resume check.)"""
    from egorelight_cli.pipeline import split_unkeyed
    from tiny_models import record_as_before_unkeyed

    assert split_unkeyed({"a": 1, "train": {"checkpoint_every": 5, "log_every": 2, "t": {"checkpoint_every": 3}}}) == (
        {"a": 1, "train": {"log_every": 2, "t": {}}}, {"train.checkpoint_every": 5, "train.t.checkpoint_every": 3})
    (tmp_path / "stages").mkdir()
    (tmp_path / "stages" / "toy.yaml").write_text(
        "stage: toy\nversion: 1\ndefaults: {train: {checkpoint_every: 2, log_every: 1}}\n"
        "presets: {tiny: {}, cpu: {}, paper: {}}\n")
    monkeypatch.setattr(config_module, "stages_dir", lambda: tmp_path / "stages")
    calls = []

    def write(w, cfg):
        calls.append(cfg.train.checkpoint_every)
        w.save_npz("motion.npz", {"theta": np.zeros((2, 2), np.float32)})

    out = tmp_path / "toy"
    StageRun("toy").produce(out, "motion", write)
    every_7 = StageRun("toy", sets=("train.checkpoint_every=7",))
    assert every_7.cache_key()[0] == StageRun("toy").cache_key()[0] == open_artifact(out).manifest["cache_key"]
    every_7.produce(out, "motion", write)
    assert calls == [2]
    manifest = open_artifact(out).manifest
    assert "checkpoint_every" not in manifest["config"]["train"]
    assert manifest["runtime"]["unkeyed_config"] == {"train.checkpoint_every": 2}
    StageRun("toy", sets=("train.log_every=3",)).produce(out, "motion", write)
    assert calls == [2, 2]
    record_as_before_unkeyed(out)  # an output from before: up to date under the value it recorded
    StageRun("toy", sets=("train.log_every=3",)).produce(out, "motion", write)
    assert calls == [2, 2]


def test_check_sequence_names_an_input_made_for_another_sequence(tmp_path):
    from egorelight_cli.artifacts import check_sequence

    with ArtifactWriter(tmp_path / "capture", kind="capture", stage="synth", config={}) as writer:
        writer.save_json("info.json", {})
    with ArtifactWriter(tmp_path / "cloud", kind="pointcloud", stage="egodepth", inputs=[open_artifact(tmp_path / "capture")],
                        config={"options": {"sequence": "wild"}}) as writer:
        writer.save_json("info.json", {})
    cloud = open_artifact(tmp_path / "cloud")
    check_sequence(cloud, "wild")
    check_sequence(None, "test")
    with pytest.raises(EgorelightError, match="made for sequence 'wild', not 'test'") as raised:
        check_sequence(cloud, "test")
    assert str(tmp_path / "cloud") in str(raised.value)
    with ArtifactWriter(tmp_path / "motion", kind="motion", stage="ik", config={}) as writer:
        writer.save_json("info.json", {})
    check_sequence(open_artifact(tmp_path / "motion"), "test")  # records no sequence: nothing to check
    # made without a capture, --seq kept its default and says nothing about the frames
    with ArtifactWriter(tmp_path / "meshes", kind="meshes", stage="animate",
                        config={"options": {"sequence": "test"}}) as writer:
        writer.save_json("info.json", {})
    check_sequence(open_artifact(tmp_path / "meshes"), "wild")
