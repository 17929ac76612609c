"""SIGINT / SIGTERM: deferred around the output swap, SIGTERM cleaning up like Ctrl-C."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from egorelight_cli.signals import Terminated, signals_deferred, terminate_as_exception

ROOT = Path(__file__).resolve().parents[1]


def test_an_interrupt_inside_the_deferred_block_arrives_when_it_ends():
    # Python's own Ctrl-C handler, whatever this process started with (a shell's background job ignores SIGINT)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        reached_the_end = False
        with pytest.raises(KeyboardInterrupt):
            with signals_deferred():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)  # a signal handler runs between bytecodes: it had every chance
                reached_the_end = True
        assert reached_the_end
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


def test_sigterm_raises_terminated_and_the_handler_is_restored():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated):
        with terminate_as_exception():
            with signals_deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
            pytest.fail("SIGTERM was held past the deferred block")
    assert signal.getsignal(signal.SIGTERM) is before


def test_ctrl_c_in_a_command_says_interrupted_in_one_line(tmp_path, monkeypatch, capsys):
    """click printed an empty line and said "aborted" (its Abort) for a KeyboardInterrupt inside a
    command; now one line, exit 130 (the real signal on a real stage: the test below)."""
    from egorelight_cli import cli

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("egorelight_cli.inspect.describe", interrupted)  # Ctrl-C while inspect reads
    np.savez(tmp_path / "a.npz", x=np.zeros(3))
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["inspect", str(tmp_path / "a.npz")])
    assert exit_info.value.code == 130
    assert capsys.readouterr().err == "egorelight: interrupted\n"


@pytest.mark.parametrize("signum,code,line", [(signal.SIGTERM, 143, "egorelight: terminated"),
                                              (signal.SIGINT, 130, "egorelight: interrupted")])
def test_a_stopped_stage_says_so_in_one_line_and_leaves_nothing(tmp_path, signum, code, line):
    """SIGTERM (a scheduler's kill) or SIGINT (Ctrl-C) mid-run of a stage with worker processes: one
    line on stderr, no traceback, no temporary folder, no worker left running (before: exit -15,
    the work folder left, and the workers went on writing into it)."""
    out = tmp_path / "capture"
    command = [str(ROOT / ".venv" / "bin" / "egorelight"), "--preset", "tiny", "--threads", "2", "synth",
               "--out", str(out)]
    if not Path(command[0]).is_file():
        command = [sys.executable, "-m", "egorelight_cli.cli", *command[1:]]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                               preexec_fn=_default_sigint)
    deadline, workers = time.time() + 120, []
    while len(workers) < 2 and time.time() < deadline:  # --threads 2: two sequences simulated at a time
        time.sleep(0.2)
        children = subprocess.run(["pgrep", "-P", str(process.pid)], capture_output=True, text=True).stdout.split()
        workers = [pid for pid in children if "resource_tracker" not in _cmdline(pid)]
    assert len(workers) == 2 and any(tmp_path.glob(".capture.tmp-*"))
    time.sleep(1.0)  # the workers are rendering
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == code, stderr
    assert stderr.splitlines()[-1] == line and "" not in stderr.splitlines() and "Traceback" not in stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    time.sleep(1.0)
    assert not [pid for pid in workers if _cmdline(pid)]


def _default_sigint() -> None:
    """In the child: Python's Ctrl-C handler even where this test runs with SIGINT ignored (a
    shell's background job), which the child would inherit."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _cmdline(pid: str) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_text(errors="ignore")
    except OSError:  # gone
        return ""
