"""How far depth init's depth moves when stage 1's points move by a hair: the amplification behind
`rig model check`'s torch-against-ONNX Runtime differences.

    .venv/bin/python benchmarks/depth_init_sensitivity.py [--checkpoint C] [--seed 0] [--noise 5e-6] [--json]

Runs stage 1 of the checkpoint (default: the shipped preview model) on the synthetic example
inputs, then depth init in float64 on its points and on the points plus Gaussian noise of --noise
metres, as trained and with occlusion_gain 0; reports the largest change of the raw (unfilled)
depth over well-covered pixels (coverage > 0.5), and at the worst of them the points that reach it:
how many, their depths, and how much the noise moved their kernel weights. In float64 the change is
the function's own sensitivity, not rounding.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from inference.model.checkpoint import load_checkpoint  # noqa: E402
from inference.model.depth_init import splat_depth  # noqa: E402
from inference.model.geometry import project, relative_pose, resize_intrinsics, transform_points  # noqa: E402
from inference.runtime.synthetic import example_inputs  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("left_image", "right_image", "left_K", "right_K", "left_pose", "right_pose")


def measure(checkpoint: Path, seed: int, noise: float) -> dict:
    model = load_checkpoint(checkpoint).eval()
    sizes = model.cfg.sizes
    arrays = example_inputs(sizes, False, seed=seed).arrays
    t = {n: torch.from_numpy(a) for n, a in arrays.items()}
    with torch.no_grad():
        _, _, st = model.run_stage1(*(t[n] for n in SOURCES))
    to_target = relative_pose(t["target_pose"], t["left_pose"]).double()
    K = resize_intrinsics(t["target_K"], sizes.output, sizes.fine).double()
    pts = torch.cat([st["stage1_points_left"].flatten(2), st["stage1_points_right"].flatten(2)], 2).double()
    op = torch.cat([st["stage1_opacity_left"].flatten(2), st["stage1_opacity_right"].flatten(2)], 2).double()
    moved = pts + noise * torch.randn(pts.shape, generator=torch.Generator().manual_seed(seed + 1), dtype=torch.float64)
    cfg = model.depth_init.cfg
    out = {"checkpoint": str(checkpoint), "seed": seed, "noise_m": noise, "radius": cfg.radius, "occlusion_gain": cfg.occlusion_gain, "variants": {}}
    w = sizes.fine[0]
    for name, c in (("as trained", cfg), ("occlusion_gain 0", dataclasses.replace(cfg, occlusion_gain=0.0))):
        with torch.no_grad():
            r0, c0 = splat_depth(pts, op, to_target, K, sizes.fine, c)
            r1, _ = splat_depth(moved, op, to_target, K, sizes.fine, c)
        change = ((r0 - r1).abs() * (c0 > 0.5)).flatten()
        i = int(change.argmax())
        out["variants"][name] = {"max_raw_change_m": float(change[i]), "pixel": list(divmod(i, w)), "coverage": float(c0.flatten()[i]),
                                 "raw_m": [float(r0.flatten()[i]), float(r1.flatten()[i])]}
    y, x = out["variants"]["as trained"]["pixel"]
    rho2 = (cfg.radius + 0.5) ** 2
    uv0, z0 = project(transform_points(to_target, pts), K)
    uv1, _ = project(transform_points(to_target, moved), K)

    def kernel(uv):
        d2 = (uv[0, 0] - x) ** 2 + (uv[0, 1] - y) ** 2
        return (1 - d2 / rho2).clamp(min=0) ** 2

    k0, k1 = kernel(uv0), kernel(uv1)
    reach = torch.nonzero((k0 > 0) | (k1 > 0)).flatten()
    shift = (uv1 - uv0)[0].norm(dim=0)
    out["worst_pixel_points"] = [{"depth_m": round(float(z0[0, 0, j]), 3), "weight": round(float(k0[j] * op[0, 0, j]), 4),
                                  "weight_change_pct": round(100 * float((k1[j] - k0[j]) / k0[j].clamp(min=1e-12)), 3),
                                  "moved_px": float(shift[j])} for j in reach.tolist()]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=Path, default=REPO / "models" / "splat-sap-preview.pt")
    ap.add_argument("--seed", type=int, default=0, help="the synthetic inputs' draw (rig model check uses 0)")
    ap.add_argument("--noise", type=float, default=5e-6, help="metres of Gaussian noise on every point (default 5e-6)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    r = measure(args.checkpoint, args.seed, args.noise)
    if args.json:
        print(json.dumps(r))
        return 0
    print(f"{r['checkpoint']}: radius {r['radius']}, occlusion_gain {r['occlusion_gain']}; {r['noise_m']:g} m of noise on every point (float64)")
    for name, v in r["variants"].items():
        print(f"  {name:<17} raw depth moves up to {v['max_raw_change_m'] * 1000:.2f} mm on covered pixels "
              f"(pixel {tuple(v['pixel'])}, coverage {v['coverage']:.2f}, {v['raw_m'][0]:.4f} -> {v['raw_m'][1]:.4f} m)")
    print(f"  the points reaching the worst pixel ({len(r['worst_pixel_points'])}):")
    for p in sorted(r["worst_pixel_points"], key=lambda p: -p["weight"]):
        print(f"    depth {p['depth_m']:6.3f} m  weight {p['weight']:.4f}  moved {p['moved_px']:.2e} px  weight {p['weight_change_pct']:+.3f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
