"""Shared fixtures. Real images live in ../shared (beside the checkout); tests that need them skip
with a clear reason when it is absent. The product itself never reads ../shared."""
from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    d = SHARED / "data"
    if not d.is_dir():
        pytest.skip(f"real test images not available: {d} is absent (they ship beside the checkout in ../shared)")
    return d
