"""Shared fixtures: the real data set beside the project (../shared/data), skipped where absent."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (it lives beside the project in CI)")
    return SHARED_DATA


def data_file(relpath: str) -> Path:
    """Path of a file in ../shared/data; skips the calling test with a reason if it is absent."""
    p = SHARED_DATA / relpath
    if not p.exists():
        pytest.skip(f"real data file {p} is absent")
    return p
