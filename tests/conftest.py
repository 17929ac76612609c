"""Shared pytest fixtures."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import pytest

# a pytest-xdist worker (make test: one per core) takes its share of the cores: every worker at
# every core would make torch, BLAS and the CLI runs it starts fight over them (OMP_NUM_THREADS
# is what --threads and the Makefile's nproc default to); a value the user set is kept
# (before anything imports torch)
if os.environ.get("PYTEST_XDIST_WORKER") and "OMP_NUM_THREADS" not in os.environ:
    from egorelight_cli.runtime import available_cores

    _workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    os.environ["OMP_NUM_THREADS"] = str(max(1, available_cores()[0] // _workers))

# this session's persistent digest cache (egorelight_cli.digest_cache), not the user's ~/.cache;
# the CLI subprocesses inherit it; removed when the session ends
os.environ["EGORELIGHT_CACHE_DIR"] = tempfile.mkdtemp(prefix="egorelight-digests-")
atexit.register(shutil.rmtree, os.environ["EGORELIGHT_CACHE_DIR"], ignore_errors=True)

from egorelight_cli.io.character import load_default_character

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DDC_EXAMPLE = SHARED / "data" / "ddc_example"
BVH_EXAMPLE = SHARED / "data" / "motion" / "cmu_131_01_start_walk_stop.bvh"


#: the modules that share the session's ``tiny_avatar``: under pytest-xdist they run on one worker,
#: which builds it once (a module using it must be listed: collection says so otherwise)
TINY_AVATAR_MODULES = ("test_composite.py", "test_envmap_inverse.py", "test_relight.py")


def pytest_xdist_auto_num_workers(config) -> int:
    """``-n auto``: one worker per core this process may use (affinity, cgroup quota,
    OMP_NUM_THREADS, Slurm: what ``--threads`` defaults to), not the host's core count."""
    from egorelight_cli.runtime import available_cores

    return available_cores()[0]


def pytest_xdist_make_scheduler(config, log):
    """``pytest -n N`` (``make test``) hands out whole modules (:mod:`module_scheduling`) unless
    another ``--dist`` mode is asked for."""
    if config.getvalue("dist") != "load":
        return None
    from module_scheduling import ModuleScheduling

    return ModuleScheduling(config, log, {name: "tiny_avatar" for name in TINY_AVATAR_MODULES})


def pytest_collection_modifyitems(config, items) -> None:
    """Checks :data:`TINY_AVATAR_MODULES`; on a pytest-xdist worker, puts the modules holding a
    ``slow`` test first, so that the longest work units are handed out first and do not end the
    run alone (without xdist the order is unchanged)."""
    by_module: dict[Path, list] = {}
    for item in items:
        by_module.setdefault(item.path, []).append(item)
    for path, module_items in by_module.items():
        if path.name not in TINY_AVATAR_MODULES and any("tiny_avatar" in i.fixturenames for i in module_items):
            raise pytest.UsageError(f"{path.name} uses tiny_avatar: list it in conftest.TINY_AVATAR_MODULES")
    if os.environ.get("PYTEST_XDIST_WORKER"):
        slow_first = sorted(by_module, key=lambda p: not any(i.get_closest_marker("slow") for i in by_module[p]))
        items[:] = [item for path in slow_first for item in by_module[path]]


@pytest.fixture
def ddc_example() -> Path:
    """The real DDC example character directory; skips when ../shared is absent."""
    if not (DDC_EXAMPLE / "ddc.character").exists():
        pytest.skip("../shared/data/ddc_example is not available")
    return DDC_EXAMPLE


@pytest.fixture(scope="session")
def character():
    """The shipped default character (shared, read-only: tests must not modify it)."""
    return load_default_character()


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> Path:
    """One ``egorelight synth --preset tiny`` capture per test session (about 40 s on 2 cores),
    with a user HDR map added to the test lighting. Read-only: tests must not modify it."""
    from egorelight_cli.cli import main
    from egorelight_cli.render.envmaps import make_envmap, write_envmap

    root = tmp_path_factory.mktemp("synth")
    user_map = root / "my_room.exr"
    write_envmap(user_map, make_envmap("indoor", 123, 16))
    out = root / "capture"
    with pytest.raises(SystemExit) as exit_info:
        main(["synth", "--preset", "tiny", "--out", str(out), "--envmap", str(user_map), "-q"])
    assert exit_info.value.code == 0
    return out


