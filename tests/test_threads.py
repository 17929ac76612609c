"""Thread control (issue 23): the cores a run may use, ``--threads``, and its effect in a stage run."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch

from egorelight_cli import runtime
from egorelight_cli.errors import EgorelightError
from egorelight_cli.runtime import apply_threads, available_cores, core_limits, parse_threads

NO_CGROUP = "/nonexistent-cgroup"


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    apply_threads(before)


def test_affinity_alone_decides_without_other_limits():
    assert available_cores({}, affinity=6, cgroup=NO_CGROUP) == (6, "affinity")


def test_real_affinity_is_read(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 2, 5})
    assert core_limits({}, cgroup=NO_CGROUP) == {"affinity": 3}


def test_cgroup_v2_quota_rounds_up_and_max_is_no_limit(tmp_path):
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert available_cores({}, affinity=8, cgroup=tmp_path) == (2, "cgroup")
    (tmp_path / "cpu.max").write_text("50000 100000\n")
    assert available_cores({}, affinity=8, cgroup=tmp_path) == (1, "cgroup")
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert available_cores({}, affinity=8, cgroup=tmp_path) == (8, "affinity")


def test_cgroup_v1_quota(tmp_path):
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("300000\n")
    (tmp_path / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert available_cores({}, affinity=8, cgroup=tmp_path) == (3, "cgroup")
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    assert available_cores({}, affinity=8, cgroup=tmp_path) == (8, "affinity")


def test_smallest_limit_wins(tmp_path):
    (tmp_path / "cpu.max").write_text("400000 100000\n")
    env = {"OMP_NUM_THREADS": "3", "SLURM_CPUS_PER_TASK": "5"}
    assert core_limits(env, affinity=8, cgroup=tmp_path) == {"affinity": 8, "cgroup": 4, "OMP_NUM_THREADS": 3,
                                                             "SLURM_CPUS_PER_TASK": 5}
    assert available_cores(env, affinity=8, cgroup=tmp_path) == (3, "OMP_NUM_THREADS")
    assert available_cores({"SLURM_CPUS_PER_TASK": "2"}, affinity=8, cgroup=tmp_path) == (2, "SLURM_CPUS_PER_TASK")
    # a limit above the affinity does not raise the count
    assert available_cores({"OMP_NUM_THREADS": "64"}, affinity=2, cgroup=NO_CGROUP) == (2, "affinity")


def test_environment_values_that_are_no_limit_are_ignored():
    env = {"OMP_NUM_THREADS": "0", "SLURM_CPUS_PER_TASK": "many"}
    assert available_cores(env, affinity=4, cgroup=NO_CGROUP) == (4, "affinity")
    # OMP_NUM_THREADS may list nested levels: the outer one counts
    assert available_cores({"OMP_NUM_THREADS": "2,4"}, affinity=4, cgroup=NO_CGROUP) == (2, "OMP_NUM_THREADS")


def test_monkeypatched_process_environment_is_read(monkeypatch):
    monkeypatch.setenv("SLURM_CPUS_PER_TASK", "1")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert available_cores(affinity=4, cgroup=NO_CGROUP) == (1, "SLURM_CPUS_PER_TASK")


@pytest.mark.parametrize("bad", ["0", "-2", "abc", "1.5", ""])
def test_parse_threads_refuses_non_positive_integers(bad):
    with pytest.raises(EgorelightError, match="--threads must be a positive integer"):
        parse_threads(bad)


def test_apply_threads_sets_every_pool(restore_threads):
    import cv2
    from threadpoolctl import threadpool_info

    for n in (1, 2):
        assert apply_threads(n) == n
        assert torch.get_num_threads() == n
        assert cv2.getNumThreads() == n
        blas = [info for info in threadpool_info() if info["user_api"] == "blas"]
        assert blas and all(info["num_threads"] == n for info in blas)
    with pytest.raises(EgorelightError):
        apply_threads(0)


def test_blas_threads_limits_inside_the_block_only(restore_threads):
    from threadpoolctl import threadpool_info

    apply_threads(2)
    with runtime.blas_threads(1):
        assert {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"} == {1}
    assert {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"} == {2}


def test_stage_run_applies_threads_before_the_stage(tmp_path, restore_threads):
    from egorelight_cli.artifacts import open_artifact
    from egorelight_cli.io.character import default_character_path, read_character_npz
    from egorelight_cli.pipeline import StageRun
    from egorelight_cli.stages.character_commands import write_character

    for n in (1, 2):
        apply_threads(3 - n)  # start from the other value
        seen = {}

        def write(writer, cfg):
            seen["torch"] = torch.get_num_threads()
            write_character(writer, read_character_npz(default_character_path()))

        out = StageRun("character", threads=n, force=True).produce(tmp_path / f"c{n}", "character", write)
        assert seen["torch"] == n
        runtime_section = open_artifact(out).manifest["runtime"]
        assert runtime_section["threads"] == n and runtime_section["threads_source"] == "--threads"


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "egorelight_cli.cli", *args], capture_output=True, text=True)


def test_threads_option_is_recorded_in_the_manifest(tmp_path):
    result = _cli("--threads", "1", "character", "default", "--out", str(tmp_path / "c"))
    assert result.returncode == 0, result.stderr
    manifest = json.loads((tmp_path / "c" / "manifest.json").read_text())
    assert manifest["runtime"]["threads"] == 1
    assert manifest["runtime"]["threads_source"] == "--threads"


@pytest.mark.parametrize("value", ["0", "two"])
def test_bad_threads_is_one_line_exit_2(tmp_path, value):
    result = _cli("character", "default", "--threads", value, "--out", str(tmp_path / "c"))
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert lines == [f"egorelight: error: --threads must be a positive integer, got '{value}'"]
    assert not (tmp_path / "c").exists()


@pytest.mark.skipif(subprocess.run(["make", "--version"], capture_output=True).returncode != 0, reason="no make")
@pytest.mark.parametrize("args, expected", [((), None), (("-j2",), max(1, len(os.sched_getaffinity(0)) // 2)),
                                            (("-j2", "THREADS=3"), 3)])
def test_make_passes_a_per_job_share(tmp_path, args, expected):
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    target = tmp_path / "character" / "manifest.json"
    result = subprocess.run(["make", "-n", *args, f"SUBJECT={tmp_path}", "CHARACTER_SOURCE=default", str(target)],
                            cwd=root, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    line = next(row for row in result.stdout.splitlines() if "character default" in row)
    assert ("--threads" not in line) if expected is None else (f"--threads {expected} " in line)


def test_single_threaded_openmp_limits_every_loaded_openmp_runtime():
    """synth's pymeshlab filters run on one OpenMP thread, whichever runtime pymeshlab bound to (its
    own libgomp, or torch's when torch came first), and the setting comes back after."""
    import pymeshlab  # noqa: F401  (loads or binds its OpenMP runtime)
    from threadpoolctl import threadpool_info, threadpool_limits

    from egorelight_cli.runtime import single_threaded_openmp

    def openmp() -> dict[str, int]:
        return {d["filepath"]: d["num_threads"] for d in threadpool_info() if d["user_api"] == "openmp"}

    with threadpool_limits(limits=2, user_api="openmp"):
        before = openmp()
        assert before and set(before.values()) == {2}
        with single_threaded_openmp():
            assert set(openmp().values()) == {1}
        assert openmp() == before
