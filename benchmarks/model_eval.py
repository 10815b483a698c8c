"""The model's figures on a named held-out set, per take and their spread, with the references.

The sets are defined in inference/evaluate/heldout.py (data-set seeds no training take uses):
`validation` (seed 3, 12 takes) to choose among variants, `test` (seed 4, 20 takes) for the model
card once per shipped model, `previous` (seed 1, 3 takes: the set earlier models were chosen on,
only to put old figures beside new ones). Each take is 1 s at 5 frame sets per second, six
640x360 cameras. The set is rendered into a temporary folder, or read from `--data DIR` (checked to
be that set: its listing's seed, rate and takes).

In one run, on the same views (`rig model eval`'s figures, inference/evaluate/model_eval.py):
- the model (`--model`, default the shipped models/splat-sap-preview.pt);
- the oracle pipeline with this model's stage 2 (unless `--without-own-oracle`), and with
  untrained stage 2 (seed-0 initial weights: the acceptance reference), both fed ground-truth depth;
- the nearer source image as it is;
- with `--untrained`, also the untrained model of the same configuration (and its own references).
Per take: the person's share of the supervision pixels and the nearest person, PSNR and SSIM over
the image and the person masks, the rendered depth's AbsRel on the person masks, "vanished" (the
share of person-mask pixels rendered over 30 % off in depth or left empty), stage-1 AbsRel; then
for every figure its mean, median, 10th-percentile take (counted from the bad side) and worst
take, for the model and each reference.

    .venv/bin/python benchmarks/model_eval.py --set validation [--model M.pt] [--data DIR] [--takes N]
        [--json | --json-out FILE] [--worst-png models/worst-test-take.png]

`--takes N` measures only the set's first N takes (say so wherever the figures go); `--worst-png`
writes the worst take's worst view (lowest PSNR) beside its ground truth, 640x180.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DEFAULT_MODEL = REPO / "models" / "splat-sap-preview.pt"


def _progress(label: str):
    started = time.monotonic()

    def report(done: int, total: int) -> None:
        spent = time.monotonic() - started
        print(f"{label}: {done}/{total} frame sets, {spent:.0f} s, about {spent / done * (total - done):.0f} s left",
              file=sys.stderr, flush=True)

    return report


def resized(model, preset: str):
    """The same weights at another size preset (no weight depends on the sizes, inference/config.py)."""
    from inference.config import ModelConfig, Sizes
    from inference.model.pipeline import build_model

    cfg = ModelConfig.from_dict(model.cfg.to_dict())
    cfg.sizes = Sizes.preset(preset)
    out = build_model(cfg, seed=0)
    out.load_state_dict(model.state_dict())
    return out.eval()


# The code the cached references are computed by: a change to any of it measures them again.
REFERENCE_CODE = ["inference/model", "inference/evaluate/model_eval.py", "inference/train/data.py", "inference/metrics.py",
                  "inference/train/losses.py", "simulator", "rig/storage"]


def reference_key(set_name: str, takes: list, picks: list, size, cfg) -> str:
    """What the model-free references depend on: the set and its frame sets, the image size, the
    untrained pipeline's configuration (all but the backbone and stage 1, which the oracle replaces)
    and the code that computes them."""
    import hashlib

    h = hashlib.sha256()
    d = cfg.to_dict()
    d.pop("backbone", None)
    d.pop("stage1", None)
    h.update(json.dumps([set_name, list(takes), list(picks), list(size), d], sort_keys=True).encode())
    for root in REFERENCE_CODE:
        p = REPO / root
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            h.update(f.relative_to(REPO).as_posix().encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def read_references(path: Path, key: str):
    try:
        entry = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return entry.get("references") if isinstance(entry, dict) and entry.get("key") == key else None


def write_references(path: Path, key: str, references: dict) -> None:
    from common.files import atomic_path

    with atomic_path(path, make_parents=True) as tmp:
        Path(tmp).write_text(json.dumps({"key": key, "references": references}) + "\n")


def main() -> int:
    from common.errors import ReportedError
    from inference.evaluate.heldout import SETS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", choices=list(SETS), default="validation",
                    help="which held-out set (default validation; test only for the model card, once per shipped model)")
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    ap.add_argument("--data", type=Path, help="the set already rendered (default: render it into a temporary folder)")
    ap.add_argument("--takes", type=int, help="only the set's first N takes")
    ap.add_argument("--size", help="render the takes at WxH instead of the set's size (quick checks only; the model's own sizes are unchanged)")
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--sets-per-take", type=int, metavar="K",
                    help="measure K frame sets of each take, spread over it (first and last among them), instead of every --every-th")
    ap.add_argument("--model-size", choices=["test", "preview", "paper"],
                    help="run the model at these sizes instead of its own (no weight depends on them)")
    ap.add_argument("--reference-cache", type=Path, metavar="JSON",
                    help="keep the references that do not depend on the model (the oracle with untrained stage 2, the nearer "
                         "source) in this file and reuse them when the set, the frame sets, the sizes and the code are the same")
    ap.add_argument("--without-own-oracle", action="store_true",
                    help="leave out the oracle with this model's stage 2 (keeps the untrained-stage-2 oracle and the nearer source; a third less time)")
    ap.add_argument("--untrained", action="store_true", help="also evaluate the untrained model of the same configuration")
    ap.add_argument("--worst-png", type=Path, metavar="PNG", help="write the worst take's worst view beside its ground truth here")
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of the text")
    ap.add_argument("--json-out", type=Path, metavar="FILE", help="also write the JSON object to FILE")
    ap.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    args = ap.parse_args()
    try:
        return run(args)
    except ReportedError as exc:  # bad input (a model, a folder that is not the set) gets one line
        print(f"error: {exc}", file=sys.stderr)
        return 2


def run(args: argparse.Namespace) -> int:
    from inference.errors import InferenceError
    from inference.evaluate.heldout import check_data, held_out_set, take_seeds
    from inference.evaluate.model_eval import depth_lines, evaluate, oracle_twin, sets_per_take, spread_lines, take_lines, vanished_lines
    from inference.model.checkpoint import load_checkpoint
    from inference.model.pipeline import build_model
    from rig.storage.dataset import TrainingSet, expand_sequences

    held = held_out_set(args.set)
    if args.takes is not None and not 1 <= args.takes <= held.takes:
        raise InferenceError(f"--takes: the {held.name} set has {held.takes} takes; give 1 to {held.takes}")
    if args.every < 1:
        raise InferenceError(f"--every must be at least 1, got {args.every}")
    size = None
    if args.size is not None:
        try:
            size = tuple(int(v) for v in args.size.lower().split("x"))
            assert len(size) == 2
        except (ValueError, AssertionError):
            raise InferenceError(f"--size {args.size}: give WxH, e.g. 320x180") from None
    if not args.model.is_file():
        raise InferenceError(f"{args.model}: no such model")
    if args.sets_per_take is not None and args.sets_per_take < 1:
        raise InferenceError(f"--sets-per-take must be at least 1, got {args.sets_per_take}")
    trained = load_checkpoint(args.model)
    if trained.needs_depth:
        raise InferenceError(f"{args.model}: an oracle model reads ground-truth depth; evaluate a trained model")
    if args.model_size is not None:
        trained = resized(trained, args.model_size)
    untrained = build_model(trained.cfg, seed=0)
    oracles = {"oracle_untrained_stage2": oracle_twin(untrained)}
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = args.data
        if data_dir is None:
            data_dir = Path(tmp) / held.name
            t0 = time.monotonic()
            held.render(data_dir, takes=args.takes, size=size)
            if not args.quiet:
                print(f"rendered {args.takes or held.takes} takes of the {held.name} set in {time.monotonic() - t0:.0f} s", file=sys.stderr)
        meta = check_data(held, data_dir)
        names = meta["takes"][: args.takes or None]
        data = TrainingSet(expand_sequences([data_dir / n for n in names]))
        seeds = take_seeds(data_dir)
        picks = sets_per_take(data, args.sets_per_take) if args.sets_per_take else list(range(0, len(data), args.every))
        cache_key = reference_key(held.name, names, picks, size or held.size, trained.cfg)
        cached = read_references(args.reference_cache, cache_key) if args.reference_cache and args.without_own_oracle else None
        results = {}
        runs = [("trained", trained, oracles)] + ([("untrained", untrained, None)] if args.untrained else [])
        for name, model, extra in runs:
            t0 = time.monotonic()
            reuse = cached is not None and name == "trained"
            results[name] = evaluate(model, data, picks=picks, oracles=extra, references=not reuse,
                                     own_oracle=not (extra and args.without_own_oracle),
                                     progress=None if args.quiet else _progress(f"{name} model"))
            if reuse:
                results[name]["references"] = cached
            elif name == "trained" and args.reference_cache and args.without_own_oracle:
                write_references(args.reference_cache, cache_key, results[name]["references"])
            results[name]["wall_s"] = round(time.monotonic() - t0, 1)
            results[name]["references_cached"] = reuse
        figure = None
        takes = results["trained"]["takes"]
        worst_take = min(takes, key=lambda k: takes[k]["psnr"])
        if args.worst_png is not None:
            from inference.evaluate.figure import view_figure

            v = takes[worst_take]["worst_view"]
            figure = view_figure(trained, data, v["frame_set_index"], v["camera"], args.worst_png,
                                 caption=f"{held.name} {worst_take} set {v['set']}, {v['psnr']:.1f} dB")
    report = {"model": str(args.model), "held_out": {"set": held.name, "seed": held.seed, "takes": len(names), "of": held.takes,
                                                   "take_seeds": [seeds.get(n) for n in names], "seconds": held.seconds,
                                                   "fps": held.fps, "size": list(size or held.size)},
              "worst_take": worst_take, "worst_png": figure, **results}
    if args.json_out is not None:
        args.json_out.write_text(json.dumps(report) + "\n")
    if args.json:
        print(json.dumps(report))
        return 0
    t = results["trained"]
    print(f"held-out set {held.name}: {len(names)} of its {held.takes} takes (data-set seed {held.seed}, take seeds "
          f"{min(seeds.get(n, 0) for n in names)} to {max(seeds.get(n, 0) for n in names)}), {held.seconds:g} s at {held.fps:g} fps, "
          f"{t['sets']} frame sets x {len(t['supervision'])} supervision cameras; model {args.model} ({t['wall_s']:.0f} s with references"
          f"{', those without the model read from ' + str(args.reference_cache) if t.get('references_cached') else ''})")
    rows = [("this model", t)] + [(n, r) for n, r in t["references"].items()]
    if args.untrained:
        u = results["untrained"]
        rows += [("untrained model", u), ("oracle, untrained (its)", u["references"].get("oracle"))]
    # People first: the person-mask PSNR, vanished and the rendered depth on the person masks.
    print(f"{'':24s} {'PSNR mask':>10s} {'vanished':>9s} {'depth mask':>10s} {'PSNR':>7s} {'SSIM':>6s} {'SSIM mask':>10s}")
    f = lambda v, fmt: (fmt % v) if v is not None else "-"
    for name, r in rows:
        if not r:
            continue
        o = r["overall"]
        person_depth = (r.get("spread") or {}).get("view_depth_absrel_person")
        vanished = r.get("vanished")
        print(f"{name:24s} {f(o['psnr_mask'], '%10.2f'):>10s} {f(None if vanished is None else 100 * vanished, '%8.2f%%'):>9s} "
              f"{f(None if person_depth is None else 100 * person_depth['mean'], '%9.1f%%'):>10s} "
              f"{f(o['psnr'], '%7.2f'):>7s} {f(o['ssim'], '%6.3f'):>6s} {f(o['ssim_mask'], '%10.3f'):>10s}")
    for line in depth_lines(t) + vanished_lines(t):
        print(line)
    print()
    print("\n".join(take_lines(t, seeds)))
    print()
    print("\n".join(spread_lines(t)))
    print(f"worst take: {worst_take} ({takes[worst_take]['psnr']:.2f} dB)" + (f"; {figure['path']} ({figure['bytes']} bytes, {figure['key']} {figure['camera']})" if figure else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
