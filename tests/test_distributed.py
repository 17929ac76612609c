"""Data-parallel training under torchrun (2 CPU processes, gloo) against one process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.nn import distributed

TESTS = Path(__file__).resolve().parent


def _torchrun(processes: int, *args, env: dict | None = None) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(processes),
               *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, cwd=TESTS,
                          env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}, timeout=300)


def test_two_processes_take_the_same_steps_as_one_with_the_global_batch(tmp_path):
    for n in (1, 2):
        result = _torchrun(n, TESTS / "distributed_toy.py", tmp_path / f"toy{n}.pt")
        assert result.returncode == 0, result.stderr[-2000:]
    one, two = (torch.load(tmp_path / f"toy{n}.pt") for n in (1, 2))
    assert two["world_size"] == 2 and one["world_size"] == 1
    # averaged gradients of equal shares = the global batch's gradient: the same Adam steps (float64)
    for name, value in one["state"].items():
        torch.testing.assert_close(two["state"][name], value, rtol=1e-9, atol=1e-10)
    for a, b in zip(one["curve"], two["curve"]):
        assert a["step"] == b["step"] and b["loss"] == pytest.approx(a["loss"], rel=1e-9)


def test_rank_share_splits_a_global_batch_and_refuses_an_uneven_one(monkeypatch):
    batch = list(range(6))
    assert distributed.rank_share(batch) == batch  # one process: everything
    monkeypatch.setattr(distributed, "world", lambda: distributed.World(rank=1, size=3, backend="gloo"))
    assert distributed.rank_share(batch) == [2, 3]
    assert distributed.rank_share(torch.arange(6)).tolist() == [2, 3]
    with pytest.raises(EgorelightError, match="multiple of 3"):
        distributed.rank_share(list(range(4)))


def test_train_egodepth_under_torchrun_matches_one_process(tiny_capture, oracle_calibration_artifact, tmp_path):
    args = ["--preset", "tiny", "--set", "train.steps=12", "--set", "train.log_every=2", "train", "egodepth",
            "--capture", tiny_capture, "--calibration", oracle_calibration_artifact]
    one = subprocess.run([sys.executable, "-m", "egorelight_cli.cli", "--threads", "1", *map(str, args),
                          "--out", str(tmp_path / "one")], capture_output=True, text=True)
    assert one.returncode == 0, one.stderr[-2000:]
    two = _torchrun(2, "-m", "egorelight_cli.cli", *args, "--out", tmp_path / "two")
    assert two.returncode == 0, two.stderr[-2000:]
    manifest = json.loads((tmp_path / "two" / "manifest.json").read_text())
    assert manifest["runtime"]["distributed"] == {"world_size": 2, "backend": "gloo", "launcher": "torchrun"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one", "two"]  # rank 1 left nothing behind
    curves = [json.loads((tmp_path / name / "curve.json").read_text()) for name in ("one", "two")]
    # the same global batches; the masked depth loss is normalised per rank, so not bit-identical
    # (the total also holds the error scale's likelihood, whose log b term makes it near zero:
    # compared are its positive parts)
    for a, b in zip(*curves):
        assert b["depth_l1_log"] == pytest.approx(a["depth_l1_log"], rel=0.03)
        assert b["mask_bce"] == pytest.approx(a["mask_bce"], rel=0.03)


def test_a_stage_that_does_not_train_refuses_torchrun(tiny_capture, tmp_path):
    env = {**os.environ, "WORLD_SIZE": "2", "RANK": "0", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "29999"}
    result = subprocess.run([sys.executable, "-m", "egorelight_cli.cli", "--preset", "tiny", "calibrate", "--capture",
                             str(tiny_capture), "--out", str(tmp_path / "cal")], capture_output=True, text=True, env=env)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "only `train <stage>` is data-parallel" in result.stderr
    assert not (tmp_path / "cal").exists()
