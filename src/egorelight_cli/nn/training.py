"""A small training loop shared by every learned stage: checkpoints, resume, curve, progress.

The stage supplies ``step_fn(step) -> {"loss": tensor, <other losses>: tensors}`` (it draws its
own batch, seeded by the step); :func:`train` runs the optimiser, logs the losses, saves a
checkpoint every ``checkpoint_every`` steps and resumes from one when it exists, so a killed
training run continues where it stopped.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import torch

from egorelight_cli import console
from egorelight_cli.errors import EgorelightError


def save_checkpoint(path: str | Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer, step: int,
                    curve: list[dict[str, float]]) -> None:
    """Atomically write a resumable checkpoint."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step, "curve": curve,
                "torch_rng": torch.get_rng_state()}, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer) -> tuple[int, list]:
    """Restore model, optimiser and RNG; returns (next step, curve so far)."""
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
        model.load_state_dict(data["model"])
        optimizer.load_state_dict(data["optimizer"])
        torch.set_rng_state(data["torch_rng"])
    except Exception as exc:
        raise EgorelightError(f"cannot resume from checkpoint ({type(exc).__name__}: {exc}); delete it to restart",
                              path) from None
    return int(data["step"]), list(data["curve"])


def train(model: torch.nn.Module, optimizer: torch.optim.Optimizer,
          step_fn: Callable[[int], dict[str, torch.Tensor]], num_steps: int,
          checkpoint: str | Path | None = None, checkpoint_every: int = 200, log_every: int = 10,
          scheduler: torch.optim.lr_scheduler.LRScheduler | None = None, desc: str = "training") -> list[dict]:
    """Optimise ``model`` for ``num_steps`` steps; returns the curve (every ``log_every`` steps,
    each loss averaged over the steps since the previous row)."""
    start, curve = 0, []
    if checkpoint is not None and Path(checkpoint).is_file():
        start, curve = load_checkpoint(checkpoint, model, optimizer)
        console.info(f"resuming {desc} at step {start} from {checkpoint}")
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
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
        for name, value in losses.items():
            sums[name] = sums.get(name, 0.0) + float(value.detach())
        count += 1
        last = step + 1 == num_steps
        if (step + 1) % log_every == 0 or last:
            curve.append({"step": step + 1, **{k: v / count for k, v in sums.items()}})
            sums, count = {}, 0
        if checkpoint is not None and ((step + 1) % checkpoint_every == 0 or last):
            save_checkpoint(checkpoint, model, optimizer, step + 1, curve)
    model.eval()
    return curve
