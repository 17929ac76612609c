"""The one exception type for known failures.

Every failure a user can cause (missing file, wrong artifact kind or version, NaN in an input,
shape mismatch, frame out of range, bad option) is raised as :class:`EgorelightError`. The CLI
prints it as one line, ``egorelight: error: <what>, <which file>``, and exits with code 2.
"""

from __future__ import annotations

from pathlib import Path


class EgorelightError(Exception):
    """A known, user-facing failure.

    Args:
        message: what is wrong, in plain words (no trailing period needed).
        path: the file or directory it is about, if any.
    """

    def __init__(self, message: str, path: str | Path | None = None):
        self.message = message
        self.path = None if path is None else str(path)
        super().__init__(str(self))

    def __str__(self) -> str:
        return self.message if self.path is None else f"{self.message}, {self.path}"
