"""Benchmark: every CPU-heavy stage's core computation idle and next to two busy processes.

A batch tool runs next to other jobs (``make -j2``, a shared cluster node). Per stage, the same
work is timed on the idle machine and then with two competing busy processes (``while True:
pass``) on the machine's cores; the slow-down ratio (loaded / idle) should stay near a fair share
(3x with two busy processes on 2 cores; goal: at most 4x, issue 23). Stages, with the setup of
their own benchmark modules:

* ``ik_lm``: ``ik --solver lm`` on 400 noisy frames (``BENCH_THREADS_IK_FRAMES``) of the DDC example character (107 DoFs,
  ``../shared/data/ddc_example``), or of the default character when that is absent;
* ``egopose_inference``: the ``cpu`` preset estimator on 16-frame batches (``bench_egopose``);
* ``egodepth_train_step``: one ``cpu`` preset training step of the depth network (batch 4, 128 px
  crops of 256 px views, forward, backward, Adam);
* ``animate_train_step``: one ``cpu`` preset training step of AnimationNet (batch 2, Chamfer to
  the skinned template, ARAP, offsets; ``bench_animate``'s motion and clouds);
* ``synth_render``: ``egorelight synth`` on the ``tiny`` preset, 2 frames of ``ego_train``
  (``bench_synth``).

Threads are set as a stage run sets them (:func:`egorelight_cli.runtime.apply_threads` with the
cores this process may use); ``BENCH_THREADS_APPLY=0`` leaves the libraries' own defaults (how
stages ran before issue 23). Each stage runs ``BENCH_THREADS_REPEATS`` (default 3) times per
condition, stopping early once ``BUDGET_S`` is spent; the median is reported with the spread
(max / min) of the repeats, which shows how noisy the shared machine was. Run
``python bench/bench_threads.py [stage ...]``; it prints a JSON dict.

Measured when issue 23 landed (2 cores that three to seven other jobs shared all along, load
average 7-9, so "idle" is itself loaded and both columns are noisy): slow-down ratio loaded/idle,
three runs each, before (``BENCH_THREADS_APPLY=0`` on the previous commit) and after:

=====================  ================  ================
stage                  before            after
=====================  ================  ================
ik_lm (DDC)            3.3*, 1.5, 1.6    1.7, 2.1, 2.0
egopose_inference      4.3, 3.8, 4.8     2.5, 2.5, 2.2
egodepth_train_step    1.8, 1.0, 7.6     1.2, 0.6, 1.1
animate_train_step     6.3, 4.1, 3.6     1.0, 1.4, 1.4
synth_render           3.0, 2.0, 2.6     2.4, 3.7, 3.1
=====================  ================  ================

(* 1000 frames.) The idle times moved more than the ratios: ik lm on 400 DDC frames 27-33 s before,
1.1-2.3 s after (2.9-5.8 ms per frame); an egodepth step 0.5-5.3 s before, 0.3-0.5 s after.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

APPLY = os.environ.get("BENCH_THREADS_APPLY", "1") != "0"
if APPLY:  # first, as the CLI does: it sets OpenMP's wait policy before torch is loaded
    from egorelight_cli import runtime

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_animate  # noqa: E402
import bench_egopose  # noqa: E402
import bench_ik  # noqa: E402
import bench_synth  # noqa: E402
from egorelight_cli.config import resolve_config  # noqa: E402

BUSY_PROCESSES = 2
REPEATS = int(os.environ.get("BENCH_THREADS_REPEATS", 3))
BUDGET_S = 12.0  # per stage and condition: no further repeats once this is spent
IK_FRAMES = int(os.environ.get("BENCH_THREADS_IK_FRAMES", 400))


# ------------------------------------------------------------------------------ workloads
def ik_lm() -> tuple[Callable[[], None], int, str]:
    from egorelight_cli.io.character import load_default_character
    from egorelight_cli.stages.ik import IKSettings, default_ik_model, solve_ik

    if bench_ik.DDC_CHARACTER.is_file():
        from egorelight_cli.stages.character_commands import load_character

        character, name = load_character(bench_ik.DDC_CHARACTER)[0], "ddc_example"
    else:
        character, name = load_default_character(), "default (../shared/data/ddc_example is not available)"
    settings = IKSettings.from_config(resolve_config("ik", "cpu"))
    model = default_ik_model(character, settings)
    keypoints, _ = bench_ik.noisy_keypoints(character, bench_ik.random_motion(character, model))
    keypoints = keypoints.select(slice(0, IK_FRAMES))
    return (lambda: solve_ik(character, keypoints, model, settings)), len(keypoints.frame_ids), name


def egopose_inference() -> tuple[Callable[[], None], int, str]:
    from egorelight_cli.nn.egopose_net import EgoPoseNet
    from egorelight_cli.stages.egopose import EgoPoseSettings

    torch.manual_seed(0)
    cfg = resolve_config("egopose", "cpu")
    net = EgoPoseNet(**EgoPoseSettings(cfg).architecture()).eval()
    geometry, size = bench_egopose.rig(), int(cfg.input_size)
    batch, repeats = 16, 2
    return (lambda: bench_egopose.time_per_frame(net, geometry, size, batch, repeats)), batch * (repeats + 1), "cpu preset"


def egodepth_train_step() -> tuple[Callable[[], None], int, str]:
    from egorelight_cli.nn.depth_net import DepthNet
    from egorelight_cli.stages.egodepth import TrainSettings, depth_losses

    torch.manual_seed(0)
    cfg = resolve_config("egodepth", "cpu")
    settings = TrainSettings.from_config(cfg)
    model = DepthNet.from_config(cfg.net).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=settings.lr)
    n, crop = settings.batch, settings.crop
    batch = {"image": torch.rand(n, 3, crop, crop), "rays": torch.randn(n, 3, crop, crop),
             "log_range": torch.rand(n, 1, crop, crop) - 1.0, "supervised": torch.rand(n, 1, crop, crop) < 0.3,
             "inside": torch.ones(n, 1, crop, crop, dtype=torch.bool)}
    if model.stereo_input:
        batch["stereo"] = torch.rand(n, 1, crop, crop) * (torch.rand(n, 1, crop, crop) < 0.5)
    steps = 2

    def train_steps() -> None:
        for _ in range(steps):
            losses = depth_losses(model, batch)
            optimizer.zero_grad(set_to_none=True)
            (losses["depth"] + losses["mask_bce"]).backward()
            optimizer.step()

    return train_steps, steps, f"cpu preset, batch {n}, {crop} px crops"


def animate_train_step() -> tuple[Callable[[], None], int, str]:
    from egorelight_cli.geometry.depth_encoding import skinned_template
    from egorelight_cli.io.character import load_default_character
    from egorelight_cli.stages.animate import (AnimationModel, DepthSettings, NetSettings, TrainSettings,
                                               animation_loss, build_training_data)

    torch.manual_seed(0)
    cfg = resolve_config("animate", "cpu")
    settings = TrainSettings.from_config(cfg)
    character = load_default_character()
    theta = bench_animate._motion(character)[:8]
    frame_ids = np.arange(len(theta))
    template = skinned_template(character, theta)
    recon = {int(f): (v, character.faces) for f, v in zip(frame_ids, template.vertices)}
    model = AnimationModel(character, NetSettings.from_config(cfg), DepthSettings.from_config(cfg))
    data = build_training_data(model, theta, frame_ids, bench_animate._clouds(character, theta), recon, settings)
    optimizer = torch.optim.Adam(model.net.parameters(), lr=settings.lr)
    rows = list(range(settings.batch))
    steps = 2

    def train_steps() -> None:
        model.net.train()
        for _ in range(steps):
            terms = animation_loss(model, data.inputs[rows], data.theta[rows], [data.targets[r] for r in rows],
                                   [data.trees[r] for r in rows], settings)
            optimizer.zero_grad(set_to_none=True)
            terms["loss"].backward()
            optimizer.step()

    return train_steps, steps, f"cpu preset, batch {settings.batch}"


def synth_render() -> tuple[Callable[[], None], int, str]:
    frames = 2
    return (lambda: bench_synth._one("tiny", frames)), frames, "tiny preset, ego_train"


STAGES = {"ik_lm": ik_lm, "egopose_inference": egopose_inference, "egodepth_train_step": egodepth_train_step,
          "animate_train_step": animate_train_step, "synth_render": synth_render}


# ------------------------------------------------------------------------------- timing
def busy_processes(count: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]


def timed(fn: Callable[[], None]) -> dict:
    """Median seconds of up to REPEATS runs (fewer once BUDGET_S is spent) and their spread."""
    seconds = []
    spent = 0.0
    while len(seconds) < REPEATS and spent < BUDGET_S:
        started = time.perf_counter()
        fn()
        seconds.append(time.perf_counter() - started)
        spent += seconds[-1]
    return {"median_s": round(statistics.median(seconds), 3), "runs": len(seconds),
            "spread": round(max(seconds) / min(seconds), 2)}


def measure(fn: Callable[[], None], units: int) -> dict:
    """Idle then loaded timings of one workload (one warm-up run first, idle)."""
    fn()
    idle = timed(fn)
    busy = busy_processes(BUSY_PROCESSES)
    try:
        time.sleep(0.3)
        loaded = timed(fn)
    finally:
        for process in busy:
            process.kill()
        for process in busy:
            process.wait()
    return {"units_per_run": units, "idle": idle, "loaded": loaded,
            "idle_ms_per_unit": round(1000 * idle["median_s"] / units, 2),
            "slowdown": round(loaded["median_s"] / idle["median_s"], 2)}


def run(selected: tuple[str, ...] = ()) -> dict:
    if APPLY:
        cores, source = runtime.available_cores()
        runtime.apply_threads(cores)
        results: dict = {"threads": f"runtime.apply_threads({cores}), OMP_WAIT_POLICY={os.environ['OMP_WAIT_POLICY']}"}
    else:
        cores, source = len(os.sched_getaffinity(0)), "affinity"
        results = {"threads": "library defaults (BENCH_THREADS_APPLY=0)"}
    results.update({"cores": cores, "cores_source": source, "busy_processes": BUSY_PROCESSES,
                    "fair_share_slowdown": round((cores + BUSY_PROCESSES) / cores, 2), "goal_max_slowdown": 4.0})
    results["torch_threads"] = torch.get_num_threads()
    for name, setup in STAGES.items():
        if selected and name not in selected:
            continue
        fn, units, what = setup()
        results[name] = {"workload": what, **measure(fn, units)}
        results[name]["goal_met"] = results[name]["slowdown"] <= results["goal_max_slowdown"]
        print(f"{name}: {json.dumps(results[name])}", file=sys.stderr, flush=True)
    return results


if __name__ == "__main__":
    print(json.dumps(run(tuple(sys.argv[1:])), indent=2))
