"""The simulator's ground truth: a take of simulated cameras carries the scene's options and the
exact cameras, from which the depth and the person masks every camera saw are rendered on demand."""
from __future__ import annotations

from typing import Any, Optional

SCHEME = "sim"  # the cameras whose takes it knows: those of the sim:// backend


def take_truth(cfg) -> Optional[dict[str, Any]]:
    """The scene's options and the exact cameras of a rig with simulated cameras, else None."""
    if not any(c.scheme == SCHEME for c in cfg.cameras):
        return None
    from simulator.sensor import sim_rig

    rig = sim_rig(cfg)
    return {"scene": dict(rig.options), "cameras": rig.calibration.to_dict()["cameras"]}


def cameras(entry: dict) -> dict:
    return entry["cameras"]


class Renderer:
    """Renders a simulated take's exact depth and person masks from what `take_truth` recorded."""

    def __init__(self, entry: dict):
        from simulator.scene import Scene

        self.scene = Scene.from_options(entry["scene"])

    def depth_and_mask(self, model, sim_time_s: float):
        from simulator.render import render

        r = render(self.scene, model, float(sim_time_s))
        return r.depth, r.mask
