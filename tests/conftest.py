"""Shared fixtures. Real images live in ../shared (beside the checkout); tests that need them skip
with a clear reason when it is absent. The product itself never reads ../shared."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def pytest_configure(config):
    """Simulated cameras cache their pre-rendered loops; a test run keeps its own cache (shared by
    its tests and the commands they start) and leaves the user's ~/.cache alone."""
    if "RIG_CACHE_DIR" not in os.environ:
        os.environ["RIG_CACHE_DIR"] = config._rig_cache = tempfile.mkdtemp(prefix="rig-test-cache-")


def pytest_unconfigure(config):
    made = getattr(config, "_rig_cache", None)
    if made:
        shutil.rmtree(made, ignore_errors=True)
        os.environ.pop("RIG_CACHE_DIR", None)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    d = SHARED / "data"
    if not d.is_dir():
        pytest.skip(f"real test images not available: {d} is absent (they ship beside the checkout in ../shared)")
    return d
