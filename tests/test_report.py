"""``egorelight report``: one HTML page for a subject directory, built from its manifests."""

from __future__ import annotations

import json
import re
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest

from egorelight_cli.artifacts import ArtifactWriter, open_artifact
from egorelight_cli.io.images import read_image, write_image
from egorelight_cli.report.metrics import baselines_of, direction, metric_rows, mpjpe_groups, runtime_row
from html_page import parse

def _write(out: Path, kind: str, stage: str, metrics: dict, inputs=(), files: dict | None = None,
           timing: dict | None = None):
    with ArtifactWriter(out, kind=kind, stage=stage, config={"seed": 0, "preset": "tiny"},
                        inputs=[open_artifact(p, verify=False) for p in inputs]) as writer:
        for name, content in (files or {}).items():
            if name.endswith(".npz"):
                writer.save_npz(name, content)
            elif isinstance(content, np.ndarray):
                write_image(writer.path(name), content)
            else:
                writer.save_json(name, content)
        writer.metrics.update(metrics)
        writer.timing.update(timing or {})
        writer.runtime.update({"device": "cpu", "threads": 2, "preset": "tiny"})
    return out


def _image(colour) -> np.ndarray:
    image = np.zeros((24, 32, 3), np.uint8)
    image[:] = colour
    return image


@pytest.fixture
def subject(tmp_path) -> Path:
    """A small fake subject: character, egopose model (curve.json, no curve.png), keypoints with a
    preview, tracked meshes and relit renders (a preview and per-frame images in a sub-folder)."""
    root = tmp_path / "subject"
    character = _write(root / "character", "character", "character", {"num_vertices": 5000},
                       files={"character.npz": {"vertices": np.zeros((4, 3), np.float32)}})
    curve = [{"step": s, "loss": 2.0 / s, "val_m": 0.5 / s ** 0.5} for s in range(1, 21)]
    model = _write(root / "models" / "egopose", "model", "egopose",
                   {"test_mpjpe_body_cm": 9.0, "test_mean_pose_mpjpe_body_cm": 10.0}, inputs=[character],
                   files={"curve.json": curve})
    keypoints = _write(root / "keypoints" / "test", "keypoints", "egopose",
                       {"mpjpe_body_cm": 8.0, "mpjpe_hands_cm": 20.0, "mean_pose_mpjpe_body_cm": 10.0,
                        "mean_pose_mpjpe_hands_cm": 15.0, "scored_frames": 26},
                       inputs=[model, character], files={"preview.png": _image((200, 30, 30))},
                       timing={"inference_ms_per_frame": 70.0})
    meshes = _write(root / "meshes" / "test", "meshes", "animate",
                    {"full_p2s_pred_to_true_cm": 1.5, "no_depth_p2s_pred_to_true_cm": 1.7,
                     "skinning_p2s_pred_to_true_cm": 1.4}, inputs=[keypoints], files={"preview.png": _image((0, 0, 200))})
    _write(root / "renders" / "test", "renders", "relight",
           {"psnr": 30.0, "lambert_psnr": 25.0, "baked_psnr": 31.0, "lpips": None,
            "lpips_fid": "need pretrained weights: not scored"}, inputs=[meshes],
           files={"preview.png": _image((30, 200, 30)), "cam_07/000010.png": _image((9, 9, 9)),
                  "cam_07/000011.png": _image((9, 9, 9))})
    return root


def _row(html: str, key: str) -> str:
    match = re.search(rf"<tr><td[^>]*>{re.escape(key)}</td>.*?</tr>", html)
    assert match, f"no metric row {key}"
    return match.group(0)


def test_report_parses_and_every_image_and_link_exists(subject, run):
    result = run("report", subject)
    assert result.returncode == 0, result.stderr
    page = subject / "report" / "index.html"
    assert result.stdout.strip() == str(page)
    parser = parse(page)
    assert parser.srcs, "no images on the page"
    for src in parser.srcs:
        target = (page.parent / unquote(src)).resolve()
        assert target.is_file(), src
        assert page.parent.resolve() in target.parents, f"image outside the report folder: {src}"
        assert read_image(target).ndim == 3
    for href in parser.hrefs:
        if href.startswith("#"):
            assert href[1:] in parser.ids, href
        else:
            assert (page.parent / unquote(href)).exists(), href
    assert len(parser.ids) == len(set(parser.ids)), "duplicate ids"
    html = page.read_text()
    # the keypoints preview and the renders preview are shown; per-frame renders are only counted
    assert sum("keypoints-test-preview" in s for s in parser.srcs) == 1
    assert any("renders-test-preview" in s for s in parser.srcs)
    assert not any("cam_07" in s for s in parser.srcs) and "2 more images" in html
    assert "relit vs truth" in html
    # inputs link to the artifacts' sections
    assert '<a href="#a-models-egopose">models/egopose</a>' in html


