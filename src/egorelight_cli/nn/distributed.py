"""Data-parallel training under ``torchrun`` (``torch.distributed``: gloo on CPU, NCCL on CUDA).

``torchrun --nproc_per_node N egorelight train <stage> ...`` starts N processes with ``RANK``,
``WORLD_SIZE``, ``LOCAL_RANK`` and a rendezvous in the environment; :func:`init_from_environment`
joins them into one process group. Every process then runs the same training loop:

* each step's **global batch** is drawn (and augmented) exactly as a single process draws it, from
  the step's seed, and each rank keeps its contiguous share (:func:`rank_share`); the global batch
  must divide evenly among the ranks, so that the mean of the ranks' mean losses is the global
  batch's mean loss;
* after ``backward`` the gradients are averaged over the ranks (:func:`average_gradients`, one
  flat ``all_reduce``: what ``DistributedDataParallel`` does, without its forward hooks, because
  the stages' step functions call their modules directly), so every rank takes the same
  optimiser step and the parameters stay identical;
* rank 0 alone writes checkpoints and the model artifact; the others write nothing.

With a single process (no ``WORLD_SIZE`` or ``WORLD_SIZE=1``) every function here is a no-op.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError

T = TypeVar("T", torch.Tensor, np.ndarray, Sequence)


@dataclass(frozen=True)
class World:
    """This process's place in the process group (``rank`` 0 of ``size`` 1 when not distributed)."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    backend: str | None = None

    @property
    def distributed(self) -> bool:
        return self.size > 1

    @property
    def primary(self) -> bool:
        """Rank 0: the process that logs, checkpoints and writes the artifact."""
        return self.rank == 0

    def manifest(self) -> dict:
        """What the manifest's ``runtime.distributed`` records."""
        return {"world_size": self.size, "backend": self.backend, "launcher": "torchrun"}


def _env_int(name: str, default: int) -> int:
    value = os.environ.get(name)
    if value is None or value == "":
        return default
    try:
        return int(value)
    except ValueError:
        raise EgorelightError(f"environment variable {name}={value!r} is not an integer") from None


def requested_world_size() -> int:
    """``WORLD_SIZE`` from the environment (1 when unset): how many processes torchrun started."""
    return max(1, _env_int("WORLD_SIZE", 1))


def world() -> World:
    """The current process group (initialised by :func:`init_from_environment`), else a single process."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return World(torch.distributed.get_rank(), torch.distributed.get_world_size(), _env_int("LOCAL_RANK", 0),
                     torch.distributed.get_backend())
    return World()


def init_from_environment(device: torch.device) -> World:
    """Join the process group torchrun described in the environment (gloo on CPU, NCCL on CUDA);
    a single process when ``WORLD_SIZE`` is unset or 1. Idempotent."""
    if requested_world_size() == 1 or (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return world()
    if not torch.distributed.is_available():
        raise EgorelightError("WORLD_SIZE > 1 but this torch build has no torch.distributed")
    for name in ("RANK", "MASTER_ADDR", "MASTER_PORT"):
        if name not in os.environ:
            raise EgorelightError(f"WORLD_SIZE={os.environ['WORLD_SIZE']} but {name} is not set: start distributed "
                                  "training with torchrun --nproc_per_node N egorelight train ...")
    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(_env_int("LOCAL_RANK", 0))
    torch.distributed.init_process_group(backend=backend)
    return world()


def barrier() -> None:
    """Wait for every rank (no-op in a single process)."""
    if world().distributed:
        torch.distributed.barrier()


def shutdown() -> None:
    """Leave the process group (at the end of a distributed command)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()


def rank_share(batch: T) -> T:
    """This rank's contiguous share of a global batch (a tensor, array or list along its first
    axis); the whole batch in a single process. The batch must divide evenly among the ranks."""
    w = world()
    if not w.distributed:
        return batch
    n = len(batch)
    if n % w.size:
        raise EgorelightError(f"a global batch of {n} does not divide among {w.size} processes: set the stage's "
                              f"batch (train.batch, or train.views_per_step for geolift and relight) to a multiple "
                              f"of {w.size}")
    share = n // w.size
    return batch[w.rank * share:(w.rank + 1) * share]


def average_gradients(parameters: Iterable[torch.nn.Parameter]) -> None:
    """Average the gradients over the ranks in place (one flat all-reduce); a parameter without a
    gradient on this rank counts as a zero gradient, so every rank reduces the same tensors."""
    w = world()
    if not w.distributed:
        return
    params = [p for p in parameters if p.requires_grad]
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
    flat = torch.cat([g.reshape(-1) for g in grads])
    torch.distributed.all_reduce(flat, op=torch.distributed.ReduceOp.SUM)
    flat /= w.size
    offset = 0
    for p, g in zip(params, grads):
        count = g.numel()
        p.grad = flat[offset:offset + count].view_as(p).clone()
        offset += count


def average_values(values: dict[str, float]) -> dict[str, float]:
    """The ranks' mean of each logged value (the same keys on every rank)."""
    w = world()
    if not w.distributed or not values:
        return values
    names = sorted(values)
    flat = torch.tensor([float(values[k]) for k in names], dtype=torch.float64)
    torch.distributed.all_reduce(flat, op=torch.distributed.ReduceOp.SUM)
    return {k: float(v) / w.size for k, v in zip(names, flat.tolist())}
