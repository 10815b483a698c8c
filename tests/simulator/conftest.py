"""Scenes and rigs shared by the simulator tests (scenes build their textures once per session)."""
from __future__ import annotations

import pytest

from simulator.rig import virtual_rig
from simulator.scene import Scene


@pytest.fixture(scope="session")
def people_scene() -> Scene:
    return Scene(seed=3, people=3, motion="mixed")


@pytest.fixture(scope="session")
def small_rig():
    return virtual_rig(6, 384, 216)
