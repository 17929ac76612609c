"""``make demo PRESET=tiny``: the whole chain on the tiny simulated subject, end to end.

One run (about 3 minutes on 2 cores) shared by the tests below: capture -> character fit ->
calibrate (the tiny headset's own calibration, down cameras included) -> egopose -> ik -> egodepth
-> animate -> geolift -> relight -> envmap -> composite -> report.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from urllib.parse import unquote

import pytest

from egorelight_cli.artifacts import open_artifact
from html_page import parse

pytestmark = pytest.mark.slow  # handed out first under pytest-xdist (conftest)

ROOT = Path(__file__).resolve().parents[1]

#: what the chain must leave, by artifact directory and kind
CHAIN = {
    "capture": "capture", "character": "character", "calibration": "calibration",
    "models/egopose": "model", "keypoints/test": "keypoints", "models/ik": "model", "motion/test": "motion",
    "models/ik_default": "model", "motion_bootstrap/ego_train": "motion", "motion_surface/ego_train": "motion",
    "motion_surface/relight_train": "motion",
    "models/egodepth": "model", "pointcloud/test": "pointcloud", "models/animate": "model",
    "meshes/test": "meshes", "models/geolift": "model", "uvmaps/test": "uvmaps", "models/relight": "model",
    "renders/test": "renders", "renders_studio/test": "renders", "renders_surface/test": "renders",
    "renders_truth/test": "renders",
    "meshes_fit/test": "meshes", "renders_fit/test": "renders", "envmap/wild": "envmap", "composite": "composite",
}


@pytest.fixture(scope="module")
def demo_subject(tmp_path_factory) -> tuple[Path, str]:
    subject = tmp_path_factory.mktemp("demo") / "subject"
    stamp = ROOT / ".venv" / ".installed-stamp"
    result = subprocess.run(["make", "-o", str(stamp), "demo", "PRESET=tiny", f"SUBJECT={subject}"], cwd=ROOT,
                            capture_output=True, text=True)
    assert result.returncode == 0, (result.stdout[-3000:], result.stderr[-3000:])
    return subject, result.stdout


def test_the_tiny_chain_writes_every_artifact_valid_and_intact(demo_subject):
    subject, _ = demo_subject
    manifests = sorted(subject.rglob("manifest.json"))
    assert {str(m.parent.relative_to(subject)) for m in manifests} >= set(CHAIN)
    for manifest in manifests:  # schema-valid, every payload's digest checked
        artifact = open_artifact(manifest)
        expected = CHAIN.get(str(manifest.parent.relative_to(subject)))
        assert expected is None or artifact.kind == expected, manifest


def test_the_tiny_headset_calibrates_all_its_cameras(demo_subject):
    subject, _ = demo_subject
    metrics = json.loads((subject / "calibration" / "manifest.json").read_text())["metrics"]
    assert metrics["uncalibrated_cameras"] == []
    assert set(metrics["handeye_residual_px"]) == {"down_left", "down_right", "front_left", "front_right"}
    # against the simulator's truth: a usable calibration, if coarser than the cpu preset's
    assert metrics["handeye_rotation_error_deg_max"] < 5.0
    assert metrics["handeye_translation_error_mm_max"] < 40.0


def test_the_ik_model_is_trained_on_the_captures_mocap(demo_subject):
    subject, _ = demo_subject
    model = json.loads((subject / "models" / "ik" / "manifest.json").read_text())["metrics"]
    assert model["source"] == "motions" and model["training_frames"] > 0
    motion = json.loads((subject / "motion" / "test" / "manifest.json").read_text())["metrics"]
    assert motion["prior"] == "motions" and motion["prior_training_frames"] == model["training_frames"]


def test_wild_scores_are_taken_in_the_trackers_own_frame(demo_subject):
    """The wild head poses live in the headset tracker's world: every geometric score of wild
    compares in that frame (before, the keypoints missed by about 1.5 m, mean pose included)."""
    subject, _ = demo_subject
    metrics = {name: json.loads((subject / name / "wild" / "manifest.json").read_text())["metrics"]
               for name in ("keypoints", "motion", "pointcloud", "meshes")}
    for name, m in metrics.items():
        assert "own world frame" in m["groundtruth_frame"], name
    assert metrics["keypoints"]["mean_pose_mpjpe_body_cm"] < 30.0
    assert metrics["pointcloud"]["depth_absrel_constant_baseline"] < 0.5
    assert metrics["meshes"]["skinning_p2s_cm"] < 50.0


def test_the_report_links_every_artifact_and_its_images_exist(demo_subject):
    subject, stdout = demo_subject
    page = subject / "report" / "index.html"
    assert str(page) in stdout  # the demo ends by saying where to look, the report first
    parser = parse(page)
    linked = {(page.parent / unquote(h)).resolve() for h in parser.hrefs if not h.startswith(("#", "http"))}
    for manifest in subject.rglob("manifest.json"):
        assert manifest.resolve() in linked, f"the report does not link {manifest.relative_to(subject)}"
    for target in linked:
        assert target.exists(), target
    for src in parser.srcs:
        assert src.startswith("data:") or (page.parent / unquote(src)).is_file(), src


def test_a_second_make_demo_finds_every_output_up_to_date(demo_subject):
    """Every stage is invoked again (the capture's manifest touched: make sees it newer than
    everything after it) and each finds its output up to date by its cache key, so nothing is
    rewritten: no key in the chain depends on anything but its inputs, config and options.
    About 25 s on 2 cores."""
    subject, _ = demo_subject
    manifests = {m: m.stat().st_mtime_ns for m in subject.rglob("manifest.json")}
    (subject / "capture" / "manifest.json").touch()
    stamp = ROOT / ".venv" / ".installed-stamp"
    result = subprocess.run(["make", "-o", str(stamp), "demo", "PRESET=tiny", f"SUBJECT={subject}"], cwd=ROOT,
                            capture_output=True, text=True)
    assert result.returncode == 0, (result.stdout[-3000:], result.stderr[-3000:])
    assert result.stderr.count("up to date") > 50 and ": wrote " not in result.stderr + result.stdout
    touched = subject / "capture" / "manifest.json"
    assert {m: t for m, t in manifests.items() if m != touched} == {
        m: m.stat().st_mtime_ns for m in subject.rglob("manifest.json") if m != touched}
