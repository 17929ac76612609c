"""Run-time choices shared by every stage: compute device, thread counts and seeding."""

from __future__ import annotations

import functools
import math
import os
import random
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError

# Idle OpenMP threads (torch's libgomp) sleep instead of spinning: next to other busy processes a
# spinning worker burns the time slice its partner needs to reach the barrier (ik lm on 400 DDC
# frames, 2 threads, 2 busy processes on 2 cores: 57 s spinning, 3-5 s passive; idle unchanged).
# libgomp reads this once when torch is loaded, so it is set here, before anything imports torch.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

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


def _positive_int(text: str | None) -> int | None:
    try:
        value = int(str(text).split(",")[0].strip())
    except (TypeError, ValueError):
        return None
    return value if value > 0 else None


def _cgroup_cores(root: Path) -> int | None:
    """CPUs allowed by the cgroup quota: v2 ``cpu.max`` ("quota period" or "max period"), else v1
    ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``; ``None`` without a quota. Rounded up."""
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
    except (OSError, ValueError):
        try:
            quota = (root / "cpu" / "cpu.cfs_quota_us").read_text().strip()
            period = (root / "cpu" / "cpu.cfs_period_us").read_text().strip()
        except OSError:
            return None
    try:
        quota_us, period_us = float(quota), float(period)
    except ValueError:  # "max": no quota
        return None
    if quota_us <= 0 or period_us <= 0:
        return None
    return max(1, math.ceil(quota_us / period_us))


def core_limits(environ: Mapping[str, str] | None = None, affinity: int | None = None,
                cgroup: str | Path = "/sys/fs/cgroup") -> dict[str, int]:
    """Every limit on the cores this process may use, by source: ``affinity`` (the CPUs it may
    run on), ``cgroup`` (the container's CPU quota), ``OMP_NUM_THREADS`` and Slurm's
    ``SLURM_CPUS_PER_TASK`` (when set to a positive integer). Arguments override the real
    environment (for tests)."""
    environ = os.environ if environ is None else environ
    if affinity is None:
        try:
            affinity = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):  # not on Linux
            affinity = os.cpu_count() or 1
    limits = {"affinity": max(1, int(affinity))}
    quota = _cgroup_cores(Path(cgroup))
    if quota is not None:
        limits["cgroup"] = quota
    for name in ("OMP_NUM_THREADS", "SLURM_CPUS_PER_TASK"):
        value = _positive_int(environ.get(name))
        if value is not None:
            limits[name] = value
    return limits


def available_cores(environ: Mapping[str, str] | None = None, affinity: int | None = None,
                    cgroup: str | Path = "/sys/fs/cgroup") -> tuple[int, str]:
    """The cores this process may use (the smallest of :func:`core_limits`) and the source that
    decided it; the default of ``--threads``."""
    limits = core_limits(environ, affinity, cgroup)
    source = min(limits, key=lambda k: (limits[k], k != "affinity"))
    return limits[source], source


def parse_threads(text: str | int | None) -> int | None:
    """``--threads`` as given: ``None`` (not given) or a positive integer, else a one-line error."""
    if text is None:
        return None
    value = _positive_int(text) if str(text).strip().lstrip("+").isdigit() else None
    if value is None:
        raise EgorelightError(f"--threads must be a positive integer, got {text!r}")
    return value


def apply_threads(n: int) -> int:
    """Use ``n`` threads in every thread pool a stage may run: torch (intra-op, and inter-op when
    torch still allows setting it), BLAS/OpenMP libraries (threadpoolctl: OpenBLAS, MKL, the
    OpenMP runtime torch uses) and OpenCV. Returns ``n``; a value below 1 is a one-line error.

    More threads than cores is what made stages 5-16x slower next to other jobs (thread pools
    spinning at barriers for a time slice), so this runs once per stage run, before the stage.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise EgorelightError(f"--threads must be a positive integer, got {n!r}")
    import scipy.linalg  # noqa: F401  (loaded now, so that the limit below covers its OpenBLAS)
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(n)
    if torch.get_num_interop_threads() != n:
        try:
            torch.set_num_interop_threads(n)
        except RuntimeError:  # only settable once, before the first inter-op parallel work
            pass
    try:
        import cv2
    except ImportError:  # OpenCV is optional for some stages' environments
        cv2 = None
    if cv2 is not None:
        cv2.setNumThreads(n)
    threadpool_limits(limits=n)  # every BLAS/OpenMP library loaded by now (numpy, scipy, torch, cv2)
    return n


@contextmanager
def single_threaded_openmp() -> Iterator[None]:
    """One thread in every OpenMP runtime loaded by now, inside the block, whichever one pymeshlab
    uses (the libgomp it ships, out of :func:`apply_threads`' reach when loaded later, or torch's
    under ``--threads``). One thread gives its filters one result whatever the thread count and
    the machine's load: synth's scan, remeshed under ``--threads 2`` while four processes shared
    two cores, once came out different from the ``--threads 1`` run."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="openmp"):
        yield


@functools.lru_cache(maxsize=1)
def _blas_controller() -> "threadpoolctl.ThreadpoolController":  # noqa: F821
    import scipy.linalg  # noqa: F401  (its OpenBLAS is one of the libraries to control)
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController().select(user_api="blas")


@contextmanager
def blas_threads(n: int) -> Iterator[None]:
    """Limit the BLAS libraries (OpenBLAS, MKL) to ``n`` threads inside the block, restoring the
    run's setting after: for long chains of small BLAS calls (ik's banded Cholesky), whose thread
    barriers cost more than the threads gain and wait for a time slice on a busy machine (the same
    factorisation measured at 0.02 s and 8 s). Cheap enough to enter per solver iteration."""
    with _blas_controller().limit(limits=n):
        yield


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
