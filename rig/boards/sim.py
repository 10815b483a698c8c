"""`sim://trigger`: the simulator's emulated trigger board, opened on a port of its own and driven
through it as a real board is; its pulse output fires the hardware-trigger inputs of the simulated
cameras, and when the simulated scene has an LED (`[sim] led = true`) the board's LED output lights
it for the cameras in this process."""
from __future__ import annotations

from typing import Callable, Optional

from rig.errors import ConfigError
from rig.sim.clock import SIM_EPOCH_NS

# cameras an emulated board can trigger: simulated ones, in this process or served by their daemons
TRIGGERABLE = ("sim", "daemon")


def open(trigger, inputs: dict[str, Callable[[int, int], None]], rig=None):  # noqa: A001 - the backend contract's name
    if rig is not None:
        not_sim = [c.name for c in rig.cameras if c.name in inputs and c.scheme not in TRIGGERABLE]
        if not_sim:
            raise ConfigError(f"trigger.uri: an emulated board ({trigger.uri}) cannot trigger real cameras ({', '.join(not_sim)})")
    emulator = emulated_trigger_board(trigger.uri, trigger.sim, list(inputs.values()))
    try:
        led = scene_led(rig) if rig is not None else None
        if led is not None:  # the simulated scene shows the board's LED to its cameras
            emulator.add_led_output(led)
    except BaseException:
        emulator.close()
        raise
    return emulator.url, emulator


def scene_led(config) -> Optional[Callable[[bool, int], None]]:
    """The simulated scene's flash LED as an output of the emulated board (`on`, host ns), or None
    when the scene has none (`[sim] led = true`). Cameras in this process see it."""
    if not (getattr(config, "sim", None) or {}).get("led"):
        return None
    from simulator.sensor import sim_rig

    led = sim_rig(config).led
    return lambda on, host_ns: led.set_live(bool(on), (host_ns - SIM_EPOCH_NS) / 1e9)


def emulated_trigger_board(uri: str, options: dict, outputs: list[Callable[[int, int], None]]):
    """The emulated trigger board of a `sim://` trigger URI, opened, its pulse output wired to
    `outputs` (the hardware-trigger inputs of sim cameras); the session talks to it over its port
    (`.url`) as to a real board. `options`: the trigger's `sim = {...}` table."""
    from simulator.trigger_board import TriggerBoardEmulator

    emulator = TriggerBoardEmulator(options, board_id="SIM-" + (uri.split("://", 1)[1].strip("/") or "trigger").upper())
    for output in outputs:
        emulator.add_pulse_output(output)
    try:
        emulator.open()
    except BaseException:
        emulator.close()
        raise
    return emulator


