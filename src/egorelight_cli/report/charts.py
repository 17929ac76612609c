"""Inline SVG charts for the report (no plotting library; the page stays one text file)."""

from __future__ import annotations

from html import escape

#: series colours (hex) in order; the paper's bars are grey
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2")
PAPER_COLOUR = "#9a9a9a"


def _nice_top(value: float) -> float:
    """A round axis maximum >= value (1, 2, 2.5 or 5 times a power of ten)."""
    if value <= 0:
        return 1.0
    power = 10.0 ** int(f"{value:e}".split("e")[1])
    for step in (1.0, 2.0, 2.5, 5.0, 10.0):
        if step * power >= value:
            return step * power
    return 10.0 * power


def bar_chart(series: dict[str, dict[str, float]], groups: tuple[str, ...] | list[str], title: str,
              unit: str = "", width: int = 520, height: int = 240) -> str:
    """Grouped bars: one group per entry of ``groups`` (x axis), one bar per series in each,
    value labels on top, a legend; series named ``paper...`` are grey. Returns an ``<svg>`` string."""
    left, right, top, bottom = 48, 150, 28, 28
    plot_w, plot_h = width - left - right, height - top - bottom
    values = [v for s in series.values() for v in s.values()]
    y_top = _nice_top(1.08 * max(values, default=1.0))  # headroom for the value labels
    names = list(series)
    group_w = plot_w / max(len(groups), 1)
    bar_w = 0.8 * group_w / max(len(names), 1)
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" class="chart" width="{width}" height="{height}" '
             f'viewBox="0 0 {width} {height}" role="img" aria-label="{escape(title)}">',
             f'<text x="{left}" y="16" class="title">{escape(title)}</text>']
    for frac in (0.0, 0.25, 0.5, 0.75, 1.0):
        y = top + plot_h * (1 - frac)
        parts.append(f'<line x1="{left}" x2="{left + plot_w}" y1="{y:.1f}" y2="{y:.1f}" class="grid"/>')
        parts.append(f'<text x="{left - 4}" y="{y + 4:.1f}" text-anchor="end">{frac * y_top:g}</text>')
    if unit:
        parts.append(f'<text x="4" y="{top - 8}">{escape(unit)}</text>')
    colours = {}
    palette = iter(PALETTE * 4)
    for name in names:
        colours[name] = PAPER_COLOUR if name.startswith("paper") else next(palette)
    for g, group in enumerate(groups):
        x0 = left + g * group_w + 0.1 * group_w
        for i, name in enumerate(names):
            value = series[name].get(group)
            if value is None:
                continue
            h = plot_h * min(value / y_top, 1.0)
            x, y = x0 + i * bar_w, top + plot_h - h
            parts.append(f'<rect x="{x:.1f}" y="{y:.1f}" width="{bar_w * 0.92:.1f}" height="{h:.1f}" '
                         f'fill="{colours[name]}"><title>{escape(name)} {escape(group)}: {value:.3g}</title></rect>')
            parts.append(f'<text x="{x + bar_w * 0.46:.1f}" y="{y - 3:.1f}" text-anchor="middle" class="value">'
                         f'{value:.3g}</text>')
        parts.append(f'<text x="{left + (g + 0.5) * group_w:.1f}" y="{height - 10}" text-anchor="middle">'
                     f'{escape(group)}</text>')
    for i, name in enumerate(names):
        y = top + 16 * i
        parts.append(f'<rect x="{width - right + 12}" y="{y}" width="10" height="10" fill="{colours[name]}"/>')
        parts.append(f'<text x="{width - right + 26}" y="{y + 9}">{escape(name)}</text>')
    parts.append("</svg>")
    return "".join(parts)
