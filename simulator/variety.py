"""What makes one simulated training take differ from another, drawn from the take's seed.

A training set needs takes that differ in everything a model could otherwise memorise. Part of that
the scene already draws from its own seed (simulator.scene): clothes colours and patterns, skin
and hair, body height (1.6-1.9 m) and girth (0.9-1.12), each person's motion phase and heading,
the room's wall and floor textures, the props' sizes and places. This module draws the rest:

- the scene options: how many people (1-3), which motions (one for all, or mixed), a room with
  props or a bare one;
- the lighting: direction and strength of the key and fill lights, the ambient level;
- the rig: span, radius, height and aim of the camera arc, the field of view, and a small random
  perturbation of every camera's position and orientation (real rigs are never placed exactly);
- the scene time of the first frame.

Everything is a pure function of the seed, and recorded in the take (`TakeVariety.to_dict`), so
that a take's images can be rendered again. The geometry (people, props, cameras) is in the scene
options and the exact cameras, from which the sequence reader renders ground-truth depth; the
lighting changes only the images, so depth rendering does not need it.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from calibration.camera import CameraModel, RigCalibration
from simulator.errors import SimulatorError
from simulator.rig import arc_rig, camera_names

# The scene's own lighting (simulator.scene.Scene), the middle of the ranges drawn here.
KEY_LIGHT = ((0.35, 1.0, 0.55), 0.55)
FILL_LIGHT = ((-0.6, 0.45, 0.35), 0.22)
AMBIENT = 0.38


@dataclass(frozen=True)
class Lighting:
    """Lambertian lights of the scene: (unit direction towards the light, intensity), plus ambient."""

    lights: tuple[tuple[tuple[float, float, float], float], ...]
    ambient: float

    def apply(self, scene) -> None:
        """Light `scene` this way. Call before its first render: the renderer keeps each camera's
        drawing of the static room and props, lighting included, in the scene."""
        if scene.static_layers:
            raise SimulatorError("set a scene's lighting before its first render (its static layers are drawn already)")
        scene.lights = [(np.asarray(d, float), float(k)) for d, k in self.lights]
        scene.ambient = float(self.ambient)

    def to_dict(self) -> dict:
        return {"lights": [{"direction": list(d), "intensity": k} for d, k in self.lights], "ambient": self.ambient}

    @classmethod
    def from_dict(cls, d: dict) -> "Lighting":
        try:
            lights = tuple((tuple(float(v) for v in x["direction"]), float(x["intensity"])) for x in d["lights"])
            return cls(lights, float(d["ambient"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise SimulatorError(f"lighting: malformed ({exc})") from None


@dataclass(frozen=True)
class RigPlacement:
    """Where the arc of cameras stands (simulator.rig.arc_rig's parameters) and how far each camera
    is knocked off its nominal pose."""

    span_deg: float = 60.0
    radius: float = 3.6
    camera_height: float = 1.5
    target: tuple[float, float, float] = (0.0, 1.0, 0.0)
    hfov_deg: float = 62.0
    position_jitter_m: float = 0.0  # standard deviation per axis of each camera's centre
    rotation_jitter_deg: float = 0.0  # standard deviation of each camera's small random rotation

    def cameras(self, width: int, height: int, n_cameras: int, seed: int, distortion: bool = True) -> RigCalibration:
        """The exact cameras: the arc rig, then each camera moved and turned a little (drawn from
        (seed, camera index), so a camera's jitter does not depend on the image size)."""
        rig = arc_rig([(n, width, height) for n in camera_names(n_cameras)], span_deg=self.span_deg, radius=self.radius,
                      camera_height=self.camera_height, target=self.target, hfov_deg=self.hfov_deg,
                      distortion=distortion, seed=seed)
        cams = []
        for i, cam in enumerate(rig.cameras):
            rng = np.random.default_rng([int(seed), 11, i])
            centre = cam.center + rng.normal(0.0, self.position_jitter_m, 3)
            dR = _small_rotation(rng.normal(0.0, math.radians(self.rotation_jitter_deg), 3))
            R = dR @ cam.R  # a turn of the camera about its own centre (camera frame)
            cams.append(CameraModel(cam.name, cam.width, cam.height, cam.K, cam.dist, R, -R @ centre))
        meta = dict(rig.meta)
        meta["placement"] = asdict(self)
        return RigCalibration(cams, meta)


@dataclass(frozen=True)
class TakeVariety:
    """Everything drawn from a take's seed."""

    seed: int
    scene: dict  # scene options (simulator.options.SCENE_OPTIONS): seed, scene, people, motion
    lighting: Lighting
    placement: RigPlacement
    start_s: float  # scene time of the take's first frame

    def to_dict(self) -> dict:
        return {"seed": self.seed, "scene": dict(self.scene), "lighting": self.lighting.to_dict(),
                "placement": asdict(self.placement), "start_s": self.start_s}


def _small_rotation(w: np.ndarray) -> np.ndarray:
    """The rotation by the vector w (axis * angle, radians): Rodrigues' formula."""
    a = float(np.linalg.norm(w))
    if a < 1e-12:
        return np.eye(3)
    k = w / a
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(a) * K + (1.0 - math.cos(a)) * (K @ K)


def _direction(rng: np.random.Generator, base, spread_deg: float) -> tuple[float, float, float]:
    """A unit vector near `base`, kept above the horizon (lights shine from above)."""
    d = np.asarray(base, float) / np.linalg.norm(base)
    d = _small_rotation(rng.normal(0.0, math.radians(spread_deg), 3)) @ d
    d[1] = max(d[1], 0.2)
    d /= np.linalg.norm(d)
    return (float(d[0]), float(d[1]), float(d[2]))


def draw_variety(seed: int) -> TakeVariety:
    """The variety of the take with this seed (scene seed = take seed)."""
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or not 0 <= seed <= 2**31 - 1:
        raise SimulatorError(f"take seed must be an integer from 0 to {2**31 - 1}, got {seed!r}")
    seed = int(seed)
    # One stream per aspect: adding a new aspect later leaves the others' draws as they were.
    r_scene, r_light, r_rig, r_time = (np.random.default_rng([seed, 101, k]) for k in range(4))
    people = int(r_scene.integers(1, 4))
    motion = "mixed" if r_scene.random() < 0.5 else str(r_scene.choice(["walk", "wave", "dance", "jump", "still"], p=[0.3, 0.2, 0.25, 0.2, 0.05]))
    room = "studio" if r_scene.random() < 0.85 else "empty"
    scene = {"seed": seed, "scene": room, "people": people, "motion": motion}

    key = (_direction(r_light, KEY_LIGHT[0], 35.0), float(r_light.uniform(0.4, 0.75)))
    fill = (_direction(r_light, FILL_LIGHT[0], 35.0), float(r_light.uniform(0.1, 0.35)))
    lighting = Lighting((key, fill), float(r_light.uniform(0.25, 0.5)))

    placement = RigPlacement(
        span_deg=float(r_rig.uniform(54.0, 66.0)),
        radius=float(r_rig.uniform(3.3, 4.0)),
        camera_height=float(r_rig.uniform(1.3, 1.75)),
        target=(float(r_rig.uniform(-0.15, 0.15)), float(r_rig.uniform(0.9, 1.1)), float(r_rig.uniform(-0.15, 0.15))),
        hfov_deg=float(r_rig.uniform(58.0, 66.0)),
        position_jitter_m=0.03,
        rotation_jitter_deg=0.8,
    )
    start_s = float(r_time.uniform(0.0, 20.0))
    return TakeVariety(seed, scene, lighting, placement, start_s)
