"""Safe outputs (``--out`` never destroys inputs, the working directory or unrelated files; stale
temporaries of killed runs are removed) and honest devices (``--device`` honoured or refused, the
manifest records the device used)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from egorelight_cli.artifacts import ArtifactWriter, open_artifact, sha256_file
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.keypoints import Keypoints, save_keypoints, write_keypoints_npz
from egorelight_cli.runtime import resolve_device
from egorelight_cli.stages.ik import IKSettings, default_ik_model, fitted_keypoints


def assert_refused(result, *fragments: str) -> None:
    """Exit 2 with one ``egorelight: error:`` line holding every fragment."""
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("egorelight: error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def tree_digest(root: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under ``root`` (a folder's content, to compare)."""
    return {p.relative_to(root).as_posix(): sha256_file(p) for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def keypoints(character) -> Keypoints:
    theta = np.repeat(default_ik_model(character, IKSettings(hand_samples=500)).theta_bar[None], 6, axis=0)
    xyz = fitted_keypoints(character, theta)
    return Keypoints(xyz, np.ones(xyz.shape[:2]), np.arange(6), character.keypoint_names, fps=30.0)


@pytest.fixture
def inputs(tmp_path, keypoints) -> Path:
    """``tmp_path`` with a lone ``k.npz`` and a keypoints artifact directory ``kp/``."""
    write_keypoints_npz(tmp_path / "k.npz", keypoints)
    with ArtifactWriter(tmp_path / "kp", kind="keypoints", stage="egopose", config={}) as writer:
        save_keypoints(writer, keypoints)
    return tmp_path


IK = ("ik", "--preset", "tiny")


# ---------------------------------------------------------------------------------- inputs
def test_out_that_is_an_input_artifact_is_refused_and_kept(run, inputs):
    before = tree_digest(inputs / "kp")
    assert_refused(run(*IK, "--in", inputs / "kp", "--out", inputs / "kp"), "is the input", "kp")
    assert tree_digest(inputs / "kp") == before
    open_artifact(inputs / "kp", kind="keypoints", verify=True)


def test_out_that_is_the_input_file_is_refused_and_kept(run, inputs):
    before = sha256_file(inputs / "k.npz")
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", inputs / "k.npz"), "is the input", "k.npz")
    assert sha256_file(inputs / "k.npz") == before and not (inputs / "k.npz.json").exists()


def test_out_containing_or_inside_an_input_is_refused(run, inputs):
    assert_refused(run(*IK, "--in", inputs / "kp", "--out", inputs / "kp" / "motion"), "inside the input")
    assert not (inputs / "kp" / "motion").exists()
    nested = inputs / "deep" / "k.npz"
    nested.parent.mkdir()
    (inputs / "k.npz").rename(nested)
    assert_refused(run(*IK, "--in", nested, "--out", inputs / "deep"), "contains the input")
    assert nested.is_file()


def test_out_inside_another_artifact_is_refused(run, inputs):
    assert run(*IK, "--in", inputs / "k.npz", "--out", inputs / "motion").returncode == 0
    before = tree_digest(inputs / "motion")
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", inputs / "motion" / "again"), "inside the artifact")
    assert tree_digest(inputs / "motion") == before


# ------------------------------------------------------------------------- working directory
def test_out_that_is_the_working_directory_or_above_is_refused(run, inputs, monkeypatch):
    here = inputs / "here"
    here.mkdir()
    (here / "notes.txt").write_text("mine")
    monkeypatch.chdir(here)
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", "."), "current directory")
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", "../here"), "current directory", "../here")
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", ".."), "current directory")
    assert (here / "notes.txt").read_text() == "mine" and (inputs / "k.npz").is_file()


# ----------------------------------------------------------------------- existing contents
def test_unrelated_folder_and_file_are_refused_and_kept(run, inputs):
    folder = inputs / "photos"
    folder.mkdir()
    (folder / "a.jpg").write_bytes(b"\xff\xd8 not really")
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", folder), "not an egorelight artifact", "photos")
    assert (folder / "a.jpg").read_bytes() == b"\xff\xd8 not really"
    lone = inputs / "result.npz"
    lone.write_bytes(b"someone's data")
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", lone), "without an egorelight sidecar", "result.npz")
    assert lone.read_bytes() == b"someone's data"


def test_only_a_previous_artifact_of_the_same_kind_is_replaced(run, inputs):
    motion = inputs / "motion"
    assert run(*IK, "--in", inputs / "k.npz", "--out", motion).returncode == 0
    assert run(*IK, "--in", inputs / "k.npz", "--out", motion, "--force").returncode == 0  # same kind: replaced
    assert run(*IK, "--in", inputs / "k.npz", "--out", inputs / "m.npz").returncode == 0
    assert run(*IK, "--in", inputs / "k.npz", "--out", inputs / "m.npz", "--force").returncode == 0
    before = tree_digest(motion)
    assert_refused(run("character", "default", "--out", motion), "egorelight/motion", "egorelight/character")
    assert_refused(run("character", "default", "--out", inputs / "m.npz"), "egorelight/motion")
    assert tree_digest(motion) == before
    (motion / "notes.txt").write_text("mine")  # a user's file inside an artifact goes nowhere
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", motion, "--force"), "notes.txt")
    assert (motion / "notes.txt").read_text() == "mine"
    empty = inputs / "empty"
    empty.mkdir()
    assert run(*IK, "--in", inputs / "k.npz", "--out", empty).returncode == 0  # an empty folder holds nothing to lose


def test_a_model_of_another_stage_is_not_replaced(run, inputs):
    animate_model = inputs / "animate_model"
    with ArtifactWriter(animate_model, kind="model", stage="animate", config={}) as writer:
        writer.save_json("notes.json", {"trained": "for days"})
    before = tree_digest(animate_model)
    assert_refused(run("train", "ik", "--preset", "tiny", "--out", animate_model), "animate model", "ik model")
    assert tree_digest(animate_model) == before
    ik_model = inputs / "ik_model"
    assert run("train", "ik", "--preset", "tiny", "--out", ik_model).returncode == 0
    assert run("train", "ik", "--preset", "tiny", "--out", ik_model, "--force").returncode == 0  # its own: replaced


def test_character_export_and_preview_outputs_are_checked(run, inputs):
    assert run("character", "default", "--out", inputs / "ch").returncode == 0
    before = tree_digest(inputs / "ch")
    assert_refused(run("character", "export-ddc", inputs / "ch", "--out", inputs / "ch"), "is the input")
    assert_refused(run("character", "preview", inputs / "ch", "--out", inputs / "ch" / "p.png"), "inside the input")
    assert_refused(run("character", "preview", inputs / "ch", "--out", inputs / "previews" / "char"), "image file")
    mine = inputs / "mine.png"
    mine.write_bytes(b"a photo")  # an image the tool did not write is kept unless --force says replace it
    assert_refused(run("character", "preview", inputs / "ch", "--out", mine), "--force")
    assert mine.read_bytes() == b"a photo"
    assert run("character", "preview", inputs / "ch", "--out", mine, "--force").returncode == 0
    assert mine.read_bytes()[1:4] == b"PNG"
    assert tree_digest(inputs / "ch") == before
    (inputs / "photos").mkdir()
    (inputs / "photos" / "a.jpg").write_text("x")
    assert_refused(run("character", "export-ddc", inputs / "ch", "--out", inputs / "photos"), "not a DDC export")
    assert (inputs / "photos" / "a.jpg").read_text() == "x"


# ------------------------------------------------------------------------- unwritable paths
def test_over_long_and_impossible_output_paths_are_one_line_errors(run, inputs):
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", inputs / ("m" * 250)), "too long")
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", inputs / ("m" * 300) / "x"), "too long")
    (inputs / "file.txt").write_text("x")
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", inputs / "file.txt" / "m"), "not a directory")
    with pytest.raises(EgorelightError, match="cannot write the output"):  # the writer itself maps OS errors
        ArtifactWriter(inputs / "file.txt" / "m", kind="motion", stage="ik")


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into read-only folders")
def test_read_only_output_folder_is_a_one_line_error(run, inputs):
    folder = inputs / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", folder / "m"), "not writable")
    finally:
        folder.chmod(0o755)


# ----------------------------------------------------------------------- stale temporaries
def test_stale_temporaries_of_killed_runs_are_removed(run, inputs):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    stale = [inputs / f".motion.tmp-{dead_pid}-0123abcd", inputs / ".motion.tmp-deadbeef",
             inputs / f".motion.old-{dead_pid}-0123abcd"]
    live = inputs / f".motion.tmp-{os.getppid()}-0123abcd"  # a run still going (our parent process)
    for path in [*stale, live]:
        path.mkdir()
        (path / "motion.npz").write_bytes(b"half written")
    other = inputs / f".other.tmp-{dead_pid}-0123abcd"  # another output's: not ours to clean
    other.mkdir()
    assert run(*IK, "--in", inputs / "k.npz", "--out", inputs / "motion").returncode == 0
    assert not any(p.exists() for p in stale)
    assert live.is_dir() and other.is_dir()
    assert sorted(p.name for p in inputs.iterdir() if p.name.startswith(".motion")) == [live.name]


def test_an_output_a_kill_left_half_swapped_is_put_back_and_found_up_to_date(run, inputs):
    """SIGKILL after the new payload of a single-file output landed, before its sidecar: the next
    run puts the previous pair back before its output checks (which refused a payload without a
    sidecar) and finds it up to date."""
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    out = inputs / "m.npz"
    assert run(*IK, "--in", inputs / "k.npz", "--out", out).returncode == 0
    before = {p.name: p.read_bytes() for p in (out, inputs / "m.npz.json")}
    os.replace(out, inputs / f".m.npz.old-{int(dead.stdout)}-0123abcd")
    os.replace(inputs / "m.npz.json", inputs / f".m.npz.json.old-{int(dead.stdout)}-4567cdef")
    out.write_bytes(b"the new payload, its sidecar never came")
    again = run(*IK, "--in", inputs / "k.npz", "--out", out)
    assert again.returncode == 0 and "up to date" in again.stderr, again.stderr
    assert {p.name: p.read_bytes() for p in (out, inputs / "m.npz.json")} == before
    assert not [p for p in inputs.iterdir() if ".old-" in p.name]


# ---------------------------------------------------------------------------------- device
def test_cuda_is_refused_by_cpu_only_stages_and_the_device_used_is_recorded(run, inputs):
    assert_refused(run(*IK, "--in", inputs / "k.npz", "--out", inputs / "m", "--device", "cuda"), "--device cuda", "ik")
    assert not (inputs / "m").exists()
    assert run(*IK, "--in", inputs / "k.npz", "--out", inputs / "m", "--device", "auto").returncode == 0
    runtime = json.loads((inputs / "m" / "manifest.json").read_text())["runtime"]
    assert runtime["device"] == "cpu" and runtime["device_requested"] == "auto"


def test_resolve_device_is_honest():
    assert resolve_device("auto", stage="ik").type == "cpu"
    assert resolve_device("cpu", stage="egodepth").type == "cpu"
    with pytest.raises(EgorelightError, match="no CUDA code path"):
        resolve_device("cuda", stage="calibrate")
    with pytest.raises(EgorelightError, match="unknown device"):
        resolve_device("tpu")
    if torch.cuda.is_available():
        assert resolve_device("cuda", stage="animate").type == "cuda"
    else:
        assert resolve_device("auto", stage="animate").type == "cpu"
        with pytest.raises(EgorelightError, match="no CUDA device is available"):
            resolve_device("cuda", stage="animate")
