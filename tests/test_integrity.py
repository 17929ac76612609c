"""Verified artifacts, complete cache keys, honest training (issue 14 items 2 and 5).

* a stage checks the sha256 of every payload it reads against the input's manifest: a modified
  payload is a one-line error naming the file, also with ``--force``;
* "up to date" needs the output's own payloads present and intact; ``inspect`` reports the bad ones;
* a command's output-affecting options (``--seq``) enter the cache key and the manifest, and an
  up-to-date run returns before importing torch;
* training resumes only with ``--resume``, only from a checkpoint of the same cache key, with the
  optimiser and the learning-rate schedule restored; egopose's pose-prior blend is fitted on one
  half of the held-out frames and reported on the other.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch


def one_line_error(result) -> str:
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("egorelight: error:"), result
    return lines[0]


@pytest.fixture(scope="module")
def character_artifact(tmp_path_factory) -> Path:
    from egorelight_cli.cli import main

    out = tmp_path_factory.mktemp("integrity") / "char"
    with pytest.raises(SystemExit) as exit_info:
        main(["character", "default", "--out", str(out), "-q"])
    assert exit_info.value.code == 0
    return out


@pytest.fixture
def character_copy(character_artifact, tmp_path) -> Path:
    import shutil

    return Path(shutil.copytree(character_artifact, tmp_path / "char"))


def flip_byte(path: Path, offset: int = -100) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


def test_modified_input_payload_is_an_error_that_force_does_not_silence(run, character_copy, tmp_path):
    flip_byte(character_copy / "template.obj")
    for extra in ((), ("--force",)):
        line = one_line_error(run("train", "ik", "--character", character_copy, "--out", tmp_path / "model", *extra))
        assert "modified" in line and str(character_copy / "template.obj") in line
        assert not (tmp_path / "model").exists()


def test_inspect_reports_missing_and_modified_payloads(run, character_copy):
    from egorelight_cli.inspect import describe

    assert describe(character_copy)["payload_problems"] == []
    flip_byte(character_copy / "character.npz")
    (character_copy / "template.obj").unlink()
    problems = {(p["problem"], Path(p["path"]).name) for p in describe(character_copy)["payload_problems"]}
    assert problems == {("modified", "character.npz"), ("missing", "template.obj")}
    result = run("inspect", character_copy)  # the description, then a health check's exit code
    assert "MODIFIED" in result.stdout and "MISSING" in result.stdout
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "2 payload(s) missing or modified" in result.stderr


def test_inspect_text_names_bad_payloads(character_copy):
    from egorelight_cli.inspect import describe, format_description

    (character_copy / "template.obj").write_text("truncated")
    text = format_description(describe(character_copy))
    assert "payloads: 1 of" in text and "MODIFIED" in text and "template.obj" in text


def test_deleted_or_truncated_output_payload_is_not_up_to_date(run, character_copy):
    from egorelight_cli.artifacts import open_artifact

    def written() -> int:  # a rewrite replaces the directory (new manifest inode); a skip keeps it
        return (character_copy / "manifest.json").stat().st_ino

    before = written()
    assert run("character", "default", "--out", character_copy).returncode == 0 and written() == before
    for damage in (lambda p: p.write_bytes(p.read_bytes()[:50]), lambda p: p.unlink()):
        damage(character_copy / "template.obj")
        before = written()
        assert run("character", "default", "--out", character_copy).returncode == 0
        assert written() != before, "a damaged output counted as up to date"
        open_artifact(character_copy).verify()  # rewritten: every payload intact again


def test_sequence_enters_the_cache_key_and_a_cached_run_skips_torch(run, tiny_capture, oracle_calibration_artifact,
                                                                    tmp_path):
    out = tmp_path / "pc"
    args = ("--preset", "tiny", "egodepth", "--method", "sgbm", "--capture", tiny_capture,
            "--calibration", oracle_calibration_artifact, "--out", out, "--set", "preview.frames=1")
    for seq in ("test", "ego_train"):
        result = run(*args, "--seq", seq)
        assert result.returncode == 0 and "up to date" not in result.stderr, (seq, result)
        manifest = json.loads((out / "manifest.json").read_text())
        assert manifest["metrics"]["sequence"] == seq and manifest["config"]["options"]["sequence"] == seq
    code = ("import sys\nfrom egorelight_cli.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit as e:\n"
            "    assert e.code == 0, e.code\nprint('torch' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code, *map(str, args), "--seq", "ego_train"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "up to date" in done.stderr, done.stderr
    assert done.stdout.strip() == "False", "an up-to-date egodepth run imported torch"


# ------------------------------------------------------------------------------------ training
def _toy(lr: float = 0.1):
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 1)
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, 10, eta_min=lr * 0.01)
    x = torch.linspace(-1, 1, 24).reshape(8, 3)

    def step_fn(step: int) -> dict[str, torch.Tensor]:
        return {"loss": ((model(x) - x.sum(1, keepdim=True) * 0.5) ** 2).mean() + 0.0 * step}

    return model, optimizer, scheduler, step_fn


def _train(checkpoint, stop_at: int | None = None, lr: float = 0.1):
    from egorelight_cli.nn.training import train

    model, optimizer, scheduler, step_fn = _toy(lr)
    if stop_at is not None:
        inner = step_fn

        def step_fn(step: int):
            if step == stop_at:
                raise KeyboardInterrupt
            return inner(step)
    curve = train(model, optimizer, step_fn, 10, checkpoint=checkpoint, checkpoint_every=4, log_every=1,
                  scheduler=scheduler)
    return model, optimizer, curve


def test_resume_restores_optimizer_and_schedule(tmp_path):
    from egorelight_cli.nn.training import Checkpoint

    whole, whole_opt, whole_curve = _train(None)
    ckpt = Checkpoint(tmp_path / "c.pt", key="k1", resume=True)
    with pytest.raises(KeyboardInterrupt):
        _train(ckpt, stop_at=6)  # killed at step 6: the checkpoint of step 4 survives
    resumed, resumed_opt, resumed_curve = _train(ckpt)
    assert [r["step"] for r in resumed_curve] == list(range(1, 11))
    for a, b in zip(whole.parameters(), resumed.parameters()):
        torch.testing.assert_close(a, b)
    assert resumed_opt.param_groups[0]["lr"] == pytest.approx(whole_opt.param_groups[0]["lr"])


def test_checkpoint_of_another_run_is_refused_or_ignored(tmp_path, caplog):
    from egorelight_cli.errors import EgorelightError
    from egorelight_cli.nn.training import Checkpoint

    path = tmp_path / "c.pt"
    with pytest.raises(KeyboardInterrupt):
        _train(Checkpoint(path, key="k1"), stop_at=6)
    with pytest.raises(EgorelightError, match="cache key differs"):
        _train(Checkpoint(path, key="k2", resume=True))
    whole, _, _ = _train(None)
    fresh, _, curve = _train(Checkpoint(path, key="k1", resume=False), lr=0.1)  # no --resume: from step 0
    assert curve[0]["step"] == 1
    for a, b in zip(whole.parameters(), fresh.parameters()):
        torch.testing.assert_close(a, b)
    assert torch.load(path, weights_only=True)["step"] == 10  # and the old checkpoint was replaced


def test_train_commands_take_resume():
    from click.testing import CliRunner

    from egorelight_cli.cli import cli

    for stage in ("egodepth", "animate", "egopose", "geolift", "relight"):
        result = CliRunner().invoke(cli, ["train", stage, "--help"])
        assert result.exit_code == 0 and "--resume" in result.output, stage


def test_egopose_blend_is_fitted_and_reported_on_disjoint_frames(monkeypatch):
    from types import SimpleNamespace

    from egorelight_cli.stages import egopose

    T = 10
    frames = egopose.EgoFrames("s", np.arange(100, 100 + T), np.arange(T), torch.zeros(T, 2, 1, 4, 4),
                               np.repeat(np.eye(4)[None], T, 0), np.ones(T, bool), np.ones(T, bool), "calibration",
                               30.0)
    fitted, reported = [], {}

    def fake_predict(net, f, rig, sigma):
        return SimpleNamespace(keypoints=SimpleNamespace(xyz=np.zeros((len(f.frame_ids), 57, 3))), ids=f.frame_ids)

    def fake_fit(pred, truth, prior, T_world):
        fitted.append(len(pred))
        return np.ones(57, np.float32)

    def fake_metrics(xyz, frame_ids, mocap, usable, prefix):
        reported[prefix] = set(int(i) for i in frame_ids)
        return {prefix + "mpjpe_cm": 1.0}

    monkeypatch.setattr(egopose, "predict", fake_predict)
    monkeypatch.setattr(egopose, "fit_prior_blend", fake_fit)
    monkeypatch.setattr(egopose, "keypoint_metrics", fake_metrics)
    monkeypatch.setattr(egopose, "mean_pose_keypoints", lambda mean, f: np.zeros((len(f.frame_ids), 57, 3)))
    mocap = SimpleNamespace(frame_ids=np.arange(100, 100 + T), xyz=np.zeros((T, 57, 3)))
    settings = SimpleNamespace(cfg=SimpleNamespace(confidence_sigma_m=0.1), train=SimpleNamespace(prior_blend=True))
    net = SimpleNamespace(prior_blend=torch.zeros(57))
    metrics = egopose._validate(net, frames, mocap, None, settings, np.zeros((57, 3)))
    fit_ids, report_ids = egopose.blend_split(T)
    assert fitted == [len(fit_ids)] and metrics["prior_blend_fit_frames"] == len(fit_ids)
    assert reported["validation_blended_"] == reported["validation_"] == set(100 + report_ids)
    assert not set(100 + fit_ids) & reported["validation_blended_"]


def test_a_stage_reading_one_sequence_verifies_that_sequence(tiny_capture, tmp_path):
    import shutil

    from egorelight_cli.errors import EgorelightError
    from egorelight_cli.io.capture import open_capture

    capture = Path(shutil.copytree(tiny_capture, tmp_path / "capture"))
    victim = sorted((capture / "sequences" / "test").rglob("*.png"))[0]
    flip_byte(victim)
    open_capture(capture, ["ego_train"])  # the modified file is not read
    for sequences in (["test"], None):
        with pytest.raises(EgorelightError, match="does not match its manifest digest") as info:
            open_capture(capture, sequences)
        assert str(victim) in str(info.value)
