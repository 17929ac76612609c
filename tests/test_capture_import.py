"""``egorelight capture import``: a converted capture (no manifest, no ground truth) made an
artifact the stages take, and its bad inputs."""

from __future__ import annotations

import json
import shutil

import pytest

from egorelight_cli.artifacts import open_artifact
from egorelight_cli.io.images import read_image


@pytest.fixture
def converted(tiny_capture, tmp_path):
    """The tiny capture as a lab would convert its own: the layout, without a manifest or groundtruth/."""
    folder = tmp_path / "converted"
    shutil.copytree(tiny_capture, folder, ignore=shutil.ignore_patterns("manifest.json", "groundtruth"))
    return folder


def _sequences(folder) -> set[str]:
    return {p.name for p in (folder / "sequences").iterdir() if (p / "sequence.json").is_file()}


def test_a_converted_capture_becomes_an_artifact_the_stages_take(converted, tmp_path, run):
    out = tmp_path / "subject" / "capture"
    result = run("--preset", "tiny", "capture", "import", converted, "--out", out)
    assert result.returncode == 0, result.stderr
    artifact = open_artifact(out, kind="capture", verify=True)  # every file listed and its digest checked
    files = sorted(p.relative_to(converted).as_posix() for p in converted.rglob("*") if p.is_file())
    assert sorted(o["path"] for o in artifact.manifest["outputs"]) == sorted(files + ["preview.png"])
    sheet = read_image(out / "preview.png")  # a row per sequence, its first ego and studio frames
    assert sheet.ndim == 3 and sheet.shape[0] > 100 * len(_sequences(converted)) and sheet.std() > 10
    metrics = artifact.metrics
    assert set(metrics["sequences"]) == _sequences(converted) and metrics["groundtruth"] is False
    assert metrics["files"] == len(files) and metrics["hard_linked_files"] == len(files)  # one disk: no copy
    test = json.loads((converted / "sequences" / "test" / "sequence.json").read_text())
    assert metrics["sequences"]["test"]["frames"] == len(test["frame_ids"])
    assert "up to date" in run("--preset", "tiny", "capture", "import", converted, "--out", out).stderr
    refused = run("--preset", "tiny", "synth", "--out", out)  # make re-runs synth after a reinstall
    assert refused.returncode == 2 and "synth does not replace it" in refused.stderr
    open_artifact(out, kind="capture", verify=True)
    # a stage runs on it unchanged, and scores nothing it has no truth for
    assert run("--preset", "tiny", "-q", "calibrate", "--capture", out, "--out", tmp_path / "subject" / "calibration"
               ).returncode == 0
    calibration = open_artifact(tmp_path / "subject" / "calibration").metrics
    assert calibration["uncalibrated_cameras"] == [] and "handeye_rotation_error_deg_max" not in calibration


def test_copies_instead_of_links_on_request(converted, tmp_path, run):
    out = tmp_path / "copied"
    assert run("--preset", "tiny", "--set", "link=false", "capture", "import", converted, "--out", out).returncode == 0
    assert open_artifact(out).metrics["hard_linked_files"] == 0
    lights = "rig/lights.json"
    assert (out / lights).read_bytes() == (converted / lights).read_bytes()
    assert (out / lights).stat().st_ino != (converted / lights).stat().st_ino


def test_masks_declared_absent_are_not_asked_for_and_linked_folders_are_followed(converted, tmp_path, run):
    path = converted / "sequences" / "test" / "sequence.json"
    doc = json.loads(path.read_text())
    doc["streams"]["masks"] = False  # a lab sequence without subject masks
    path.write_text(json.dumps(doc))
    shutil.rmtree(converted / "sequences" / "test" / "masks")
    ego = converted / "sequences" / "test" / "ego"
    shutil.move(ego, tmp_path / "frames_elsewhere")  # a large frame folder linked in
    ego.symlink_to(tmp_path / "frames_elsewhere", target_is_directory=True)
    out = tmp_path / "capture"
    assert run("--preset", "tiny", "capture", "import", converted, "--out", out).returncode == 0
    listed = {o["path"] for o in open_artifact(out, verify=True).manifest["outputs"]}
    assert any(p.startswith("sequences/test/ego/") for p in listed)
    assert not any(p.startswith("sequences/test/masks/") for p in listed)
    inside = run("--preset", "tiny", "capture", "import", converted, "--out", converted / "imported")
    assert inside.returncode == 2 and "inside the capture folder" in inside.stderr
    assert not (converted / "imported").exists()


def _break(folder, how: str):
    if how == "artifact":
        (folder / "manifest.json").write_text("{}")
    elif how == "lights":
        (folder / "rig" / "lights.json").unlink()
    elif how == "frame":
        next((folder / "sequences" / "test" / "ego").rglob("*.png")).unlink()
    elif how == "camera":
        path = folder / "sequences" / "test" / "sequence.json"
        doc = json.loads(path.read_text())
        doc["streams"]["studio"] = [*doc["streams"]["studio"], "cam99"]
        path.write_text(json.dumps(doc))
    elif how == "no sequence":
        shutil.rmtree(folder / "sequences")
        (folder / "sequences").mkdir()


@pytest.mark.parametrize("how, message", [
    ("artifact", "already a finished artifact"), ("lights", "the rig lacks lights.json"),
    ("frame", "frame files sequence.json implies are missing"), ("camera", "studio cameras the rig lacks: cam99"),
    ("no sequence", "no sequence"),
])
def test_a_capture_the_stages_could_not_read_is_a_one_line_error(converted, tmp_path, run, how, message):
    _break(converted, how)
    result = run("--preset", "tiny", "capture", "import", converted, "--out", tmp_path / "capture")
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and message in result.stderr, result.stderr
    assert not (tmp_path / "capture").exists()
