"""Shared test fixtures: where the real third-party data lives."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# CI clones the repository beside shared/, so ../shared/data from the repository root.
SHARED_DATA = Path(os.environ.get("DOSEQSLAM_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.fail(f"real test data not found at {SHARED_DATA} (set DOSEQSLAM_SHARED_DATA)")
    return SHARED_DATA
