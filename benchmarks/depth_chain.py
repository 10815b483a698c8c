"""Where the person's depth is lost between stage 1 and the rendered view.

The rendered depth on people can be far worse than stage 1's own depth on them (people41-c on the
validation set: 19.6 % against 9.2 % AbsRel). This follows a model's depth through the pipeline,
at every supervision camera of two frame sets per take of a simulator set (ground-truth depth and
person masks), on the person masks and over the whole view:

- stage 1: AbsRel of the sources' depth where both see (as `rig model eval`), and the share of
  their person pixels more than 20 % off (and more than 20 % too far: the wall taken for the person);
- initial: depth initialisation's splatted depth in the target (fine size), with the share of
  person pixels no point reached (holes, filled by push-pull) and of those beyond stage 2's search
  range, nearer (something in front of the person) and farther (the wall behind shows through),
  farther by over 20 % (the surface behind, not a small error of the person's depth), and farther
  inside the person mask eroded by 2 pixels (not the silhouette's edge);
- refined: stage 2's refined depth (fine size);
- rendered: the Gaussians' depth (output size), where they cover the pixel over one half;
- vanished: rendered over 30 % off or not covered (as `rig model eval`).

`--set KEY=VALUE` changes a weight-free part of the model's configuration before measuring (for
instance `depth_init.opacity_power=0`), to see what such a change would do without training.

    .venv/bin/python benchmarks/depth_chain.py --model M.pt --data data/validation [--model-size preview]
        [--sets-per-take 2] [--takes N] [--set depth_init.opacity_power=0 ...] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def configured(model, size: str | None, settings: list[str]):
    """The same weights with the sizes of `size` and the configuration changes KEY=VALUE of `settings`."""
    from inference.config import ModelConfig, Sizes
    from inference.errors import InferenceError
    from inference.model.pipeline import build_model

    d = model.cfg.to_dict()
    for s in settings:
        key, sep, value = s.partition("=")
        parts = key.split(".")
        node = d
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                raise InferenceError(f"--set {s}: the configuration has no section {p!r}")
            node = node[p]
        if not sep or parts[-1] not in node:
            raise InferenceError(f"--set {s}: give KEY=VALUE with a key the configuration has")
        node[parts[-1]] = json.loads(value)
    cfg = ModelConfig.from_dict(d)
    if size:
        cfg.sizes = Sizes.preset(size)
    out = build_model(cfg, seed=0)
    out.load_state_dict(model.state_dict())
    return out.eval()


class Chain:
    """Per-view errors of one depth stage, pooled over the views."""

    def __init__(self) -> None:
        self.person: list[float] = []
        self.full: list[float] = []
        self.person_far = [0, 0, 0]  # pixels beyond the search range nearer, farther, pixels counted
        # farther by over 20 % (the surface behind, not a small error of the person's own depth): pixels;
        # farther inside the mask eroded by 2 pixels (not the silhouette's edge): pixels, pixels counted
        self.person_behind = 0
        self.interior_far = [0, 0]
        self.person_holes = [0, 0]

    def add(self, depth, truth, mask, covered=None, far: float = 0.06) -> None:
        import numpy as np

        d = depth[0, 0].detach().float().numpy()
        keep = (truth > 0) & (d > 0)
        if covered is not None:
            keep &= covered
        if keep.any():
            self.full.append(float(np.mean(np.abs(d[keep] / truth[keep] - 1))))
        pk = keep & mask
        if pk.any():
            ratio = d[pk] / truth[pk]
            self.person.append(float(np.abs(ratio - 1).mean()))
            self.person_far[0] += int((ratio < 1 - far).sum())
            self.person_far[1] += int((ratio > 1 + far).sum())
            self.person_behind += int((ratio > 1.2).sum())
            inner = eroded(mask, 2) & keep
            self.interior_far[0] += int((d[inner] / truth[inner] > 1 + far).sum())
            self.interior_far[1] += int((eroded(mask, 2) & (truth > 0)).sum())
        self.person_far[2] += int((mask & (truth > 0)).sum())

    def summary(self) -> dict:
        import numpy as np

        return {"person_absrel": round(float(np.mean(self.person)), 5) if self.person else None,
                "absrel": round(float(np.mean(self.full)), 5) if self.full else None,
                "person_nearer": round(self.person_far[0] / self.person_far[2], 5) if self.person_far[2] else None,
                "person_farther": round(self.person_far[1] / self.person_far[2], 5) if self.person_far[2] else None,
                "person_holes": round(self.person_holes[0] / self.person_holes[1], 5) if self.person_holes[1] else None,
                "person_behind": round(self.person_behind / self.person_far[2], 5) if self.person_far[2] else None,
                "interior_farther": round(self.interior_far[0] / self.interior_far[1], 5) if self.interior_far[1] else None}


def eroded(mask, n: int):
    """`mask` less every pixel within n pixels (4-neighbour steps) of its outside or the image's edge."""
    import numpy as np

    m = mask.copy()
    for _ in range(n):
        p = np.pad(m, 1, constant_values=False)
        m = m & p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
    return m


