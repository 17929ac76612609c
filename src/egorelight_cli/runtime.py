"""Run-time choices shared by every stage: compute device and seeding."""

from __future__ import annotations

import random
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from egorelight_cli.errors import EgorelightError

DEVICES = ("auto", "cpu", "cuda")


def resolve_device(name: str = "auto") -> "torch.device":  # noqa: F821
    """``auto`` -> CUDA when available, else CPU; ``cuda`` without a GPU is an error."""
    import torch

    if name not in DEVICES:
        raise EgorelightError(f"unknown device {name!r}; choose one of {', '.join(DEVICES)}")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise EgorelightError("--device cuda was requested but no CUDA device is available")
    return torch.device(name)


def seed_everything(seed: int) -> np.random.Generator:
    """Seed Python, NumPy and torch; returns a NumPy Generator for explicit use."""
    import torch

    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)
    return np.random.default_rng(seed)


@contextmanager
def single_torch_thread() -> Iterator[None]:
    """Run torch ops (camera unprojection) on one intra-op thread, restoring the setting after.

    The unprojection of a camera's pixel grid takes ~20 ms single-threaded, but with torch's
    default thread pool on a loaded CPU (other processes, Embree's threads) its many small
    parallel regions were measured 10-100x slower (up to seconds per view).
    """
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
