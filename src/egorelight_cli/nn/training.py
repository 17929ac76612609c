"""A small training loop shared by every learned stage: checkpoints, resume, curve, progress.

The stage supplies ``step_fn(step) -> {"loss": tensor, <other losses>: tensors}`` (it draws its
own batch, seeded by the step); :func:`train` runs the optimiser, logs the losses, saves a
checkpoint every ``checkpoint_every`` steps and, only when asked (``--resume``, see
:class:`Checkpoint`), continues a killed run from a checkpoint of the same cache key with its
optimiser and learning-rate schedule restored. With a :class:`BestOnValidation` it scores the model
on held-out samples before the first step and every ``every`` steps, and ends with the weights that
scored best (early stopping by model selection).

Under ``torchrun`` (:mod:`egorelight_cli.nn.distributed`) the step function computes its loss on
this rank's share of the step's global batch, the loop averages the gradients over the ranks
before each optimiser step and the logged losses over the ranks, and only rank 0 checkpoints.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from egorelight_cli import console
from egorelight_cli.atomic_output import remove_stale_temporaries, temporary_sibling
from egorelight_cli.errors import EgorelightError
from egorelight_cli.nn.distributed import average_gradients, average_values, world


@dataclass(frozen=True)
class Checkpoint:
    """Where a training run keeps its resumable state, and whether to continue from it.

    A run without ``resume`` ignores (and later replaces) an existing checkpoint. With
    ``resume``, a checkpoint is continued only when it was written under the same ``key`` (the
    run's cache key: stage, config, options and input digests); one made with another key is a
    one-line error (run without ``--resume`` to start over), never a silent mix of two runs.
    ``checkpoint / "name.pt"`` is the same choice for a file below ``path`` (a stage with phases).
    """

    path: Path
    key: str | None = None
    resume: bool = False

    def __truediv__(self, name: str) -> "Checkpoint":
        return replace(self, path=Path(self.path) / name)


@dataclass
class BestOnValidation:
    """Keeps the weights that score lowest on held-out samples during :func:`train`.

    ``score()`` (no gradients, the model in eval mode) returns the validation error of the model as
    it stands; :func:`train` calls it before the first step, every ``every`` steps and after the
    last, and restores the best weights at the end. ``first`` / ``best`` / ``best_step`` say what it
    saw (step 0: the untrained model). The state travels in the checkpoint, so a resumed run selects
    as an uninterrupted one would.
    """

    score: Callable[[], float]
    every: int
    first: float | None = None
    best: float | None = None
    best_step: int | None = None
    best_state: dict | None = field(default=None, repr=False)

    def observe(self, model: torch.nn.Module, step: int) -> float:
        """Score ``model`` after ``step`` steps; keep a copy of its weights when it is the best so far."""
        model.eval()
        with torch.no_grad():
            value = float(self.score())
        model.train()
        if self.first is None:
            self.first = value
        if self.best is None or value < self.best:
            self.best, self.best_step = value, step
            self.best_state = copy.deepcopy(model.state_dict())
        return value

    def restore(self, model: torch.nn.Module) -> None:
        """Load the best weights seen into ``model``."""
        if self.best_state is not None:
            model.load_state_dict(self.best_state)

    def state(self) -> dict:
        return {"first": self.first, "best": self.best, "best_step": self.best_step, "best_state": self.best_state}

    def load(self, state: dict | None) -> None:
        if state:
            self.first, self.best, self.best_step = state["first"], state["best"], state["best_step"]
            self.best_state = state["best_state"]


def checkpoint_beside(out: str | Path, suffix: str = ".pt") -> Path:
    """The hidden checkpoint location of a training run writing ``out``: ``.<name>.checkpoint<suffix>``
    next to it (removed once the model artifact is written)."""
    out = Path(out)
    return out.parent / f".{out.name}.checkpoint{suffix}"


def as_checkpoint(checkpoint: "Checkpoint | str | Path | None") -> Checkpoint | None:
    """A plain path is a checkpoint that is written but never resumed from."""
    if checkpoint is None or isinstance(checkpoint, Checkpoint):
        return checkpoint
    return Checkpoint(Path(checkpoint))


def save_checkpoint(checkpoint: Checkpoint, model: torch.nn.Module, optimizer: torch.optim.Optimizer, step: int,
                    curve: list[dict[str, float]], scheduler: torch.optim.lr_scheduler.LRScheduler | None = None,
                    selection: BestOnValidation | None = None) -> None:
    """Atomically write a resumable checkpoint: model, optimiser, scheduler, RNG, step, curve, key
    and the validation selection's state."""
    path = Path(checkpoint.path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)  # a save a kill interrupted
    tmp = temporary_sibling(path)
    try:
        torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                    "scheduler": scheduler.state_dict() if scheduler is not None else None, "step": step,
                    "curve": curve, "torch_rng": torch.get_rng_state(), "key": checkpoint.key,
                    "selection": selection.state() if selection is not None else None}, tmp)
        os.replace(tmp, path)
    except BaseException:  # interrupted mid-save: the previous checkpoint stands, no half file beside it
        tmp.unlink(missing_ok=True)
        raise


