"""Run-time choices shared by every stage: compute device and seeding."""

from __future__ import annotations

import random
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from egorelight_cli.errors import EgorelightError

DEVICES = ("auto", "cpu", "cuda")
# stages with a CUDA code path; every other stage runs on the CPU and refuses --device cuda
CUDA_STAGES = frozenset({"egodepth", "animate"})


def resolve_device(name: str = "auto", stage: str | None = None) -> "torch.device":  # noqa: F821
    """The device a run actually uses, or a one-line error; the manifest records this one.

    ``auto`` -> CUDA when available, else CPU; ``cuda`` without a GPU is an error. With ``stage``
    given, a stage outside :data:`CUDA_STAGES` runs on the CPU: ``auto`` resolves to ``cpu`` and
    ``cuda`` is an error (it would otherwise run on the CPU while the user believes otherwise).
    """
    import torch

    if name not in DEVICES:
        raise EgorelightError(f"unknown device {name!r}; choose one of {', '.join(DEVICES)}")
    if stage is not None and stage not in CUDA_STAGES:
        if name == "cuda":
            raise EgorelightError(f"--device cuda: the {stage} stage has no CUDA code path and runs on the CPU; "
                                  "use --device cpu (or auto)")
        return torch.device("cpu")
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
