"""People: articulated bodies of capsules and ellipsoids, moved by procedural motions of time.

A body is described in its own frame (x to its side, y up, z forward) by segment directions, each
given as two angles: `flex` (swing forward, radians) and `abd` (swing out to the side). A motion is a
function of time returning the root position on the floor, heading, and those angles; forward
kinematics then places the primitives. Everything is a pure function of (person, time).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from simulator.primitives import Capsule, Ellipsoid, Primitive, cross3

MOTIONS = ("walk", "wave", "dance", "jump", "still")


@dataclass(frozen=True)
class PersonSpec:
    """Body size, look and motion of one person."""

    name: str
    height: float  # metres
    build: float  # girth scale
    motion: str
    home: tuple[float, float]  # (x, z) on the floor where the motion is centred
    heading: float  # radians; 0 faces +z (the rig)
    phase: float  # seconds of offset into the motion
    short_sleeves: bool
    materials: dict  # part -> material name: skin, hair, shirt, pants, shoes


@dataclass
class Pose:
    root: np.ndarray  # pelvis centre, world
    yaw: float
    lean: float  # forward tilt of the upper body
    sway: float  # sideways tilt of the upper body
    head_yaw: float
    limbs: dict  # segment name -> (flex, abd)


def _limb_dir(flex: float, abd: float, side: float) -> np.ndarray:
    """Unit direction in the body frame of a segment hanging down, swung forward by `flex` and out to
    `side` (+1 left, -1 right) by `abd`."""
    ca = math.cos(abd)
    return np.array([side * math.sin(abd), -ca * math.cos(flex), ca * math.sin(flex)])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _frame_along(axis: np.ndarray, hint: np.ndarray) -> np.ndarray:
    """Rotation whose y column is `axis` and whose z column is as close to `hint` as possible."""
    y = axis / np.linalg.norm(axis)
    z = hint - y * float(hint @ y)
    if np.linalg.norm(z) < 1e-6:  # segment along the hint: any perpendicular will do
        z = cross3(y, [1.0, 0.0, 0.0] if abs(y[0]) < 0.9 else [0.0, 1.0, 0.0])
    z /= np.linalg.norm(z)
    x = cross3(y, z)
    return np.stack([x, y, z], axis=1)


# ---- motions ------------------------------------------------------------------------------------

def _still_limbs(t: float) -> dict:
    b = 0.03 * math.sin(2 * math.pi * 0.25 * t)
    return {
        "thigh_l": (0.0, 0.05), "shin_l": (0.0, 0.05), "thigh_r": (0.0, 0.05), "shin_r": (0.0, 0.05),
        "upper_arm_l": (0.05 + b, 0.12), "forearm_l": (0.25 + b, 0.1),
        "upper_arm_r": (0.05 - b, 0.12), "forearm_r": (0.25 - b, 0.1),
    }


def motion_pose(p: PersonSpec, t: float) -> tuple[tuple[float, float], float, float, float, float, float, dict]:
    """(x, z), yaw, lift, lean, sway, head_yaw, limb angles at time t for the person's motion."""
    tt = t + p.phase
    x, z = p.home
    yaw = p.heading
    lift = lean = sway = head = 0.0
    if p.motion == "walk":
        radius = 1.45
        speed = 0.85  # m/s
        ang = speed / radius * tt
        x, z = p.home[0] + radius * math.cos(ang), p.home[1] + radius * math.sin(ang)
        yaw = math.atan2(-math.sin(ang), math.cos(ang))  # forward = tangent (counter-clockwise seen from above)
        g = 2 * math.pi * 0.9 * tt  # gait cycle
        s = math.sin(g)
        limbs = {
            "thigh_l": (0.42 * s, 0.03), "shin_l": (0.42 * s - 0.15 - 0.55 * max(0.0, math.sin(g - 1.2)), 0.03),
            "thigh_r": (-0.42 * s, 0.03), "shin_r": (-0.42 * s - 0.15 - 0.55 * max(0.0, math.sin(g + math.pi - 1.2)), 0.03),
            "upper_arm_l": (-0.35 * s, 0.08), "forearm_l": (-0.35 * s + 0.35 + 0.15 * max(0.0, -s), 0.06),
            "upper_arm_r": (0.35 * s, 0.08), "forearm_r": (0.35 * s + 0.35 + 0.15 * max(0.0, s), 0.06),
        }
        lift = 0.0125 * (1.0 + math.cos(2 * g))  # the body rises over the supporting leg
        lean = 0.05
        sway = 0.03 * s
        head = 0.25 * math.sin(2 * math.pi * 0.13 * tt)
    elif p.motion == "wave":
        w = math.sin(2 * math.pi * 1.6 * tt)
        limbs = _still_limbs(tt)
        limbs["upper_arm_r"] = (0.3, 2.25 + 0.05 * w)
        limbs["forearm_r"] = (0.2, 2.75 + 0.38 * w)
        sway = 0.03 * math.sin(2 * math.pi * 0.3 * tt)
        yaw = p.heading + 0.2 * math.sin(2 * math.pi * 0.1 * tt)
        head = 0.15 * math.sin(2 * math.pi * 0.2 * tt)
    elif p.motion == "dance":
        b = 2 * math.pi * 1.0 * tt
        k = 0.5 * (1 + math.sin(2 * b))
        limbs = {
            "thigh_l": (0.25 * k, 0.12), "shin_l": (0.25 * k - 0.55 * k, 0.12),
            "thigh_r": (0.25 * k, 0.12), "shin_r": (0.25 * k - 0.55 * k, 0.12),
            "upper_arm_l": (0.6 + 0.5 * math.sin(b), 0.9 + 0.7 * math.sin(b)),
            "forearm_l": (1.3 + 0.6 * math.sin(b + 0.8), 1.0 + 0.8 * math.sin(b)),
            "upper_arm_r": (0.6 - 0.5 * math.sin(b), 0.9 - 0.7 * math.sin(b)),
            "forearm_r": (1.3 - 0.6 * math.sin(b + 0.8), 1.0 - 0.8 * math.sin(b)),
        }
        sway = 0.12 * math.sin(b)
        lean = 0.08 * k
        yaw = p.heading + 0.9 * math.sin(2 * math.pi * 0.12 * tt)
        head = -0.3 * math.sin(b)
    elif p.motion == "jump":
        period = 1.4
        ph = (tt / period) % 1.0
        limbs = _still_limbs(tt)
        if ph < 0.35:  # crouch then push off
            c = math.sin(math.pi * ph / 0.35)
            bend, arms = 0.9 * c, -0.5 * c
        elif ph < 0.7:  # flight
            f = (ph - 0.35) / 0.35
            lift = 4 * 0.28 * f * (1 - f)
            bend, arms = 0.15, 2.6 * math.sin(math.pi * f)
        else:  # landing
            c = math.sin(math.pi * (ph - 0.7) / 0.3)
            bend, arms = 0.6 * c, 0.3 * c
        for s in ("l", "r"):
            limbs[f"thigh_{s}"] = (bend, 0.08)
            limbs[f"shin_{s}"] = (-bend, 0.08)
            limbs[f"upper_arm_{s}"] = (arms, 0.25)
            limbs[f"forearm_{s}"] = (arms + 0.3, 0.2)
        lean = 0.35 * bend
    elif p.motion == "still":
        limbs = _still_limbs(tt)
        head = 0.3 * math.sin(2 * math.pi * 0.07 * tt)
    else:  # validated by Scene; kept as a guard for direct callers
        raise ValueError(f"unknown motion {p.motion!r} (allowed: {', '.join(MOTIONS)})")
    return (x, z), yaw, lift, lean, sway, head, limbs


