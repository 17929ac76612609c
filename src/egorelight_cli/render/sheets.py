"""Contact sheets: rows of labelled image tiles, the preview format several stages write (synth's
sequences, capture import, calibrate's detections, envmap's panoramas, composite's frames)."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

#: RGB of tile labels (yellow: readable on dark and bright renders alike).
LABEL_COLOUR = (255, 255, 0)
#: Largest sheet width in pixels (wider rows are cropped).
MAX_WIDTH = 4096


def label(image: np.ndarray, text: str, colour: tuple[int, int, int] = LABEL_COLOUR) -> np.ndarray:
    """(H,W,3) uint8 copy of ``image`` (uint8) with ``text`` written at its top left."""
    if np.asarray(image).dtype != np.uint8:
        raise ValueError(f"contact-sheet tiles are uint8 images, got {np.asarray(image).dtype}")
    image = np.array(image, order="C", copy=True)
    if text:
        cv2.putText(image, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    return image


def fit_tile(image: np.ndarray, height: int | None = None, width: int | None = None) -> np.ndarray:
    """(h,w,3) uint8: ``image`` (H,W), (H,W,3) or (H,W,4, alpha dropped) resized to ``height`` or
    ``width`` pixels (exactly one given), aspect kept."""
    if (height is None) == (width is None):
        raise ValueError("give exactly one of height and width")
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    image = np.ascontiguousarray(image[..., :3])
    h, w = image.shape[:2]
    if height is not None:
        size = (max(1, round(w * height / h)), height)
    else:
        size = (width, max(1, round(h * width / w)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def tile_row(tiles: Sequence[tuple[str, np.ndarray]], height: int | None = None,
             width: int | None = None) -> np.ndarray:
    """(h,w,3) uint8: the ``(label, image)`` tiles side by side, each fitted to ``height`` or
    ``width`` (:func:`fit_tile`) and labelled; rows of different heights are bottom-padded."""
    parts = [label(fit_tile(image, height, width), text) for text, image in tiles]
    if not parts:
        return np.zeros((height or width, 1, 3), np.uint8)
    tallest = max(p.shape[0] for p in parts)
    return np.concatenate([np.pad(p, ((0, tallest - p.shape[0]), (0, 0), (0, 0))) for p in parts], axis=1)


def stack_rows(rows: Sequence[np.ndarray], max_width: int | None = MAX_WIDTH, fill: int = 0) -> np.ndarray:
    """(H,W,3) uint8: ``rows`` one under another, narrower ones padded on the right with ``fill``,
    wider ones cropped to ``max_width`` (None: never)."""
    width = max(r.shape[1] for r in rows)
    width = width if max_width is None else min(width, max_width)
    return np.concatenate([np.pad(r[:, :width], ((0, 0), (0, width - min(r.shape[1], width)), (0, 0)),
                                  constant_values=fill) for r in rows], axis=0)


def labelled_rows(rows: Sequence[tuple[str, Sequence[np.ndarray]]], tile_width: int) -> np.ndarray:
    """(H,W,3) uint8: per ``(text, images)`` a row of the images fitted to ``tile_width`` with
    ``text`` written across the row (not clipped to its first tile)."""
    return stack_rows([label(tile_row([("", image) for image in images], width=tile_width), text)
                       for text, images in rows])


def contact_sheet(rows: Sequence[Sequence[tuple[str, np.ndarray]]], title: str | None = None,
                  tile_height: int | None = None, tile_width: int | None = None) -> np.ndarray:
    """(H,W,3) uint8: one row of labelled tiles per entry of ``rows`` (:func:`tile_row`; empty rows
    left out) under an optional title bar; tiles fitted to ``tile_height`` or ``tile_width``."""
    body = [tile_row(row, tile_height, tile_width) for row in rows if row]
    if not body:
        body = [np.zeros((tile_height or tile_width, 640, 3), np.uint8)]
    width = min(max(r.shape[1] for r in body), MAX_WIDTH)
    if title is not None:
        header = np.full((22, width, 3), 30, np.uint8)
        cv2.putText(header, title, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        body = [header] + body
    return stack_rows(body)
