"""Stage declarations (declarations.py, stage_spec.py): the CLI, the cache key, the manifest's
inputs and the README table derive from them."""

from __future__ import annotations

import inspect
import json
from pathlib import Path
from types import SimpleNamespace

import click
import pytest

from egorelight_cli.declarations import COMMANDS, command
from egorelight_cli.pipeline import StageRun
from egorelight_cli.stage_spec import Command, Input, Option, Output, markdown_table, replace_table

ROOT = Path(__file__).resolve().parents[1]
UNDECLARED = {("inspect",), ("report",), ("merge",)}  # tools over artifacts, not stages


def _click_commands(group: click.Group, prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], click.Command]:
    found = {}
    for name, cmd in group.commands.items():
        if isinstance(cmd, click.Group):
            found.update(_click_commands(cmd, prefix + (name,)))
        else:
            found[prefix + (name,)] = cmd
    return found


def _defaults(declared: Command) -> dict:
    values = {p.name: (getattr(p, "default", None) if not getattr(p, "multiple", False) else ()) for p in declared.params()}
    if declared.per_frame:
        values.update(frames=None, shard=None)
    return values


def test_every_stage_command_is_built_from_its_declaration():
    from egorelight_cli.cli import cli

    built = _click_commands(cli)
    assert set(built) - UNDECLARED == {c.path for c in COMMANDS}
    for declared in COMMANDS:
        names = [p.name for p in built[declared.path].params]
        own = [p.name for p in declared.params()] + (["frames", "shard"] if declared.per_frame else [])
        assert names[:len(own)] == own, declared.name  # declared order, then the global options
        assert "device" in names and "preset" in names


def test_handlers_take_exactly_the_declared_values():
    for declared in COMMANDS:
        handler = declared.handler_function()
        inspect.signature(handler).bind(SimpleNamespace(), **declared.handler_values(_defaults(declared)))


def _alternative(option: Option, stage: str):
    """A value of ``option`` other than its default (for a config-key option: other than the config's)."""
    if option.type is bool:
        return not option.default
    if isinstance(option.type, tuple):
        current = option.default
        if option.config_key is not None:
            from egorelight_cli.config import flatten, resolve_config

            current = flatten(resolve_config(stage, "tiny").to_dict())[option.config_key]
        return next(v for v in option.type if v != current)
    if option.multiple:
        return ("elsewhere",)
    if option.type in (int, float):
        return (option.default or 0) + 1
    return f"{option.default or ''}x"


@pytest.mark.parametrize("declared", [c for c in COMMANDS if c.options or c.per_frame], ids=lambda c: c.name)
def test_every_declared_option_changes_the_cache_key(declared):
    """An option cannot change an output without entering its key: each keyed option by itself,
    and each config-key option through the config."""
    base = _defaults(declared)

    def key(values):
        run = StageRun(declared.stage, preset="tiny", sets=tuple(declared.config_sets(values)), command=declared,
                       values=values)
        return run.cache_key()[0]

    reference = key(base)
    for option in declared.options:
        changed = {**base, option.name: _alternative(option, declared.stage)}
        assert (key(changed) != reference) == option.keyed or option.config_key is not None, option.flag
        if option.config_key is not None:
            assert key(changed) != reference, option.flag
    if declared.per_frame:
        assert key({**base, "frames": "0:2"}) != reference and key({**base, "shard": "0/2"}) != reference


def test_config_key_options_are_set_in_the_config():
    ik = command("ik")
    run = StageRun("ik", sets=tuple(ik.config_sets({"solver": "lbfgs"})), command=ik, values={"solver": "lbfgs"})
    assert run.config().solver == "lbfgs"
    train = command("train", "egopose")
    assert train.config_sets({"no_jitter": True}) == ["train.colour_jitter=false"]
    assert train.config_sets({"no_jitter": False}) == []


def test_an_unkeyed_option_must_say_why():
    with pytest.raises(ValueError, match="say why"):
        Option("--fast", "fast", "help", keyed=False)
    unkeyed = [o for c in COMMANDS for o in c.options if not o.keyed]
    assert unkeyed and all(o.why_not_keyed for o in unkeyed)