# ---- body ----------------------------------------------------------------------------------------

def person_primitives(p: PersonSpec, t: float) -> list[Primitive]:
    """The person's primitives at time t (world frame)."""
    H = p.height
    g = p.build
    (x, z), yaw, lift, lean, sway, head_yaw, limbs = motion_pose(p, t)
    Rb = _rot_y(yaw)  # body (legs) frame
    Ru = Rb @ _rot_x(lean) @ _rot_z(-sway)  # upper body frame: lean forward tilts +y toward +z

    thigh, shin = 0.245 * H, 0.245 * H
    ankle_h = 0.045 * H
    hip_w = 0.052 * H * g
    hip_drop = 0.02 * H  # hip joints sit this far below the pelvis centre

    # Place the pelvis so that the lower ankle stands on the floor (plus the jump's lift).
    drops = []
    for s in ("l", "r"):
        d1 = _limb_dir(*limbs[f"thigh_{s}"], 1.0)
        d2 = _limb_dir(*limbs[f"shin_{s}"], 1.0)
        drops.append(-(thigh * d1[1] + shin * d2[1]))
    pelvis = np.array([x, max(drops) + hip_drop + ankle_h + lift, z])

    m = p.materials
    prims: list[Primitive] = []
    name = p.name

    def ell(part, center, axes, radii, mat):
        prims.append(Ellipsoid(f"{name}.{part}", m[mat], True, np.asarray(center, float), axes, np.asarray(radii, float)))

    def cap(part, a, b, r, mat, ref):
        prims.append(Capsule(f"{name}.{part}", m[mat], True, a, b, float(r), ref))

    fwd = Rb[:, 2]
    # torso
    chest_c = pelvis + Ru @ np.array([0.0, 0.2 * H, 0.0])
    ell("pelvis", pelvis + Ru @ np.array([0.0, 0.015 * H, 0.0]), Ru, [0.088 * H * g, 0.062 * H, 0.058 * H * g], "pants")
    ell("belly", pelvis + Ru @ np.array([0.0, 0.09 * H, 0.004 * H]), Ru, [0.084 * H * g, 0.08 * H, 0.056 * H * g], "shirt")
    ell("chest", chest_c, Ru, [0.096 * H * g, 0.11 * H, 0.06 * H * g], "shirt")
    neck_base = pelvis + Ru @ np.array([0.0, 0.3 * H, 0.0])
    Rh = Ru @ _rot_y(head_yaw)
    head_c = neck_base + Ru @ np.array([0.0, 0.09 * H, 0.008 * H])
    cap("neck", neck_base - Ru[:, 1] * 0.02 * H, head_c - Ru[:, 1] * 0.04 * H, 0.029 * H * g, "skin", fwd)
    ell("head", head_c, Rh, [0.046 * H, 0.064 * H, 0.056 * H], "skin")
    ell("hair", head_c + Rh @ np.array([0.0, 0.012 * H, -0.01 * H]), Rh, [0.05 * H, 0.058 * H, 0.056 * H], "hair")
    # nose: a small feature that makes the head's orientation readable
    ell("nose", head_c + Rh @ np.array([0.0, -0.005 * H, 0.054 * H]), Rh, [0.008 * H, 0.014 * H, 0.01 * H], "skin")

    # arms
    for s, side in (("l", 1.0), ("r", -1.0)):
        shoulder = pelvis + Ru @ np.array([side * 0.112 * H * g, 0.275 * H, -0.005 * H])
        d_up = Ru @ _limb_dir(*limbs[f"upper_arm_{s}"], side)
        elbow = shoulder + 0.17 * H * d_up
        d_fo = Ru @ _limb_dir(*limbs[f"forearm_{s}"], side)
        wrist = elbow + 0.145 * H * d_fo
        cap(f"upper_arm_{s}", shoulder, elbow, 0.03 * H * g, "shirt", Ru[:, 2])
        cap(f"forearm_{s}", elbow, wrist, 0.024 * H * g, "skin" if p.short_sleeves else "shirt", Ru[:, 2])
        Q = _frame_along(d_fo, Ru[:, 2])
        ell(f"hand_{s}", wrist + 0.05 * H * d_fo, Q, [0.024 * H, 0.05 * H, 0.014 * H], "skin")

    # legs
    for s, side in (("l", 1.0), ("r", -1.0)):
        hip = pelvis + Rb @ np.array([side * hip_w, -hip_drop, 0.0])
        d1 = Rb @ _limb_dir(*limbs[f"thigh_{s}"], side)
        knee = hip + thigh * d1
        d2 = Rb @ _limb_dir(*limbs[f"shin_{s}"], side)
        ankle = knee + shin * d2
        cap(f"thigh_{s}", hip, knee, 0.05 * H * g, "pants", fwd)
        cap(f"shin_{s}", knee, ankle, 0.036 * H * g, "pants", fwd)
        foot_c = ankle + fwd * 0.045 * H + np.array([0.0, -0.022 * H, 0.0])
        ell(f"foot_{s}", foot_c, Rb, [0.03 * H, 0.024 * H, 0.068 * H], "shoes")
    return prims


def person_ground(p: PersonSpec, t: float) -> tuple[float, float]:
    """Floor position (x, z) of the person at time t (for contact shadows)."""
    (x, z), *_ = motion_pose(p, t)
    return x, z
