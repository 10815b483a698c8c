"""Rig configuration: one TOML file describes cameras, trigger board, calibration, storage, live server.

Every mistake becomes one `ConfigError` whose message names the key and what is allowed.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from rig.errors import ConfigError
from sync.frames import PIXEL_FORMATS

ROLES = ("left", "right", "supervision")
TRIGGER_MODES = ("hardware", "software", "free")


@dataclass
class CameraConfig:
    name: str
    uri: str
    role: str = "supervision"
    width: int = 640
    height: int = 480
    pixel_format: str = "Mono8"
    fps: float = 30.0
    trigger: str = "free"
    exposure_us: Optional[float] = None
    gain: Optional[float] = None
    latency_ms: Optional[float] = None  # exposure start to host arrival (free-running cameras' grouping)
    sim: dict[str, Any] = field(default_factory=dict)  # sensor-model options of sim:// cameras
    rig = None  # the RigConfig this camera belongs to (set when the config is parsed)

    @property
    def scheme(self) -> str:
        return self.uri.split("://", 1)[0]


@dataclass
class TriggerConfig:
    uri: str
    rate_hz: float = 30.0
    pulse_width_us: float = 100.0
    sim: dict[str, Any] = field(default_factory=dict)  # emulator options of sim://trigger


@dataclass
class LiveConfig:
    host: str = "127.0.0.1"
    port: int = 8080


@dataclass
class RigConfig:
    name: str
    cameras: list[CameraConfig]
    trigger: Optional[TriggerConfig] = None
    calibration: Optional[str] = None
    storage: str = "recordings"
    live: LiveConfig = field(default_factory=LiveConfig)
    sim: dict[str, Any] = field(default_factory=dict)  # simulated scene options
    path: Optional[Path] = None

    def camera(self, name: str) -> CameraConfig:
        for c in self.cameras:
            if c.name == name:
                return c
        raise ConfigError(f"no camera named '{name}' in the rig (have: {', '.join(c.name for c in self.cameras)})")

    def by_role(self, role: str) -> Optional[CameraConfig]:
        for c in self.cameras:
            if c.role == role:
                return c
        return None

    def resolve(self, p: str) -> Path:
        """Paths in the file are relative to the file's folder."""
        path = Path(p)
        if not path.is_absolute() and self.path is not None:
            path = self.path.parent / path
        return path


# ---- validation: every problem is collected, one line each ---------------------------------------

