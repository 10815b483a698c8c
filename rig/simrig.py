"""The configuration of a simulated rig, as `rig config init --sim` and `rig demo` write it."""
from __future__ import annotations

from typing import Any


def camera_names(n_cameras: int) -> list[str]:
    """Arc order: left, the supervision cameras, right (the simulator's virtual rig uses the same)."""
    return ["left"] + [f"sup{i}" for i in range(1, n_cameras - 1)] + ["right"]


def sim_rig_config(n_cameras: int = 2, width: int = 640, height: int = 360, fps: float = 30.0,
                   trigger: str = "software", pixel_format: str = "RGB8") -> dict[str, Any]:
    cameras = []
    for i, name in enumerate(camera_names(n_cameras)):
        role = name if name in ("left", "right") else "supervision"
        cameras.append({
            "name": name,
            "uri": f"sim://{name}",
            "role": role,
            "width": width,
            "height": height,
            "pixel_format": pixel_format,
            "fps": fps,
            "trigger": trigger,
            "exposure_us": 5000.0,
            "gain": 0.0,
            "sim": {"seed": i},
        })
    return {"rig": {"name": f"sim-{n_cameras}cam", "storage": "recordings"}, "sim": {"seed": 0, "people": 2}, "cameras": cameras}
