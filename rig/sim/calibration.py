"""A simulated calibration session for `rig calibrate capture`."""
from __future__ import annotations

from typing import Any, Optional

from rig.errors import ConfigError

SCHEME = "sim"  # the cameras it applies to: those of the sim:// backend


def calibration_session(settings: list, board, views_per_station: int = 1) -> Optional[Any]:
    """Switch the sim:// cameras among `settings` to a calibration session, for `rig calibrate
    capture`: the simulated scene becomes `board` (the board file the user gave) held by someone at
    a series of stations planned to cover every camera's image and to be seen by several cameras at
    once, with nobody else in the scene, whatever the config's `[sim]` table says about people, a
    board or a pre-rendered loop. The cameras are fired by software trigger, and the k-th
    synchronised view shows the k-th station, so the capture depends neither on start-up time nor on
    how fast the host renders.

    `settings` are the CameraConfig copies the capture opens, each with `.rig` (the whole config);
    they are changed in place. Returns the session (`.sets`: the views it offers, `.describe()`,
    `.truth`: the cameras' exact calibration), or None when no camera is simulated.
    `views_per_station`: synchronised views the board is held still for at each station (the
    console keeps a view once the board is still: 2).
    """
    sims = [s for s in settings if s.scheme == SCHEME]
    if not sims:
        return None
    rig = getattr(sims[0], "rig", None)
    if rig is None:
        raise ConfigError("a simulated calibration session needs the rig configuration of its cameras")
    from simulator.calibration_session import CalibrationSession
    from simulator.errors import SimulatorError

    try:
        session = CalibrationSession(rig, board, views_per_station=views_per_station)
    except SimulatorError as exc:
        raise ConfigError(str(exc)) from None
    for s in sims:
        s.calibration_session = session
        s.trigger = "software"
    return session
