"""``.skin`` files (per-vertex bone influences), including the run-together rows quirk."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.io.ddc.text import SKIN_HEADER, _clip, _join, _Lines, _read_text, _write_text_lines


@dataclass
class SkinFile:
    """The contents of a ``.skin`` file: bone names and, per vertex (in order), its influences
    ``(bone index, weight)`` as listed (largest first in DDC files)."""

    bones: list[str]
    influences: list[list[tuple[int, float]]]

    @property
    def num_vertices(self) -> int:
        return len(self.influences)

    def dense(self) -> np.ndarray:
        """(V,B) float64 weight matrix."""
        W = np.zeros((len(self.influences), len(self.bones)))
        for v, row in enumerate(self.influences):
            for b, w in row:
                W[v, b] += w
        return W

    @classmethod
    def from_dense(cls, bones, weights: np.ndarray) -> "SkinFile":
        """Rows with the non-zero weights, largest first (ties by bone index)."""
        weights = np.asarray(weights, dtype=np.float64)
        influences = []
        for row in weights:
            nz = np.nonzero(row)[0]
            order = nz[np.argsort(-row[nz], kind="stable")]
            influences.append([(int(b), float(row[b])) for b in order])
        return cls(list(bones), influences)


def _skin_rows_run_together(rows: list[tuple[int, list[str]]]) -> bool:
    """Whether the weight tokens carry the vertex-id suffix (see the module notes).

    True when every multi-influence row's non-last weights end with the row's vertex id, the
    stripped tokens still parse, and stripping brings the row sums at least as close to 1.
    """
    dev_plain = dev_strip = 0.0
    multi = 0
    for _, tokens in rows:
        vid = tokens[0]
        ws = tokens[2::2]
        if len(ws) < 2:
            continue
        multi += 1
        stripped = []
        for w in ws[:-1]:
            if not w.endswith(vid):
                return False
            try:
                stripped.append(float(w[: -len(vid)]))
            except ValueError:
                return False
        try:
            plain = [float(w) for w in ws]
            last = float(ws[-1])
        except ValueError:
            return False
        dev_plain += abs(sum(plain) - 1.0)
        dev_strip += abs(sum(stripped) + last - 1.0)
    return multi > 0 and dev_strip <= dev_plain


def parse_skin(text: str, path: str | Path = "<skin>", num_vertices: int | None = None) -> SkinFile:
    """Parse the text of a ``.skin`` file (handles the run-together rows)."""
    path = Path(path)
    lines = _Lines(path, text, "skin file")
    lines.header(SKIN_HEADER)
    number, line, tokens = lines.next("'bones:'")
    if tokens != ["bones:"]:
        raise lines.error(f"expected 'bones:', found {_clip(line)!r}", number)
    number, line, bones = lines.next("the bone names")
    if bones == ["vertex", "weights:"]:
        raise lines.error("the bone list is empty", number)
    if len(set(bones)) != len(bones):
        raise lines.error("a bone name appears twice", number)
    number, line, tokens = lines.next("'vertex weights:'")
    if tokens != ["vertex", "weights:"]:
        raise lines.error(f"expected 'vertex weights:', found {_clip(line)!r}", number)
    rows = []
    while not lines.at_end():
        number, line, tokens = lines.next("a vertex row")
        if len(tokens) % 2 != 1:
            raise lines.error(f"a vertex row must be 'v b w b w ...', found {len(tokens)} fields: {_clip(line)!r}", number)
        rows.append((number, tokens))
    strip = _skin_rows_run_together(rows)
    B = len(bones)
    influences: list[list[tuple[int, float]]] = []
    for expected, (number, tokens) in enumerate(rows):
        vid = lines.int(tokens[0], number, "vertex id")
        if vid != expected:
            raise lines.error(f"vertex rows must be in order: expected vertex {expected}, found {tokens[0]!r}", number)
        row = []
        pairs = tokens[1:]
        for k in range(0, len(pairs), 2):
            b = lines.int(pairs[k], number, "bone index")
            if not 0 <= b < B:
                raise lines.error(f"bone index {b} is out of range (the file lists {B} bones)", number)
            w_tok = pairs[k + 1]
            if strip and k + 2 < len(pairs):
                w_tok = w_tok[: -len(tokens[0])]
            w = lines.float(w_tok, number, "weight")
            if not math.isfinite(w):
                raise lines.error(f"weight {pairs[k + 1]!r} is not finite", number)
            row.append((b, w))
        influences.append(row)
    if num_vertices is not None and len(influences) != num_vertices:
        raise lines.error(f"the file has {len(influences)} vertex rows but the template has {num_vertices} vertices")
    return SkinFile(list(bones), influences)


def read_skin(path: str | Path, num_vertices: int | None = None) -> SkinFile:
    """Read a ``.skin`` file; ``num_vertices`` checks the row count."""
    path = Path(path)
    return parse_skin(_read_text(path, "skin file"), path, num_vertices)


def format_skin(skin: SkinFile) -> list[str]:
    out = [SKIN_HEADER, "bones:", " ".join(skin.bones), "vertex weights:"]
    for v, row in enumerate(skin.influences):
        tokens: list = [v]
        for b, w in row:
            tokens += [int(b), float(w)]
        out.append(_join(tokens))
    return out


def write_skin(skin: SkinFile, path: str | Path) -> Path:
    """Write a ``.skin`` file with clean ``v b w b w ...`` rows."""
    return _write_text_lines(Path(path), format_skin(skin))
