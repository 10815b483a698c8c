"""benchmarks/gpu_check.py, the prepared GPU device check, in its CPU dry run: every step still runs
(tiny sizes, a step or two), so that the script cannot rot between the rare runs on a GPU."""
from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "benchmarks" / "gpu_check.py"
STEPS = ["cuda_tests", "model_speed", "live_engine", "train", "eval"]

sys.path.insert(0, str(REPO / "benchmarks"))
import gpu_check  # noqa: E402


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_dry_run_on_the_cpu_runs_every_step_and_writes_one_json_and_a_summary(tmp_path):
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, str(SCRIPT), "--device", "cpu", "--dry-run", "--out", str(out)],
                         cwd=REPO, capture_output=True, text=True, timeout=840)
    assert sorted(p.name for p in out.iterdir()) == ["gpu_check.json", "gpu_check.txt"]
    results = json.loads((out / "gpu_check.json").read_text())
    steps = results["steps"]
    assert list(steps) == STEPS
    for name, rec in steps.items():
        assert rec["status"] in ("passed", "skipped", "failed") and rec["seconds"] >= 0, name
        assert rec["status"] != "failed", f"{name}: {rec.get('error')}"
    # Without a GPU the cuda tests are collected and skipped, saying why.
    assert steps["cuda_tests"]["status"] == "skipped" and "GPU" in steps["cuda_tests"]["why"]
    speed = steps["model_speed"]["runs"]
    assert {(r["precision"], r["variant"]) for r in speed} == {("fp32", "eager"), ("fp32", "compiled"), ("bf16", "eager")}
    for r in speed:
        assert r["stage1_ms"] > 0 and r["view_ms"] > 0
        if r["precision"] == "fp32":  # the same computation on the same device as the reference
            assert r["max_abs_diff_cpu"] <= gpu_check.PARITY_TOLERANCE
    assert [r["graphs"] for r in speed if r["variant"] == "compiled"] == ["compiled"]
    live = steps["live_engine"]
    assert live["frames_out"] > 0 and live["fps_in"] > 0 and live["latency_ms"]["p50"] > 0
    assert live["runtime"]["kind"] == "torch" and live["runtime"]["device"] == "cpu"
    assert steps["train"]["steps"] >= 1 and steps["train"]["checkpoint"]
    assert steps["eval"]["figures"]["overall"]["psnr"] > 0
    # The summary line: printed last, written beside, naming every step.
    line = run.stdout.strip().splitlines()[-1]
    assert (out / "gpu_check.txt").read_text().strip() == line == results["summary"]
    assert all(f"{name} {steps[name]['status']}" in line for name in STEPS)
    assert run.returncode == 0, run.stderr[-2000:]


def test_a_device_that_is_not_cpu_or_cuda_is_one_line_and_exit_2(tmp_path):
    run = subprocess.run([sys.executable, str(SCRIPT), "--device", "tpu", "--out", str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and "--device tpu" in run.stderr


def test_a_missing_carry_folder_is_one_line_and_exit_2(tmp_path):
    run = subprocess.run([sys.executable, str(SCRIPT), "--carry", str(tmp_path / "none"), "--out", str(tmp_path)],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and "--prepare" in run.stderr


def wheel(folder: Path, name: str, files: dict[str, str]) -> Path:
    path = folder / name
    with zipfile.ZipFile(path, "w") as z:
        for member, text in files.items():
            z.writestr(member, text)
    return path


def test_carried_wheels_are_unpacked_only_for_what_python_lacks(tmp_path):
    carry = tmp_path / "carry"
    carry.mkdir()
    # A package this interpreter has (json: nothing to unpack) and one it lacks, with a .data folder.
    wheel(carry, "json-9.0-py3-none-any.whl", {"json/__init__.py": "", "json-9.0.dist-info/METADATA": "Name: json\n"})
    wheel(carry, "rig_carried_probe-1.0-py3-none-any.whl", {
        "rig_carried_probe/__init__.py": "VALUE = 7\n",
        "rig_carried_probe-1.0.data/purelib/rig_carried_extra.py": "VALUE = 8\n",
        "rig_carried_probe-1.0.data/scripts/tool": "#!/bin/sh\n",
        "rig_carried_probe-1.0.dist-info/METADATA": "Name: rig-carried-probe\n"})
    # A binary wheel for another interpreter is reported, not unpacked.
    wheel(carry, "rig_other_abi-1.0-cp27-cp27mu-manylinux1_x86_64.whl", {"rig_other_abi/__init__.py": ""})
    site = tmp_path / "site"
    report = gpu_check.install_carried(carry, site)
    assert report["present"] == ["json-9.0-py3-none-any.whl"]
    assert report["installed"] == ["rig_carried_probe-1.0-py3-none-any.whl"]
    assert report["unusable"] == ["rig_other_abi-1.0-cp27-cp27mu-manylinux1_x86_64.whl"]
    assert sorted(p.name for p in site.iterdir()) == ["rig_carried_extra.py", "rig_carried_probe", "rig_carried_probe-1.0.dist-info"]
    run = subprocess.run([sys.executable, "-c", "import rig_carried_probe, rig_carried_extra; print(rig_carried_probe.VALUE + rig_carried_extra.VALUE)"],
                         env={"PYTHONPATH": str(site)}, capture_output=True, text=True, timeout=60)
    assert run.stdout.strip() == "15"
