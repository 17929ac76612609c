"""Fuzz the readers through the CLI: seeded random truncations and bit flips of npz, EXR,
manifest (JSON), BVH and DDC files must end in exit 0 or in exit 2 with exactly one line on
stderr (``egorelight: error: ...``), never in an internal error (exit 1) or a traceback.

Each reader gets a bounded number of mutations of a small valid file; the whole file runs in well
under a minute on two cores. The BVH and DDC cases read the reference data in ``../shared`` and
skip when it is absent.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import BVH_EXAMPLE

MUTATIONS = 12  # per reader: half truncations, half bit flips


def mutations(data: bytes, seed: int, count: int = MUTATIONS):
    """``count`` seeded variants of ``data``: truncations to a random length, then 1-8 bit flips."""
    rng = np.random.default_rng(seed)
    for i in range(count):
        if i % 2 == 0:
            yield f"truncated to {(n := int(rng.integers(0, len(data))))} bytes", data[:n]
        else:
            mutated = bytearray(data)
            positions = rng.integers(0, len(data), int(rng.integers(1, 9)))
            for p in positions:
                mutated[p] ^= 1 << int(rng.integers(0, 8))
            yield f"bits flipped at {sorted(int(p) for p in positions)}", bytes(mutated)


def check_each_mutation(run, target: Path, args, seed: int, count: int = MUTATIONS, must_fail: bool = False) -> None:
    """Run ``egorelight *args`` once per mutation of ``target`` (restored afterwards); with
    ``must_fail`` (a payload its manifest holds the digest of) exit 0 is not accepted either."""
    original = target.read_bytes()
    failures = []
    try:
        for what, data in mutations(original, seed, count):
            target.write_bytes(data)
            result = run(*args, "-q")
            lines = result.stderr.strip().splitlines()
            ok = (result.returncode == 0 and not must_fail) or (
                result.returncode == 2 and len(lines) == 1 and lines[0].startswith("egorelight: error:"))
            if not ok or "Traceback" in result.stderr:
                failures.append(f"{target.name} {what}: exit {result.returncode}: {result.stderr.strip()[:300]}")
    finally:
        target.write_bytes(original)
    assert not failures, "\n".join(failures)


@pytest.fixture(scope="module")
def small_artifacts(tmp_path_factory) -> Path:
    """A keypoints npz (lone and with its sidecar), an EXR and a character artifact directory."""
    from egorelight_cli.artifacts import ArtifactWriter
    from egorelight_cli.io.exr import write_exr

    root = tmp_path_factory.mktemp("fuzz")
    rng = np.random.default_rng(0)
    with ArtifactWriter(root / "kp.npz", kind="keypoints", stage="test") as writer:
        writer.save_npz("kp.npz", {"xyz": rng.normal(0, 0.3, (3, 57, 3)).astype(np.float32) + [0, 1, 0],
                                   "confidence": np.ones((3, 57), np.float32), "frame_ids": np.arange(3)},
                        frame_ids=np.arange(3), units={"xyz": "m"})
    write_exr(root / "image.exr", {"R": rng.random((8, 8)).astype(np.float32),
                                   "G": rng.random((8, 8)).astype(np.float32)})
    with ArtifactWriter(root / "art", kind="keypoints", stage="test") as writer:
        writer.save_json("info.json", {"frames": 3})
    return root


def test_npz_reader(run, small_artifacts, tmp_path):
    lone = tmp_path / "lone.npz"
    shutil.copy(small_artifacts / "kp.npz", lone)
    check_each_mutation(run, lone, ("inspect", lone), seed=1)
    check_each_mutation(run, lone, ("ik", "--preset", "tiny", "--in", lone, "--out", tmp_path / "m.npz"), seed=2,
                        count=60)  # most corruptions fail fast: many cases


def test_exr_reader(run, small_artifacts):
    path = small_artifacts / "image.exr"
    check_each_mutation(run, path, ("inspect", path), seed=3)


def test_manifest_reader(run, small_artifacts, tmp_path):
    check_each_mutation(run, small_artifacts / "art" / "manifest.json", ("inspect", small_artifacts / "art"), seed=4)
    single = small_artifacts / "kp.npz"
    check_each_mutation(run, single.with_name("kp.npz.json"), ("inspect", single), seed=5)
    check_each_mutation(run, single.with_name("kp.npz.json"),
                        ("ik", "--preset", "tiny", "--in", single, "--out", tmp_path / "m.npz"), seed=6)
    # the payload of a single-file artifact: its sidecar holds its digest, so every change is caught
    check_each_mutation(run, single, ("ik", "--preset", "tiny", "--in", single, "--out", tmp_path / "p.npz"), seed=12,
                        count=6, must_fail=True)


def test_bvh_reader(run, tmp_path):
    if not BVH_EXAMPLE.is_file():
        pytest.skip("../shared/data/motion is not available")
    text = BVH_EXAMPLE.read_text()
    head, motion = text.split("MOTION", 1)
    lines = motion.strip().splitlines()
    frames = [line for line in lines if line and line[0] in "-0123456789"][:3]
    clip = tmp_path / "clip.bvh"
    clip.write_text(head + "MOTION\nFrames: 3\n" + next(l for l in lines if l.startswith("Frame Time")) + "\n"
                    + "\n".join(frames) + "\n")
    check_each_mutation(run, clip, ("ik", "--preset", "tiny", "--in", clip, "--out", tmp_path / "m.npz"), seed=7)


def test_ddc_readers(run, ddc_example, tmp_path):
    ddc = tmp_path / "ddc"
    shutil.copytree(ddc_example, ddc)
    motion = ddc / "ddc.motion"
    motion.write_text("\n".join(motion.read_text().splitlines()[:3]) + "\n")  # header + 2 frames: fast
    for seed, name in enumerate(("ddc.character", "ddc.skeleton", "ddc.skin"), start=8):
        check_each_mutation(run, ddc / name, ("character", "import-ddc", ddc / "ddc.character",
                                              "--out", tmp_path / f"c{seed}"), seed=seed)
    check_each_mutation(run, motion, ("ik", "--preset", "tiny", "--in", motion, "--character", ddc / "ddc.character",
                                      "--out", tmp_path / "m.npz"), seed=11)
