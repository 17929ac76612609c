"""Shared setup of the appearance stages' tests: the CLI in-process and tiny geolift uvmaps."""

from __future__ import annotations

from pathlib import Path


def cli_exit_code(*args) -> int:
    """Run ``egorelight ARGS`` in-process (as the console script does); returns its exit code."""
    from egorelight_cli.cli import main

    try:
        main([str(a) for a in args])
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def tiny_geolift_uvmaps(root: Path, capture: Path, skinned_meshes: Path, sequences) -> Path:
    """Train a tiny geolift model on ``relight_train`` into ``root/geolift`` and write
    ``root/uvmaps_<seq>`` (with the lighting features) for each of ``sequences``; returns ``root``."""
    assert cli_exit_code("--preset", "tiny", "-q", "train", "geolift", "--capture", capture, "--meshes",
                         skinned_meshes / "relight_train.npz", "--out", root / "geolift") == 0
    for seq in sequences:
        assert cli_exit_code("--preset", "tiny", "-q", "geolift", "--meshes", skinned_meshes / f"{seq}.npz", "--model",
                             root / "geolift", "--capture", capture, "--seq", seq, "--out", root / f"uvmaps_{seq}") == 0
    return root
