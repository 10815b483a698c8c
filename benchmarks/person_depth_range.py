"""How near the simulator places people to the source cameras, against the stereo backbone's planes.

The stereo backbone sweeps planes between `stereo_near` and `stereo_far` baselines (docs/model.md);
its soft-argmin cannot give a depth outside them. This measures, from the scene geometry alone (no
image is rendered), the nearest person point each source camera sees over the takes of many seeds:
every person primitive (capsules and ellipsoids, simulator.people) is sampled on its surface at
the take's scene times, projected into the left and right cameras of the take's exact rig
(simulator.variety), and the smallest depth along the optical axis of a point inside the image is
kept, in metres and in baselines (the distance between the two sources). The farthest depth the
sources see (the room's walls) is read from a small rendering of their depth at the take's first
instant (the room does not move), so the span of the scene can be set against the planes'.

    .venv/bin/python benchmarks/person_depth_range.py [--data-seeds 0-9] [--takes 20] [--seconds 4] [--fps 10] [--json]

Take i of data-set seed K is seeded K*1000 + i, as `rig sim dataset` does.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.config import BackboneConfig  # noqa: E402
from simulator.primitives import Capsule, Ellipsoid  # noqa: E402
from simulator.scene import Scene  # noqa: E402
from simulator.variety import draw_variety  # noqa: E402


def _unit_sphere(n: int) -> np.ndarray:
    """n points spread evenly on the unit sphere (Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = np.pi * (1 + 5**0.5) * k
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


SPHERE = _unit_sphere(256)


def surface_points(prim) -> np.ndarray:
    """Points on a person primitive's surface (a capsule as spheres swept along its axis)."""
    if isinstance(prim, Ellipsoid):
        return prim.center + (SPHERE * prim.radii) @ prim.axes.T
    if isinstance(prim, Capsule):
        s = np.linspace(0.0, 1.0, 9)[:, None, None]
        axis = prim.a + s * (prim.b - prim.a)
        return (axis + prim.radius * SPHERE[None]).reshape(-1, 3)
    return np.zeros((0, 3))


def nearest_seen(points: np.ndarray, cam) -> float:
    """The smallest optical-axis depth of the points inside the camera's pinhole image (inf: none)."""
    pc = points @ cam.R.T + cam.t
    z = pc[:, 2]
    front = z > 1e-3
    if not front.any():
        return float("inf")
    pc, z = pc[front], z[front]
    u = cam.K[0, 0] * pc[:, 0] / z + cam.K[0, 2]
    v = cam.K[1, 1] * pc[:, 1] / z + cam.K[1, 2]
    inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return float(z[inside].min()) if inside.any() else float("inf")


def take_figures(seed: int, seconds: float, fps: float) -> dict:
    variety = draw_variety(seed)
    scene = Scene.from_options(variety.scene)
    rig = variety.placement.cameras(640, 360, 6, variety.seed, distortion=False)
    left, right = rig["left"], rig["right"]
    baseline = float(np.linalg.norm(left.center - right.center))
    nearest = float("inf")
    for s in range(max(1, int(round(seconds * fps)))):
        t = variety.start_s + s / fps
        pts = [surface_points(p) for p in scene.primitives(t) if getattr(p, "person", False)]
        if not pts:
            continue
        pts = np.concatenate(pts)
        nearest = min(nearest, nearest_seen(pts, left), nearest_seen(pts, right))
    from simulator.render import render

    small = variety.placement.cameras(96, 54, 6, variety.seed, distortion=False)
    farthest = max(float(render(scene, small[c], variety.start_s).depth.max()) for c in ("left", "right"))
    return {"seed": seed, "baseline_m": baseline, "nearest_m": nearest, "nearest_baselines": nearest / baseline,
            "farthest_m": farthest, "farthest_baselines": farthest / baseline, "radius_m": variety.placement.radius}


def _seeds(spec: str) -> list[int]:
    if "-" in spec:
        a, b = spec.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in spec.split(",")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-seeds", default="0-9", help="data-set seeds (a range a-b or a list), default 0-9")
    ap.add_argument("--takes", type=int, default=20, help="takes per data-set seed (default 20)")
    ap.add_argument("--seconds", type=float, default=4.0, help="scene time per take (default 4)")
    ap.add_argument("--fps", type=float, default=10.0, help="instants per second (default 10)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    rows = [take_figures(k * 1000 + i, args.seconds, args.fps) for k in _seeds(args.data_seeds) for i in range(args.takes)]
    seen = [r for r in rows if np.isfinite(r["nearest_m"])]
    bb = BackboneConfig()
    near_b = np.array([r["nearest_baselines"] for r in seen])
    near_m = np.array([r["nearest_m"] for r in seen])
    base = np.array([r["baseline_m"] for r in seen])
    worst = min(seen, key=lambda r: r["nearest_baselines"])
    far_b = np.array([r["farthest_baselines"] for r in rows])
    summary = {
        "takes": len(rows), "takes_with_a_person_in_view": len(seen),
        "planes_baselines": [bb.stereo_near, bb.stereo_far],
        "baseline_m": {"min": round(float(base.min()), 3), "max": round(float(base.max()), 3)},
        "nearest_person_m": {"min": round(float(near_m.min()), 3), "p5": round(float(np.percentile(near_m, 5)), 3),
                             "median": round(float(np.median(near_m)), 3)},
        "nearest_person_baselines": {"min": round(float(near_b.min()), 3), "p5": round(float(np.percentile(near_b, 5)), 3),
                                     "median": round(float(np.median(near_b)), 3)},
        "takes_nearer_than_near_plane": int((near_b < bb.stereo_near).sum()),
        "farthest_seen_m": round(max(r["farthest_m"] for r in rows), 3),
        "farthest_seen_baselines": {"max": round(float(far_b.max()), 3), "median": round(float(np.median(far_b)), 3)},
        "worst_take": {k: (round(v, 3) if isinstance(v, float) else v) for k, v in worst.items()},
    }
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        print(f"{summary['takes']} takes ({args.seconds:g} s at {args.fps:g} per second), a person in view in {len(seen)}")
        print(f"baseline {summary['baseline_m']['min']:.2f} to {summary['baseline_m']['max']:.2f} m; "
              f"planes {bb.stereo_near:g} to {bb.stereo_far:g} baselines")
        n, b = summary["nearest_person_m"], summary["nearest_person_baselines"]
        print(f"nearest person point a source sees, per take: min {n['min']:.2f} m ({b['min']:.3f} baselines), "
              f"5th percentile {n['p5']:.2f} m ({b['p5']:.3f}), median {n['median']:.2f} m ({b['median']:.3f})")
        print(f"takes with a person nearer than the nearest plane: {summary['takes_nearer_than_near_plane']} of {len(seen)}")
        f = summary["farthest_seen_baselines"]
        print(f"farthest depth a source sees (the room): {summary['farthest_seen_m']:.2f} m; "
              f"max {f['max']:.3f} baselines, median {f['median']:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
