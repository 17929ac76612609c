"""Per-vertex label files: ``segmentation.txt`` (human parsing) and ``hand_segmentation.txt``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from egorelight_cli.io.ddc.text import _Lines, _read_text, _write_text_lines

#: Human-parsing (LIP) labels used by DDC's ``segmentation.txt``.
HUMAN_PARSING_LABELS: dict[int, str] = {
    0: "background", 1: "hat", 2: "hair", 3: "glove", 4: "sunglasses", 5: "upper_clothes",
    6: "dress", 7: "coat", 8: "socks", 9: "pants", 10: "jumpsuits", 11: "scarf", 12: "skirt",
    13: "face", 14: "left_arm", 15: "right_arm", 16: "left_leg", 17: "right_leg",
    18: "left_shoe", 19: "right_shoe",
}
#: Labels of ``hand_segmentation.txt``.
HAND_SEGMENTATION_LABELS: dict[int, str] = {0: "body", 1: "left_hand", 2: "right_hand"}


def read_labels(path: str | Path, num_vertices: int | None = None, what: str = "segmentation file") -> np.ndarray:
    """Read one integer label per vertex (one per line)."""
    path = Path(path)
    lines = _Lines(path, _read_text(path, what), what)
    labels = []
    for number, line, tokens in lines.lines:
        for t in tokens:
            labels.append(lines.int(t, number, "label"))
    if num_vertices is not None and len(labels) != num_vertices:
        raise lines.error(f"the file has {len(labels)} labels but the template has {num_vertices} vertices")
    return np.array(labels, dtype=np.int64)


def write_labels(labels: np.ndarray, path: str | Path) -> Path:
    return _write_text_lines(Path(path), [str(int(x)) for x in np.asarray(labels).reshape(-1)])
