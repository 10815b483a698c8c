"""The held-out simulator sets the model is measured on: the one place that names them.

    from inference.evaluate.heldout import VALIDATION, TEST, held_out_set
    VALIDATION.render("data/validation")      # rig sim dataset --takes 12 --seconds 1 --fps 5 --seed 3
    check_data(TEST, Path("data/test"))       # a folder claimed to be the test set really is it

Protocol (docs/training.md, "Evaluation"): choose among variants (configurations, checkpoints,
schedules) on VALIDATION only; run TEST once per model that is to ship, and put its figures in the
model card. A set that has been used to choose stops measuring what a new user gets: the figures
of whatever won on it are biased upwards.

Seeds. Take i of a data set with seed K has the take seed K * 1000 + i (simulator.takes), so two
data-set seeds never share a take. Seeds already spent, and why they are not held-out sets here:
- 0: the training data (`rig sim dataset --seed 0`, docs/training.md; rig train's own default);
- 1: the three-take set every earlier variant was chosen on (PREVIOUS below, kept only so that old
  figures can be put beside new ones); its takes are also easy, one person far from the cameras
  (2.4 to 4.6 % of the supervision pixels);
- 2: looked at by issue 35's author to show that 1 was easy (8 takes), so it has informed choices.
Hence VALIDATION uses 3 and TEST 4, both fresh. Their takes draw the variety `rig sim dataset`
draws (simulator.variety: 1 to 3 people, walkers circling 1.45 m from the middle of the room, which
brings them within about 1.7 to 2 m of a camera); measured from the ground truth before any model
was run on them (smallest person depth in any camera, person share of the supervision pixels):
validation 1.95 to 3.14 m, 6.2 to 15.2 %; test 1.73 to 3.64 m, 4.5 to 29.5 %. benchmarks/model_eval.py
prints both per take.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from inference.errors import InferenceError

TRAINING_SEED = 0  # the data-set seed training uses (docs/training.md)
SPENT_SEEDS = {0: "training data", 1: "the previous held-out set, used to choose variants", 2: "inspected for issue 35"}


@dataclass(frozen=True)
class HeldOutSet:
    """A held-out set: `takes` takes of the data set with seed `seed`, each `seconds` long at `fps`
    frame sets per second, `cameras` cameras of `size` (what `rig sim dataset` renders)."""

    name: str
    seed: int
    takes: int
    purpose: str
    seconds: float = 1.0
    fps: float = 5.0
    size: tuple[int, int] = (640, 360)
    cameras: int = 6

    def command(self) -> str:
        """The `rig sim dataset` line that renders this set (for docs and messages)."""
        return (f"rig sim dataset -o DIR --takes {self.takes} --seconds {self.seconds:g} --fps {self.fps:g} "
                f"--seed {self.seed} --size {self.size[0]}x{self.size[1]}")

    def render(self, out_dir, takes: Optional[int] = None, size: Optional[tuple[int, int]] = None,
               progress: Optional[Callable[[int, int], None]] = None) -> dict:
        """Render the set (or its first `takes` takes; at `size` for quick checks) into the new
        folder `out_dir`; returns simulator.takes.write_dataset's summary."""
        from simulator.takes import write_dataset

        n = self.takes if takes is None else takes
        if not 1 <= n <= self.takes:
            raise InferenceError(f"the {self.name} set has {self.takes} takes; asked for {n}")
        return write_dataset(out_dir, n, self.seconds, seed=self.seed, fps=self.fps, size=size or self.size,
                             cameras=self.cameras, progress=progress)


VALIDATION = HeldOutSet("validation", seed=3, takes=12, purpose="choose among variants here")
TEST = HeldOutSet("test", seed=4, takes=20, purpose="the model card's figures, once per shipped model; never choose on it")
PREVIOUS = HeldOutSet("previous", seed=1, takes=3, purpose="the set earlier models were chosen on: only to compare with old figures")
SETS = {s.name: s for s in (VALIDATION, TEST, PREVIOUS)}


def held_out_set(name: str) -> HeldOutSet:
    if name not in SETS:
        raise InferenceError(f"no held-out set {name!r}; choose one of {', '.join(SETS)}")
    return SETS[name]


def check_data(held: HeldOutSet, data_dir: Path) -> dict:
    """The listing (dataset.json) of `data_dir`, checked to be `held` or its first takes rendered
    as `held.render` does (any image size): figures reported as the test set's must come from it."""
    listing = Path(data_dir) / "dataset.json"
    try:
        meta = json.loads(listing.read_text())
    except (OSError, ValueError):
        raise InferenceError(f"{listing}: no readable data-set listing; render the {held.name} set with: {held.command()}") from None
    got = {k: meta.get(k) for k in ("seed", "fps", "sets_per_take")}
    want = {"seed": held.seed, "fps": float(held.fps), "sets_per_take": max(1, int(round(held.seconds * held.fps)))}
    takes = meta.get("takes")
    if got != want or not isinstance(takes, list) or not 1 <= len(takes) <= held.takes or len(meta.get("cameras", [])) != held.cameras:
        raise InferenceError(f"{data_dir}: not the {held.name} set (seed {meta.get('seed')}, {meta.get('fps')} fps, "
                             f"{meta.get('sets_per_take')} sets per take, {len(takes) if isinstance(takes, list) else '?'} takes); "
                             f"render it with: {held.command()}")
    return meta


def take_seeds(data_dir: Path) -> dict[str, int]:
    """Take folder name -> take seed, from a data set's listing (empty where there is none)."""
    try:
        meta = json.loads((Path(data_dir) / "dataset.json").read_text())
        return dict(zip(meta["takes"], meta["take_seeds"]))
    except (OSError, ValueError, KeyError, TypeError):
        return {}
