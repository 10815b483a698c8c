"""The configuration of a simulated rig, and the calibration board that suits it."""
from __future__ import annotations

import json
from typing import Any

from simulator.rig import camera_names

# The calibration board that suits a simulated rig: A0 size (1.155 x 0.84 m), what a rig whose
# cameras stand 3.6 m from the volume needs (docs/calibration.md, "Boards").
SIM_RIG_BOARD = {"type": "charuco", "squares_x": 11, "squares_y": 8, "square_size": 0.105, "marker_size": 0.078,
                 "dictionary": "DICT_5X5_100"}


def board_toml(board: dict) -> str:
    """A board file (`--board`) for `board`."""
    return "".join(f"{k} = {json.dumps(v)}\n" for k, v in board.items())


def sim_rig_config(n_cameras: int = 2, width: int = 640, height: int = 360, fps: float = 30.0,
                   trigger: str = "hardware", pixel_format: str = "RGB8") -> dict[str, Any]:
    """The configuration of a simulated rig, as `rig config init --sim` and `rig demo` write it: cameras named as the virtual rig names them, fired by the emulated trigger board."""
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
    cfg = {"rig": {"name": f"sim-{n_cameras}cam", "storage": "recordings"}, "sim": {"seed": 0, "people": 2, "loop_frames": 30}, "cameras": cameras}
    if trigger == "hardware":
        cfg["trigger"] = {"uri": "sim://trigger", "rate_hz": fps, "pulse_width_us": 100.0}
    return cfg