def _artifact(path: Path, kind: str):
    return SimpleNamespace(path=path, kind=kind)


def test_input_params_label_and_check_the_inputs(tmp_path):
    declared = Command(("toy",), "ik", "Toy.", "x:y", Output("motion", "out"),
                       inputs=(Input("--in", "input", "in", ("keypoints",)), Input("--gt", "gt", "gt", ("motion",)),
                               Input("--character", "character", "c", ("character",), default="default")))
    keypoints, gt = tmp_path / "kp", tmp_path / "gt"
    values = {"input": keypoints, "gt": gt, "character": "default"}
    params = declared.input_params(values, [_artifact(keypoints, "keypoints"), _artifact(gt / "inner", "motion"),
                                            _artifact(tmp_path / "found", "capture")], [])
    assert params == ["--in", "--gt", None]  # the last was found by the command itself
    with pytest.raises(RuntimeError, match="--in read a motion artifact"):
        declared.input_params(values, [_artifact(keypoints, "motion"), _artifact(gt, "motion")], [])
    with pytest.raises(RuntimeError, match="--gt .* did not enter the cache key"):
        declared.input_params(values, [_artifact(keypoints, "keypoints")], [])
    assert declared.input_params(values, [_artifact(keypoints, "keypoints")], [gt / "keypoints.npz"]) == ["--in"]


def test_manifest_inputs_name_their_param_and_options_are_recorded(tmp_path, tiny_capture, run):
    """Through the real CLI: each input artifact is labelled with its declared param, --solver lands in
    the config, --seq in config.options, and a run with another --seq is not "up to date"."""
    def manifest(*args):
        result = run("--preset", "tiny", *args)
        assert result.returncode == 0, result.stderr
        return json.loads((Path(args[-1]) / "manifest.json").read_text())

    character = manifest("character", "default", "--out", tmp_path / "character")
    assert character["runtime"]["command"] == "character default"
    truth = tiny_capture / "groundtruth" / "test"
    motion = manifest("ik", "--in", truth / "keypoints.npz", "--character", tmp_path / "character", "--solver",
                      "lbfgs", "--set", "lbfgs.iterations=2", "--out", tmp_path / "motion")
    assert motion["config"]["solver"] == "lbfgs" and motion["runtime"]["command"] == "ik"
    assert [i.get("param") for i in motion["inputs"]] == ["--character"]
    model = manifest("train", "ik", tmp_path / "motion", "--character", tmp_path / "character", "--out",
                     tmp_path / "model")
    assert sorted(i.get("param") for i in model["inputs"]) == ["--character", "MOTIONS"]
    assert "options" not in model["config"]  # train ik has no options of its own
    shown = run("inspect", tmp_path / "model")
    assert shown.returncode == 0 and "via MOTIONS" in shown.stdout and "via --character" in shown.stdout


def test_readme_table_is_generated_from_the_declarations():
    readme = (ROOT / "README.md").read_text()
    assert replace_table(readme, markdown_table(COMMANDS)) == readme, "stale README table: run `make readme`"
    for declared in COMMANDS:
        assert f"| `{declared.name}`:" in readme


def test_a_cached_no_op_is_decided_from_the_recorded_manifest(tmp_path, tiny_capture, run, monkeypatch):
    """The early check (StageRun.recorded_up_to_date) skips an up-to-date run without importing its
    handler, and steps aside (the handler runs) when an option, the config or an input changed."""
    from egorelight_cli import stage_spec

    truth = tiny_capture / "groundtruth" / "test"
    character, motion = tmp_path / "character", tmp_path / "motion"
    assert run("--preset", "tiny", "character", "default", "--out", character).returncode == 0
    args = ("--preset", "tiny", "ik", "--in", truth / "keypoints.npz", "--character", character, "--out", motion)
    assert run(*args).returncode == 0

    def handler_must_not_run(self):
        raise AssertionError(f"{self.name}: the handler ran")

    monkeypatch.setattr(stage_spec.Command, "handler_function", handler_must_not_run)
    result = run(*args)
    assert result.returncode == 0 and "up to date" in result.stderr
    for changed in (("--solver", "lbfgs"), ("--set", "lm.iterations=3"), ("--seed", "5"), ("--force",)):
        result = run(*args, *changed)
        assert result.returncode == 1 and "the handler ran" in result.stderr, changed
    payload = character / "character.npz"
    payload.write_bytes(payload.read_bytes() + b"\0")  # an input payload modified
    result = run(*args)
    assert result.returncode == 1 and "the handler ran" in result.stderr


