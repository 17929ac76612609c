"""Swapping a finished output into place: rollback on failure, repair after a killed swap."""

from __future__ import annotations

import errno
import os
import subprocess
import sys

import pytest

from egorelight_cli import atomic_output
from egorelight_cli.artifacts import ArtifactWriter
from egorelight_cli.atomic_output import (remove_stale_temporaries, replace_directory, replace_file_pair,
                                          restore_interrupted_swap)
from egorelight_cli.errors import EgorelightError


@pytest.fixture(scope="module")
def dead_pid() -> int:
    """The pid of a process that has exited."""
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(done.stdout)


def _pair(folder, payload: bytes, manifest: bytes):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "m.npz").write_bytes(payload)
    (folder / "m.npz.json").write_bytes(manifest)
    return folder / "m.npz", folder / "m.npz.json"


def _rename_fails(monkeypatch, source, error: int) -> None:
    """``os.replace`` as the swap calls it fails for ``source`` (and works for anything else)."""
    real = os.replace

    def replace(src, dst):
        if str(src) == str(source):
            raise OSError(error, os.strerror(error), str(dst))
        real(src, dst)

    monkeypatch.setattr(atomic_output.os, "replace", replace)


def test_a_file_pair_is_replaced_and_nothing_is_left_beside_it(tmp_path):
    out, sidecar = _pair(tmp_path, b"old", b"old manifest")
    new, new_sidecar = _pair(tmp_path / ".m.npz.tmp-1-x", b"new", b"new manifest")
    replace_file_pair(new, new_sidecar, out, sidecar)
    assert (out.read_bytes(), sidecar.read_bytes()) == (b"new", b"new manifest")
    assert sorted(p.name for p in tmp_path.iterdir()) == [".m.npz.tmp-1-x", "m.npz", "m.npz.json"]


def test_a_failed_file_pair_swap_puts_the_old_pair_back(tmp_path, monkeypatch):
    """The sidecar's rename fails after the payload's: the old pair comes back whole (before, the
    new payload stood beside the old sidecar, neither readable)."""
    out, sidecar = _pair(tmp_path, b"old", b"old manifest")
    new, new_sidecar = _pair(tmp_path / "work", b"new", b"new manifest")
    _rename_fails(monkeypatch, new_sidecar, errno.EPERM)
    with pytest.raises(OSError):
        replace_file_pair(new, new_sidecar, out, sidecar)
    assert (out.read_bytes(), sidecar.read_bytes()) == (b"old", b"old manifest")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz", "m.npz.json", "work"]


def test_a_failed_payload_rename_and_a_first_write_leave_nothing_aside(tmp_path, monkeypatch):
    out, sidecar = _pair(tmp_path / "out", b"old", b"old manifest")
    new, new_sidecar = _pair(tmp_path / "work", b"new", b"new manifest")
    _rename_fails(monkeypatch, new, errno.ENOSPC)  # the first of the two new files
    with pytest.raises(OSError):
        replace_file_pair(new, new_sidecar, out, sidecar)
    assert (out.read_bytes(), sidecar.read_bytes()) == (b"old", b"old manifest")
    assert sorted(p.name for p in out.parent.iterdir()) == ["m.npz", "m.npz.json"]
    monkeypatch.undo()
    first = tmp_path / "first"
    first.mkdir()
    replace_file_pair(new, new_sidecar, first / "m.npz", first / "m.npz.json")
    assert sorted(p.name for p in first.iterdir()) == ["m.npz", "m.npz.json"]


def test_our_own_pid_on_a_leftover_is_a_killed_runs(tmp_path):
    """In a container every run may be pid 1: a leftover with our pid is from a run before us."""
    out = tmp_path / "motion"
    aside = tmp_path / f".motion.old-{os.getpid()}-0123abcd"
    aside.mkdir()
    (aside / "manifest.json").write_text("{}")
    assert restore_interrupted_swap(out) == [out] and (out / "manifest.json").is_file()


