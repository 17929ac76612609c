"""``egorelight train animate`` and ``egorelight animate`` on the tiny capture.

The point clouds here are built from the ground truth (ray cast from the down cameras with the
oracle calibration, plus noise) by the evaluation helper, standing in for ``egodepth``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from egorelight_cli.io.motion import Motion, read_motion_npz, write_motion_npz


pytestmark = pytest.mark.slow  # handed out first under pytest-xdist (conftest)

def _metrics(artifact: Path) -> dict:
    return json.loads((artifact / "manifest.json").read_text())["metrics"]


@pytest.fixture(scope="module")
def animate_inputs(tiny_capture, tmp_path_factory):
    """GT-derived motion subsets and point clouds, and a model trained on ego_train (tiny preset)."""
    from egorelight_cli.io.pointcloud import write_pointcloud_npz
    from egorelight_cli.stages.animate_eval import groundtruth_pointcloud

    root = tmp_path_factory.mktemp("animate")
    gt = Path(tiny_capture) / "groundtruth"
    for seq in ("ego_train", "test"):
        write_pointcloud_npz(root / f"{seq}_cloud.npz", groundtruth_pointcloud(tiny_capture, seq, stride=2),
                             source="ground truth (test)")
    motion = read_motion_npz(gt / "test" / "motion.npz")
    keep = motion.frame_ids >= motion.frame_ids.max() - 3  # the content frames and one before
    write_motion_npz(root / "test_motion.npz", Motion(motion.theta[keep], motion.dof_names, motion.frame_ids[keep],
                                                      motion.fps))
    model = root / "model"
    with pytest.raises(SystemExit) as exit_info:
        from egorelight_cli.cli import main

        main(["--preset", "tiny", "-q", "train", "animate", "--capture", str(tiny_capture), "--motion",
              str(gt / "ego_train" / "motion.npz"), "--pointcloud", str(root / "ego_train_cloud.npz"), "--out",
              str(model)])
    assert exit_info.value.code in (0, None)
    return {"root": root, "model": model, "motion": root / "test_motion.npz", "cloud": root / "test_cloud.npz",
            "capture": Path(tiny_capture)}


@pytest.fixture(scope="module")
def retopologized_capture(tiny_capture, tmp_path_factory) -> Path:
    """The tiny capture with a true surface of another topology (:mod:`retopologize`)."""
    from retopologize import subdivided_truth_capture

    return subdivided_truth_capture(tiny_capture, tmp_path_factory.mktemp("retopologized") / "capture")


def _run(*args):
    from egorelight_cli.cli import main

    try:
        main([str(a) for a in args])
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def test_training_a_few_steps_lowers_the_chamfer_loss(animate_inputs):
    metrics = _metrics(animate_inputs["model"])
    assert metrics["training_frames"] == 3 and metrics["frames_with_cloud"] == 9
    assert metrics["train_chamfer_cm_after"] < metrics["train_chamfer_cm_before"]
    assert (animate_inputs["model"] / "model.pt").is_file() and (animate_inputs["model"] / "curve.png").is_file()


def test_validation_frames_are_set_aside_and_the_best_weights_kept(animate_inputs):
    """train.validation_frames: frames never trained on, scored from step 0 on; the model keeps the
    weights that scored best there (never worse than the untrained, skinning-like start)."""
    from egorelight_cli.io.model import read_model

    gt = animate_inputs["capture"] / "groundtruth"
    base = ("--preset", "tiny", "-q", "--set", "train.steps=6", "--set", "train.validate_every=2")
    args = ("train", "animate", "--capture", animate_inputs["capture"], "--motion", gt / "ego_train" / "motion.npz",
            "--pointcloud", animate_inputs["root"] / "ego_train_cloud.npz")
    out = animate_inputs["root"] / "model_validated"
    assert _run(*base, "--set", "train.validation_frames=1", *args, "--out", out) == 0
    m = _metrics(out)
    assert m["validation_frames"] == 1 and m["training_frames"] == 2 and m["validation_samples"] == 1
    extra = read_model(out, stage="animate").extra
    assert len(extra["validation_frames"]) == 1 and not set(extra["validation_frames"]) & set(extra["frames"])
    # the manifest's best is the lowest of the scores the curve recorded (step 0: the start), at its step
    curve = json.loads((out / "curve.json").read_text())
    scored = [(0, m["validation_chamfer_cm_start"])] + [(r["step"], r["validation"]) for r in curve if "validation" in r]
    assert [step for step, _ in scored] == [0, 2, 4, 6]
    best_step, best = min(scored, key=lambda s: (s[1], s[0]))
    assert m["best_step"] == best_step and m["validation_chamfer_cm_best"] == pytest.approx(best, rel=1e-12)
    # three frames cannot spare two: no validation, every frame trains, said in the manifest
    out = animate_inputs["root"] / "model_unvalidated"
    assert _run(*base, "--set", "train.validation_frames=2", *args, "--out", out) == 0
    m = _metrics(out)
    assert m["validation_frames"] == 0 and m["validation_samples"] == 0 and m["training_frames"] == 3


def test_a_motion_artifact_and_its_copy_train_as_two_motions(animate_inputs, tmp_path):
    """Two --motion artifacts with the same content at two paths (a copy) are two inputs, each
    in the cache key (was an internal error: the second did not enter the key)."""
    import shutil

    from egorelight_cli.artifacts import ArtifactWriter
    from egorelight_cli.io.motion import save_motion

    with ArtifactWriter(tmp_path / "motion", kind="motion", stage="ik", config={}) as writer:
        save_motion(writer, read_motion_npz(animate_inputs["capture"] / "groundtruth" / "ego_train" / "motion.npz"))
    shutil.copytree(tmp_path / "motion", tmp_path / "copy")
    out = tmp_path / "model"
    assert _run("--preset", "tiny", "-q", "--set", "train.steps=2", "train", "animate", "--capture",
                animate_inputs["capture"], "--motion", tmp_path / "motion", "--motion", tmp_path / "copy",
                "--pointcloud", animate_inputs["root"] / "ego_train_cloud.npz", "--out", out) == 0
    m = _metrics(out)
    assert m["training_motions"] == 2 and m["training_frames"] == 6
    inputs = json.loads((out / "manifest.json").read_text())["inputs"]
    assert {Path(i["path"]).name for i in inputs if i["kind"].endswith("/motion")} == {"motion", "copy"}


def _motion_off_by(source: Path, out: Path, sigma_m: float, seed: int) -> Path:
    """``source`` with its root translation off by N(0, sigma_m) per axis and frame (a stand-in for
    a headset estimate: the tiny capture has too few frames to train egopose)."""
    motion = read_motion_npz(source)
    theta = motion.theta.copy()
    theta[:, :3] += np.random.default_rng(seed).normal(0.0, sigma_m, (len(theta), 3))
    write_motion_npz(out, Motion(theta, motion.dof_names, motion.frame_ids, motion.fps))
    return out


def test_trained_under_a_motion_that_is_off_the_depth_corrects_held_out_frames(animate_inputs):
    """Issue 21 item 4 on tiny: trained on ego_train under four copies of its true motion, each with
    the root 2 cm off per axis (repeatable --motion), the network scores test's frames (another
    draw of the error) better with the depth than without, and better than skinning."""
    gt = animate_inputs["capture"] / "groundtruth"
    root = animate_inputs["root"]
    motions = [_motion_off_by(gt / "ego_train" / "motion.npz", root / f"ego_train_off_{i}.npz", 0.02, i)
               for i in range(4)]
    model = root / "model_off"
    code = _run("--preset", "tiny", "-q", "--set", "train.steps=400", "train", "animate", "--capture",
                animate_inputs["capture"], *[a for m in motions for a in ("--motion", m)], "--pointcloud",
                root / "ego_train_cloud.npz", "--out", model)
    assert code == 0
    trained = _metrics(model)
    assert trained["training_frames"] == 4 * 3 and trained["training_motions"] == 4
    sources = {Path(s["path"]).name for s in json.loads((model / "manifest.json").read_text())["sources"]}
    assert {m.name for m in motions} <= sources
    test_motion = _motion_off_by(gt / "test" / "motion.npz", root / "test_off.npz", 0.02, 10)
    out = root / "meshes_off"
    code = _run("--preset", "tiny", "-q", "animate", "--motion", test_motion, "--pointcloud", animate_inputs["cloud"],
                "--model", model, "--capture", animate_inputs["capture"], "--out", out)
    assert code == 0
    m = _metrics(out)
    # measured full / no depth / skinning at 400 steps: 1.74 / 2.02 / 3.14 cm (full body), 2.52 / 2.84 / 3.57
    # (ego-visible); 600 steps: 1.67 / 1.97 / 3.14 and 2.42 / 2.75 / 3.57 for 1.5x the time (CI budget); without
    # the node skip the ego-visible pair was 2.71 / 2.73
    for region in ("", "ego_visible_"):
        full, blind, skinning = (m[f"{v}_p2s_{region}pred_to_true_cm"] for v in ("full", "no_depth", "skinning"))
        assert full < 0.97 * blind and blind < 0.9 * skinning, (region, full, blind, skinning)


@pytest.fixture(scope="module")
def animated(animate_inputs) -> Path:
    """``animate`` of the test motion with the tiny capture's ground truth (scored), PLY export."""
    out = animate_inputs["root"] / "meshes"
    code = _run("--preset", "tiny", "-q", "animate", "--motion", animate_inputs["motion"], "--pointcloud",
                animate_inputs["cloud"], "--model", animate_inputs["model"], "--capture", animate_inputs["capture"],
                "--export", "ply", "--out", out)
    assert code == 0
    return out


