"""The report page: one HTML file plus ``assets/`` (copied previews, plotted curves), written
atomically. Every image and link is relative to the page, so the report folder stays valid where
the subject is (links to manifests) and its images travel with it."""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import shutil
from html import escape
from pathlib import Path
from urllib.parse import quote

from egorelight_cli import __version__
from egorelight_cli.atomic_output import remove_stale_temporaries, replace_directory, temporary_sibling
from egorelight_cli.errors import EgorelightError
from egorelight_cli.report.charts import bar_chart
from egorelight_cli.report.discover import OTHER, STAGES, Found, StageInfo, discover, loose_previews
from egorelight_cli.report.metrics import (GROUPS, MetricRow, is_number, metric_rows, mpjpe_groups, runtime_row,
                                           verdict)

INDEX = "index.html"
ASSETS = "assets"
#: files a desktop leaves in any folder: a report folder holding them may still be replaced
OS_LITTER = (".DS_Store", "Thumbs.db", "desktop.ini")
MAX_IMAGES = 12  # previews shown per artifact; the rest are counted
MAX_OUTPUTS_LISTED = 40
RELIT_VS_TRUTH = ("relit vs truth, side by side: captured target | relit render | Lambert baseline | baked texture "
                  "(one row per sampled held-out view)")
#: (section, file name) -> what a preview shows
CAPTIONS = {
    ("egopose", "preview.png"): "both down-facing views per frame: true keypoints green, predicted red",
    ("ik", "preview.png"): "fitted skeleton and keypoints (body red, hands green/blue) over the targets (black rings)",
    ("egodepth", "preview.png"): "per ego view: image | predicted range | true range",
    ("egodepth", "preview_pointcloud.png"): "fused points over the true mesh (grey), coloured by distance to it: "
                                            "green 0 -> red >= 3 cm",
    ("animate", "preview.png"): "P2S heat map: ego view with the visible vertices | tracked mesh coloured by its "
                                "distance to the true surface (blue 0 -> red 2 cm)",
    ("geolift", "preview.png"): "per frame: coarse UV normals | GeoLift normals | flat-lit texture | true normals",
    ("relight", "preview.png"): RELIT_VS_TRUTH,
    ("character", "preview.png"): "the template fitted to the scan, coloured by its distance to it",
    ("character", "character.png"): "rest pose with skeleton and keypoints",
    ("envmap", "preview.png"): "envmap estimated vs true: observed panorama (unobserved dark red) | estimated HDR "
                               "map | true map in the same frame (tone-mapped)",
    ("envmap", "coverage.png"): "coverage: white where a front camera saw the texel",
}
STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1200px;padding:0 1em;color:#222}
h2{border-bottom:2px solid #ccc;padding-bottom:.2em;margin-top:2em}
h3{margin-bottom:.3em} .meta{color:#555;font-size:.9em} .problem{color:#b00020}
table{border-collapse:collapse;font-size:.88em;margin:.5em 0} td,th{border:1px solid #ddd;padding:2px 6px;text-align:left}
td.num{text-align:right;font-variant-numeric:tabular-nums} .better{background:#d8f3dc} .worse{background:#ffd6d6}
.mixed{background:#fff3c4} .notrun{color:#888} .paper{color:#555}
figure{display:inline-block;margin:.4em;vertical-align:top;max-width:100%} figure img{max-width:100%;max-height:380px;border:1px solid #ccc}
figcaption{font-size:.8em;color:#444;max-width:60em} pre{font-size:.8em;background:#f6f6f6;padding:.5em;overflow:auto}
svg.chart text{font-size:11px;fill:#222} svg.chart .title{font-weight:bold} svg.chart .grid{stroke:#e3e3e3}
svg.chart .value{font-size:9px} .artifact{margin-left:.5em;padding-left:.8em;border-left:3px solid #eee}
"""


def fmt(value) -> str:
    """A metric value as text: numbers to 4 significant digits, lists/strings shortened."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return str(value).lower()
    if is_number(value):
        return f"{value:.4g}" if isinstance(value, float) else str(value)
    text = value if isinstance(value, str) else json.dumps(value)
    return text if len(text) <= 120 else text[:117] + "..."


class Page:
    """Builds the HTML of one report; images are copied into ``<work>/assets``.

    Args:
        subject: the subject directory.
        out: where the report folder will live (links are made relative to it).
        work: the temporary folder being written (renamed to ``out`` at the end).
    """

    def __init__(self, subject: Path, out: Path, work: Path):
        self.subject, self.out, self.work = subject, out, work
        self.found = discover(subject, skip=out)
        self.by_root = {f.root.resolve() if f.manifest_path.name == "manifest.json" else
                        f.manifest_path.with_name(f.manifest_path.name.removesuffix(".json")).resolve(): f
                        for f in self.found}
        self.asset_names: set[str] = set()

    # -------------------------------------------------------------------- helpers
    def href(self, path: Path) -> str:
        """A relative URL from the page to ``path``."""
        return quote(Path(os.path.relpath(path.resolve(), self.out.resolve())).as_posix())

    def asset(self, source: Path, name: str) -> str:
        """Copy ``source`` into assets/ under a unique ``name``; returns the relative URL."""
        name = re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-") or "image"
        stem, dot, suffix = name.rpartition(".")
        unique, n = name, 1
        while unique in self.asset_names:
            n += 1
            unique = f"{stem}-{n}{dot}{suffix}"
        self.asset_names.add(unique)
        shutil.copyfile(source, self.work / ASSETS / unique)
        return f"{ASSETS}/{quote(unique)}"

    def figure(self, source: Path, name: str, caption: str) -> str:
        url = self.asset(source, name)
        return (f'<figure><a href="{url}"><img src="{url}" alt="{escape(caption)}" loading="lazy"></a>'
                f"<figcaption>{escape(caption)}</figcaption></figure>")

    # -------------------------------------------------------------------- page
    def html(self) -> str:
        sections = {info.name: [f for f in self.found if f.section == info.name] for info in STAGES + (OTHER,)}
        loose = loose_previews(self.subject)
        body = [f"<h1>egorelight report: {escape(self.subject.resolve().name)}</h1>",
                f'<p class="meta">subject <code>{escape(str(self.subject))}</code> · {len(self.found)} artifacts · '
                f"generated {_dt.datetime.now().isoformat(timespec='seconds')} by egorelight {__version__} "
                "from the artifacts' manifests (nothing re-run). Green: better than the baseline it is shown "
                "next to; red: worse. Paper figures are on real captures, ours on this subject.</p>",
                self.summary(sections)]
        for info in STAGES + (OTHER,):
            items = sections[info.name]
            extra = [p for p in loose if p.stem in (info.name, *info.kinds)]
            if info is OTHER:
                extra = [p for p in loose if not any(p.stem in (s.name, *s.kinds) for s in STAGES)]
                if not items and not extra:
                    continue
            body.append(self.section(info, items, extra))
        return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
                f"<title>egorelight report: {escape(self.subject.resolve().name)}</title>"
                f"<style>{STYLE}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")

    def summary(self, sections: dict[str, list[Found]]) -> str:
        rows = ["<table><tr><th>stage</th><th>artifacts</th><th>wall time</th><th>vs baselines</th></tr>"]
        for info in STAGES + (OTHER,):
            items = sections[info.name]
            if info is OTHER and not items:
                continue
            link = f'<a href="#{info.name}">{escape(info.title)}</a>'
            if not items:
                rows.append(f'<tr class="notrun"><td>{link}</td><td colspan="3">not run</td></tr>')
                continue
            wall = sum(float(f.manifest.get("timing", {}).get("wall_s", 0) or 0) for f in items
                       if isinstance(f.manifest.get("timing"), dict))
            votes = [verdict(r) for f in items for r in metric_rows(f.kind, f.manifest.get("metrics") or {})]
            better, worse = votes.count("better"), votes.count("worse") + votes.count("mixed")
            problems = sum(bool(f.problems) for f in items)
            names = ", ".join(f'<a href="#{f.anchor}">{escape(f.rel)}</a>' for f in items)
            rows.append(f"<tr><td>{link}</td><td>{names}"
                        + (f' <span class="problem">({problems} with problems)</span>' if problems else "")
                        + f'</td><td class="num">{_duration(wall)}</td>'
                        f"<td>{_votes(better, worse)}</td></tr>")
        rows.append("</table>")
        return "\n".join(rows)

    def section(self, info: StageInfo, items: list[Found], loose: list[Path]) -> str:
        parts = [f'<section id="{info.name}"><h2>{escape(info.title)}</h2>']
        if not items:
            expected = ", ".join(f"<code>{escape(p)}</code>" for p in info.layout)
            parts.append('<p class="notrun">not run: no artifact of this stage under the subject'
                         + (f" (the Makefile writes {expected})" if expected else "") + ".</p>")
        for found in items:
            parts.append(self.artifact(found))
        for path in loose:
            parts.append(self.figure(path, f"previews-{path.name}",
                                     CAPTIONS.get((info.name, path.name), f"previews/{path.name}")))
        parts.append("</section>")
        return "\n".join(parts)

    def artifact(self, found: Found) -> str:
        m = found.manifest
        parts = [f'<div class="artifact" id="{found.anchor}"><h3>{escape(found.rel)} '
                 f'<small class="meta">{escape(found.kind)} · stage {escape(str(m.get("stage", "?")))}'
                 f' · <a href="{self.href(found.manifest_path)}">manifest</a></small></h3>']
        parts += [f'<p class="problem">{escape(p)}</p>' for p in found.problems]
        parts.append(self.meta_line(found))
        parts.append(self.inputs(found))
        parts.append(self.metrics_table(found))
        parts.append(self.charts(found))
        parts.append(self.curve(found))
        parts.append(self.previews(found))
        parts.append(_details("config", f"<pre>{escape(json.dumps(m.get('config', {}), indent=1))}</pre>"))
        outputs = found.outputs()
        listed = "".join(f"<li>{escape(str(o['path']))}</li>" for o in outputs[:MAX_OUTPUTS_LISTED])
        more = f"<li>... and {len(outputs) - MAX_OUTPUTS_LISTED} more</li>" if len(outputs) > MAX_OUTPUTS_LISTED else ""
        parts.append(_details(f"payload files: {len(outputs)}", f"<ul>{listed}{more}</ul>"))
        parts.append("</div>")
        return "\n".join(p for p in parts if p)

    def meta_line(self, found: Found) -> str:
        m = found.manifest
        runtime = m.get("runtime") if isinstance(m.get("runtime"), dict) else {}
        timing = m.get("timing") if isinstance(m.get("timing"), dict) else {}
        bits = [f"created {escape(str(m.get('created', '?')))}"]
        device = ", ".join(f"{k} {escape(fmt(runtime[k]))}" for k in ("device", "threads", "preset", "host") if k in runtime)
        if device:
            bits.append(device)
        if timing:
            bits.append("timing: " + ", ".join(f"{escape(k)} {escape(fmt(v))}" for k, v in timing.items()))
        line = f'<p class="meta">{" · ".join(bits)}</p>'
        runtime_vs_paper = runtime_row(found.section, m) if found.kind != "model" else None
        if runtime_vs_paper is not None:
            ours, paper, source = runtime_vs_paper
            line += (f'<p class="meta paper">runtime: {ours:.4g} ms/frame here ({escape(fmt(runtime.get("device")))}) '
                     f"vs {paper:g} ms/frame in the paper ({escape(source)})</p>")
        return line

    def inputs(self, found: Found) -> str:
        entries = found.manifest.get("inputs") or []
        if not entries:
            return ""
        items = []
        for entry in entries:
            if not isinstance(entry, dict):
                continue
            kind = escape(str(entry.get("kind", "?")).removeprefix("egorelight/"))
            if entry.get("param"):  # the declared input it was read through
                kind += f" ({escape(str(entry['param']))})"
            path = (found.root / str(entry.get("path", ""))).resolve()
            target = self.by_root.get(path)
            if target is not None:
                items.append(f'<li>{kind}: <a href="#{target.anchor}">{escape(target.rel)}</a></li>')
            elif path.exists():
                items.append(f'<li>{kind}: <a href="{self.href(path)}">{escape(str(entry.get("path")))}</a> '
                             "(outside the subject)</li>")
            else:
                items.append(f'<li>{kind}: {escape(str(entry.get("path")))} <span class="problem">(missing)</span></li>')
        return f'<p class="meta">inputs:</p><ul class="meta">{"".join(items)}</ul>'

    def metrics_table(self, found: Found) -> str:
        rows = metric_rows(found.kind, found.manifest.get("metrics") or {}, found.manifest.get("units") or {})
        if not rows:
            return ""
        baselines = any(r.comparisons for r in rows)
        paper = any(r.paper is not None or any(c.paper for c in r.comparisons) for r in rows)
        out = ["<table><tr><th>metric</th><th>value</th>"
               + ("<th>baselines (green: ours better, red: worse)</th>" if baselines else "")
               + ("<th>paper (real data)</th>" if paper else "") + "</tr>"]
        for row in rows:
            out.append(_metric_row(row, baselines, paper))
        out.append("</table>")
        table = "\n".join(out)
        return table if len(rows) <= 30 else _details(f"{len(rows)} metrics", table)

    def charts(self, found: Found) -> str:
        charts = mpjpe_groups(found.kind, found.manifest.get("metrics") or {})
        svgs = []
        for split, series in charts.items():
            groups = [g for g in GROUPS if any(g in s for s in series.values())]
            svgs.append(bar_chart(series, groups, f"MPJPE per joint group ({split})", "cm"))
        return "\n".join(svgs)

    def curve(self, found: Found) -> str:
        """The training curve: the stage's own curve.png, else one plotted from curve.json;
        with the first and last value of every series."""
        path = found.root / "curve.json"
        if not path.is_file():
            return ""
        try:
            curve = json.loads(path.read_text())
        except (OSError, ValueError):
            return '<p class="problem">curve.json is unreadable</p>'
        rows = [r for r in curve if isinstance(r, dict)] if isinstance(curve, list) else []
        parts = []
        stage_png = found.root / "curve.png"
        if stage_png.is_file():
            parts.append(self.figure(stage_png, f"{found.rel}-curve.png", "training curve (curve.json)"))
        elif rows:
            from egorelight_cli.io.images import write_image
            from egorelight_cli.render.plots import curve_plot

            plotted = self.work / ASSETS / f".curve-{found.anchor}.png"
            write_image(plotted, curve_plot(rows, f"{found.manifest.get('stage', '')} training"))
            parts.append(self.figure(plotted, f"{found.rel}-curve.png", "training curve (plotted from curve.json)"))
            plotted.unlink()
        names = sorted({k for r in rows for k, v in r.items() if k != "step" and is_number(v)})
        if names:
            first = {n: next(r[n] for r in rows if is_number(r.get(n))) for n in names}
            last = {n: next(r[n] for r in reversed(rows) if is_number(r.get(n))) for n in names}
            table = "".join(f'<tr><td>{escape(n)}</td><td class="num">{fmt(first[n])}</td>'
                            f'<td class="num">{fmt(last[n])}</td></tr>' for n in names)
            parts.append(f"<table><tr><th>curve series</th><th>first</th><th>last</th></tr>{table}</table>")
        return "\n".join(parts)

    def previews(self, found: Found) -> str:
        """Preview images of the artifact: top-level images and those under previews/ (per-frame
        images in sub-folders are counted, not shown)."""
        images = [p for p in found.images() if Path(p).name != "curve.png"]
        shown = [p for p in images if "/" not in p or p.startswith("previews/")]
        parts = []
        for rel in shown[:MAX_IMAGES]:
            source = found.root / rel
            if source.is_file():
                caption = CAPTIONS.get((found.section, Path(rel).name), rel)
                if caption != rel:
                    caption = f"{rel}: {caption}"
                parts.append(self.figure(source, f"{found.rel}-{rel}", caption))
        rest = len(images) - min(len(shown), MAX_IMAGES)
        if rest > 0:
            parts.append(f'<p class="meta">... and {rest} more images in the artifact (per-frame outputs)</p>')
        return "\n".join(parts)


def _metric_row(row: MetricRow, baselines: bool = True, paper: bool = True) -> str:
    """One table row: name (unit as tooltip), our value coloured by :func:`verdict`, each baseline
    coloured by whether ours beats it, and the paper's figure."""
    name = f'<td title="{escape(row.unit)}">{escape(row.key)}</td>' if row.unit else f"<td>{escape(row.key)}</td>"
    classes = " ".join(c for c in ("num" if is_number(row.value) else "", verdict(row)) if c)
    cells = [name, f"<td{_class(classes)}>{escape(fmt(row.value))}</td>"]
    if baselines:
        shown = []
        for c in row.comparisons:
            figure = f' <span class="paper">(paper {c.paper[0]:g})</span>' if c.paper else ""
            shown.append(f'<span{_class(_mark(c.better))} title="{escape(c.key)}">{escape(c.label)} '
                         f"{escape(fmt(c.value))}</span>{figure}")
        cells.append(f'<td>{" · ".join(shown)}</td>')
    if paper:
        figure = ""
        if row.paper is not None:
            figure = (f'<span{_class(_mark(row.paper.better))} title="{escape(row.paper.label)}">'
                      f"{row.paper.value:g}</span>")
        cells.append(f'<td class="paper">{figure}</td>')
    return "<tr>" + "".join(cells) + "</tr>"


def _mark(better: bool | None) -> str:
    return "" if better is None else ("better" if better else "worse")


def _class(names: str) -> str:
    return f' class="{names}"' if names else ""


def _details(summary: str, content: str, open_: bool = False) -> str:
    return f"<details{' open' if open_ else ''}><summary>{escape(summary)}</summary>{content}</details>"


def _duration(seconds: float) -> str:
    if seconds <= 0:
        return "—"
    return f"{seconds:.1f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def _votes(better: int, worse: int) -> str:
    if not better and not worse:
        return "—"
    return (f'<span class="better">{better} better</span> · ' if better else "") + (
        f'<span class="worse">{worse} not better</span>' if worse else "")


def is_report_folder(folder: Path) -> bool:
    """Whether ``folder`` (a directory) may be replaced by a report: it is empty or holds only what
    a report writes (``index.html`` and ``assets/``), and perhaps a desktop's :data:`OS_LITTER`."""
    try:
        return all(entry.name in (INDEX, ASSETS, *OS_LITTER) for entry in folder.iterdir())
    except OSError as exc:
        raise EgorelightError(f"cannot read the report folder ({exc.strerror or exc})", folder) from None


def build_report(subject: str | Path, out: str | Path | None = None) -> Path:
    """Write ``<out>/index.html`` (default ``<subject>/report``) and its ``assets/`` atomically
    from the artifacts under ``subject``; returns the page's path."""
    subject = Path(subject)
    if not subject.is_dir():
        raise EgorelightError("not a subject directory", subject)
    out = Path(out) if out is not None else subject / "report"
    if out.exists() and not out.is_dir():
        raise EgorelightError("report output exists and is not a directory", out)
    if out.is_dir() and not is_report_folder(out):
        raise EgorelightError(f"exists and is not a report folder (only {INDEX} and {ASSETS}/): not replacing it",
                              out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(out)
        work = temporary_sibling(out)
        (work / ASSETS).mkdir(parents=True)
    except OSError as exc:
        raise EgorelightError(f"cannot write the report ({exc.strerror or exc})", out) from None
    try:
        page = Page(subject, out, work)
        if not page.found:
            raise EgorelightError("no egorelight artifacts (no manifest.json) under the subject directory", subject)
        (work / INDEX).write_text(page.html(), encoding="utf-8")
        replace_directory(work, out)
    except OSError as exc:
        raise EgorelightError(f"cannot write the report ({exc.strerror or exc})", exc.filename or out) from None
    finally:
        if work.exists():
            shutil.rmtree(work, ignore_errors=True)
    return out / INDEX
