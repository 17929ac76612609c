"""``.motion`` files: one row per frame, frame index then the DoF values."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.io.ddc.text import MOTION_HEADER, _join, _Lines, _read_text, _write_text_lines


@dataclass
class MotionFile:
    """The contents of a ``.motion`` file: ``frame_ids`` (T,) int64 and ``values`` (T,D)."""

    frame_ids: np.ndarray
    values: np.ndarray

    def __post_init__(self) -> None:
        self.values = np.asarray(self.values, dtype=np.float64)
        if self.values.ndim == 1:
            self.values = self.values[None]
        self.frame_ids = np.asarray(self.frame_ids, dtype=np.int64).reshape(-1)


def read_motion(path: str | Path, num_dofs: int | None = None) -> MotionFile:
    """Read a ``.motion`` file; ``num_dofs`` checks the column count."""
    path = Path(path)
    lines = _Lines(path, _read_text(path, "motion file"), "motion file")
    lines.header(MOTION_HEADER)
    ids, rows = [], []
    width = None
    while not lines.at_end():
        number, line, tokens = lines.next("a frame row")
        if width is None:
            width = len(tokens)
            if num_dofs is not None and width != num_dofs + 1:
                raise lines.error(f"a frame row has {width - 1} DoF values but the skeleton has {num_dofs} DoFs", number)
        elif len(tokens) != width:
            raise lines.error(f"a frame row has {len(tokens)} fields, the first row had {width}", number)
        ids.append(lines.int(tokens[0], number, "frame index"))
        rows.append(lines.floats(tokens[1:], number, "DoF value"))
    D = (width - 1) if width is not None else (num_dofs or 0)
    return MotionFile(np.array(ids, dtype=np.int64), np.array(rows, dtype=np.float64).reshape(len(rows), D))


def write_motion(motion: MotionFile, path: str | Path) -> Path:
    """Write a ``.motion`` file: one row per frame, frame index then the DoF values."""
    out = [MOTION_HEADER]
    for fid, row in zip(motion.frame_ids, motion.values):
        out.append(_join([int(fid), *(float(v) for v in row)]))
    return _write_text_lines(Path(path), out)