@pytest.fixture(scope="session")
def skinned_meshes(tiny_capture, tmp_path_factory) -> Path:
    """Tracked meshes in the character's topology for every sequence of the tiny capture: the
    default character posed with the TRUE motion by its own skinning (no graph offsets), as
    ``<seq>.npz`` meshes payloads. The true surface is the subject's own (another topology), so
    the appearance stages' tests drive them with these instead. Read-only."""
    import numpy as np
    import torch

    from egorelight_cli.geometry.embedded_graph import pose_character
    from egorelight_cli.io.mesh_sequence import MeshSequence, write_meshes_npz
    from egorelight_cli.io.npz import read_npz

    character = load_default_character()
    out = tmp_path_factory.mktemp("skinned")
    for folder in sorted((tiny_capture / "groundtruth").iterdir()):
        if not (folder / "meshes.npz").is_file():
            continue
        arrays, _ = read_npz(folder / "meshes.npz")
        theta = arrays["theta"].astype(np.float64)
        vertices = pose_character(character, torch.as_tensor(theta), skinning="dqs").numpy().astype(np.float32)
        T, N = len(theta), character.graph.num_nodes
        zeros = np.zeros((T, N, 3), np.float32)
        write_meshes_npz(out / f"{folder.name}.npz", MeshSequence(
            vertices, character.faces.astype(np.int32), theta.astype(np.float32), zeros, zeros,
            np.zeros_like(vertices), arrays["frame_ids"], ego_frame_ids=arrays.get("ego_frame_ids")))
    return out


@pytest.fixture(scope="session")
def tiny_avatar(tiny_capture, skinned_meshes, tmp_path_factory) -> Path:
    """The appearance stages' shared tiny avatar, in one folder: a geolift model (``geolift``),
    uvmaps with lighting features of relight_train, wild, ego_train and test (``uvmaps_<seq>``)
    and a relight model trained 4 steps on relight_train (``relight``). Read-only; a module may add
    an output of its own under a name nobody else uses (composite's ``envmap``)."""
    from tiny_models import cli_exit_code, tiny_geolift_uvmaps

    root = tmp_path_factory.mktemp("avatar")
    tiny_geolift_uvmaps(root, tiny_capture, skinned_meshes, ("relight_train", "wild", "ego_train", "test"))
    assert cli_exit_code("--preset", "tiny", "-q", "--set", "train.steps=4", "train", "relight", "--capture",
                         tiny_capture, "--meshes", skinned_meshes / "relight_train.npz", "--uvmaps",
                         root / "uvmaps_relight_train", "--out", root / "relight") == 0
    return root


@pytest.fixture(scope="session")
def oracle_calibration(tiny_capture):
    """The tiny capture's calibration taken from its ground truth (for stages downstream of calibrate)."""
    from egorelight_cli.synth.groundtruth import oracle_calibration as from_groundtruth

    return from_groundtruth(tiny_capture)


@pytest.fixture(scope="session")
def oracle_calibration_artifact(tiny_capture, tmp_path_factory) -> Path:
    """The oracle calibration written as a calibration artifact directory."""
    from egorelight_cli.synth.groundtruth import write_oracle_calibration

    return write_oracle_calibration(tiny_capture, tmp_path_factory.mktemp("oracle") / "calibration")


@dataclass
class Result:
    """What a CLI run ended with: exit code, stderr and stdout."""

    returncode: int
    stderr: str
    stdout: str = ""


@pytest.fixture
def run(capsys):
    """The CLI in-process (``main`` as the console script runs it): ``run(*args) -> Result``."""
    from egorelight_cli.cli import main

    def invoke(*args) -> Result:
        capsys.readouterr()
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as exc:
            code = int(exc.code or 0)
        captured = capsys.readouterr()
        return Result(code, captured.err, captured.out)
    return invoke
