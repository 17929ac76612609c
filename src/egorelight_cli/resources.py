"""Where the tool's own files live: JSON schemas, stage YAMLs and shipped data.

The repository keeps ``schemas/`` and ``stages/`` at its top level (that is what users read and
edit); the package reaches them through ``egorelight_cli/resources/``, which links to them in a
source checkout and holds copies in a built wheel.
"""

from __future__ import annotations

from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent


def schemas_dir() -> Path:
    return PACKAGE_DIR / "resources" / "schemas"


def stages_dir() -> Path:
    return PACKAGE_DIR / "resources" / "stages"


def data_dir() -> Path:
    return PACKAGE_DIR / "data"
