"""Benchmark: simulated capture speed, seconds per simulated frame per camera (studio and ego).

Runs ``egorelight synth`` on the ``tiny`` and ``cpu`` settings restricted to the ``ego_train``
sequence (every camera kind, the HMD, recon and normals) with few frames, and reports the
renderer's per-frame-per-camera times from the capture's manifest plus the wall time per frame.
Run ``python bench/bench_synth.py``; it prints a JSON dict.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

from egorelight_cli.artifacts import open_artifact
from egorelight_cli.pipeline import StageRun
from egorelight_cli.stages.synth import SynthCommand


def _one(preset: str, frames: int) -> dict:
    sets = ("sequences_enabled=[ego_train]", f"sequences.ego_train.frames={frames}")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "capture"
        started = time.perf_counter()
        SynthCommand(StageRun("synth", preset=preset, sets=sets, force=True))(out, None, (), None)
        wall = time.perf_counter() - started
        artifact = open_artifact(out)
        metrics = artifact.metrics
    per = artifact.manifest["timing"]["render_s_per_frame_per_camera"]
    return {
        "frames": metrics["frames"],
        "wall_s": round(wall, 2),
        "wall_s_per_frame": round(wall / metrics["frames"], 3),
        "studio_s_per_frame_per_camera": per.get("studio"),
        "tracking_s_per_frame_per_camera": per.get("tracking"),
        "ego_s_per_frame_per_camera": per.get("ego"),
        "ego_backdrop_s_per_frame_per_camera": per.get("backdrop"),
        "light_visibility_s_per_frame": per.get("visibility"),
    }


def run() -> dict:
    return {"tiny": _one("tiny", 4), "cpu": _one("cpu", 6)}


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
