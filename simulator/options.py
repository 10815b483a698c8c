"""Options of the simulated hardware, as they appear in a rig config.

Three kinds of table: `[sim]` (the scene), a camera's `sim = {...}` (its sensor model) and the
trigger board's `sim = {...}` (the emulator). Each option has a type, a range and a default; this
table is the single place that defines them (the config checker and the simulator both read it).
"""
from __future__ import annotations

from typing import Any

# name: (type, min, max, default, help)
SCENE_OPTIONS: dict[str, tuple] = {
    "seed": (int, 0, 2**31 - 1, 0, "random seed of the scene"),
    "scene": (str, None, None, "studio", "studio (room with props) | empty (bare room)"),
    "people": (int, 0, 3, 2, "number of people in the scene"),
    "motion": (str, None, None, "mixed", "walk | wave | dance | jump | mixed | still"),
    "board": (str, None, None, "none", "none | charuco | chessboard: a board carried through the volume"),
    "loop_frames": (int, 0, 100000, 0, "pre-render this many frames per camera and replay them (0 = render live)"),
    "loop_fps": (float, 0.1, 1000.0, 30.0, "frame rate of the pre-rendered loop (the loop lasts loop_frames / loop_fps s)"),
    "noise_variants": (int, 0, 64, 4, "loop replay: noise realisations drawn per loop frame at prerender (0 = fresh noise every frame, costs CPU)"),
    "led": (bool, None, None, False, "the trigger board's flash LED hangs above the stage, seen by every camera"),
}

CAMERA_OPTIONS: dict[str, tuple] = {
    "drop_rate": (float, 0.0, 1.0, 0.0, "probability that a frame is lost"),
    "clock_offset_ns": (int, -(2**62), 2**62, 0, "device clock offset from the simulated time"),
    "drift_ppm": (float, -10000.0, 10000.0, 0.0, "device clock drift"),
    "latency_us": (float, 0.0, 1e6, 20.0, "trigger-to-exposure latency"),
    "jitter_us": (float, 0.0, 1e6, 0.0, "standard deviation of the trigger latency"),
    "shot_noise": (float, 0.0, 100.0, 1.0, "shot-noise scale (1 = physical at full well)"),
    "read_noise": (float, 0.0, 100.0, 1.0, "read noise, in 8-bit digital numbers (std)"),
    "motion_blur": (bool, None, None, True, "integrate motion over the exposure time"),
    "blur_samples": (int, 1, 16, 3, "renders averaged over the exposure when motion_blur is on"),
    "full_well": (float, 100.0, 1e6, 10000.0, "electrons at full scale (gain 0 dB): sets the shot-noise level"),
    "bayer": (str, None, None, "", "deliver raw Bayer (RG, GR, GB, BG); empty = as pixel_format says"),
    "seed": (int, 0, 2**31 - 1, 0, "random seed of this sensor's noise, drops and jitter"),
    "disconnect_after_s": (float, 0.0, 1e9, 0.0, "the camera vanishes this long after it starts (0 = never)"),
    "reconnect_after_s": (float, 0.0, 1e9, 0.0, "a vanished camera comes back this long after it vanished (0 = never)"),
    "open_s": (float, 0.0, 600.0, 0.0, "seconds every open (and reconnect) of the camera takes, as a GigE camera's can"),
}

TRIGGER_OPTIONS: dict[str, tuple] = {
    "clock_offset_us": (int, 0, 2**62, 0, "board clock reading at power-up (the board counts microseconds from there)"),
    "drift_ppm": (float, -10000.0, 10000.0, 0.0, "board clock drift"),
    "reply_jitter_us": (float, 0.0, 1e6, 0.0, "mean of the random (exponential) delay of every line the board sends"),
    "drop_pulse_rate": (float, 0.0, 1.0, 0.0, "probability that a pulse is not delivered to the cameras"),
    "corrupt_rate": (float, 0.0, 1.0, 0.0, "probability that a line (either direction) is corrupted"),
    "delay_rate": (float, 0.0, 1.0, 0.0, "probability that a line the board sends is held back and overtaken"),
    "delay_ms": (float, 0.0, 10000.0, 50.0, "how long a held-back line waits"),
    "transport": (str, None, None, "pty", "pty | socket: how the host reaches the emulated board"),
    "seed": (int, 0, 2**31 - 1, 0, "random seed of the emulator"),
}

OPTIONS = {"scene": SCENE_OPTIONS, "camera": CAMERA_OPTIONS, "trigger": TRIGGER_OPTIONS}

_CHOICES = {
    ("scene", "scene"): ("studio", "empty"),
    ("scene", "motion"): ("walk", "wave", "dance", "jump", "mixed", "still"),
    ("scene", "board"): ("none", "charuco", "chessboard"),
    ("camera", "bayer"): ("", "RG", "GR", "GB", "BG"),
    ("trigger", "transport"): ("pty", "socket"),
}


def validate_options(table: dict[str, Any], kind: str) -> dict[str, Any]:
    """Check a table of options; raise ValueError("key: what is wrong") on the first mistake."""
    spec = OPTIONS[kind]
    for key, value in table.items():
        if key not in spec:
            raise ValueError(f"{key}: unknown option (allowed: {', '.join(spec)})")
        typ, lo, hi, _default, _help = spec[key]
        if typ is float:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        elif typ is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:
            ok = isinstance(value, typ)
        if not ok:
            raise ValueError(f"{key}: must be {typ.__name__}, got {value!r}")
        if lo is not None and not lo <= value <= hi:
            raise ValueError(f"{key}: must be between {lo} and {hi}, got {value!r}")
        choices = _CHOICES.get((kind, key))
        if choices is not None and value not in choices:
            raise ValueError(f"{key}: {value!r} is not allowed (allowed: {', '.join(repr(c) for c in choices)})")
    return with_defaults(table, kind)


def with_defaults(table: dict[str, Any], kind: str) -> dict[str, Any]:
    out = {k: v[3] for k, v in OPTIONS[kind].items()}
    out.update(table)
    return out
