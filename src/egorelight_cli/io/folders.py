"""Listing the files of a user's folder (a converted capture, a model folder)."""

from __future__ import annotations

import os
from pathlib import Path


def visible_files(root: str | Path) -> list[Path]:
    """Every file under ``root``, sorted, folders linked in followed; hidden files and folders
    (``.git/``, ``.DS_Store``, editors' and killed runs' leftovers) left out."""
    files = []
    for folder, dirs, names in os.walk(root, followlinks=True):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        files += [Path(folder, n) for n in names if not n.startswith(".")]
    return sorted(files)
