"""Virtual viewpoints between the two source cameras of a rig (numpy only: the live path).

A browser chooses what it sees with a small JSON message; `parse_viewpoint` checks it against the
rig and gives a `Viewpoint` (a frozen dataclass: hashable, so a renderer can cache per viewpoint),
and `Viewpoint.camera(rig, size)` gives the pinhole `CameraModel` to render:

    {"type": "viewpoint", "t": 0.3}                                  0.3 of the way from left to right
    {"type": "viewpoint", "preset": "sup2"}                          a calibrated camera, by name
    {"type": "viewpoint", "t": 0.5, "yaw": 10, "pitch": -5, "zoom": 1.5}   orbit and zoom on top

The arc (`arc_camera`). The virtual camera at t in [0, 1] has
- the rotation of the quaternion slerp between the sources' rotations (the shorter way);
- its centre on the arc through the two source centres around the subject point P (below): behind
  P along the slerped viewing direction, at a distance from P interpolated linearly between the
  sources' (measured along their optical axes). So the camera at every t looks at P, and the
  centres of a rig aimed at its subject (both axes through P, as the simulator's arc) follow the
  circle the rig stands on. Where the axes miss each other, what each misses P by (half the
  closest approach) is interpolated linearly, so t = 0 and t = 1 are the source centres exactly.
  When the closest approach is degenerate (parallel or diverging axes, a meeting point behind
  either camera or more than `MAX_SUBJECT_BASELINES` baselines away) there is no subject to turn
  about, and the centre is interpolated linearly between the two centres instead;
- intrinsics interpolated linearly (fx, fy, cx, cy, skew; each source's K first scaled to the
  output size with `CameraModel.scaled`'s pixel-centre convention) and no distortion.
At t = 0 it is exactly the left camera's pinhole (`inference.runtime.preprocess.pinhole`), at t = 1
the right one's (at the output size; the default size is the left camera's).

The subject point P is the midpoint of the closest approach of the two sources' optical axes;
when that is degenerate (see above), the point on the mean optical axis from the middle of the
baseline at `distance` metres (default: the baseline length, as a rig's cameras stand about as far
from the actors as from each other).

Orbit and zoom. `yaw` (degrees) turns the camera about the orbit axis through P, positive towards
the right source. The orbit axis is the axis of the rotation from the left source's orientation to
the right one's (what the slerp turns about, so yawing and moving along the arc agree: on a
symmetric rig, t with yaw y is the arc camera at t + y / span), or the sources' mean up direction
when they are (nearly) parallel. `pitch` (degrees) then turns it about its own horizontal axis
through P, positive upwards (it looks down more); `zoom` multiplies the focal lengths (the
principal point stays). Values are first checked (a ValueError outside the accepted ranges:
|yaw| <= 180, |pitch| <= 90, 0.05 <= zoom <= 20) and then clamped to the sane bounds: the camera's
azimuth about the orbit axis stays within the source arc widened by `YAW_MARGIN_DEG` (15 degrees)
on each side (a preset camera already outside it may stay or turn towards the arc, not further
out), |pitch| <= `PITCH_LIMIT_DEG` (20 degrees, relative to the arc or preset camera),
zoom within `ZOOM_RANGE` (0.5 to 3). The Viewpoint keeps the clamped values (`describe()` tells the
browser what it gets). `preset` and `t` exclude each other; a message with neither means t = 0.5.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from calibration.camera import CameraModel, RigCalibration

YAW_MARGIN_DEG = 15.0  # orbit beyond the source arc, each side
PITCH_LIMIT_DEG = 20.0
ZOOM_RANGE = (0.5, 3.0)
# Accepted input ranges (beyond them a message is refused rather than clamped).
YAW_ACCEPT_DEG = 180.0
PITCH_ACCEPT_DEG = 90.0
ZOOM_ACCEPT = (0.05, 20.0)
MAX_SUBJECT_BASELINES = 100.0  # a closest approach farther than this counts as parallel axes
MAX_NAME_LENGTH = 128
DEFAULT_SOURCES = ("left", "right")
MESSAGE_KEYS = ("type", "t", "preset", "yaw", "pitch", "zoom")


# -- quaternions (w, x, y, z), unit norm -----------------------------------------------------------
def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method; w >= 0)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 0.0))
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 0.0))
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions along the shorter arc; unit norm."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(np.dot(q0, q1))
    if dot < 0:  # q and -q are the same rotation: take the short way
        q1, dot = -q1, -dot
    if dot > 0.9999995:  # nearly the same rotation: linear interpolation is exact to rounding
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(min(dot, 1.0))
    s = math.sin(theta)
    q = (math.sin((1 - t) * theta) / s) * q0 + (math.sin(t * theta) / s) * q1
    return q / np.linalg.norm(q)


def axis_angle(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation matrix about a unit axis (right-hand rule)."""
    x, y, z = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    C = 1 - c
    return np.array([
        [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
        [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
        [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
    ])


# -- the geometry of a source pair ----------------------------------------------------------------
def optical_axis(camera: CameraModel) -> np.ndarray:
    """The camera's viewing direction (its +z axis) in world coordinates, unit length."""
    return camera.R[2].copy()


@dataclass(frozen=True)
class SourceArc:
    """What the arc and the orbit need of two source cameras: the subject point, whether the arc
    is a circle about it (else linear), the orbit axis and the angle the sources span about it."""

    subject: tuple[float, float, float]
    circular: bool
    axis: tuple[float, float, float]  # unit; yaw turns about it, positive from left towards right
    reference: tuple[float, float, float]  # the left source's direction from P on the orbit plane (azimuth 0)
    span_deg: float = 0.0  # azimuth of the right source

    @property
    def point(self) -> np.ndarray:
        return np.array(self.subject)

    def azimuth_deg(self, center: np.ndarray) -> float:
        """Signed angle about the orbit axis of a camera centre seen from P, from the left source's."""
        n = np.array(self.axis)
        ref = np.array(self.reference)
        v = np.asarray(center, dtype=np.float64) - self.point
        v = v - np.dot(v, n) * n
        if np.linalg.norm(v) < 1e-12 or not np.any(ref):
            return 0.0
        return math.degrees(math.atan2(float(np.dot(np.cross(ref, v), n)), float(np.dot(ref, v))))


def _closest_approach(c0, d0, c1, d1) -> Optional[tuple[np.ndarray, float, float]]:
    """Midpoint of the closest approach of two lines c + s d, with s and u along each; None when
    parallel."""
    w = c0 - c1
    a, b, c = np.dot(d0, d0), np.dot(d0, d1), np.dot(d1, d1)
    d, e = np.dot(d0, w), np.dot(d1, w)
    den = a * c - b * b
    if den < 1e-10 * a * c:
        return None
    s = (b * e - c * d) / den
    u = (a * e - b * d) / den
    return 0.5 * ((c0 + s * d0) + (c1 + u * d1)), float(s), float(u)


def subject_point(left: CameraModel, right: CameraModel, distance: Optional[float] = None) -> tuple[np.ndarray, bool]:
    """(P, found): the midpoint of the closest approach of the two optical axes when it is in front
    of both cameras and within MAX_SUBJECT_BASELINES baselines (found = True); otherwise the point
    `distance` metres (default: the baseline) along the mean optical axis from the middle of the
    baseline (found = False)."""
    c0, c1 = left.center, right.center
    d0, d1 = optical_axis(left), optical_axis(right)
    baseline = float(np.linalg.norm(c1 - c0))
    hit = _closest_approach(c0, d0, c1, d1)
    if hit is not None and baseline > 0:
        p, s, u = hit
        if 0 < s <= MAX_SUBJECT_BASELINES * baseline and 0 < u <= MAX_SUBJECT_BASELINES * baseline:
            return p, True
    mean = d0 + d1
    mean = mean / np.linalg.norm(mean) if np.linalg.norm(mean) > 1e-9 else d0
    dist = float(distance) if distance is not None else (baseline if baseline > 0 else 1.0)
    return 0.5 * (c0 + c1) + dist * mean, False


def rotation_axis_angle(R: np.ndarray) -> tuple[np.ndarray, float]:
    """(unit axis, angle in [0, pi]) of a rotation matrix; the axis is arbitrary for angle 0."""
    q = quat_from_matrix(R)  # w >= 0: angle in [0, pi]
    s = float(np.linalg.norm(q[1:]))
    if s < 1e-12:
        return np.array([0.0, 0.0, 1.0]), 0.0
    return q[1:] / s, 2.0 * math.atan2(s, q[0])


def source_arc(left: CameraModel, right: CameraModel, distance: Optional[float] = None) -> SourceArc:
    """The subject point and the orbit axis of two sources. The axis is that of the rotation taking
    the left camera's orientation to the right one's (what the slerp turns about), so that moving
    along the arc and yawing turn about the same axis; for sources with (nearly) the same
    orientation, their mean up direction."""
    p, found = subject_point(left, right, distance)
    axis, angle = rotation_axis_angle(right.R.T @ left.R)
    if angle < 1e-6:
        axis = -(left.R[1] + right.R[1])  # camera y points down in the image
        axis = axis / np.linalg.norm(axis) if np.linalg.norm(axis) > 1e-9 else -left.R[1]
    a = left.center - p
    ref = a - np.dot(a, axis) * axis
    ref = ref / np.linalg.norm(ref) if np.linalg.norm(ref) > 1e-12 else np.zeros(3)
    arc = SourceArc(_floats(p), bool(found), _floats(axis), _floats(ref))
    return SourceArc(arc.subject, arc.circular, arc.axis, arc.reference, arc.azimuth_deg(right.center))


def _floats(v) -> tuple[float, float, float]:
    return tuple(float(x) for x in v)


# -- cameras --------------------------------------------------------------------------------------
def _pinhole(camera: CameraModel, size: tuple[int, int], name: Optional[str] = None) -> CameraModel:
    c = camera.scaled(int(size[0]), int(size[1])) if (camera.width, camera.height) != tuple(size) else camera
    return CameraModel(name or camera.name, c.width, c.height, c.K.copy(), np.zeros(5), camera.R.copy(), camera.t.copy())


def _size(camera: CameraModel, size) -> tuple[int, int]:
    if size is None:
        return camera.width, camera.height
    w, h = int(size[0]), int(size[1])
    if w <= 0 or h <= 0:
        raise ValueError(f"size must be positive, got {w}x{h}")
    return w, h


def arc_camera(left: CameraModel, right: CameraModel, t: float, size: Optional[tuple[int, int]] = None,
               name: str = "virtual", distance: Optional[float] = None) -> CameraModel:
    """The virtual pinhole camera at t in [0, 1] on the arc from `left` (t = 0: its pinhole) to
    `right` (t = 1), at `size` (W, H; default the left camera's size). See the module docstring."""
    t = float(t)
    if not (math.isfinite(t) and 0.0 <= t <= 1.0):
        raise ValueError(f"t must be between 0 and 1, got {t!r}")
    size = _size(left, size)
    K = (1 - t) * _pinhole(left, size).K + t * _pinhole(right, size).K
    K[2] = (0.0, 0.0, 1.0)
    if t == 0.0 or t == 1.0:
        src = left if t == 0.0 else right
        return CameraModel(name, size[0], size[1], K, np.zeros(5), src.R.copy(), src.t.copy())
    R = matrix_from_quat(slerp(quat_from_matrix(left.R), quat_from_matrix(right.R), t))
    p, found = subject_point(left, right, distance)
    if found:
        # Around P: the centre sits behind P along the slerped viewing direction, at the distance
        # interpolated between the sources' (along their axes); what the sources' axes miss P by
        # (half their closest approach) is interpolated linearly, so both ends are exact.
        dl, dr = optical_axis(left), optical_axis(right)
        rl, rr = float(np.dot(p - left.center, dl)), float(np.dot(p - right.center, dr))
        el, er = left.center - (p - rl * dl), right.center - (p - rr * dr)
        center = p - ((1 - t) * rl + t * rr) * R[2] + (1 - t) * el + t * er
    else:
        center = (1 - t) * left.center + t * right.center
    return CameraModel(name, size[0], size[1], K, np.zeros(5), R, -R @ center)


def orbit_camera(camera: CameraModel, arc: SourceArc, yaw_deg: float = 0.0, pitch_deg: float = 0.0,
                 zoom: float = 1.0) -> CameraModel:
    """`camera` turned rigidly about the subject point: by `yaw_deg` about the orbit axis, then by
    `pitch_deg` about its own horizontal axis (positive: up, looking down), focal lengths times
    `zoom`. No clamping here (parse_viewpoint clamps)."""
    R, center = camera.R, camera.center
    p = arc.point
    if yaw_deg:
        rot = axis_angle(np.array(arc.axis), math.radians(yaw_deg))
        center = p + rot @ (center - p)
        R = R @ rot.T
    if pitch_deg:
        # About the camera's x axis, by the sign that moves the centre towards the camera's up (-y).
        rot = axis_angle(R[0], -math.radians(pitch_deg))
        center = p + rot @ (center - p)
        R = R @ rot.T
    K = camera.K.copy()
    if zoom != 1.0:
        K[0, 0] *= zoom
        K[0, 1] *= zoom
        K[1, 1] *= zoom
    return CameraModel(camera.name, camera.width, camera.height, K, np.zeros(5), R, -R @ center)


# -- presets and messages -------------------------------------------------------------------------
def _sources(rig: RigCalibration, sources) -> tuple[CameraModel, CameraModel]:
    left, right = sources
    missing = [n for n in (left, right) if n not in rig]
    if missing:
        raise ValueError(f"the rig has no source camera {', '.join(repr(m) for m in missing)} (cameras: {', '.join(rig.names)})")
    return rig[left], rig[right]


def presets(rig: RigCalibration, sources: tuple[str, str] = DEFAULT_SOURCES) -> list[dict]:
    """Every calibrated camera of the rig, in calibration order: [{"name", "kind": "source" |
    "supervision", "t"}, ...] (what rig.live.api.Engine.presets returns). `t`: where the camera
    stands along the arc between the sources (0 and 1 for them; for another camera the arc's point
    nearest its pinhole, to 0.005), what a viewer's slider shows once the camera is chosen; None
    without both sources."""
    ends = _sources(rig, sources) if all(n in rig for n in sources) else None
    grid = np.linspace(0.0, 1.0, 201)
    centres = np.array([arc_camera(*ends, t).center for t in grid]) if ends else None
    out = []
    for c in rig.cameras:
        if c.name in sources:
            t = None if ends is None else float(sources.index(c.name))
        else:
            t = None if ends is None else round(float(grid[np.argmin(np.linalg.norm(centres - c.center, axis=1))]), 3)
        out.append({"name": c.name, "kind": "source" if c.name in sources else "supervision", "t": t})
    return out


@dataclass(frozen=True)
class Viewpoint:
    """Where a viewer looks from: a point on the source arc (`t`) or a calibrated camera
    (`preset`), orbited by `yaw`/`pitch` degrees about the subject and zoomed (already clamped)."""

    t: Optional[float] = 0.5
    preset: Optional[str] = None
    yaw: float = 0.0
    pitch: float = 0.0
    zoom: float = 1.0

    def camera(self, rig: RigCalibration, size: Optional[tuple[int, int]] = None,
               sources: tuple[str, str] = DEFAULT_SOURCES) -> CameraModel:
        """The pinhole camera to render at `size` (W, H; default: the left source's size, or the
        preset camera's)."""
        left, right = _sources(rig, sources)
        if self.preset is not None:
            if self.preset not in rig:
                raise ValueError(f"unknown preset {self.preset!r} (cameras: {', '.join(rig.names)})")
            cam = rig[self.preset]
            base = _pinhole(cam, _size(cam, size))
        else:
            base = arc_camera(left, right, self._t, size, name=f"t={self._t:g}")
        if self.yaw == 0.0 and self.pitch == 0.0 and self.zoom == 1.0:
            return base
        return orbit_camera(base, source_arc(left, right), self.yaw, self.pitch, self.zoom)

    def label(self) -> str:
        """Short text for people: "t=0.5", "sup2", "t=0.5 yaw=10 pitch=-5 zoom=1.5"."""
        base = self.preset if self.preset is not None else f"t={self._t:g}"
        extra = [f"{k}={v:g}" for k, v, rest in (("yaw", self.yaw, 0.0), ("pitch", self.pitch, 0.0), ("zoom", self.zoom, 1.0)) if v != rest]
        return " ".join([base] + extra)

    @property
    def _t(self) -> float:
        return 0.5 if self.t is None else self.t

    def describe(self) -> dict:
        """JSON-able: the effective (clamped) fields; {"type": "viewpoint", **describe()} parses
        back to the same Viewpoint."""
        out: dict[str, Any] = {"preset": self.preset} if self.preset is not None else {"t": self._t}
        out.update(yaw=self.yaw, pitch=self.pitch, zoom=self.zoom)
        return out

    def to_message(self) -> dict:
        return {"type": "viewpoint", **self.describe()}


def _number(message: dict, key: str, low: float, high: float) -> Optional[float]:
    if key not in message:
        return None
    v = message[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"viewpoint {key} must be a number, got {type(v).__name__}")
    try:
        f = float(v)
    except OverflowError:  # an int beyond float range
        raise ValueError(f"viewpoint {key} must be between {low:g} and {high:g}") from None
    if not math.isfinite(f):
        raise ValueError(f"viewpoint {key} must be a finite number")
    if not low <= f <= high:
        raise ValueError(f"viewpoint {key} must be between {low:g} and {high:g}, got {f:.6g}")
    return f


def parse_viewpoint(message: Any, rig: RigCalibration, sources: tuple[str, str] = DEFAULT_SOURCES) -> Viewpoint:
    """A browser's viewpoint message, checked and clamped (see the module docstring). Raises
    ValueError with a one-line reason for anything else: not an object, another type, unknown keys,
    both or a wrong `t`/`preset`, a field that is not a finite number in its accepted range."""
    if not isinstance(message, dict):
        raise ValueError(f"a viewpoint message must be a JSON object, got {type(message).__name__}")
    if message.get("type") != "viewpoint":
        raise ValueError("a viewpoint message needs \"type\": \"viewpoint\"")
    unknown = [k for k in message if k not in MESSAGE_KEYS]
    if unknown:
        shown = ", ".join(repr(k)[:40] for k in unknown[:3])
        raise ValueError(f"unknown viewpoint field(s) {shown} (allowed: {', '.join(MESSAGE_KEYS)})")
    t = _number(message, "t", 0.0, 1.0)
    preset = message.get("preset")
    if "preset" in message:
        if not isinstance(preset, str):
            raise ValueError(f"viewpoint preset must be a camera name (a string), got {type(preset).__name__}")
        if t is not None:
            raise ValueError("a viewpoint has either t or preset, not both")
        if len(preset) > MAX_NAME_LENGTH or preset not in rig:
            raise ValueError(f"unknown preset {preset[:40]!r} (cameras: {', '.join(rig.names)})")
    yaw = _number(message, "yaw", -YAW_ACCEPT_DEG, YAW_ACCEPT_DEG) or 0.0
    pitch = _number(message, "pitch", -PITCH_ACCEPT_DEG, PITCH_ACCEPT_DEG) or 0.0
    zoom = _number(message, "zoom", *ZOOM_ACCEPT)
    zoom = 1.0 if zoom is None else min(max(zoom, ZOOM_RANGE[0]), ZOOM_RANGE[1])
    pitch = min(max(pitch, -PITCH_LIMIT_DEG), PITCH_LIMIT_DEG)
    left, right = _sources(rig, sources)
    if yaw:
        arc = source_arc(left, right)
        center = rig[preset].center if preset is not None else arc_camera(left, right, 0.5 if t is None else t).center
        base = arc.azimuth_deg(center)
        low = min(0.0, arc.span_deg) - YAW_MARGIN_DEG - base
        high = max(0.0, arc.span_deg) + YAW_MARGIN_DEG - base
        # A preset already outside the bounds may stay where it is or turn towards the arc.
        yaw = min(max(yaw, min(low, 0.0)), max(high, 0.0))
    if preset is not None:
        return Viewpoint(t=None, preset=preset, yaw=float(yaw), pitch=float(pitch), zoom=float(zoom))
    return Viewpoint(t=0.5 if t is None else float(t), yaw=float(yaw), pitch=float(pitch), zoom=float(zoom))
