"""Contact sheets of a simulated sequence: tone-mapped studio views, ego views, environment maps."""

from __future__ import annotations

import cv2
import numpy as np

from egorelight_cli.io.images import linear_to_srgb

TILE_HEIGHT = 160


def tonemap(hdr: np.ndarray, mask: np.ndarray | None = None, percentile: float = 99.0) -> np.ndarray:
    """(H,W,3) uint8 sRGB of a linear HDR image scaled so the ``percentile`` (of the mask) is ~0.9."""
    values = hdr.max(axis=-1)
    values = values[mask] if mask is not None and mask.any() else values
    level = float(np.percentile(values, percentile)) if values.size else 0.0
    scale = 0.9 / level if level > 1e-8 else 1.0
    return np.round(linear_to_srgb(hdr * scale) * 255).astype(np.uint8)


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