def measure(model, data, picks, search: float) -> dict:
    import numpy as np
    import torch

    from inference.evaluate.model_eval import vanished_pixels
    from inference.train.data import Preprocessor
    from inference.train.depth_figures import depth_ratios

    pre = Preprocessor()
    sizes = model.cfg.sizes
    chains = {k: Chain() for k in ("initial", "refined", "rendered")}
    stage1_person, off, counted = [], 0, 0
    with torch.no_grad():
        for index in picks:
            fs = data.frame_set(index, with_truth=True)
            L = pre.views(fs, [data.left], sizes.fine)
            R = pre.views(fs, [data.right], sizes.fine)
            _, affine, stage1 = model.run_stage1(L.images, R.images, L.K, R.K, L.poses, R.poses)
            if all(fs.depth.get(c) is not None and fs.masks.get(c) is not None for c in (data.left, data.right)):
                gt = {c: pre.depth(fs.depth[c], fs.cameras[c], sizes.coarse) for c in (data.left, data.right)}
                masks = {c: pre.depth(fs.masks[c].astype(np.float32), fs.cameras[c], sizes.coarse) > 0.5 for c in (data.left, data.right)}
                stage1_person += depth_ratios(affine, L, R, fs, data, gt, sizes.coarse, masks)
            for sup in data.supervision:
                if fs.depth.get(sup) is None or fs.masks.get(sup) is None:
                    continue
                T = pre.views(fs, [sup], sizes.output)
                out = model.run_view(stage1, L.images, R.images, L.K, R.K, L.poses, R.poses, T.K, T.poses)
                truth_fine = pre.depth(fs.depth[sup], fs.cameras[sup], sizes.fine)
                mask_fine = pre.depth(fs.masks[sup].astype(np.float32), fs.cameras[sup], sizes.fine) > 0.5
                truth_out = pre.depth(fs.depth[sup], fs.cameras[sup], sizes.output)
                mask_out = pre.depth(fs.masks[sup].astype(np.float32), fs.cameras[sup], sizes.output) > 0.5
                init = out["initial_depth"]
                chains["initial"].add(init.depth, truth_fine, mask_fine, far=search)
                holes = (init.coverage[0, 0].numpy() <= 0) & mask_fine & (truth_fine > 0)
                chains["initial"].person_holes[0] += int(holes.sum())
                chains["initial"].person_holes[1] += int((mask_fine & (truth_fine > 0)).sum())
                chains["refined"].add(out["refined"].depth, truth_fine, mask_fine, far=search)
                chains["rendered"].add(out["depth"], truth_out, mask_out, covered=out["alpha"][0, 0].numpy() > 0.5, far=search)
                o, c = vanished_pixels(out["depth"], out["alpha"], truth_out, mask_out)
                off, counted = off + o, counted + c
    ratios = np.concatenate(stage1_person) if stage1_person else None
    return {"stage1_person_absrel": round(float(np.mean([np.mean(np.abs(r - 1)) for r in stage1_person])), 5) if stage1_person else None,
            # the share of stage 1's person pixels more than 20 % off, and more than 20 % too far
            "stage1_person_off20": round(float(np.mean(np.abs(ratios - 1) > 0.2)), 5) if ratios is not None else None,
            "stage1_person_behind": round(float(np.mean(ratios > 1.2)), 5) if ratios is not None else None,
            **{k: v.summary() for k, v in chains.items()},
            "vanished": round(off / counted, 5) if counted else None, "views": len(chains["rendered"].full)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True, help="a simulator set (rig sim dataset): ground-truth depth and person masks")
    ap.add_argument("--model-size", choices=["test", "preview", "paper"], help="measure at these sizes (default: the model's own)")
    ap.add_argument("--sets-per-take", type=int, default=2)
    ap.add_argument("--takes", type=int, help="only the first N takes")
    ap.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                    help="change a weight-free configuration value first (repeatable)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    from inference.errors import InferenceError
    from inference.evaluate.model_eval import sets_per_take
    from inference.model.checkpoint import load_checkpoint
    from rig.storage.dataset import TrainingSet, expand_sequences

    try:
        if not args.model.is_file():
            raise InferenceError(f"{args.model}: no such model")
        model = configured(load_checkpoint(args.model), args.model_size, args.settings)
        names = sorted(p.name for p in args.data.iterdir() if (p / "sequence.json").is_file())[: args.takes or None]
        if not names:
            raise InferenceError(f"{args.data}: no sequences (render one with rig sim dataset)")
        data = TrainingSet(expand_sequences([args.data / n for n in names]))
    except (InferenceError, ValueError, json.JSONDecodeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    search = float(model.cfg.stage2.search_range)
    result = measure(model, data, sets_per_take(data, args.sets_per_take), search)
    result.update(model=str(args.model), settings=args.settings, takes=len(names), search_range=search,
                  wall_s=round(time.monotonic() - t0, 1))
    if args.json:
        print(json.dumps(result))
        return 0
    pct = lambda v: "-" if v is None else f"{100 * v:.1f} %"
    print(f"{args.model} {' '.join(args.settings)}: {len(names)} takes, {result['views']} views, {result['wall_s']} s")
    print(f"stage 1 (sources, where both see): people {pct(result['stage1_person_absrel'])}, "
          f"over 20 % off {pct(result['stage1_person_off20'])}, over 20 % too far {pct(result['stage1_person_behind'])}")
    beyond = format(100 * search, '.0f')
    print(f"{'':10s} {'people':>8s} {'all':>8s} {'people >' + beyond + ' % nearer':>19s} {'people >' + beyond + ' % farther':>20s} {'people in holes':>16s} {'people >20 % farther':>21s} {'inside farther':>15s}")
    for k in ("initial", "refined", "rendered"):
        r = result[k]
        print(f"{k:10s} {pct(r['person_absrel']):>8s} {pct(r['absrel']):>8s} {pct(r['person_nearer']):>19s} {pct(r['person_farther']):>20s} {pct(r['person_holes']):>16s} {pct(r['person_behind']):>21s} {pct(r['interior_farther']):>15s}")
    print(f"vanished {pct(result['vanished'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
