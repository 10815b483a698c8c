"""Bad input through the `rig` command line, as a newcomer types it, on the simulator.

    .venv/bin/python benchmarks/bad_inputs.py            # every case; a markdown table; exit 1 if any fails
    .venv/bin/python benchmarks/bad_inputs.py --fast     # the quick subset tests/rig/test_bad_inputs.py runs
    .venv/bin/python benchmarks/bad_inputs.py -k record  # the cases whose name contains "record"

Each case runs `python -m rig ...` in a subprocess, in a folder of its own holding copies of what it
needs (a sim rig config, a recorded take, a grab, a calibration, ...), and passes when:
  - the exit code is the expected one: 2 for bad input (arguments, a config, files given, an output
    path that cannot be written or is occupied, found before the work), 1 for a failure found during
    the work (a take that validates as damaged);
  - stderr is exactly one line (`rig: error: ...`, or argparse's `rig CMD: error: ...`) holding the
    case's fragment, and no traceback; `rig config check` prints one line per problem;
  - nothing recorded is lost: the files of the takes, grabs and calibrations the case protects have
    the same checksums afterwards (a repair must keep every good set and the original index);
  - where a limit is set, the command gave up within it (arguments checked before the work).

`CASES` is the table; tests/rig/test_bad_inputs.py imports this file by path and runs the `fast` ones.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

REPO = Path(__file__).resolve().parents[1]
UNWRITABLE = "/proc/rig-bad-input"  # nobody, root included, can create anything under /proc
ERROR_LINE = re.compile(r"^rig( [\w-]+)*: error: ")


@dataclass
class Case:
    name: str
    argv: list[str]  # paths are relative to the case's folder
    code: int  # expected exit status
    fragment: str = ""  # must appear in the stderr line
    needs: tuple[str, ...] = ()  # fixtures copied into the case's folder (see FIXTURES)
    protect: tuple[str, ...] = ()  # files or folders whose every file must be unchanged afterwards
    prepare: Optional[Callable[[Path], None]] = None  # damage the copies before the run
    check: Optional[Callable[[Path, dict], list[str]]] = None  # extra checks: (folder, checksums before) -> problems
    lines: int = 1  # stderr lines expected
    max_s: Optional[float] = None  # must give up within this many seconds
    fast: bool = False  # in the quick subset the tests run
    point: str = ""  # the issue-11 point that fixes it, where it fails before that fix


# ---- fixtures: made once per run, copied into each case's folder ------------------------------------

def _rig(*args: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig", *args], cwd=cwd, capture_output=True, text=True, timeout=timeout)


def build_fixtures(base: Path) -> Path:
    """A small sim rig (160x96, two cameras), an 8-set take and a 2-frame grab recorded with it, the
    simulator's exact calibration of it (and one at another size), a ChArUco board description,
    garbage files and a folder of garbage images."""
    sys.path.insert(0, str(REPO))
    from simulator.rig import arc_rig
    from simulator.scene import default_board

    fx = base / "fixtures"
    fx.mkdir(parents=True)
    for argv in (["config", "init", "--sim", "--width", "160", "--height", "96", "rig.toml"],
                 ["record", "-c", "rig.toml", "-o", "take", "--sets", "8"],
                 ["grab", "-c", "rig.toml", "-n", "2", "-o", "grab"]):
        proc = _rig(*argv, cwd=fx)
        if proc.returncode != 0:
            raise RuntimeError(f"fixture `rig {' '.join(argv)}` failed: {proc.stderr.strip()}")
    arc_rig([("left", 160, 96), ("right", 160, 96)]).save(fx / "calib.json")
    arc_rig([("left", 320, 192), ("right", 320, 192)]).save(fx / "calib-other-size.json")
    (fx / "board.toml").write_text("".join(f"{k} = {json.dumps(v)}\n" for k, v in default_board("charuco").to_dict().items()))
    (fx / "garbage.bin").write_bytes(bytes(range(256)) * 8)
    (fx / "garbage.toml").write_text("[rig\nname = = 3\n")
    for cam in ("left", "right"):
        (fx / "images" / cam).mkdir(parents=True)
        for i in range(3):
            (fx / "images" / cam / f"{i:04d}.png").write_bytes(b"\x89PNG not really" * 10)
    (fx / "notes.txt").write_text("not a sequence\n")
    return fx


# ---- damage --------------------------------------------------------------------------------------

def _config_with(extra_rig: str = "", replace: tuple[str, str] = ("", "")) -> Callable[[Path], None]:
    def prepare(d: Path) -> None:
        text = (d / "rig.toml").read_text()
        if extra_rig:
            text = text.replace('storage = "recordings"', f'storage = "recordings"\n{extra_rig}')
        if replace[0]:
            text = text.replace(*replace)
        (d / "rig.toml").write_text(text)
    return prepare


def _garbage_index_line(n: int) -> Callable[[Path], None]:
    def prepare(d: Path) -> None:
        index = d / "take" / "index.jsonl"
        lines = index.read_bytes().splitlines(keepends=True)
        lines[n] = b'{"set": 3, "frames": {"left": \x00\x17garbage\n'
        index.write_bytes(b"".join(lines))
    return prepare


def _frame_file(d: Path, set_no: int, cam: str) -> Path:
    rows = [json.loads(line) for line in (d / "take" / "index.jsonl").read_text().splitlines() if line.strip()]
    return d / "take" / rows[set_no]["frames"][cam]["file"]


def _remove_image(set_no: int, cam: str) -> Callable[[Path], None]:
    return lambda d: _frame_file(d, set_no, cam).unlink()


def _truncate_image(set_no: int, cam: str) -> Callable[[Path], None]:
    def prepare(d: Path) -> None:
        f = _frame_file(d, set_no, cam)
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    return prepare


def _then(*steps: Callable[[Path], None]) -> Callable[[Path], None]:
    def prepare(d: Path) -> None:
        for s in steps:
            s(d)
    return prepare


# ---- what "nothing lost" means -------------------------------------------------------------------

def checksums(root: Path, rels: tuple[str, ...]) -> dict[str, str]:
    out = {}
    for rel in rels:
        p = root / rel
        files = [p] if p.is_file() else sorted(f for f in p.rglob("*") if f.is_file()) if p.exists() else []
        for f in files:
            out[str(f.relative_to(root))] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


def _lost(before: dict[str, str], after: dict[str, str], except_: tuple[str, ...] = ()) -> list[str]:
    problems = []
    for rel, digest in before.items():
        if rel in except_:
            continue
        if rel not in after:
            problems.append(f"{rel} was removed")
        elif after[rel] != digest:
            problems.append(f"{rel} was changed")
    return problems


def _repair_keeps(good_rows: int) -> Callable[[Path, dict], list[str]]:
    """A repair may rewrite the index only: every image stays, the original index is kept beside
    (some file in the take has its checksum), and the repaired index keeps `good_rows` sets."""
    def check(d: Path, before: dict[str, str]) -> list[str]:
        index = "take/index.jsonl"
        after = checksums(d, ("take",))
        problems = _lost(before, after, except_=(index,))
        if before[index] not in after.values():
            problems.append("the original index.jsonl was not kept beside the repaired one")
        rows = 0
        for line in (d / index).read_text(errors="replace").splitlines():
            try:
                rows += isinstance(json.loads(line), dict)
            except ValueError:
                pass
        if rows < good_rows:
            problems.append(f"the repaired index keeps {rows} sets of the {good_rows} good ones")
        return problems
    return check


# ---- the cases -----------------------------------------------------------------------------------

RIG = ("rig.toml",)
TAKE = ("rig.toml", "take")
C = Case
CASES: list[Case] = [
    # the command line itself
    C("no command", [], 2, "required", fast=True),
    C("unknown command", ["frobnicate"], 2, "invalid choice"),
    C("unknown option", ["discover", "--colour"], 2, "unrecognized arguments", fast=True),
    # rig config init / check
    C("config init: unwritable path", ["config", "init", "--sim", f"{UNWRITABLE}/rig.toml"], 2, UNWRITABLE.rsplit("/", 1)[0], fast=True),
    C("config init: over an existing config", ["config", "init", "--sim", "rig.toml"], 2, "already exists", RIG, RIG),
    C("config init: a folder", ["config", "init", "--sim", "take"], 2, "folder", TAKE, TAKE),
    C("config init: one camera", ["config", "init", "--sim", "--cameras", "1", "new.toml"], 2, "--cameras"),
    C("config init: width not a number", ["config", "init", "--sim", "--width", "wide", "new.toml"], 2, "--width"),
    C("config init: width 0", ["config", "init", "--sim", "--width", "0", "new.toml"], 2, "width"),
    C("config check: missing file", ["config", "check", "nope.toml"], 2, "no such config file"),
    C("config check: binary garbage", ["config", "check", "garbage.bin"], 2, "garbage.bin", ("garbage.bin",)),
    C("config check: not TOML", ["config", "check", "garbage.toml"], 2, "not valid TOML", ("garbage.toml",), fast=True),
    C("config check: a folder", ["config", "check", "take"], 2, "folder", TAKE, TAKE),
    C("config check: three problems, three lines", ["config", "check", "rig.toml"], 2, "rig.toml", RIG, lines=3, fast=True,
      prepare=_then(_config_with('colour = "red"', ('uri = "sim://left"', 'uri = "sim//left"')),
                    _config_with(replace=("rate_hz = 30.0", "rate_hz = -1.0"))), point="9"),
    C("config check: missing calibration", ["config", "check", "rig.toml"], 2, "does not exist", RIG,
      prepare=_config_with('calibration = "calib.json"'), fast=True, point="5"),
    C("config check: garbage calibration", ["config", "check", "rig.toml"], 2, "garbage.bin", ("rig.toml", "garbage.bin"),
      prepare=_config_with('calibration = "garbage.bin"'), point="5"),
    C("config check: calibration at another size (two cameras, two lines)", ["config", "check", "rig.toml"], 2, "320x192",
      ("rig.toml", "calib-other-size.json"), prepare=_config_with('calibration = "calib-other-size.json"'), lines=2, fast=True, point="5"),
    C("config check: bad URI (and its sim options, two lines)", ["config", "check", "rig.toml"], 2, "firewire", RIG,
      prepare=_config_with(replace=('uri = "sim://left"', 'uri = "firewire://left"')), lines=2, fast=True),
    C("grab: bad URI", ["grab", "-c", "rig.toml", "-n", "1", "-o", "out"], 2, "firewire", RIG,
      prepare=_config_with(replace=('uri = "sim://left"', 'uri = "firewire://left"'))),
    # rig discover
    C("discover: positional argument", ["discover", "all"], 2, "unrecognized arguments"),
    # rig grab
    C("grab: -n 0", ["grab", "-c", "rig.toml", "-n", "0", "-o", "out"], 2, "-n", RIG, fast=True),
    C("grab: -n not a number", ["grab", "-c", "rig.toml", "-n", "two", "-o", "out"], 2, "-n", RIG),
    C("grab: missing config", ["grab", "-c", "none.toml", "-n", "1", "-o", "out"], 2, "no such config file"),
    C("grab: unwritable output", ["grab", "-c", "rig.toml", "-n", "1", "-o", f"{UNWRITABLE}/g"], 2, "/proc", RIG, max_s=15, fast=True),
    C("grab: into an earlier grab", ["grab", "-c", "rig.toml", "-n", "1", "-o", "grab"], 2, "grab", ("rig.toml", "grab"), ("grab",),
      fast=True, point="2"),
    C("grab: empty sim URI", ["grab", "-c", "rig.toml", "-n", "1", "-o", "out"], 2, "sim://", RIG,
      prepare=_config_with(replace=('uri = "sim://right"', 'uri = "sim://"'))),
    C("grab: garbage calibration", ["grab", "-c", "rig.toml", "-n", "1", "-o", "out"], 2, "rig.calibration", ("rig.toml", "garbage.bin"),
      prepare=_config_with('calibration = "garbage.bin"'), point="5"),
    # rig sync check
    C("sync check: --seconds -1", ["sync", "check", "-c", "rig.toml", "--seconds", "-1"], 2, "--seconds", RIG, fast=True),
    C("sync check: --seconds nan", ["sync", "check", "-c", "rig.toml", "--seconds", "nan"], 2, "--seconds", RIG),
    C("sync check: negative limit", ["sync", "check", "-c", "rig.toml", "--max-skew-us", "-5"], 2, "--max-skew-us", RIG),
    C("sync check: garbage config", ["sync", "check", "-c", "garbage.bin"], 2, "garbage.bin", ("garbage.bin",)),
    # rig calibrate
    C("calibrate board: missing board file", ["calibrate", "board", "none.toml", "-o", "b.png"], 2, "none.toml", fast=True),
    C("calibrate board: garbage board file", ["calibrate", "board", "garbage.toml", "-o", "b.png"], 2, "garbage.toml", ("garbage.toml",)),
    C("calibrate board: unwritable output", ["calibrate", "board", "board.toml", "-o", f"{UNWRITABLE}/b.png"], 2, "/proc", ("board.toml",),
      fast=True),
    C("calibrate board: --dpi -300", ["calibrate", "board", "board.toml", "-o", "b.png", "--dpi", "-300"], 2, "dpi", ("board.toml",)),
    C("calibrate run: missing image folder", ["calibrate", "run", "--images", "none", "--board", "board.toml", "-o", "c.json"], 2,
      "none", ("board.toml",)),
    C("calibrate run: garbage images", ["calibrate", "run", "--images", "images", "--board", "board.toml", "-o", "c.json"], 2,
      "images", ("board.toml", "images"), ("images",)),
    C("calibrate run: unwritable output", ["calibrate", "run", "--images", "images", "--board", "board.toml", "-o", f"{UNWRITABLE}/c.json"],
      2, "/proc", ("board.toml", "images"), max_s=15, point="3"),
    C("calibrate run: over the calibration in use", ["calibrate", "run", "--images", "images", "--board", "board.toml", "-o", "calib.json"],
      2, "", ("board.toml", "images", "calib.json"), ("calib.json",)),
    C("calibrate capture: views into an occupied folder", ["calibrate", "capture", "-c", "rig.toml", "--board", "board.toml", "-o", "images"],
      2, "images", ("rig.toml", "board.toml", "images"), ("images",), fast=True),
    C("calibrate capture: --views 0", ["calibrate", "capture", "-c", "rig.toml", "--board", "board.toml", "-o", "v", "--views", "0"],
      2, "--views", ("rig.toml", "board.toml")),
    C("calibrate report: garbage calibration", ["calibrate", "report", "garbage.bin"], 2, "garbage.bin", ("garbage.bin",), fast=True),
    C("calibrate report: missing calibration", ["calibrate", "report", "none.json"], 2, "none.json"),
    C("calibrate export: unwritable output", ["calibrate", "export", "calib.json", "--format", "colmap", "-o", f"{UNWRITABLE}/x"], 2,
      "/proc", ("calib.json",), ("calib.json",), fast=True, point="3"),
    C("calibrate export: output is a file", ["calibrate", "export", "calib.json", "--format", "opencv", "-o", "rig.toml"], 2,
      "rig.toml", ("calib.json", "rig.toml"), ("calib.json", "rig.toml"), point="3"),
    C("calibrate export: unknown format", ["calibrate", "export", "calib.json", "--format", "blender", "-o", "x"], 2, "--format",
      ("calib.json",)),
    # rig record
    C("record: into an existing take", ["record", "-c", "rig.toml", "-o", "take", "--sets", "2"], 2, "take", TAKE, ("take",), fast=True),
    C("record: unwritable output", ["record", "-c", "rig.toml", "-o", f"{UNWRITABLE}/t", "--sets", "2"], 2, "/proc", RIG, max_s=15, fast=True),
    C("record: --seconds -1", ["record", "-c", "rig.toml", "-o", "t", "--seconds", "-1"], 2, "positive", RIG, fast=True),
    C("record: --sets and --seconds", ["record", "-c", "rig.toml", "-o", "t", "--sets", "2", "--seconds", "1"], 2, "not allowed with", RIG),
    C("record: no config", ["record", "-o", "t", "--sets", "2"], 2, "-c"),
    C("record: garbage calibration", ["record", "-c", "rig.toml", "-o", "t", "--sets", "2"], 2, "garbage.bin", ("rig.toml", "garbage.bin"),
      prepare=_config_with('calibration = "garbage.bin"'), fast=True, point="5"),
    C("record: calibration missing a camera", ["record", "-c", "rig.toml", "-o", "t", "--sets", "2"], 2, "'right'",
      prepare=_then(_config_with('calibration = "one.json"'),
                    lambda d: (d / "one.json").write_text(json.dumps(dict(json.loads((d / "calib.json").read_text()),
                                                                          cameras=json.loads((d / "calib.json").read_text())["cameras"][:1])))),
      needs=("rig.toml", "calib.json"), point="5"),
    C("record validate: no such folder", ["record", "validate", "none"], 2, "none"),
    C("record validate: a file", ["record", "validate", "notes.txt"], 2, "notes.txt", ("notes.txt",)),
    C("record validate: not a sequence", ["record", "validate", "images"], 2, "images", ("images",), ("images",), fast=True),
    C("record validate: garbage index line", ["record", "validate", "take"], 1, "corrupt", TAKE, ("take",),
      prepare=_garbage_index_line(3), fast=True),
    C("record validate: missing image", ["record", "validate", "take"], 1, "missing", TAKE, ("take",), prepare=_remove_image(4, "right")),
    C("record validate: torn image, --pixels after the folder", ["record", "validate", "take", "--pixels"], 1, "", TAKE, ("take",),
      prepare=_truncate_image(2, "left"), fast=True, point="7"),
    C("record repair: no such folder", ["record", "repair", "none"], 2, "none"),
    C("record repair: garbage index line keeps every good set", ["record", "repair", "take"], 0, "", TAKE,
      ("take",), fast=True, prepare=_garbage_index_line(3), check=_repair_keeps(7), lines=0, point="1"),
    C("record repair: missing image keeps every set", ["record", "repair", "take"], 0, "", TAKE,
      ("take",), prepare=_remove_image(2, "right"), check=_repair_keeps(8), lines=0, point="1"),
    # rig sim snapshot
    C("sim snapshot: -t -1", ["sim", "snapshot", "-c", "rig.toml", "-t", "-1", "-o", "s"], 2, "-t", RIG),
    C("sim snapshot: unwritable output", ["sim", "snapshot", "-c", "rig.toml", "-t", "0", "-o", f"{UNWRITABLE}/s"], 2, "/proc", RIG, max_s=15),
    C("sim snapshot: over a take", ["sim", "snapshot", "-c", "rig.toml", "-t", "0", "-o", "take"], 2, "take", TAKE, ("take",), max_s=15),
    # rig model (torch loads: slow, none in the quick subset)
    C("model export: unwritable output", ["model", "export", "--size", "test", "-o", f"{UNWRITABLE}/m.onnx"], 2, "/proc", max_s=30),
    C("model export: --opset 9", ["model", "export", "--size", "test", "--opset", "9", "-o", "m.onnx"], 2, "opset"),
    C("model check: garbage model", ["model", "check", "garbage.bin"], 2, "garbage.bin", ("garbage.bin",)),
    C("model check: missing model", ["model", "check", "none.onnx"], 2, "none.onnx"),
    C("model bench: unknown size", ["model", "bench", "--size", "huge"], 2, "huge"),
    C("train: a take without supervision cameras", ["train", "take", "-o", "run"], 2, "supervision", ("take",), max_s=30),
    C("train: not a sequence", ["train", "notes.txt", "-o", "run"], 2, "notes.txt", max_s=30),
    C("train: unwritable output", ["train", "take", "-o", UNWRITABLE], 2, "/proc", ("take",), max_s=30),
    C("train: --resume without a run", ["train", "take", "-o", "run", "--resume"], 2, "checkpoint", ("take",), max_s=30),
    C("train: garbage config", ["train", "take", "-o", "run", "--config", "garbage.bin"], 2, "garbage.bin", ("take", "garbage.bin"), max_s=30),
    C("train: --nproc 0", ["train", "take", "-o", "run", "--nproc", "0"], 2, "nproc", max_s=30),
    C("model eval: garbage model", ["model", "eval", "--model", "garbage.bin", "--sequence", "take"], 2, "garbage.bin", ("take", "garbage.bin"), max_s=60),
    C("model eval: missing model", ["model", "eval", "--model", "none.pt", "--sequence", "take"], 2, "none.pt", ("take",), max_s=60),
    C("model bench: --repeat 0", ["model", "bench", "--size", "test", "--repeat", "0"], 2, "repeat", max_s=30),
    # rig live (checked before the rig starts) and rig model render
    C("live: garbage model", ["live", "-c", "rig.toml", "--model", "garbage.bin", "--seconds", "1"], 2, "garbage", ("rig.toml", "garbage.bin"), max_s=30),
    C("live: missing model", ["live", "-c", "rig.toml", "--model", "none.onnx", "--seconds", "1"], 2, "none.onnx", RIG, max_s=30),
    C("live: short token", ["live", "-c", "rig.toml", "--token", "abc", "--seconds", "1"], 2, "--token", RIG, max_s=30),
    C("live: port 70000", ["live", "-c", "rig.toml", "--port", "70000", "--seconds", "1"], 2, "--port", RIG, max_s=30),
    C("live: video over an existing file", ["live", "-c", "rig.toml", "--record-output", "garbage.bin", "--seconds", "1"], 2, "--record-output",
      ("rig.toml", "garbage.bin"), max_s=30),
    C("live: replay of a non-sequence", ["live", "-c", "rig.toml", "--replay", "notes.txt", "--seconds", "1"], 2, "--replay", RIG, max_s=30),
    C("model render: missing sequence", ["model", "render", "--sequence", "nope", "--view", "0.5", "-o", "v.png"], 2, "nope", max_s=30),
    C("model render: unknown camera", ["model", "render", "--sequence", "take", "--view", "cam9", "-o", "v.png"], 2, "cam9", TAKE, max_s=30),
    C("model render: set out of range", ["model", "render", "--sequence", "take", "--set", "99999", "--view", "0.5", "-o", "v.png"], 2, "99999", TAKE, max_s=30),
    C("model render: unwritable output", ["model", "render", "--sequence", "take", "--view", "0.5", "-o", f"{UNWRITABLE}/v.png"], 2, "/proc", TAKE, max_s=30),
    # rig demo (arguments checked before the 20 s calibration)
    C("demo: one camera", ["demo", "--cameras", "1", "-o", "d"], 2, "cameras", max_s=15, point="6"),
    C("demo: --seconds -1", ["demo", "--seconds", "-1", "-o", "d"], 2, "seconds", max_s=15, fast=True, point="6"),
    C("demo: unwritable output", ["demo", "-o", f"{UNWRITABLE}/d"], 2, "/proc", max_s=15, fast=True),
    C("demo: into an earlier demo", ["demo", "-o", "."], 2, "earlier demo", TAKE, TAKE, max_s=15),
]


# ---- running -------------------------------------------------------------------------------------

@dataclass
class Result:
    case: Case
    code: Optional[int]
    seconds: float
    stderr: str
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def run_case(case: Case, fixtures: Path, work: Path, timeout: float = 300) -> Result:
    d = work / re.sub(r"[^\w]+", "-", case.name).strip("-")
    d.mkdir(parents=True)
    for rel in case.needs:
        src = fixtures / rel
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, d / rel)
    if case.prepare:
        case.prepare(d)
    before = checksums(d, case.protect)
    t0 = time.monotonic()
    try:
        proc = _rig(*case.argv, cwd=d, timeout=timeout)
        code, stderr = proc.returncode, proc.stderr
    except subprocess.TimeoutExpired as exc:
        code, stderr = None, (exc.stderr or b"").decode(errors="replace") if isinstance(exc.stderr, bytes) else (exc.stderr or "")
    seconds = time.monotonic() - t0
    r = Result(case, code, seconds, stderr)
    lines = stderr.strip().splitlines()
    if code is None:
        r.problems.append(f"still running after {timeout:g} s")
    elif code != case.code:
        r.problems.append(f"exit {code}, expected {case.code}")
    if "Traceback" in stderr:
        r.problems.append("traceback")
    if len(lines) != case.lines:
        r.problems.append(f"{len(lines)} stderr lines, expected {case.lines}")
    for line in lines:
        if not ERROR_LINE.match(line):
            r.problems.append(f"stderr line is not an error line: {line[:80]!r}")
            break
    if case.fragment and lines and not any(case.fragment in line for line in lines):
        r.problems.append(f"stderr does not mention {case.fragment!r}")
    if case.max_s is not None and seconds > case.max_s:
        r.problems.append(f"took {seconds:.1f} s (> {case.max_s:g} s: checked after the work?)")
    if case.check:
        r.problems += case.check(d, before)
    else:
        r.problems += _lost(before, checksums(d, case.protect))
    return r


def run_all(cases: list[Case], work: Path, progress: Callable[[Result], None] = lambda r: None) -> list[Result]:
    fixtures = build_fixtures(work)
    results = []
    for case in cases:
        r = run_case(case, fixtures, work / "cases")
        progress(r)
        results.append(r)
    return results


def table(results: list[Result]) -> str:
    out = ["| # | case | exit (expected) | stderr | s | result |", "|---|---|---|---|---|---|"]
    for i, r in enumerate(results, 1):
        first = r.stderr.strip().splitlines()[0] if r.stderr.strip() else ""
        first = first.replace("|", "\\|")
        if len(first) > 90:
            first = first[:87] + "..."
        verdict = "ok" if r.ok else "FAIL: " + "; ".join(r.problems).replace("|", "\\|")
        if not r.ok and r.case.point:
            verdict += f" (point {r.case.point})"
        out.append(f"| {i} | {r.case.name} | {r.code} ({r.case.code}) | `{first}` | {r.seconds:.1f} | {verdict} |")
    failed = sum(not r.ok for r in results)
    out.append("")
    out.append(f"{len(results) - failed} of {len(results)} cases pass, {failed} fail")
    return "\n".join(out)


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fast", action="store_true", help="only the quick subset the tests run")
    ap.add_argument("-k", metavar="TEXT", help="only the cases whose name contains TEXT")
    ap.add_argument("--keep", action="store_true", help="keep the work folder (printed)")
    args = ap.parse_args(argv)
    cases = [c for c in CASES if (not args.fast or c.fast) and (not args.k or args.k in c.name)]
    work = Path(tempfile.mkdtemp(prefix="rig-bad-inputs-"))
    try:
        results = run_all(cases, work, progress=lambda r: print(f"{'ok  ' if r.ok else 'FAIL'} {r.seconds:5.1f} s  {r.case.name}"
                                                                  + ("" if r.ok else f": {'; '.join(r.problems)}"),
                                                                  file=sys.stderr, flush=True))
    finally:
        if args.keep:
            print(f"work folder: {work}", file=sys.stderr)
        else:
            shutil.rmtree(work, ignore_errors=True)
    print(table(results))
    return 0 if all(r.ok for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