def test_animate_writes_meshes_metrics_preview_and_export(animated, character):
    from egorelight_cli.io.mesh_sequence import load_meshes
    from egorelight_cli.stages.animate_eval import SCORED

    out = animated
    meshes, artifact = load_meshes(out)
    assert artifact is not None and artifact.kind == "meshes"
    T = meshes.num_frames
    assert T == 4 and meshes.vertices.shape == (T, character.num_vertices, 3)
    assert meshes.eg_rotation.shape == (T, character.graph.num_nodes, 3) and meshes.offsets.shape == meshes.vertices.shape
    metrics = _metrics(out)
    # a sanity range: the simulated subject is not the character (issue 15), a tiny model is far off
    for variant in ("skinning", "no_depth", "full"):
        for measure in SCORED:
            value = metrics[f"{variant}_p2s_{measure}_cm"]
            assert np.isfinite(value) and 0 <= value < 8.0, (variant, measure, value)
        assert metrics[f"{variant}_p2s_cm"] == metrics[f"{variant}_p2s_pred_to_true_cm"]
        assert metrics[f"{variant}_p2s_ego_visible_cm"] == metrics[f"{variant}_p2s_ego_visible_pred_to_true_cm"]
    for key in [f"p2s_{measure}_cm" for measure in SCORED] + ["p2s_cm", "p2s_ego_visible_cm"]:
        assert metrics[key] == metrics[f"full_{key}"]
    assert metrics["eval_frames"] == 4 and 0.05 < metrics["ego_visible_true_area_fraction"] < 0.6
    assert metrics["xi_vertices_per_frame"] > 200  # the GT cloud explains many template vertices
    assert (out / "preview.png").is_file()
    assert sorted(p.name for p in (out / "export").iterdir()) == [f"{int(f):06d}.ply" for f in meshes.frame_ids]


