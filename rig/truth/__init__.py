"""Ground truth a take carries, from the sources that know it, found by name as the camera backends
are (rig.cameras): each module of this package is a source, named after the entry it writes in a
take's `extra` (sequence.json, docs/sequence-format.md). Recording and reading a take name no
source; adding one is adding a module. A source defines
- `take_truth(config)`: its entry for a take of this rig, or None when it knows nothing of the rig;
- `cameras(entry)`: the exact cameras the entry holds (the "cameras" of a calibration file);
- `Renderer(entry)`: `depth_and_mask(model, time_s)`, the exact depth (metres, 0 = nothing) and
  person mask (bool) that camera `model` saw at time `time_s` of the take.
"""
from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType
from typing import Any, Optional


def _sources() -> dict[str, ModuleType]:
    return {info.name: importlib.import_module(f"{__name__}.{info.name}")
            for info in pkgutil.iter_modules(__path__) if not info.name.startswith("_")}


def take_truth(config) -> dict[str, Any]:
    """The entries a take of `config`'s rig records for its ground truth ({} when no source knows it)."""
    entries = {name: source.take_truth(config) for name, source in _sources().items()}
    return {name: entry for name, entry in entries.items() if entry is not None}


def _recorded(extra: dict) -> Optional[tuple[ModuleType, Any]]:
    """The source of the ground truth a take's `extra` holds, with its entry; None when it holds none."""
    for name, source in _sources().items():
        if extra.get(name):
            return source, extra[name]
    return None


def truth_cameras(extra: dict) -> Optional[dict]:
    """The exact cameras of a take's ground truth, as a calibration file's "cameras"; None without one."""
    found = _recorded(extra)
    return None if found is None else found[0].cameras(found[1])


def renderer(extra: dict):
    """What renders a take's ground truth (`depth_and_mask(model, time_s)`); None without one."""
    found = _recorded(extra)
    return None if found is None else found[0].Renderer(found[1])