class _Problems:
    """The mistakes found so far. Checks add to it and go on, so that `rig config check` lists every
    problem of a file at once instead of one per run."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def add(self, line: str) -> None:
        self.lines.append(line)

    def raise_if_any(self, prefix: str = "") -> None:
        if self.lines:
            raise ConfigError.of([prefix + line for line in self.lines])


_BAD = object()  # a value that failed its check (the problem is already recorded)


def _type_name(t) -> str:
    return {int: "an integer", float: "a number", str: "a string", bool: "true or false", dict: "a table"}[t]


def _check_type(where: str, key: str, value: Any, typ, problems: _Problems) -> Any:
    if typ is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif typ is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, typ)
    if ok:
        return value
    problems.add(f"{where}.{key}: must be {_type_name(typ)}, got {type(value).__name__} {value!r}")
    return _BAD


def _fields(where: str, table: dict, spec: dict, problems: _Problems, required: tuple = ()) -> dict:
    """The table's well-typed known keys; unknown keys, missing required keys and wrong types are
    recorded and left out."""
    for key in table:
        if key not in spec:
            problems.add(f"{where}: unknown key '{key}' (allowed: {', '.join(spec)})")
    for key in required:
        if key not in table:
            problems.add(f"{where}: missing key '{key}'")
    out = {}
    for k, v in table.items():
        if k in spec:
            v = _check_type(where, k, v, spec[k], problems)
            if v is not _BAD:
                out[k] = v
    return out


CAMERA_KEYS = {
    "name": str,
    "uri": str,
    "role": str,
    "width": int,
    "height": int,
    "pixel_format": str,
    "fps": float,
    "trigger": str,
    "exposure_us": float,
    "gain": float,
    "latency_ms": float,
    "sim": dict,
}
TRIGGER_KEYS = {"uri": str, "rate_hz": float, "pulse_width_us": float, "sim": dict}
RIG_KEYS = {"name": str, "calibration": str, "storage": str}
LIVE_KEYS = {"host": str, "port": int}
TOP_KEYS = {"rig": dict, "cameras": list, "trigger": dict, "live": dict, "sim": dict}


def known_schemes() -> list[str]:
    from rig.cameras import schemes

    return schemes()


def parse_config(data: dict, path: Optional[Path] = None) -> RigConfig:
    """A RigConfig from parsed TOML; a `ConfigError` lists every problem found (`.problems`)."""
    problems = _Problems()
    for key in data:
        if key not in TOP_KEYS:
            problems.add(f"config: unknown key '{key}' (allowed: {', '.join(TOP_KEYS)})")
    tables = {}
    for key, typ in TOP_KEYS.items():
        if key in data and not isinstance(data[key], typ):
            what = "an array of tables ([[cameras]])" if typ is list else "a table"
            problems.add(f"{key}: must be {what}")
        elif key in data:
            tables[key] = data[key]
    rig = _fields("rig", tables.get("rig", {}), RIG_KEYS, problems)
    cameras, hardware = _parse_cameras(tables.get("cameras"), "cameras" in data, problems)
    trigger = _parse_trigger(tables, hardware, problems)
    _check_timing(cameras, trigger, problems)
    live_vals = _fields("live", tables.get("live", {}), LIVE_KEYS, problems)
    if "port" in live_vals and not 0 < live_vals["port"] < 65536:
        problems.add(f"live.port: must be between 1 and 65535, got {live_vals.pop('port')}")
    sim = tables.get("sim", {})
    if sim:
        _check_sim_options("sim", sim, "scene", problems)
    problems.raise_if_any()
    cfg = RigConfig(
        name=rig.get("name", "rig"),
        cameras=cameras,
        trigger=trigger,
        calibration=rig.get("calibration"),
        storage=rig.get("storage", "recordings"),
        live=LiveConfig(**live_vals),
        sim=dict(sim),
        path=path,
    )
    for c in cameras:
        c.rig = cfg  # backends that need the whole rig (the sim:// scene) find it here; not a dataclass field
    return cfg


def _parse_cameras(cams_raw, given: bool, problems: _Problems) -> tuple[list[CameraConfig], list[str]]:
    """The cameras without a mistake, and the names of those (good or not) set to hardware trigger."""
    if not cams_raw:
        if not given or isinstance(cams_raw, list):
            problems.add("cameras: at least one [[cameras]] entry is required")
        return [], []
    hardware: list[str] = []
    schemes = known_schemes()
    cameras: list[CameraConfig] = []
    seen_names: set[str] = set()
    seen_roles: dict[str, str] = {}
    for i, raw in enumerate(cams_raw):
        where = f"cameras[{i}]"
        if not isinstance(raw, dict):
            problems.add(f"{where}: must be a table")
            continue
        before = len(problems.lines)
        vals = _fields(where, raw, CAMERA_KEYS, problems, required=("name", "uri"))
        name = vals.get("name")
        if name is not None:
            where = f"cameras[{i}] ('{name}')"
            if not name or not all(ch.isalnum() or ch in "-_" for ch in name):
                problems.add(f"{where}.name: use letters, digits, '-' and '_' only, got {name!r}")
            elif name in seen_names:
                problems.add(f"{where}.name: duplicate camera name '{name}' (names must be unique)")
            seen_names.add(name)
        uri = vals.get("uri")
        scheme = None
        if uri is not None:
            if "://" not in uri:
                problems.add(f"{where}.uri: {uri!r} is not a URI (expected scheme://address, e.g. aravis://127.0.0.1, sim://left)")
            else:
                scheme = uri.split("://", 1)[0]
                if scheme not in schemes:
                    problems.add(f"{where}.uri: unknown scheme '{scheme}' (allowed: {', '.join(schemes)})")
        role = vals.get("role", "supervision")
        if role not in ROLES:
            problems.add(f"{where}.role: {role!r} is not allowed (allowed: {', '.join(ROLES)})")
        elif role in ("left", "right"):
            if role in seen_roles:
                problems.add(f"{where}.role: a second '{role}' camera (already '{seen_roles[role]}'); at most one left and one right")
            else:
                seen_roles[role] = name
        pf = vals.get("pixel_format", "Mono8")
        if pf not in PIXEL_FORMATS:
            problems.add(f"{where}.pixel_format: unsupported {pf!r} (allowed: {', '.join(PIXEL_FORMATS)})")
        trig = vals.get("trigger", "free")
        if trig == "hardware":
            hardware.append(name or where)
        if trig not in TRIGGER_MODES:
            problems.add(f"{where}.trigger: {trig!r} is not allowed (allowed: {', '.join(TRIGGER_MODES)})")
        for key in ("width", "height"):
            if key in vals and not 1 <= vals[key] <= 16384:
                problems.add(f"{where}.{key}: must be between 1 and 16384, got {vals[key]}")
        if "fps" in vals and not 0 < vals["fps"] <= 10000:
            problems.add(f"{where}.fps: must be between 0 and 10000, got {vals['fps']}")
        if "exposure_us" in vals and vals["exposure_us"] <= 0:
            problems.add(f"{where}.exposure_us: must be positive, got {vals['exposure_us']}")
        if "latency_ms" in vals and not 0 <= vals["latency_ms"] <= 10000:
            problems.add(f"{where}.latency_ms: must be between 0 and 10000, got {vals['latency_ms']}")
        if vals.get("sim") and scheme == "sim":
            _check_sim_options(f"{where}.sim", vals["sim"], "camera", problems)
        elif vals.get("sim") and scheme is not None:
            problems.add(f"{where}.sim: sensor-model options apply to sim:// cameras only")
        if len(problems.lines) == before:
            cam = CameraConfig(**vals)
            for line in _backend_problems(cam):
                problems.add(f"{where}: {line}")
            if len(problems.lines) == before:
                cameras.append(cam)
    return cameras, hardware


def _backend_problems(cam: CameraConfig) -> list[str]:
    """What the camera's backend says of these settings (a GoPro cannot be triggered, a webcam URI
    names a device, ...): backends that can check define `problems(uri, settings)`."""
    from rig.cameras import backend

    check = getattr(backend(cam.scheme), "problems", None)
    return check(cam.uri, cam) if check is not None else []


def _parse_trigger(tables: dict, hardware: list[str], problems: _Problems) -> Optional[TriggerConfig]:
    if "trigger" not in tables:
        if hardware:
            problems.add(f"cameras ('{hardware[0]}').trigger: 'hardware' needs a [trigger] board (add [trigger] uri = ...)")
        return None
    before = len(problems.lines)
    t = _fields("trigger", tables["trigger"], TRIGGER_KEYS, problems, required=("uri",))
    if "uri" in t and "://" not in t["uri"]:
        problems.add(f"trigger.uri: {t['uri']!r} is not a URI (e.g. serial:///dev/ttyACM0, socket://127.0.0.1:7000, sim://trigger)")
    if "rate_hz" in t and not 0 < t["rate_hz"] <= 10000:
        problems.add(f"trigger.rate_hz: must be between 0 and 10000, got {t['rate_hz']}")
    if "pulse_width_us" in t and t["pulse_width_us"] <= 0:
        problems.add(f"trigger.pulse_width_us: must be positive, got {t['pulse_width_us']}")
    if t.get("sim"):
        _check_sim_options("trigger.sim", t["sim"], "trigger", problems)
    return TriggerConfig(**t) if len(problems.lines) == before else None


def _check_timing(cameras: list[CameraConfig], trigger: Optional[TriggerConfig], problems: _Problems) -> None:
    """An exposure must end before the next frame starts: longer than the trigger's period (or a
    free-running camera's frame time) every other pulse finds the camera busy and its frame is lost;
    the trigger's pulse must end before its next one."""
    if trigger is not None:
        period_us = 1e6 / trigger.rate_hz
        if trigger.pulse_width_us is not None and trigger.pulse_width_us >= period_us:
            problems.add(f"trigger.pulse_width_us: {trigger.pulse_width_us:g} us is not shorter than the pulse period "
                         f"({period_us:g} us at {trigger.rate_hz:g} Hz)")
    for i, cam in enumerate(cameras):
        if cam.exposure_us is None:
            continue
        if cam.trigger == "hardware" and trigger is not None:
            period_us, what = 1e6 / trigger.rate_hz, f"the trigger's period ({1e6 / trigger.rate_hz:g} us at {trigger.rate_hz:g} Hz)"
        elif cam.fps:
            period_us, what = 1e6 / cam.fps, f"its frame time ({1e6 / cam.fps:g} us at {cam.fps:g} fps)"
        else:
            continue
        if cam.exposure_us >= period_us:
            problems.add(f"cameras[{i}] ('{cam.name}').exposure_us: {cam.exposure_us:g} us is not shorter than {what}; "
                         "every other frame would be lost")


