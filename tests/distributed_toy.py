"""A toy data-parallel run for tests/test_distributed.py, started by torchrun (or plainly).

Fits a small MLP with :func:`egorelight_cli.nn.training.train` on a fixed regression problem;
each step draws a global batch of 8 from the step's seed and keeps this rank's share. Writes the
final parameters and the curve to ``argv[1]`` (rank 0 only).
"""

from __future__ import annotations

import sys

import torch

from egorelight_cli.nn import distributed
from egorelight_cli.nn.training import train


def main(out: str) -> None:
    group = distributed.init_from_environment(torch.device("cpu"))
    torch.manual_seed(0)
    x = torch.randn(64, 5, dtype=torch.float64)
    y = torch.sin(x @ torch.randn(5, 2, dtype=torch.float64))
    model = torch.nn.Sequential(torch.nn.Linear(5, 16), torch.nn.Tanh(), torch.nn.Linear(16, 2)).double()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)

    def step_fn(step: int) -> dict[str, torch.Tensor]:
        index = torch.randint(0, 64, (8,), generator=torch.Generator().manual_seed(step))
        index = distributed.rank_share(index)
        loss = ((model(x[index]) - y[index]) ** 2).mean()
        return {"loss": loss}

    curve = train(model, optimizer, step_fn, 30, log_every=5, desc="toy")
    if group.primary:
        torch.save({"state": model.state_dict(), "curve": curve, "world_size": group.size}, out)
    distributed.barrier()
    distributed.shutdown()


if __name__ == "__main__":
    main(sys.argv[1])
