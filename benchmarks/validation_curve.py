"""A training run's validation curve: each of its snapshots measured on the validation set.

`rig train` keeps the weights every `snapshot_every` steps in RUN/snapshots/step-NNNNNN.pt; its own
evaluations read its training takes, which say nothing about an unseen take. This measures every
snapshot not yet measured on the held-out validation set (inference/evaluate/heldout.py) with the
quick protocol of benchmarks/model_eval.py: two frame sets of each take (its first and last), the
references that do not depend on the model computed once and kept in a cache, the oracle with the
model's own stage 2 left out. Each point is one line of RUN/validation.jsonl (people first: the
person-mask PSNR, vanished, the rendered depth on the person masks; then the full image and stage
1's depth), and RUN/validation.png plots them beside the references.

    .venv/bin/python benchmarks/validation_curve.py RUN --data data/validation [--sets-per-take 2] [--model-size preview]
        [--watch MINUTES]     # keep measuring new snapshots as the run writes them, until none came for that long
        [--also M.pt ...]     # measure other models too (the shipped one, say), as points named by their file

A run's validation points let a variant be chosen on the validation set only; the test set is for
the model card, once per shipped model (benchmarks/model_eval.py --set test).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# (key in validation.jsonl, label, percent): the figures kept per point, people first.
FIGURES = [("psnr_mask", "PSNR on the person masks (dB)", False), ("vanished", "vanished (%)", True),
           ("view_depth_absrel_person", "rendered depth on people, AbsRel (%)", True), ("psnr", "PSNR (dB)", False),
           ("psnr_mask_p10", "person-mask PSNR, 10th-percentile take (dB)", False), ("psnr_p10", "PSNR, 10th-percentile take (dB)", False),
           ("depth_absrel", "stage-1 AbsRel (%)", True), ("depth_absrel_person", "stage-1 AbsRel on people (%)", True)]


def point(report: dict) -> dict:
    """The figures of one benchmarks/model_eval.py report that a validation point keeps."""
    t = report["trained"]
    spread = t.get("spread") or {}
    refs = t.get("references") or {}

    def ref(name: str) -> dict:
        r = refs.get(name) or {}
        return {"psnr_mask": r.get("overall", {}).get("psnr_mask"), "psnr": r.get("overall", {}).get("psnr"),
                "vanished": r.get("vanished")}

    return {"psnr_mask": t["overall"]["psnr_mask"], "vanished": t.get("vanished"),
            "view_depth_absrel_person": t.get("view_depth_absrel_person"), "psnr": t["overall"]["psnr"],
            "psnr_mask_p10": (spread.get("psnr_mask") or {}).get("p10"), "psnr_p10": (spread.get("psnr") or {}).get("p10"),
            "depth_absrel": t.get("depth_absrel"), "depth_absrel_person": t.get("depth_absrel_person"),
            "sets": t["sets"], "wall_s": t.get("wall_s"),
            "references": {"oracle_untrained_stage2": ref("oracle_untrained_stage2"), "nearest_source": ref("nearest_source")}}


def measure(model: Path, args: argparse.Namespace) -> dict:
    """One model through benchmarks/model_eval.py (its own process: a crash loses one point, not the curve)."""
    out = args.run / "validation" / f"{model.stem}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, str(REPO / "benchmarks" / "model_eval.py"), "--set", "validation", "--data", str(args.data),
           "--model", str(model), "--sets-per-take", str(args.sets_per_take), "--without-own-oracle",
           "--reference-cache", str(args.reference_cache or args.run / "validation" / "references.json"),
           "--json-out", str(out), "--quiet", "--json"]
    if args.model_size:
        cmd += ["--model-size", args.model_size]
    if args.takes:
        cmd += ["--takes", str(args.takes)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"error: {model}: model_eval.py failed (exit {done.returncode}): {done.stderr.strip().splitlines()[-1:]}")
    return point(json.loads(out.read_text()))


def measured(path: Path) -> dict[str, dict]:
    rows = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                row = json.loads(line)
                rows[row["model"]] = row
            except (ValueError, KeyError, TypeError):
                continue
    return rows


def step_of(snapshot: Path) -> int | None:
    stem = snapshot.stem
    return int(stem.split("-", 1)[1]) if stem.startswith("step-") and stem.split("-", 1)[1].isdigit() else None


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common.files import atomic_path

    steps = [r for r in rows if r.get("step") is not None]
    steps.sort(key=lambda r: r["step"])
    if not steps:
        return
    keys = [k for k in FIGURES if k[0] in ("psnr_mask", "vanished", "view_depth_absrel_person", "psnr", "depth_absrel_person")]
    fig, axes = plt.subplots(1, len(keys), figsize=(4 * len(keys), 3.2))
    for ax, (key, label, pct) in zip(axes, keys):
        k = 100.0 if pct else 1.0
        xs = [r["step"] for r in steps if r.get(key) is not None]
        ax.plot(xs, [k * r[key] for r in steps if r.get(key) is not None], "o-", label="model")
        for name, style in (("oracle_untrained_stage2", "--"), ("nearest_source", ":")):
            v = steps[-1]["references"][name].get(key)
            if v is not None:
                ax.axhline(k * v, linestyle=style, color="grey", label=name.replace("_", " "))
        for r in rows:
            if r.get("step") is None and r.get(key) is not None:
                ax.axhline(k * r[key], linestyle="-.", color="tab:red", label=Path(r["model"]).name)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(out, make_parents=True) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="the training run's folder (rig train -o RUN, with snapshot_every > 0)")
    ap.add_argument("--data", type=Path, required=True, help="the validation set, rendered (rig sim dataset --takes 12 --seconds 1 --fps 5 --seed 3)")
    ap.add_argument("--sets-per-take", type=int, default=2)
    ap.add_argument("--takes", type=int, help="only the set's first N takes")
    ap.add_argument("--model-size", choices=["test", "preview", "paper"], help="measure at these sizes (default: the model's own)")
    ap.add_argument("--reference-cache", type=Path, help="default RUN/validation/references.json")
    ap.add_argument("--also", type=Path, nargs="*", default=[], help="other models to measure as points of their own")
    ap.add_argument("--watch", type=float, metavar="MINUTES", help="keep measuring new snapshots until none came for this long")
    args = ap.parse_args()
    if not args.run.is_dir():
        print(f"error: {args.run}: no such run folder", file=sys.stderr)
        return 2
    log = args.run / "validation.jsonl"
    last_new = time.monotonic()
    while True:
        rows = measured(log)
        todo = [m for m in args.also if str(m) not in rows]
        todo += [s for s in sorted((args.run / "snapshots").glob("step-*.pt")) if str(s) not in rows and step_of(s) is not None]
        for model in todo:
            row = {"model": str(model), "step": step_of(model) if model.parent.name == "snapshots" else None, **measure(model, args)}
            with log.open("a") as f:
                f.write(json.dumps(row) + "\n")
            rows[row["model"]] = row
            print(json.dumps({k: row[k] for k in ("model", "step", "psnr_mask", "vanished", "view_depth_absrel_person", "psnr",
                                                 "depth_absrel_person")}), flush=True)
            plot(list(rows.values()), args.run / "validation.png")
            last_new = time.monotonic()
        if args.watch is None or time.monotonic() - last_new > 60.0 * args.watch:
            break
        time.sleep(30)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