def _check_sim_options(where: str, table: dict, kind: str, problems: _Problems) -> None:
    """Simulator options are validated by the simulator, which owns their meaning; one key at a time,
    so that every bad key is reported."""
    from rig.sim.options import check_options

    for key, value in table.items():
        try:
            check_options({key: value}, kind)
        except ValueError as exc:
            problems.add(f"{where}.{exc}")


# ---- the calibration file a config names -----------------------------------------------------------

def calibration_problems(cfg: RigConfig) -> list[str]:
    """What is wrong with the calibration file `cfg` names, one line each (empty when it is fine or
    there is none): it must exist, parse, and hold every camera of the config at the config's size.
    A take recorded with a calibration that does not fit its cameras would be unusable."""
    if not cfg.calibration:
        return []
    from calibration.camera import CalibrationError, RigCalibration

    path = cfg.resolve(cfg.calibration)
    fix = "recalibrate (`rig calibrate capture`, then `rig calibrate run`) or remove the key"
    if not path.is_file():
        what = "is a folder, not a file" if path.is_dir() else "does not exist"
        return [f"rig.calibration: {path} {what} ({fix})"]
    try:
        calib = RigCalibration.load(path)
    except CalibrationError as exc:
        return [f"rig.calibration: {exc} ({fix})"]
    except (UnicodeDecodeError, ValueError):  # binary garbage: not even text
        return [f"rig.calibration: {path}: not a calibration file (not JSON text) ({fix})"]
    out = []
    for cam in cfg.cameras:
        if cam.name not in calib:
            out.append(f"rig.calibration: camera '{cam.name}' of the config is not in {path} (it has: {', '.join(calib.names)}); {fix}")
            continue
        model = calib[cam.name]
        if (model.width, model.height) != (cam.width, cam.height):
            out.append(f"rig.calibration: camera '{cam.name}' is {cam.width}x{cam.height} in the config but "
                       f"{model.width}x{model.height} in {path}; {fix}, or set its width and height back")
    return out