def test_report_pairs_metrics_with_baselines_and_paper(subject, run):
    assert run("report", subject).returncode == 0
    html = (subject / "report" / "index.html").read_text()
    body = _row(html, "mpjpe_body_cm")
    assert "mean pose 10" in body and 'class="num better"' in body and "4.11" in body
    hands = _row(html, "mpjpe_hands_cm")
    assert "mean pose 15" in hands and 'class="num worse"' in hands and "4.71" in hands
    assert "mean_pose_mpjpe_body_cm" not in re.findall(r"<tr><td[^>]*>([^<]+)</td>", html)
    psnr = _row(html, "psnr")
    assert re.search(r'class="better"[^>]*>Lambert 25<', psnr) and re.search(r'class="worse"[^>]*>baked texture 31<', psnr)
    assert 'class="num mixed"' in psnr and "34.81" in psnr
    p2s = _row(html, "full_p2s_pred_to_true_cm")
    assert "no depth 1.7" in p2s and "skinning only 1.4" in p2s and "1.23" in p2s
    assert "need pretrained weights: not scored" in html
    # MPJPE per joint group as a bar chart with the paper's bars, and the runtime next to the paper's
    assert "MPJPE per joint group (all frames)" in html and "paper (real data) body: 4.11" in html
    assert "runtime: 70 ms/frame here (cpu) vs 17.62 ms/frame in the paper (network inference" in html


def test_report_lists_missing_stages_and_plots_curves(subject, run):
    assert run("report", subject).returncode == 0
    page = subject / "report" / "index.html"
    html = page.read_text()
    for stage in ("synth", "calibrate", "ik", "egodepth", "geolift", "envmap", "composite"):
        section = re.search(rf'<section id="{stage}">.*?</section>', html, re.S).group(0)
        assert "not run" in section, stage
    for stage in ("egopose", "animate", "relight"):
        section = re.search(rf'<section id="{stage}">.*?</section>', html, re.S).group(0)
        assert "not run" not in section, stage
    # the model has curve.json and no curve.png: the report plots it and lists first/last values
    curve = [s for s in parse(page).srcs if "models-egopose-curve" in s]
    assert len(curve) == 1 and read_image(page.parent / unquote(curve[0])).shape[:2] == (400, 640)
    assert re.search(r"<td>loss</td><td class=\"num\">2</td><td class=\"num\">0.1</td>", html)
    # the section order follows the pipeline DAG
    order = [m for m in re.findall(r'<section id="([a-z]+)">', html)]
    assert order.index("egopose") < order.index("ik") < order.index("animate") < order.index("relight")


def test_report_rewrites_atomically_and_elsewhere(subject, tmp_path, run):
    assert run("report", subject).returncode == 0
    assert run("report", subject).returncode == 0  # replaces the previous report, not read as an artifact
    assert not [p for p in (subject).iterdir() if p.name.startswith(".report")]
    html = (subject / "report" / "index.html").read_text()
    assert html.count('class="artifact"') == 5
    elsewhere = tmp_path / "copies" / "my report"
    result = run("report", subject, "--out", elsewhere)
    assert result.returncode == 0 and result.stdout.strip() == str(elsewhere / "index.html")
    parser = parse(elsewhere / "index.html")
    for link in parser.hrefs + parser.srcs:
        if not link.startswith("#"):
            assert (elsewhere / unquote(link)).exists(), link
    # a folder that holds anything else is not replaced (it used to be emptied): the user's files,
    # an artifact, the subject's own parent
    theirs = tmp_path / "theirs"
    (theirs / "docs").mkdir(parents=True)
    (theirs / "docs" / "thesis.tex").write_text("x")
    for folder in (theirs, subject / "keypoints" / "test", subject, subject.parent):
        before = sorted(str(p) for p in folder.rglob("*"))
        result = run("report", subject, "--out", folder)
        assert result.returncode == 2 and "not a report folder" in result.stderr, (folder, result.stderr)
        assert result.stderr.count("\n") == 1 and sorted(str(p) for p in folder.rglob("*")) == before
    (tmp_path / "empty_folder").mkdir()
    assert run("report", subject, "--out", tmp_path / "empty_folder").returncode == 0  # empty: fine


def test_report_shows_a_broken_artifact_instead_of_failing(subject, run):
    broken = subject / "motion" / "test"
    broken.mkdir(parents=True)
    (broken / "manifest.json").write_text("{not json")
    (subject / "keypoints" / "test" / "preview.png").unlink()
    result = run("report", subject)
    assert result.returncode == 0, result.stderr
    html = (subject / "report" / "index.html").read_text()
    assert "unreadable manifest" in html and "1 payload file(s) missing, e.g. preview.png" in html
    parse(subject / "report" / "index.html")


def test_report_bad_input_is_one_line_exit_2(tmp_path, run):
    result = run("report", tmp_path / "nowhere")
    assert result.returncode == 2 and result.stderr.startswith("egorelight: error: not a subject directory")
    assert result.stderr.count("\n") == 1
    empty = tmp_path / "empty"
    (empty / "capture").mkdir(parents=True)
    result = run("report", empty)
    assert result.returncode == 2 and "no egorelight artifacts" in result.stderr and result.stderr.count("\n") == 1
    assert not (empty / "report").exists() and not [p for p in empty.iterdir() if p.name.startswith(".")]
    afile = tmp_path / "file.txt"
    afile.write_text("x")
    result = run("report", afile)
    assert result.returncode == 2 and "not a subject directory" in result.stderr


