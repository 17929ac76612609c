"""``character.npz``: a :class:`Character` as one self-describing npz payload."""

from __future__ import annotations

from pathlib import Path

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import read_npz, write_npz
from egorelight_cli.structures.character import Character

CHARACTER_KIND = "egorelight/character"
CHARACTER_VERSION = 1


def write_character_npz(path: str | Path, character: Character, **meta) -> None:
    """Write ``character`` (all fields, float64 kept) with a ``__meta__`` entry."""
    write_npz(path, character.to_arrays(), {"kind": CHARACTER_KIND, "version": CHARACTER_VERSION,
                                           "units": {"length": "m", "angle": "rad"}, "name": character.name, **meta})


def read_character_npz(path: str | Path) -> Character:
    """Read a ``character.npz``; wrong kind/version or missing fields are EgorelightErrors."""
    arrays, meta = read_npz(path)
    if meta.get("kind") != CHARACTER_KIND:
        raise EgorelightError(f"wrong payload kind: expected {CHARACTER_KIND}, found {meta.get('kind')}", path)
    if meta.get("version") != CHARACTER_VERSION:
        raise EgorelightError(f"{CHARACTER_KIND} version mismatch: file is version {meta.get('version')}, "
                              f"this tool reads version {CHARACTER_VERSION}", path)
    try:
        return Character.from_arrays(arrays)
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None
