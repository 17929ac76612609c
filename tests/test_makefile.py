"""The Makefile's DAG, checked with ``make -n`` (nothing runs)."""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _dry_run(tmp_path, *targets) -> str:
    stamp = ROOT / ".venv" / ".installed-stamp"
    result = subprocess.run(["make", "-n", "-o", str(stamp), f"SUBJECT={tmp_path}", *targets], cwd=ROOT,
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_the_demo_relights_test_on_tracked_studio_surface_and_true_keypoint_meshes(tmp_path):
    out = _dry_run(tmp_path, "subject")
    assert f"--out {tmp_path}/renders/test" in out
    assert f"--out {tmp_path}/renders_studio/test" in out
    assert f"--meshes {tmp_path}/meshes_student/test --uvmaps {tmp_path}/uvmaps_student/test" in out
    # the truth row is made only where the capture has ground truth (known after synth ran)
    assert f"groundtruth/test/keypoints.npz ]; then" in out and "renders_truth/test/manifest.json" in out
    truth = _dry_run(tmp_path, f"{tmp_path}/renders_truth/test/manifest.json")
    assert f"ik --in {tmp_path}/capture/groundtruth/test/keypoints.npz" in truth
    assert f"animate --no-depth --motion {tmp_path}/motion_truth/test" in truth
    # the surface-tracked row only where the sequence has reconstructions
    assert f"capture/sequences/test/recon ]; then" in out and "renders_surface/test/manifest.json" in out
    surface = _dry_run(tmp_path, f"{tmp_path}/renders_surface/test/manifest.json")
    line = next(line for line in surface.splitlines() if f"--out {tmp_path}/meshes_surface/test" in line)
    assert f"animate --no-depth --motion {tmp_path}/motion_surface/test" in line
    assert f"--fit-recon {tmp_path}/capture --seq test" in surface
    assert f"--meshes {tmp_path}/meshes_surface/test --uvmaps {tmp_path}/uvmaps_surface/test" in surface
    # the row on meshes fitted to the true surface, likewise only with a true surface
    assert f"groundtruth/test/meshes.npz ]; then" in out and "renders_fit/test/manifest.json" in out
    fit = _dry_run(tmp_path, f"{tmp_path}/renders_fit/test/manifest.json")
    line = next(line for line in fit.splitlines() if f"--out {tmp_path}/meshes_fit/test" in line)
    assert f"--motion {tmp_path}/motion_truth/test" in line and line.rstrip().endswith("--fit-truth")
    assert f"--meshes {tmp_path}/meshes_fit/test --uvmaps {tmp_path}/uvmaps_fit/test" in fit


def test_relight_ablation_trains_each_variant_and_prints_one_table(tmp_path):
    out = _dry_run(tmp_path, "relight-ablation")
    for option, name in (("net.rays=2", "rays2"), ("net.rays=8", "rays8"), ("net.rays=32", "rays32"),
                         ("net.attention=false", "noattention")):
        assert f"--set {option} " in out and f"--out {tmp_path}/models/relight_{name}" in out
        assert f"relight_{name} --character" in out.replace("  ", " ")
    table = next(line for line in out.splitlines() if "egorelight_cli.report.table" in line)
    assert table.count("manifest.json") == 5


def test_learning_curves_train_one_model_per_frame_count_and_print_tables(tmp_path):
    out = _dry_run(tmp_path, "CURVE_FRAMES=4 0", "egopose-curve", "egodepth-curve")
    for n in ("4", "0"):
        assert f"train egopose --capture {tmp_path}/capture --calibration {tmp_path}/calibration " \
               f"--set train.max_frames={n} --set evaluate_sequence=test" in out
        assert f"--set train.max_frames={n} --out {tmp_path}/curves/egodepth_model/{n}" in out
        assert f"--model {tmp_path}/curves/egodepth_model/{n} --method net --seq test" in out
    tables = [line for line in out.splitlines() if "egorelight_cli.report.table" in line]
    assert len(tables) == 2 and all(t.count("manifest.json") == 2 for t in tables)
    assert "test_mean_pose_mpjpe_body_cm" in tables[0] and "sgbm_point_to_surface_cm" in tables[1]


def test_sharded_stages_run_as_shards_and_merge(tmp_path):
    out = _dry_run(tmp_path, "SHARDS=3", f"{tmp_path}/renders/test/manifest.json")
    for folder, command in (("keypoints", "egopose"), ("pointcloud", "egodepth"), ("uvmaps", "geolift"),
                            ("renders", "relight")):
        for i in range(3):
            line = next(line for line in out.splitlines() if f"--out {tmp_path}/shards/{folder}/test/{i}of3" in line)
            assert f" {command} " in line and f"--shard {i}/3" in line
        merge = next(line for line in out.splitlines() if f"merge {tmp_path}/shards/{folder}/test/0of3" in line)
        assert merge.endswith(f"--out {tmp_path}/{folder}/test")
        assert out.index(f"--out {tmp_path}/shards/{folder}/test/2of3") < out.index(merge)
    assert "--shard" not in _dry_run(tmp_path, f"{tmp_path}/renders/test/manifest.json")  # SHARDS=1: one run


def test_slurm_mode_runs_every_stage_command_through_srun(tmp_path):
    out = _dry_run(tmp_path, "SCHEDULER=slurm", "SHARDS=2", "THREADS=8", f"{tmp_path}/keypoints/test/manifest.json")
    commands = [line for line in out.splitlines() if "bin/egorelight" in line]
    assert commands and all(line.startswith("srun --ntasks=1 --cpus-per-task=8 --job-name=egorelight ")
                            for line in commands)
    assert sum("--shard" in line for line in commands) == 2


def test_synth_runs_alone_and_takes_every_core_under_make_j(tmp_path):
    import os

    def synth_line(*args):
        return next(line for line in _dry_run(tmp_path, *args, f"{tmp_path}/character/manifest.json").splitlines()
                    if " synth " in line)

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    nproc = subprocess.run(["nproc"], capture_output=True, text=True).stdout.strip() or str(cores)
    assert f"--threads {nproc} synth" in synth_line("-j2")
    assert "--threads 3 synth" in synth_line("-j2", "THREADS=3")  # a thread count given is kept
    assert "--threads" not in synth_line()  # no -j: every core it may anyway
    # the stages after it keep their share
    assert "--threads 1 character" in _dry_run(tmp_path, "-j2", "THREADS=1", f"{tmp_path}/character/manifest.json")


def _commands(out: str) -> list[str]:
    """``make -n`` output as one line per command (continuation lines joined, blanks squeezed)."""
    return [" ".join(line.split()) for line in out.replace("\\\n", " ").splitlines()]


def test_animate_trains_on_the_estimated_motion_the_mocap_and_the_mocap_fitted_to_the_surface(tmp_path):
    out = _commands(_dry_run(tmp_path, f"{tmp_path}/models/animate/manifest.json"))
    train = next(line for line in out if " train animate " in line)
    assert (f"--motion {tmp_path}/motion/ego_train --motion {tmp_path}/motion_mocap/ego_train "
            f"--motion {tmp_path}/motion_surface/ego_train") in train
    assert any(f"ik --in {tmp_path}/keypoints/ego_train " in line for line in out)  # egopose -> ik on it
    surface = next(line for line in out if f"--out {tmp_path}/motion_surface/ego_train" in line)
    assert f"ik --in {tmp_path}/capture/sequences/ego_train/mocap.npz " in surface
    assert surface.rstrip().endswith(f"--fit-recon {tmp_path}/capture --seq ego_train")
    alone = _dry_run(tmp_path, "ANIMATE_TRAIN_MOTIONS=motion", f"{tmp_path}/models/animate/manifest.json")
    train = next(line for line in _commands(alone) if " train animate " in line)
    assert f"--motion {tmp_path}/motion/ego_train " in train and "motion_mocap" not in train


def test_the_student_is_fine_tuned_on_the_mocap_and_the_mocap_fitted_to_the_surface(tmp_path):
    out = _commands(_dry_run(tmp_path, f"{tmp_path}/models/animate_student/manifest.json"))
    train = next(line for line in out if " train animate --no-depth " in line)
    assert (f"--init {tmp_path}/models/animate " in train and "--seq relight_train "
            f"--motion {tmp_path}/motion_mocap/relight_train --motion {tmp_path}/motion_surface/relight_train " in train)
    surface = next(line for line in out if f"--out {tmp_path}/motion_surface/relight_train" in line)
    assert surface.rstrip().endswith(f"--fit-recon {tmp_path}/capture --seq relight_train")
    alone = _dry_run(tmp_path, "ANIMATE_STUDENT_MOTIONS=motion_mocap", f"{tmp_path}/models/animate_student/manifest.json")
    train = next(line for line in _commands(alone) if " train animate --no-depth " in line)
    assert "motion_surface/relight_train" not in train


def test_geolift_trains_on_the_student_meshes_refined_onto_the_reconstruction(tmp_path):
    out = _dry_run(tmp_path, f"{tmp_path}/models/geolift/manifest.json")
    for seq in ("relight_train", "ego_train"):
        line = next(line for line in out.splitlines() if f"--out {tmp_path}/meshes_recon/{seq}" in line)
        assert f"--motion {tmp_path}/motion_mocap/{seq}" in line and line.rstrip().endswith("--fit-recon")
        assert f"--meshes {tmp_path}/meshes_recon/{seq} --seq {seq}" in out
    # relight keeps training on the student's own meshes
    relight = _dry_run(tmp_path, f"{tmp_path}/models/relight/manifest.json")
    assert f"--meshes {tmp_path}/meshes_student/relight_train --uvmaps {tmp_path}/uvmaps_student/relight_train" \
        in relight
