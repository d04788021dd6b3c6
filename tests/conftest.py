"""Shared fixtures: the real RGB-D frames shipped in ``tests/data/real``."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
REAL_DATA = REPO_ROOT / "tests" / "data" / "real"


@pytest.fixture(scope="session")
def real_data() -> Path:
    """``tests/data/real``: real RGB-D frames (read-only; see its README for origin and licence)."""
    return REAL_DATA