def test_animate_scores_against_a_truth_of_another_topology(animate_inputs, animated, retopologized_capture):
    out = animate_inputs["root"] / "meshes_retopologized"
    code = _run("--preset", "tiny", "-q", "animate", "--motion", animate_inputs["motion"], "--pointcloud",
                animate_inputs["cloud"], "--model", animate_inputs["model"], "--capture", retopologized_capture,
                "--out", out)
    assert code == 0
    metrics, reference = _metrics(out), _metrics(animated)
    assert metrics["eval_frames"] == reference["eval_frames"] == 4
    # the subdivided truth is the same surface: the same distances, whatever its tessellation
    for variant in ("skinning", "no_depth", "full"):
        for direction, tolerance in (("pred_to_true", 0.01), ("true_to_pred", 0.02)):
            for region in ("", "ego_visible_"):
                key = f"{variant}_p2s_{region}{direction}_cm"
                assert metrics[key] == pytest.approx(reference[key], abs=tolerance), key
    assert metrics["ego_visible_true_area_fraction"] == pytest.approx(reference["ego_visible_true_area_fraction"],
                                                                      abs=0.02)


def test_no_depth_ablation_needs_no_cloud(animate_inputs):
    out = animate_inputs["root"] / "meshes_nodepth.npz"
    code = _run("--preset", "tiny", "-q", "animate", "--motion", animate_inputs["motion"], "--model",
                animate_inputs["model"], "--no-depth", "--out", out)
    assert code == 0
    from egorelight_cli.io.mesh_sequence import load_meshes

    meshes, _ = load_meshes(out)
    assert meshes.num_frames == 4


