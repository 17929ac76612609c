"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

from egorelight_cli.io.character import load_default_character

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DDC_EXAMPLE = SHARED / "data" / "ddc_example"
BVH_EXAMPLE = SHARED / "data" / "motion" / "cmu_131_01_start_walk_stop.bvh"


@pytest.fixture
def ddc_example() -> Path:
    """The real DDC example character directory; skips when ../shared is absent."""
    if not (DDC_EXAMPLE / "ddc.character").exists():
        pytest.skip("../shared/data/ddc_example is not available")
    return DDC_EXAMPLE


@pytest.fixture(scope="session")
def character():
    """The shipped default character (shared, read-only: tests must not modify it)."""
    return load_default_character()
