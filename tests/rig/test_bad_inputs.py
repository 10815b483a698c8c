"""Bad input never loses data: the quick subset of benchmarks/bad_inputs.py (the full table runs there).

Every case runs `rig ...` in a subprocess in a folder of its own and must exit with the expected
status, print exactly one error line on stderr with no traceback, and leave every recorded file it
protects unchanged. The case table is the benchmark's `CASES`, imported by path.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bad_inputs.py"


def _load_bench():
    spec = importlib.util.spec_from_file_location("rig_bad_inputs_bench", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


bench = _load_bench()
FAST = [c for c in bench.CASES if c.fast]


def test_the_benchmark_covers_every_command_with_at_least_30_cases():
    assert len(bench.CASES) >= 30
    covered = {" ".join(a for a in c.argv[:2] if not a.startswith("-")) for c in bench.CASES}
    for command in ("config init", "config check", "discover", "grab", "sync check", "calibrate board", "calibrate run",
                    "calibrate capture", "calibrate report", "calibrate export", "record", "record validate", "record repair",
                    "sim snapshot", "model export", "model check", "model bench", "demo"):
        assert any(c == command or c.startswith(command + " ") or c.split(" ")[0] == command for c in covered), command
    assert len({c.name for c in bench.CASES}) == len(bench.CASES)


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory) -> Path:
    return bench.build_fixtures(tmp_path_factory.mktemp("bad-inputs"))


@pytest.mark.parametrize("case", FAST, ids=[c.name for c in FAST])
def test_bad_input(case, fixtures, tmp_path):
    # a case with a time limit is stopped soon after it (it fails then): the subset stays under a minute
    result = bench.run_case(case, fixtures, tmp_path, timeout=case.max_s + 5 if case.max_s else 60)
    assert result.ok, f"{case.name}: {'; '.join(result.problems)}\nstderr: {result.stderr[-2000:]}"