def test_only_a_finished_directory_is_put_back(tmp_path, dead_pid):
    """What lies aside without its manifest was never a finished output: removed, not restored."""
    out = tmp_path / "motion"
    aside = tmp_path / f".motion.old-{dead_pid}-0123abcd"
    aside.mkdir()
    (aside / "motion.npz").write_bytes(b"half written")
    assert restore_interrupted_swap(out) == [] and remove_stale_temporaries(out) == [aside]
    assert list(tmp_path.iterdir()) == []


def test_a_directory_a_killed_swap_left_aside_is_put_back(tmp_path, dead_pid):
    out = tmp_path / "motion"
    aside = tmp_path / f".motion.old-{dead_pid}-0123abcd"  # renamed aside, then SIGKILL
    aside.mkdir()
    (aside / "manifest.json").write_text("{}")
    assert restore_interrupted_swap(out) == [out]
    assert (out / "manifest.json").read_text() == "{}" and not aside.exists()
    # an output that exists is the new one: what is aside is stale, and removed
    aside.mkdir()
    assert restore_interrupted_swap(out) == [] and remove_stale_temporaries(out) == [aside]
    assert out.is_dir() and not aside.exists()


@pytest.mark.parametrize("killed_after", ["payload aside", "sidecar aside", "new payload in place"])
def test_a_file_pair_a_killed_swap_left_half_done_is_put_back(tmp_path, dead_pid, killed_after):
    out, sidecar = _pair(tmp_path, b"old", b"old manifest")
    os.replace(out, tmp_path / f".m.npz.old-{dead_pid}-aaaa")
    if killed_after != "payload aside":
        os.replace(sidecar, tmp_path / f".m.npz.json.old-{dead_pid}-bbbb")
    if killed_after == "new payload in place":
        out.write_bytes(b"new")
    remove_stale_temporaries(out)
    assert (out.read_bytes(), sidecar.read_bytes()) == (b"old", b"old manifest")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz", "m.npz.json"]


def test_a_file_pair_whose_new_sidecar_landed_stands(tmp_path, dead_pid):
    out, sidecar = _pair(tmp_path, b"new", b"new manifest")  # killed before the old pair was removed
    (tmp_path / f".m.npz.old-{dead_pid}-aaaa").write_bytes(b"old")
    (tmp_path / f".m.npz.json.old-{dead_pid}-bbbb").write_bytes(b"old manifest")
    remove_stale_temporaries(out)
    assert (out.read_bytes(), sidecar.read_bytes()) == (b"new", b"new manifest")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz", "m.npz.json"]


def test_a_live_runs_aside_copy_is_not_touched(tmp_path):
    out = tmp_path / "motion"
    live = tmp_path / f".motion.old-{os.getppid()}-0123abcd"  # our parent: a run still swapping
    live.mkdir()
    assert restore_interrupted_swap(out) == [] and remove_stale_temporaries(out) == []
    assert live.is_dir() and not out.exists()


def test_a_failed_directory_swap_keeps_the_old_directory(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a").write_text("old")
    work = tmp_path / ".out.tmp-1-x"
    work.mkdir()
    _rename_fails(monkeypatch, work, errno.ENOSPC)
    with pytest.raises(OSError):
        replace_directory(work, out)
    assert (out / "a").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.tmp-1-x", "out"]


def test_a_full_disk_while_writing_is_a_one_line_output_error(tmp_path):
    """An OSError of the writing (disk full) is the usual output error naming the output, not an
    internal error; the half-written work folder is gone."""
    with pytest.raises(EgorelightError, match=r"cannot write the output \(No space left on device\)"):
        with ArtifactWriter(tmp_path / "m", kind="motion", stage="ik", config={}):
            raise OSError(errno.ENOSPC, "No space left on device")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(FileNotFoundError):  # an input's error is not the output's
        with ArtifactWriter(tmp_path / "m", kind="motion", stage="ik", config={}):
            raise FileNotFoundError(errno.ENOENT, "No such file or directory", str(tmp_path / "input.npz"))
