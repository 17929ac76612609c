"""Benchmark: the ``calibrate`` stage on a capture (timing and accuracy against its ground truth).

Runs the whole stage (``cpu`` preset config) on the capture named by ``BENCH_CALIBRATE_CAPTURE``
(default ``/tmp/cap_cpu``, made by ``egorelight synth --preset cpu``); skipped when it is absent
(making one takes ~15 min on 2 cores). Reports wall seconds per step group and the metrics the
stage writes (hand-eye rotation/translation errors per camera, head-pose errors, sync, wild).

Goal (issue 5): hand-eye under 0.5 degrees and 5 mm on the cpu preset. Run
``python bench/bench_calibrate.py``; it prints a JSON dict.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from egorelight_cli.config import resolve_config
from egorelight_cli.io.capture import Capture
from egorelight_cli.stages.calibrate import calibrate, evaluate

CAPTURE = Path(os.environ.get("BENCH_CALIBRATE_CAPTURE", "/tmp/cap_cpu"))


def run() -> dict:
    if not (CAPTURE / "manifest.json").exists():
        return {"skipped": f"no capture at {CAPTURE} (set BENCH_CALIBRATE_CAPTURE)"}
    cfg = resolve_config("calibrate", "cpu", (), None)
    capture = Capture(CAPTURE)
    started = time.perf_counter()
    result = calibrate(capture, cfg)
    seconds = time.perf_counter() - started
    metrics = evaluate(capture, result)
    out = {"calibrate_wall_s": round(seconds, 2)}
    out.update({k: metrics[k] for k in ("handeye_rotation_error_deg", "handeye_translation_error_mm",
                                        "sync_all_correct", "head_pose", "wild") if k in metrics})
    rot = metrics.get("handeye_rotation_error_deg", {})
    trans = metrics.get("handeye_translation_error_mm", {})
    out["handeye_goal_met"] = bool(rot) and max(rot.values()) < 0.5 and max(trans.values()) < 5.0
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