def test_the_early_check_steps_aside_when_an_input_is_left_out_swapped_or_built_in(tmp_path, tiny_capture, run,
                                                                                  monkeypatch):
    """The recorded inputs must come through the same flags as now, in the same order: dropping
    ``--gt``, swapping the files of ``--in`` and ``--gt``, or naming the built-in character in place
    of an artifact each make another cache key, so the handler runs (it used to be skipped)."""
    import numpy as np

    from egorelight_cli import stage_spec

    truth = tiny_capture / "groundtruth" / "test" / "keypoints.npz"
    other = tmp_path / "other_keypoints.npz"
    with np.load(truth) as arrays:
        moved = {k: arrays[k] for k in arrays.files}
    moved["xyz"] = moved["xyz"] + 0.01  # another keypoint file of the same layout
    np.savez(other, **moved)
    character, motion = tmp_path / "character", tmp_path / "motion"
    assert run("--preset", "tiny", "character", "default", "--out", character).returncode == 0
    base = ("--preset", "tiny", "ik", "--character", character, "--out", motion)
    assert run(*base, "--in", truth, "--gt", other).returncode == 0

    def handler_must_not_run(self):
        raise AssertionError(f"{self.name}: the handler ran")

    monkeypatch.setattr(stage_spec.Command, "handler_function", handler_must_not_run)
    result = run(*base, "--in", truth, "--gt", other)
    assert result.returncode == 0 and "up to date" in result.stderr
    manifest = json.loads((motion / "manifest.json").read_text())
    assert [s.get("param") for s in manifest["sources"]] == ["--in", "--gt"]
    for changed in (("--in", truth), ("--in", other, "--gt", truth)):
        result = run(*base[:-2], "--out", motion, *changed)
        assert result.returncode == 1 and "the handler ran" in result.stderr, changed
    built_in = ("--preset", "tiny", "ik", "--character", "default", "--in", truth, "--gt", other, "--out", motion)
    result = run(*built_in)
    assert result.returncode == 1 and "the handler ran" in result.stderr


def test_re_making_an_input_with_the_same_content_keeps_what_depends_on_it_current(tmp_path, tiny_capture, run,
                                                                                   monkeypatch):
    """An artifact's digest leaves out when and how fast it was made (artifacts.content_digest):
    `character default --force` writes a manifest with another `created` and timing, and the motion
    made from the character stays up to date (it used to re-run, and so did everything after it)."""
    from egorelight_cli import stage_spec
    from egorelight_cli.artifacts import open_artifact

    truth = tiny_capture / "groundtruth" / "test" / "keypoints.npz"
    character, motion = tmp_path / "character", tmp_path / "motion"
    assert run("--preset", "tiny", "character", "default", "--out", character).returncode == 0
    before = open_artifact(character)
    args = ("--preset", "tiny", "ik", "--in", truth, "--character", character, "--out", motion)
    assert run(*args).returncode == 0
    import time

    time.sleep(1.1)  # another `created` second
    assert run("--preset", "tiny", "character", "default", "--out", character, "--force").returncode == 0
    after = open_artifact(character)
    assert after.manifest["created"] != before.manifest["created"] and after.digest == before.digest

    def handler_must_not_run(self):
        raise AssertionError(f"{self.name}: the handler ran")

    monkeypatch.setattr(stage_spec.Command, "handler_function", handler_must_not_run)
    result = run(*args)
    assert result.returncode == 0 and "up to date" in result.stderr