def load_config(path: str | Path, check_calibration: bool = True) -> RigConfig:
    """Read and check a config file. Every problem is collected: the `ConfigError` says the first in
    its message and lists them all in `.problems`, each prefixed with the file's path. With
    `check_calibration` (every command but the one that makes a calibration) the calibration file the
    config names is checked too."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, not a config file") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file (a rig config is TOML)") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    try:
        cfg = parse_config(data, path)
    except ConfigError as exc:
        raise ConfigError.of([f"{path}: {line}" for line in exc.problems]) from None
    if check_calibration:
        problems = calibration_problems(cfg)
        if problems:
            raise ConfigError.of([f"{path}: {line}" for line in problems])
    return cfg


# ---- writing ---------------------------------------------------------------------------------------

def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_config(cfg: RigConfig) -> str:
    """TOML text for a config (round-trips through `parse_config`)."""
    out = ["[rig]", f"name = {_toml_value(cfg.name)}", f"storage = {_toml_value(cfg.storage)}"]
    if cfg.calibration:
        out.append(f"calibration = {_toml_value(cfg.calibration)}")
    if cfg.sim:
        out += ["", "[sim]"] + [f"{k} = {_toml_value(v)}" for k, v in cfg.sim.items()]
    if cfg.trigger:
        t = cfg.trigger
        out += ["", "[trigger]", f"uri = {_toml_value(t.uri)}", f"rate_hz = {_toml_value(t.rate_hz)}",
                f"pulse_width_us = {_toml_value(t.pulse_width_us)}"]
        if t.sim:
            out.append(f"sim = {_toml_value(t.sim)}")
    out += ["", "[live]", f"host = {_toml_value(cfg.live.host)}", f"port = {cfg.live.port}"]
    for c in cfg.cameras:
        out += ["", "[[cameras]]"]
        for key in CAMERA_KEYS:
            v = getattr(c, key)
            if v is None or (key == "sim" and not v):
                continue
            out.append(f"{key} = {_toml_value(v)}")
    return "\n".join(out) + "\n"
