"""A plain-text table of chosen metrics of several artifacts (for ``make *-ablation`` targets).

``python -m egorelight_cli.report.table --keys psnr,ssim A/manifest.json B/manifest.json ...`` prints
one row per artifact (named by its directory), one column per key; a missing or non-numeric value
is ``-``. It reads manifests only.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def metric_table(manifests: list[Path], keys: list[str]) -> str:
    """The table as text: a header, then one row per manifest."""
    rows = []
    for path in manifests:
        metrics = json.loads(Path(path).read_text()).get("metrics", {})
        cells = []
        for key in keys:
            value = metrics.get(key)
            cells.append(f"{value:.2f}" if isinstance(value, (int, float)) and not isinstance(value, bool) else "-")
        rows.append([Path(path).parent.name if Path(path).name == "manifest.json" else Path(path).name] + cells)
    header = ["artifact"] + keys
    widths = [max(len(str(r[i])) for r in [header] + rows) for i in range(len(header))]
    lines = ["  ".join(str(c).ljust(w) if i == 0 else str(c).rjust(w) for i, (c, w) in enumerate(zip(r, widths)))
             for r in [header] + rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keys", required=True, help="comma-separated metric names")
    parser.add_argument("manifests", nargs="+", type=Path)
    args = parser.parse_args(argv)
    print(metric_table(args.manifests, [k for k in args.keys.split(",") if k]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
