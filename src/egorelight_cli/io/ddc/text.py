"""Text helpers shared by the DDC readers and writers: tokenised lines with line numbers for
errors, number formatting, millimetre rounding and atomic CRLF writing."""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError

MM_PER_M = 1000.0

SKELETON_HEADER = "Skeletool Skeleton Definition V1.0"
SKIN_HEADER = "Skeletool character skinning file V1.0"
MOTION_HEADER = "Skeletool Motion File V1.0"
CALIBRATION_HEADER = "Skeletool Camera Calibration File V1.0"
CHARACTER_HEADER = "skeletool character file v1.0"


def _read_text(path: Path, what: str) -> str:
    if not path.is_file():
        raise EgorelightError(f"{what} not found", path)
    try:
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise EgorelightError(f"{what} is not a text file (byte {exc.start} is not UTF-8)", path) from None
    except OSError as exc:
        raise EgorelightError(f"cannot read {what}: {exc.strerror}", path) from None


class _Lines:
    """Cursor over the non-empty lines of a text file, with 1-based line numbers for errors."""

    def __init__(self, path: Path, text: str, what: str):
        self.path = path
        self.what = what
        self.lines: list[tuple[int, str, list[str]]] = []
        for number, raw in enumerate(text.split("\n"), start=1):
            line = raw[:-1] if raw.endswith("\r") else raw
            tokens = line.split()
            if tokens:
                self.lines.append((number, line.strip(), tokens))
        self.pos = 0

    def error(self, message: str, line: int | None = None) -> EgorelightError:
        where = f"line {line}: " if line is not None else ""
        return EgorelightError(f"{self.what}: {where}{message}", self.path)

    def at_end(self) -> bool:
        return self.pos >= len(self.lines)

    def peek(self) -> tuple[int, str, list[str]] | None:
        return None if self.at_end() else self.lines[self.pos]

    def next(self, expecting: str) -> tuple[int, str, list[str]]:
        if self.at_end():
            last = self.lines[-1][0] if self.lines else 0
            raise self.error(f"file ends after line {last} while expecting {expecting}")
        item = self.lines[self.pos]
        self.pos += 1
        return item

    def header(self, expected: str) -> None:
        number, line, tokens = self.next(f"the header {expected!r}")
        if " ".join(tokens).lstrip("\ufeff").lower() != expected.lower():
            raise self.error(f"expected the header {expected!r}, found {_clip(line)!r}", number)

    def count(self, keyword: str) -> int:
        """Read a ``keyword N`` line (keyword may be several tokens, e.g. ``scaling joints:``)."""
        words = keyword.split()
        number, line, tokens = self.next(f"'{keyword} N'")
        if len(tokens) != len(words) + 1 or [t.lower() for t in tokens[:-1]] != [w.lower() for w in words]:
            raise self.error(f"expected '{keyword} N', found {_clip(line)!r}", number)
        return self.int(tokens[-1], number, f"the {keyword[:-1] if keyword.endswith(':') else keyword} count",
                        minimum=0)

    def float(self, token: str, line: int, what: str) -> float:
        try:
            return float(token)
        except ValueError:
            raise self.error(f"{what} {token!r} is not a number", line) from None

    def int(self, token: str, line: int, what: str, minimum: int | None = None) -> int:
        try:
            value = int(token)
        except ValueError:
            try:
                as_float = float(token)
            except ValueError:
                raise self.error(f"{what} {token!r} is not an integer", line) from None
            if not as_float.is_integer():
                raise self.error(f"{what} {token!r} is not an integer", line) from None
            value = int(as_float)
        if minimum is not None and value < minimum:
            raise self.error(f"{what} {token!r} is below {minimum}", line)
        return value

    def floats(self, tokens: list[str], line: int, what: str) -> list[float]:
        return [self.float(t, line, what) for t in tokens]


def _clip(text: str, n: int = 60) -> str:
    return text if len(text) <= n else text[: n - 3] + "..."


def _fmt(x: float) -> str:
    """A number token: integers as integers, floats as the shortest text that reads back exactly."""
    if isinstance(x, (int, np.integer)) and not isinstance(x, bool):
        return str(int(x))
    x = float(x)
    if x == 0.0:
        return "0"
    s = repr(x)
    return s[:-2] if s.endswith(".0") else s


def _to_mm(values) -> np.ndarray:
    """Metres -> millimetres, rounded to 15 significant digits.

    ``x / 1000 * 1000`` is not always ``x`` in binary floating point; the rounding removes that
    last-bit noise so that ``52.3472`` is written back as ``52.3472``, not ``52.347199999999994``.
    """
    a = np.asarray(values, dtype=np.float64) * MM_PER_M
    flat = [float("%.15g" % v) for v in a.reshape(-1).tolist()]
    return np.array(flat, dtype=np.float64).reshape(a.shape)


def _join(tokens) -> str:
    return " ".join(t if isinstance(t, str) else _fmt(t) for t in tokens)


def _write_text_lines(path: Path, lines: list[str]) -> Path:
    """Write ``lines`` with CRLF endings and a final newline, atomically (temp file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = ("\r\n".join(lines) + "\r\n").encode("utf-8")
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        with open(tmp, "xb") as fh:  # default permissions (umask), unlike mkstemp's 0600
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def _base_name(name: str) -> str:
    return name.split("_", 1)[0]


def _trim_trailing_blank(lines: list[str]) -> list[str]:
    lines = list(lines)
    while lines and not lines[-1].strip():
        lines.pop()
    return lines