def test_metric_pairing_conventions():
    flat = {"normal_deg": 10.0, "normal_deg_coarse": 12.0, "texture_l1": 0.1, "texture_l1_mean_texture": 0.05,
            "depth_absrel": 0.2, "sgbm_depth_absrel": 0.05, "depth_absrel_constant_baseline": 0.4,
            "val_psnr": 20.0, "val_lambert_psnr": 18.0, "full_p2s_cm": 1.0, "skinning_p2s_cm": 1.2,
            "test_mpjpe_all_cm": 5.0, "test_mean_pose_mpjpe_all_cm": 6.0, "frames": 10}
    assert baselines_of("normal_deg", flat) == [("coarse mesh normal", "normal_deg_coarse")]
    assert baselines_of("texture_l1", flat) == [("mean texture", "texture_l1_mean_texture")]
    assert baselines_of("depth_absrel", flat) == [("SGBM stereo", "sgbm_depth_absrel"),
                                                  ("constant depth", "depth_absrel_constant_baseline")]
    assert baselines_of("val_psnr", flat) == [("Lambert", "val_lambert_psnr")]
    assert baselines_of("full_p2s_cm", flat) == [("skinning only", "skinning_p2s_cm")]
    assert baselines_of("test_mpjpe_all_cm", flat) == [("mean pose", "test_mean_pose_mpjpe_all_cm")]
    assert baselines_of("sgbm_depth_absrel", flat) == [] and baselines_of("frames", flat) == []
    parts = {"parts.pants.psnr": 19.0, "parts.pants.lambert_psnr": 18.0, "parts.pants.olat_tail_psnr": 15.0,
             "parts.pants.olat_tail_diffuse_only_psnr": 16.0, "lambert_psnr": 17.0}
    assert baselines_of("parts.pants.psnr", parts) == [("Lambert", "parts.pants.lambert_psnr")]
    assert baselines_of("parts.pants.olat_tail_psnr", parts) == [("diffuse only", "parts.pants.olat_tail_diffuse_only_psnr")]
    assert baselines_of("parts.pants.lambert_psnr", parts) == []
    assert direction("val_psnr") == 1 and direction("normal_deg") == -1 and direction("frames") == 0
    rows = {r.key: r for r in metric_rows("uvmaps", flat)}
    assert "normal_deg_coarse" not in rows and "sgbm_depth_absrel" not in rows
    assert rows["normal_deg"].comparisons[0].better is True and rows["texture_l1"].comparisons[0].better is False
    assert [c.better for c in rows["depth_absrel"].comparisons] == [False, True]
    nested = {r.key for r in metric_rows("calibration", {"head_pose": {"test": {"valid_fraction": 0.9}}})}
    assert nested == {"head_pose.test.valid_fraction"}


def test_mpjpe_groups_for_bar_charts():
    charts = mpjpe_groups("model", {"test_mpjpe_body_cm": 9.0, "test_mpjpe_hands_cm": 12.0,
                                    "test_mean_pose_mpjpe_body_cm": 10.0, "train_mpjpe_all_cm": 3.0,
                                    "mpjpe_input_body_cm": 1.0, "frames": 3})
    assert charts["test"] == {"ours": {"body": 9.0, "hands": 12.0}, "mean pose": {"body": 10.0},
                              "paper (real data)": {"body": 4.11, "hands": 4.71}}
    assert charts["train"] == {"ours": {"all": 3.0}}
    assert charts["all frames"] == {"input": {"body": 1.0}}
    assert json.dumps(charts)  # plain data


def test_runtime_next_to_the_papers():
    assert runtime_row("animate", {"timing": {"frames_per_s": 50.0}})[:2] == (20.0, 21.50)
    ours, paper, what = runtime_row("relight", {"timing": {"wall_s": 10.0}, "metrics": {"views": 50}})
    assert (ours, paper) == (200.0, 100.19) and "loading included" in what
    assert runtime_row("relight", {"timing": {"wall_s": 10.0}, "metrics": {}}) is None
    assert runtime_row("character", {"timing": {"wall_s": 1.0}}) is None


def test_metric_table_lists_each_artifact_and_key(tmp_path):
    from egorelight_cli.report.table import metric_table

    paths = []
    for name, metrics in (("rays2", {"psnr": 15.234, "ssim": 24.9}), ("noattention", {"psnr": 14.0, "ssim": None})):
        (tmp_path / name).mkdir()
        paths.append(tmp_path / name / "manifest.json")
        paths[-1].write_text(json.dumps({"metrics": metrics}))
    lines = metric_table(paths, ["psnr", "ssim", "fid"]).splitlines()
    assert lines[0].split() == ["artifact", "psnr", "ssim", "fid"]
    assert lines[1].split() == ["rays2", "15.23", "24.90", "-"]
    assert lines[2].split() == ["noattention", "14.00", "-", "-"]
