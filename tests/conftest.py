"""Shared fixtures. Real images live in ../shared (beside the checkout); tests that need them skip
with a clear reason when it is absent. The product itself never reads ../shared."""
from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def pytest_configure(config):
    """Simulated cameras cache their pre-rendered loops; a test run keeps its own cache (shared by
    its tests and the commands they start) and leaves the user's ~/.cache alone.

    Under pytest-xdist each worker gets its share of the cores for torch's, OpenMP's and BLAS's
    threads (it and the commands it starts): two workers each spinning two threads on two cores spend
    much of the machine waiting for each other."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if workers > 0:
        share = str(max(1, (os.cpu_count() or 1) // workers))
        # numpy's OpenBLAS spins its own threads too (it reads its variable when numpy loads, after
        # this hook): oversubscribed, its solves ran about 100 times slower under load
        # (OpenCV's own pool reads OPENCV_FOR_THREADS_NUM; ONNX Runtime's sessions OMP_NUM_THREADS)
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OPENCV_FOR_THREADS_NUM"):
            os.environ[var] = share
        import cv2
        import torch

        torch.set_num_threads(int(share))
        cv2.setNumThreads(int(share))
    if "RIG_CACHE_DIR" not in os.environ:
        os.environ["RIG_CACHE_DIR"] = config._rig_cache = tempfile.mkdtemp(prefix="rig-test-cache-")


def pytest_collection_modifyitems(session, config, items):
    """The long tests (marked slow) first: pytest-xdist hands out the files in this order, so the
    longest start at once and the short ones fill in around them, instead of one long file running
    alone at the end. Tests marked cuda skip, saying why, where torch sees no GPU."""
    items.sort(key=lambda item: 0 if item.get_closest_marker("slow") else 1)
    if any(item.get_closest_marker("cuda") for item in items):
        import torch

        if not torch.cuda.is_available():
            why = "no CUDA GPU: torch was built without CUDA" if torch.version.cuda is None else "no CUDA GPU: torch sees none"
            for item in items:
                if item.get_closest_marker("cuda"):
                    item.add_marker(pytest.mark.skip(reason=why))


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


# --- small exported models (test size), made once per test run ------------------------------------

@dataclass
class Exported:
    path: Path
    backbone: str


def _export(tmp_path_factory, backbone: str, *options: str) -> Exported:
    """Export through the command line, as a user would; once per test run, also when pytest-xdist
    runs the tests in several processes (they share the parent of their temp folders, and the
    first to take the lock exports)."""
    import os

    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # pytest-N/popen-gwK under xdist
    folder = shared / f"exported-model-{backbone}"
    with FileLock(str(shared / f"exported-model-{backbone}.lock")):
        out = folder / f"{backbone}.onnx"
        if not out.is_file():
            folder.mkdir(exist_ok=True)
            _export_to(out, backbone, *options)
    return Exported(out, backbone)


def _export_to(out: Path, backbone: str, *options: str) -> None:
    import contextlib
    import io
    import json

    from rig.cli import main

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        rc = main(["model", "export", "--backbone", backbone, "--size", "test", "--fp16", *options, "-o", str(out), "--json"])
    assert rc == 0 and out.is_file()
    assert json.loads(printed.getvalue())["files"] == [str(out), str(out.with_name(f"{backbone}.fp16.onnx"))]


@pytest.fixture(scope="session")
def tiny_onnx(tmp_path_factory) -> Exported:
    return _export(tmp_path_factory, "tiny")


@pytest.fixture(scope="session")
def oracle_onnx(tmp_path_factory) -> Exported:
    # its weights in one data file beside it, as the shipped models: every test of it reads them so
    return _export(tmp_path_factory, "oracle", "--shared-data")
