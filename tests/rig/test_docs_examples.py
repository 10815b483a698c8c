"""The examples of docs/dataset.md run as written: its shell lines make a small simulator take, and
each python block then reads it (the blocks assert what they show)."""
from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

DOC = Path(__file__).resolve().parents[2] / "docs" / "dataset.md"


def _blocks(lang: str) -> list[str]:
    return [body for kind, body in re.findall(r"```(\w+)\n(.*?)```", DOC.read_text(), re.S) if kind == lang]


def test_dataset_doc_examples_run_on_a_recorded_sim_take(tmp_path):
    shell, python = _blocks("bash"), _blocks("python")
    assert len(shell) == 1 and len(python) >= 2
    for line in shell[0].strip().splitlines():
        argv = shlex.split(line)
        assert argv[0] == "rig", line
        proc = subprocess.run([sys.executable, "-m", "rig", *argv[1:]], cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, (line, proc.stderr)
    for block in python:
        proc = subprocess.run([sys.executable, "-c", block], cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, (block, proc.stderr)
        assert proc.stdout.strip(), block
