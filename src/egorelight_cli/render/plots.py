"""Small line charts drawn with OpenCV (training curves, error plots) — no plotting library."""

from __future__ import annotations

import cv2
import numpy as np

SERIES_COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75)]


def line_plot(series: dict[str, tuple[np.ndarray, np.ndarray]], title: str = "", width: int = 640,
              height: int = 400, log_y: bool = True, x_label: str = "step") -> np.ndarray:
    """(height, width, 3) uint8 RGB chart of named (x, y) series; non-finite and (with log_y)
    non-positive values are skipped."""
    image = np.full((height, width, 3), 255, np.uint8)
    left, right, top, bottom = 70, 20, 30, 40
    cleaned = {}
    for name, (x, y) in series.items():
        x, y = np.asarray(x, float), np.asarray(y, float)
        keep = np.isfinite(x) & np.isfinite(y) & ((y > 0) if log_y else True)
        if keep.any():
            cleaned[name] = (x[keep], np.log10(y[keep]) if log_y else y[keep])
    cv2.putText(image, title, (left, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(image, (left, top), (width - right, height - bottom), (0, 0, 0), 1)
    if not cleaned:
        cv2.putText(image, "no data", (width // 2 - 30, height // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
        return image
    xs = np.concatenate([x for x, _ in cleaned.values()])
    ys = np.concatenate([y for _, y in cleaned.values()])
    x0, x1 = xs.min(), max(xs.max(), xs.min() + 1e-9)
    y0, y1 = ys.min(), max(ys.max(), ys.min() + 1e-9)

    def to_px(x, y):
        px = left + (x - x0) / (x1 - x0) * (width - left - right)
        py = height - bottom - (y - y0) / (y1 - y0) * (height - top - bottom)
        return np.stack([px, py], axis=-1).round().astype(np.int32)

    for i, (name, (x, y)) in enumerate(cleaned.items()):
        colour = SERIES_COLOURS[i % len(SERIES_COLOURS)]
        cv2.polylines(image, [to_px(x, y).reshape(-1, 1, 2)], False, colour, 1, cv2.LINE_AA)
        cv2.putText(image, name, (width - right - 150, top + 18 * (i + 1)), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    colour, 1, cv2.LINE_AA)
    for frac in (0.0, 0.5, 1.0):
        value = y0 + frac * (y1 - y0)
        label = f"{10**value:.3g}" if log_y else f"{value:.3g}"
        py = int(round(height - bottom - frac * (height - top - bottom)))
        cv2.putText(image, label, (5, py + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for frac in (0.0, 1.0):
        value = x0 + frac * (x1 - x0)
        px = int(round(left + frac * (width - left - right)))
        cv2.putText(image, f"{value:.0f}", (px - 10, height - bottom + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(image, x_label, (width // 2 - 15, height - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    return image


def curve_plot(curve: list[dict], title: str) -> np.ndarray:
    """:func:`line_plot` (log y) of every numeric series of a training curve, rows
    ``{"step": int, <name>: float, ...}`` (``curve.json`` of a model artifact); a row without a
    number for a series is skipped for it."""
    rows = [r for r in curve if isinstance(r, dict) and _is_number(r.get("step"))]
    names = sorted({k for r in rows for k, v in r.items() if k != "step" and _is_number(v)})
    series = {n: (np.array([r["step"] for r in rows if _is_number(r.get(n))], float),
                  np.array([r[n] for r in rows if _is_number(r.get(n))], float)) for n in names}
    return line_plot(series, title=title)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)