def test_depth_agnostic_student_fine_tunes_on_flat_lit_relight_frames(animate_inputs):
    gt = animate_inputs["capture"] / "groundtruth"
    out = animate_inputs["root"] / "student"
    # a run from a model takes train.finetune_steps (the cpu preset: 300 of 3000), not train.steps
    code = _run("--preset", "tiny", "-q", "--set", "train.steps=500", "--set", "train.finetune_steps=2", "train",
                "animate", "--capture", animate_inputs["capture"], "--seq", "relight_train", "--motion",
                gt / "relight_train" / "motion.npz", "--no-depth", "--init", animate_inputs["model"], "--out", out)
    assert code == 0
    metrics = _metrics(out)
    assert metrics["steps"] == 2 and len(json.loads((out / "curve.json").read_text())) <= 2
    assert _metrics(animate_inputs["model"])["steps"] == 6  # the tiny preset's train.steps, no --init
    assert metrics["no_depth"] is True
    assert metrics["training_frames"] == 2  # frames 0 and 2 are flat-lit, 1 and 3 env-lit
    # the student drives meshes_student/relight_train, scored on a sequence without the HMD
    meshes = animate_inputs["root"] / "meshes_student"
    code = _run("--preset", "tiny", "-q", "animate", "--no-depth", "--motion", gt / "relight_train" / "motion.npz",
                "--model", out, "--capture", animate_inputs["capture"], "--seq", "relight_train", "--out", meshes)
    assert code == 0
    scores = _metrics(meshes)
    assert scores["no_depth_p2s_cm"] < 5.0 and scores["no_depth_p2s_true_to_pred_cm"] < 5.0
    for key in ("p2s_ego_visible_cm", "p2s_ego_visible_pred_to_true_cm", "p2s_ego_visible_true_to_pred_cm"):
        assert scores[key] is None  # no ego view: NaN -> null


def _one_line_error(capsys, code: int, *fragments: str) -> None:
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("egorelight: error: "), err
    for fragment in fragments:
        assert fragment in err[0], err


def test_bad_inputs_give_one_line_errors(animate_inputs, tmp_path, capsys):
    base = ("--preset", "tiny", "animate", "--motion", animate_inputs["motion"], "--model", animate_inputs["model"])
    capsys.readouterr()
    _one_line_error(capsys, _run(*base, "--out", tmp_path / "a"), "point cloud is required")
    _one_line_error(capsys, _run("--preset", "tiny", "animate", "--motion", animate_inputs["motion"], "--model",
                                 animate_inputs["motion"], "--no-depth", "--out", tmp_path / "b"))
    # a cloud that shares no frame with the motion
    from egorelight_cli.io.pointcloud import PointCloudSequence, write_pointcloud_npz

    write_pointcloud_npz(tmp_path / "late.npz", PointCloudSequence(np.zeros((1, 4, 3)), np.zeros((1, 4, 3)),
                                                                    np.zeros((1, 4), bool), np.array([999])))
    _one_line_error(capsys, _run(*base, "--pointcloud", tmp_path / "late.npz", "--out", tmp_path / "c"),
                    "share no frame")
    _one_line_error(capsys, _run("--preset", "tiny", "animate", "--motion", tmp_path / "missing.npz", "--model",
                                 animate_inputs["model"], "--no-depth", "--out", tmp_path / "d"), "not found")
    # --no-depth reads no cloud: one given is refused (was an internal error), nothing written
    _one_line_error(capsys, _run(*base, "--no-depth", "--pointcloud", tmp_path / "late.npz", "--out", tmp_path / "e"),
                    "--no-depth reads no point cloud", "late.npz")
    assert not (tmp_path / "e").exists()
    # a sequence the capture lacks (a typo) is an error, not a run without ground truth
    _one_line_error(capsys, _run(*base, "--pointcloud", animate_inputs["cloud"], "--capture", animate_inputs["capture"],
                                 "--seq", "tset", "--out", tmp_path / "f"), "no sequence 'tset'")
    assert not (tmp_path / "f").exists()
