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


# ---- validation helpers ----------------------------------------------------------------------------

def _type_name(t) -> str:
    return {int: "an integer", float: "a number", str: "a string", bool: "true or false", dict: "a table"}[t]


def _check_type(where: str, key: str, value: Any, typ) -> Any:
    if typ is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        return float(value) if ok else _bad_type(where, key, value, typ)
    if typ is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, typ)
    return value if ok else _bad_type(where, key, value, typ)


def _bad_type(where: str, key: str, value: Any, typ):
    raise ConfigError(f"{where}.{key}: must be {_type_name(typ)}, got {type(value).__name__} {value!r}")


def _check_keys(where: str, table: dict, allowed: dict) -> None:
    for key in table:
        if key not in allowed:
            raise ConfigError(f"{where}: unknown key '{key}' (allowed: {', '.join(allowed)})")


def _fields(where: str, table: dict, spec: dict, required: tuple = ()) -> dict:
    _check_keys(where, table, spec)
    for key in required:
        if key not in table:
            raise ConfigError(f"{where}: missing key '{key}'")
    return {k: _check_type(where, k, v, spec[k]) for k, v in table.items()}


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
    _check_keys("config", data, TOP_KEYS)
    for key, typ in TOP_KEYS.items():
        if key in data and not isinstance(data[key], typ):
            what = "an array of tables ([[cameras]])" if typ is list else "a table"
            raise ConfigError(f"{key}: must be {what}")
    rig = _fields("rig", data.get("rig", {}), RIG_KEYS)
    cams_raw = data.get("cameras")
    if not cams_raw:
        raise ConfigError("cameras: at least one [[cameras]] entry is required")

    schemes = known_schemes()
    cameras: list[CameraConfig] = []
    seen_names: set[str] = set()
    seen_roles: dict[str, str] = {}
    for i, raw in enumerate(cams_raw):
        where = f"cameras[{i}]"
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: must be a table")
        vals = _fields(where, raw, CAMERA_KEYS, required=("name", "uri"))
        name = vals["name"]
        where = f"cameras[{i}] ('{name}')"
        if not name or not all(ch.isalnum() or ch in "-_" for ch in name):
            raise ConfigError(f"{where}.name: use letters, digits, '-' and '_' only, got {name!r}")
        if name in seen_names:
            raise ConfigError(f"{where}.name: duplicate camera name '{name}' (names must be unique)")
        seen_names.add(name)
        uri = vals["uri"]
        if "://" not in uri:
            raise ConfigError(f"{where}.uri: {uri!r} is not a URI (expected scheme://address, e.g. aravis://127.0.0.1, sim://left)")
        scheme = uri.split("://", 1)[0]
        if scheme not in schemes:
            raise ConfigError(f"{where}.uri: unknown scheme '{scheme}' (allowed: {', '.join(schemes)})")
        role = vals.get("role", "supervision")
        if role not in ROLES:
            raise ConfigError(f"{where}.role: {role!r} is not allowed (allowed: {', '.join(ROLES)})")
        if role in ("left", "right"):
            if role in seen_roles:
                raise ConfigError(f"{where}.role: a second '{role}' camera (already '{seen_roles[role]}'); at most one left and one right")
            seen_roles[role] = name
        pf = vals.get("pixel_format", "Mono8")
        if pf not in PIXEL_FORMATS:
            raise ConfigError(f"{where}.pixel_format: unsupported {pf!r} (allowed: {', '.join(PIXEL_FORMATS)})")
        trig = vals.get("trigger", "free")
        if trig not in TRIGGER_MODES:
            raise ConfigError(f"{where}.trigger: {trig!r} is not allowed (allowed: {', '.join(TRIGGER_MODES)})")
        for key in ("width", "height"):
            if key in vals and not 1 <= vals[key] <= 16384:
                raise ConfigError(f"{where}.{key}: must be between 1 and 16384, got {vals[key]}")
        if "fps" in vals and not 0 < vals["fps"] <= 10000:
            raise ConfigError(f"{where}.fps: must be between 0 and 10000, got {vals['fps']}")
        if "exposure_us" in vals and vals["exposure_us"] <= 0:
            raise ConfigError(f"{where}.exposure_us: must be positive, got {vals['exposure_us']}")
        if scheme == "sim" and vals.get("sim"):
            _check_sim_options(f"{where}.sim", vals["sim"], "camera")
        elif vals.get("sim"):
            raise ConfigError(f"{where}.sim: sensor-model options apply to sim:// cameras only")
        cameras.append(CameraConfig(**vals))

    trigger = None
    if "trigger" in data:
        t = _fields("trigger", data["trigger"], TRIGGER_KEYS, required=("uri",))
        if "://" not in t["uri"]:
            raise ConfigError(f"trigger.uri: {t['uri']!r} is not a URI (e.g. serial:///dev/ttyACM0, socket://127.0.0.1:7000, sim://trigger)")
        if "rate_hz" in t and not 0 < t["rate_hz"] <= 10000:
            raise ConfigError(f"trigger.rate_hz: must be between 0 and 10000, got {t['rate_hz']}")
        if "pulse_width_us" in t and t["pulse_width_us"] <= 0:
            raise ConfigError(f"trigger.pulse_width_us: must be positive, got {t['pulse_width_us']}")
        if t.get("sim"):
            _check_sim_options("trigger.sim", t["sim"], "trigger")
        trigger = TriggerConfig(**t)
    elif any(c.trigger == "hardware" for c in cameras):
        first = next(c.name for c in cameras if c.trigger == "hardware")
        raise ConfigError(f"cameras ('{first}').trigger: 'hardware' needs a [trigger] board (add [trigger] uri = ...)")

    live = LiveConfig(**_fields("live", data.get("live", {}), LIVE_KEYS))
    if not 0 < live.port < 65536:
        raise ConfigError(f"live.port: must be between 1 and 65535, got {live.port}")
    sim = data.get("sim", {})
    if sim:
        _check_sim_options("sim", sim, "scene")
    cfg = RigConfig(
        name=rig.get("name", "rig"),
        cameras=cameras,
        trigger=trigger,
        calibration=rig.get("calibration"),
        storage=rig.get("storage", "recordings"),
        live=live,
        sim=dict(sim),
        path=path,
    )
    for c in cameras:
        c.rig = cfg  # backends that need the whole rig (the sim:// scene) find it here; not a dataclass field
    return cfg


def _check_sim_options(where: str, table: dict, kind: str) -> None:
    """Simulator options are validated by the simulator, which owns their meaning."""
    from rig.cameras.sim import check_options

    try:
        check_options(table, kind)
    except ValueError as exc:
        raise ConfigError(f"{where}.{exc}") from None


def load_config(path: str | Path) -> RigConfig:
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    try:
        return parse_config(data, path)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


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
