"""Shared fixtures: where the independent reference data lives."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# ../shared/data beside the checkout (CI clones main with shared/ beside it);
# NEURAL_BRDF_SHARED overrides.
SHARED = Path(os.environ.get("NEURAL_BRDF_SHARED", REPO.parent / "shared"))
DATA = SHARED / "data"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA.is_dir():
        raise FileNotFoundError(
            f"reference data not found at {DATA}; set NEURAL_BRDF_SHARED to the shared/ folder")
    return DATA
