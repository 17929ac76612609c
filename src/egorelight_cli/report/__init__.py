"""``egorelight report``: one HTML page for a subject directory.

It finds every artifact by its manifest (:mod:`~egorelight_cli.report.discover`), orders them by
the pipeline DAG, and shows per stage the inputs, config, timing, device, metrics next to their
baselines and the paper's figures (:mod:`~egorelight_cli.report.metrics`), MPJPE bar charts
(:mod:`~egorelight_cli.report.charts`), training curves and previews
(:mod:`~egorelight_cli.report.page`). It reads artifacts only; it never re-runs a stage.
"""

from egorelight_cli.report.page import build_report

__all__ = ["build_report"]
