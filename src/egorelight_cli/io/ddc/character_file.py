"""``.character`` files: the paths of a character's skeleton, mesh, skin and pose files."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from egorelight_cli.io.ddc.text import CHARACTER_HEADER, _Lines, _read_text, _write_text_lines


@dataclass
class CharacterFile:
    """The contents of a ``.character`` file: referenced paths (relative to the file, as written).

    ``other`` keeps any further ``keyword`` / ``path`` pairs in order.
    """

    skeleton: str
    mesh: str
    skin: str
    pose: str | None = None
    other: list[tuple[str, str]] = field(default_factory=list)


_CHARACTER_KEYS = ("skeleton", "mesh", "skin", "pose")


def read_character_file(path: str | Path) -> CharacterFile:
    """Read a ``.character`` file (keyword line, then a path line, per entry)."""
    path = Path(path)
    lines = _Lines(path, _read_text(path, "character file"), "character file")
    lines.header(CHARACTER_HEADER)
    found: dict[str, str] = {}
    other: list[tuple[str, str]] = []
    while not lines.at_end():
        number, line, tokens = lines.next("a keyword")
        keyword = tokens[0]
        if len(tokens) > 1:  # tolerate 'keyword path' on one line
            value = line.split(None, 1)[1].strip()
        else:
            _, value, _ = lines.next(f"the path after {keyword!r}")
        if keyword in _CHARACTER_KEYS:
            if keyword in found:
                raise lines.error(f"{keyword!r} appears twice", number)
            found[keyword] = value
        else:
            other.append((keyword, value))
    missing = [k for k in ("skeleton", "mesh", "skin") if k not in found]
    if missing:
        raise lines.error(f"the file names no {', '.join(missing)}")
    return CharacterFile(found["skeleton"], found["mesh"], found["skin"], found.get("pose"), other)


def write_character_file(cf: CharacterFile, path: str | Path) -> Path:
    out = [CHARACTER_HEADER]
    for key in _CHARACTER_KEYS:
        value = getattr(cf, key)
        if value is not None:
            out += [key, value]
    for key, value in cf.other:
        out += [key, value]
    return _write_text_lines(Path(path), out)
