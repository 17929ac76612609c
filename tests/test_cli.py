"""The command line as a user meets it: exit codes and one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from egorelight_cli.io.npz import write_npz


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "egorelight_cli.cli", *args], capture_output=True, text=True, cwd=cwd)


def assert_one_line_error(result, *fragments):
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("egorelight: error: ")
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0]


def test_missing_input_is_one_line_exit_2(tmp_path):
    assert_one_line_error(run("inspect", str(tmp_path / "missing.npz")), "not found", "missing.npz")


def test_corrupt_npz_is_one_line_exit_2(tmp_path):
    write_npz(tmp_path / "ok.npz", {"a": np.ones(500)}, {"kind": "egorelight/motion", "version": 1})
    data = (tmp_path / "ok.npz").read_bytes()
    (tmp_path / "bad.npz").write_bytes(data[:100])
    assert_one_line_error(run("inspect", str(tmp_path / "bad.npz")), "corrupt npz", "bad.npz")


def test_wrong_kind_is_one_line(tmp_path):
    write_npz(tmp_path / "k.npz", {"a": np.ones(3)}, {"kind": "egorelight/motion", "version": 1})
    result = run("character", "preview", str(tmp_path / "k.npz"), "--out", str(tmp_path / "p.png"))
    assert_one_line_error(result, "k.npz")


def test_inspect_json_and_global_options_both_sides(tmp_path):
    write_npz(tmp_path / "k.npz", {"a": np.ones(3)}, {"kind": "egorelight/motion", "version": 1})
    before = run("-q", "inspect", "--json", str(tmp_path / "k.npz"))
    after = run("inspect", "--json", "-q", str(tmp_path / "k.npz"))
    assert before.returncode == 0 and after.returncode == 0
    assert json.loads(before.stdout)["kind"] == "egorelight/motion" == json.loads(after.stdout)["kind"]


def test_unknown_set_key_is_one_line(tmp_path):
    result = run("character", "default", "--out", str(tmp_path / "c"), "--set", "no_such_key=1")
    assert_one_line_error(result, "unknown config key 'no_such_key'", "target_vertices")


def test_usage_errors_are_one_line_exit_2():
    assert_one_line_error(run("inspect"), "Missing argument", "egorelight inspect --help")
    assert_one_line_error(run("ik", "--in", "k.npz"), "Missing option '--out'", "egorelight ik --help")
    assert_one_line_error(run("egodepth", "--method", "foo", "--out", "x"), "'foo' is not one of")
    assert_one_line_error(run("no-such-command"), "No such command")
    shown = run("train")  # a group without its command shows its help, not an error line
    assert "Usage:" in shown.stdout + shown.stderr and "egorelight: error" not in shown.stderr


def test_version():
    result = run("--version")
    assert result.returncode == 0 and "egorelight" in result.stdout


def test_an_option_and_a_set_of_its_key_must_agree(tmp_path):
    """``--solver`` is shorthand for ``--set solver=...``: both given and disagreeing is an error
    (the option won silently); both agreeing, in any YAML spelling, is fine."""
    assert_one_line_error(run("ik", "--in", str(tmp_path / "k.npz"), "--solver", "lbfgs", "--set", "solver=lm",
                              "--out", str(tmp_path / "m")), "--solver sets solver=lbfgs", "--set solver=lm")
    assert_one_line_error(run("train", "egopose", "--no-jitter", "--set", "train.colour_jitter=true", "--capture",
                              str(tmp_path), "--calibration", str(tmp_path), "--out", str(tmp_path / "e")),
                          "--no-jitter")
    agreeing = run("train", "egopose", "--no-jitter", "--set", "train.colour_jitter=False", "--capture", str(tmp_path),
                   "--calibration", str(tmp_path), "--out", str(tmp_path / "e"))
    assert_one_line_error(agreeing, "not a finished egorelight artifact")  # past the options, to the capture
    assert_one_line_error(run("ik", "--in", str(tmp_path / "k.npz"), "--solver", "lm", "--set", "solver",
                              "--out", str(tmp_path / "m")), "solver")  # no "=": the config's error, not a crash
    assert not (tmp_path / "m").exists() and not (tmp_path / "e").exists()
