"""Ground-truth snapshots of a simulated rig: every camera's image, depth and person mask at one
instant, and the exact calibration in the project's calibration file schema."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from simulator.errors import SimulatorError
from simulator.render import render
from simulator.scene import check_time
from simulator.sensor import SimRig

CALIBRATION_FILE = "cameras.json"


def write_snapshot(config, t: float, out_dir, progress: Optional[Callable[[str], None]] = None) -> dict:
    """Render every sim:// camera of `config` (a RigConfig) at time `t` into `out_dir`:
    NAME.png (RGB), NAME.depth.npy (float32 metres, 0 where nothing is hit), NAME.mask.png
    (255 on people) and cameras.json. Returns a summary (what `rig sim snapshot --json` prints)."""
    t = check_time(t)
    rig = SimRig(config)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SimulatorError(f"{out}: cannot create the output folder ({exc.strerror})") from None
    cameras = []
    for i, cam in enumerate(rig.calibration.cameras):
        if progress:
            progress(f"rendering {cam.name} ({i + 1}/{len(rig.calibration.cameras)})")
        r = render(rig.scene, cam, t)
        files = {"image": f"{cam.name}.png", "depth": f"{cam.name}.depth.npy", "mask": f"{cam.name}.mask.png"}
        _write_png(out / files["image"], cv2.cvtColor(r.rgb, cv2.COLOR_RGB2BGR))
        np.save(out / files["depth"], r.depth.astype(np.float32))
        _write_png(out / files["mask"], r.mask.astype(np.uint8) * 255)
        hit = r.depth > 0
        cameras.append({
            "name": cam.name, "width": cam.width, "height": cam.height, **files,
            "person_pixels": int(r.mask.sum()),
            "depth_min_m": float(r.depth[hit].min()) if hit.any() else 0.0,
            "depth_max_m": float(r.depth[hit].max()) if hit.any() else 0.0,
        })
    rig.calibration.meta.update({"time_s": t, "scene": dict(rig.options)})
    rig.calibration.save(out / CALIBRATION_FILE)
    return {"time_s": t, "out": str(out), "calibration": CALIBRATION_FILE, "scene": dict(rig.options), "cameras": cameras}


def _write_png(path: Path, img: np.ndarray) -> None:
    try:
        ok = cv2.imwrite(str(path), img)
    except cv2.error as exc:
        raise SimulatorError(f"{path}: cannot write ({exc})") from None
    if not ok:
        raise SimulatorError(f"{path}: cannot write the image (is the folder writable?)")
