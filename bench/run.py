"""`make bench`: run every bench/bench_*.py module's ``run()`` and report the results.

Each benchmark returns a dict of measurements (units in the key names). Results are printed and
saved to ``bench/results/latest.json``. Speed goals live here, never in timed tests.
"""

from __future__ import annotations

import importlib.util
import json
import platform
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # the benchmarks share bench/timing.py


def load(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> int:
    selected = sys.argv[1:]
    results = {"machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine()}}
    failed = False
    for path in sorted(HERE.glob("bench_*.py")):
        name = path.stem.removeprefix("bench_")
        if selected and name not in selected:
            continue
        started = time.perf_counter()
        try:
            results[name] = load(path).run()
        except Exception as exc:  # report and carry on with the other benchmarks
            results[name] = {"error": f"{type(exc).__name__}: {exc}"}
            failed = True
        results[name]["bench_wall_s"] = round(time.perf_counter() - started, 2)
        print(f"{name}: {json.dumps(results[name], indent=2)}", flush=True)
    out = HERE / "results" / "latest.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"saved {out}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
