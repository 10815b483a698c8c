"""`rig/commands/` parses arguments, calls the function of each step and prints what it gives: no
command loops over frames, frame sets, views or takes. That work lives in the package of its step
(rig.capture, rig.storage, rig.render, rig.demo, inference, calibration), where it can be tested
and reused without a command line.

Read from the source: a `for` statement or comprehension in rig/commands/*.py whose iterable names
such a collection (a name or attribute ending in frames, sets, views, viewpoints, positions,
takes, sequences, samples, picks or images, also inside enumerate/zip/sorted/range/...), or a
`while` whose condition names one, is reported. A literal list of (option, value) pairs is a check
of the options. Iterating a mapping's `.items()`, `.keys()` or `.values()` goes over its keys (the
per-camera counts a command prints), and iterating what a function returns (the lines of a
report) is printing: neither is reported. The last tests plant such loops to show the check fails.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
COMMANDS = REPO / "rig" / "commands"
WORK = re.compile(r"(^|_)(frames|sets|views|viewpoints|positions|takes|sequences|samples|picks|images)$")
WRAPPERS = {"enumerate", "zip", "sorted", "reversed", "list", "tuple", "set", "range", "len", "iter", "min", "max"}
MAPPING = {"items", "keys", "values"}


def _collections(node: ast.expr):
    """The names of the collections an iterable goes over."""
    if isinstance(node, ast.Call):
        f = node.func
        if isinstance(f, ast.Name) and f.id in WRAPPERS:
            for arg in node.args:
                yield from _collections(arg)
        return  # a mapping's keys, or what a function returns
    if isinstance(node, ast.Name):
        yield node.id
    elif isinstance(node, ast.Attribute):
        yield node.attr
    elif isinstance(node, ast.Subscript):
        yield from _collections(node.value)
    elif isinstance(node, (ast.Tuple, ast.List)):
        for elt in node.elts:
            named_option = isinstance(elt, ast.Tuple) and elt.elts and isinstance(elt.elts[0], ast.Constant) \
                and isinstance(elt.elts[0].value, str)
            if not named_option:  # ("--frames", args.frames): a check of the options, not a loop over frames
                yield from _collections(elt)


def work_loops(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    found: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.For, ast.AsyncFor)):
            iterable, line = node.iter, node.lineno
        elif isinstance(node, ast.comprehension):
            iterable, line = node.iter, node.iter.lineno
        elif isinstance(node, ast.While):  # `while len(kept) < views`: a loop until enough views
            iterable, line = node.test, node.lineno
            names = [n.id if isinstance(n, ast.Name) else n.attr for n in ast.walk(node.test) if isinstance(n, (ast.Name, ast.Attribute))]
            names = [n for n in names if WORK.search(n.lower())]
            if names:
                found.append(f"{path.relative_to(path.parents[2])}:{line}: loops over {', '.join(names)} ({ast.unparse(iterable)})")
            continue
        else:
            continue
        names = [n for n in _collections(iterable) if WORK.search(n.lower())]
        if names:
            found.append(f"{path.relative_to(path.parents[2])}:{line}: loops over {', '.join(names)} ({ast.unparse(iterable)})")
    return sorted(found, key=lambda f: int(f.split(":")[1]))


# Loops still in a command, by file, with where they belong; each must still be there (so the entry
# goes when the loop moves), and nothing else may be.
NOT_YET_MOVED: dict[str, tuple[str, str]] = {}


def test_no_command_loops_over_frames_sets_views_or_takes():
    found = [line for path in sorted(COMMANDS.glob("*.py")) for line in work_loops(path)]
    pending = {f for f in found if any(f.startswith(name + ":") and what in f for name, (what, _) in NOT_YET_MOVED.items())}
    assert sorted(set(found) - pending) == []
    for name, (what, where) in NOT_YET_MOVED.items():
        assert any(f.startswith(name + ":") and what in f for f in pending), f"{name} no longer {what}: remove it from NOT_YET_MOVED"


# ---- the check fails on such a loop ----------------------------------------------------------------

def _command(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "rig" / "commands" / "planted.py"
    path.parent.mkdir(parents=True)
    path.write_text(text)
    return path


def test_a_loop_over_a_takes_sets_is_caught(tmp_path):
    path = _command(tmp_path, "def cmd(seq):\n    for p in seq.complete_sets(['left']):\n        pass\n"
                               "    for p in range(len(seq.positions)):\n        pass\n")
    found = work_loops(path)
    assert len(found) == 1 and "planted.py:4: loops over positions" in found[0]  # a function's result is not read


def test_loops_in_comprehensions_and_behind_wrappers_are_caught(tmp_path):
    path = _command(tmp_path, "def cmd(data, views, viewpoints):\n"
                               "    roots = [s.root for s in data.sequences]\n"
                               "    for i, (v, vp) in enumerate(zip(views, viewpoints)):\n        pass\n")
    found = work_loops(path)
    assert [f.split(": ", 1)[1].split(" (")[0] for f in found] == ["loops over sequences", "loops over views, viewpoints"]


def test_a_while_loop_until_enough_views_is_caught(tmp_path):
    path = _command(tmp_path, "def cmd(views):\n    kept = []\n    while len(kept) < views:\n        kept.append(1)\n"
                               "    for flag, value in ((\"--views\", views), (\"--frames\", 3)):\n        pass\n")
    found = work_loops(path)
    assert len(found) == 1 and "planted.py:3: loops over views" in found[0]


def test_printing_a_mapping_per_camera_or_a_reports_lines_is_not_a_loop_over_frames(tmp_path):
    path = _command(tmp_path, "def cmd(result, report):\n"
                               "    for name, n in result.frames.items():\n        print(name, n)\n"
                               "    for line in report_lines(report):\n        print(line)\n")
    assert work_loops(path) == []