def load_checkpoint(checkpoint: Checkpoint, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
                    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None,
                    selection: BestOnValidation | None = None) -> tuple[int, list]:
    """Restore model, optimiser, scheduler and RNG; returns (next step, curve so far)."""
    path = checkpoint.path
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise EgorelightError(f"cannot resume from checkpoint ({type(exc).__name__}: {exc}); run without --resume "
                              "to start over", path) from None
    if not isinstance(data, dict) or data.get("key") != checkpoint.key:
        raise EgorelightError("cannot resume: the checkpoint was made with other settings or inputs (its cache key "
                              "differs); run without --resume to start over", path)
    if (scheduler is not None) != (data.get("scheduler") is not None):
        raise EgorelightError("cannot resume: the checkpoint's learning-rate schedule does not match this run", path)
    try:
        model.load_state_dict(data["model"])
        optimizer.load_state_dict(data["optimizer"])
        if scheduler is not None:
            scheduler.load_state_dict(data["scheduler"])
        torch.set_rng_state(data["torch_rng"])
        if selection is not None:
            selection.load(data.get("selection"))
        return int(data["step"]), list(data["curve"])
    except Exception as exc:
        raise EgorelightError(f"cannot resume from checkpoint ({type(exc).__name__}: {exc}); run without --resume "
                              "to start over", path) from None


def _start(checkpoint: Checkpoint | None, model, optimizer, scheduler, desc: str,
           selection: BestOnValidation | None = None) -> tuple[int, list]:
    """(first step, curve): from the checkpoint when resuming, else from scratch."""
    if checkpoint is None:
        return 0, []
    if not checkpoint.resume:
        if Path(checkpoint.path).is_file():
            console.info(f"{desc}: starting from step 0; the existing checkpoint {checkpoint.path} is ignored and "
                         "replaced (--resume continues from it)")
        return 0, []
    if not Path(checkpoint.path).is_file():
        console.info(f"{desc}: --resume given but there is no checkpoint at {checkpoint.path}; starting from step 0")
        return 0, []
    start, curve = load_checkpoint(checkpoint, model, optimizer, scheduler, selection)
    console.info(f"resuming {desc} at step {start} from {checkpoint.path}")
    return start, curve


def train(model: torch.nn.Module, optimizer: torch.optim.Optimizer,
          step_fn: Callable[[int], dict[str, torch.Tensor]], num_steps: int,
          checkpoint: Checkpoint | str | Path | None = None, checkpoint_every: int = 200, log_every: int = 10,
          scheduler: torch.optim.lr_scheduler.LRScheduler | None = None, desc: str = "training",
          selection: BestOnValidation | None = None) -> list[dict]:
    """Optimise ``model`` for ``num_steps`` steps; returns the curve (every ``log_every`` steps,
    each loss averaged over the steps since the previous row; ``validation`` in the rows where
    ``selection`` scored). ``checkpoint``: see :class:`Checkpoint` (a plain path is written, never
    resumed from). ``selection``: the model ends with the weights that scored best on it."""
    checkpoint = as_checkpoint(checkpoint)
    start, curve = _start(checkpoint, model, optimizer, scheduler, desc, selection)
    if selection is not None and start == 0:
        selection.observe(model, 0)
    primary = world().primary
    parameters = [p for group in optimizer.param_groups for p in group["params"]]
    model.train()
    sums: dict[str, float] = {}
    count = 0
    for step in console.progress(range(start, num_steps), total=num_steps - start, desc=desc):
        losses = step_fn(step)
        loss = losses["loss"]
        if not torch.isfinite(loss):
            raise EgorelightError(f"{desc}: loss became {loss.item()} at step {step} (lower the learning rate?)")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        average_gradients(parameters)  # no-op in a single process
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
        for name, value in losses.items():
            sums[name] = sums.get(name, 0.0) + float(value.detach())
        count += 1
        last = step + 1 == num_steps
        scored = None
        if selection is not None and ((step + 1) % selection.every == 0 or last):
            scored = selection.observe(model, step + 1)
        if (step + 1) % log_every == 0 or last:
            row = {"step": step + 1, **average_values({k: v / count for k, v in sums.items()})}
            curve.append(row if scored is None else {**row, "validation": scored})
            sums, count = {}, 0
        if checkpoint is not None and primary and ((step + 1) % checkpoint_every == 0 or last):
            save_checkpoint(checkpoint, model, optimizer, step + 1, curve, scheduler, selection)
    if selection is not None:
        selection.restore(model)
    model.eval()
    return curve
