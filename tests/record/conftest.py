"""A small filesystem to fill: a tmpfs of a chosen size (needs root to mount; skipped otherwise)."""
from __future__ import annotations

import subprocess

import pytest


@pytest.fixture
def small_filesystem(tmp_path):
    """`small_filesystem(megabytes)` mounts a fresh tmpfs of that size and returns its folder."""
    mounted = []

    def mount(megabytes: int):
        mnt = tmp_path / f"small{len(mounted)}"
        mnt.mkdir()
        if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={megabytes}m", "tmpfs", str(mnt)], capture_output=True).returncode != 0:
            pytest.skip("cannot mount a small tmpfs here (needs root)")
        mounted.append(mnt)
        return mnt

    try:
        yield mount
    finally:
        for mnt in mounted:
            subprocess.run(["umount", "-l", str(mnt)])
