"""Contact sheets of a simulated sequence: tone-mapped studio views, ego views, environment maps."""

from __future__ import annotations

import cv2
import numpy as np

from egorelight_cli.io.images import tonemap  # noqa: F401  (re-exported: synth.capture, tests)

TILE_HEIGHT = 160


def _fit(image: np.ndarray, height: int = TILE_HEIGHT) -> np.ndarray:
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    width = max(1, round(image.shape[1] * height / image.shape[0]))
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def _label(image: np.ndarray, text: str) -> np.ndarray:
    image = image.copy()
    cv2.putText(image, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (255, 255, 0), 1, cv2.LINE_AA)
    return image


def _row(tiles: list[tuple[str, np.ndarray]], width: int) -> np.ndarray:
    parts = [_label(_fit(img), name) for name, img in tiles]
    row = np.concatenate(parts, axis=1) if parts else np.zeros((TILE_HEIGHT, 1, 3), np.uint8)
    if row.shape[1] < width:
        row = np.pad(row, ((0, 0), (0, width - row.shape[1]), (0, 0)))
    return row[:, :width]


def contact_sheet(title: str, rows: list[list[tuple[str, np.ndarray]]]) -> np.ndarray:
    """(H,W,3) uint8: one row of labelled tiles per entry, under a title bar."""
    widths = [sum(_fit(img).shape[1] for _, img in row) for row in rows if row] or [640]
    width = min(max(widths), 4096)
    body = [_row(row, width) for row in rows if row]
    header = np.full((22, width, 3), 30, np.uint8)
    cv2.putText(header, title, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([header] + body, axis=0)
