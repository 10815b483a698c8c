"""Options go before or after positionals on every subcommand (issue 11 point 7: `rig record validate
--pixels DIR` and `rig record validate --json DIR` failed with "unrecognized arguments").

The parser tree is walked, so a subcommand added later is covered too; the journeys a user types
run through the real CLI on a recorded take, a rig config and a calibration."""
from __future__ import annotations

import argparse
import json

import pytest

from rig.commands import build_parser
from tests.record.test_record import rig_file
from tests.rig.cli_helpers import run_rig


def _leaves(parser: argparse.ArgumentParser, path=()):
    """(command words, parser) of every parser that runs a command."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
        return
    for name, child in subs[0].choices.items():
        yield from _leaves(child, path + (name,))


def _value(action: argparse.Action) -> list[str]:
    if action.choices:
        return [str(next(iter(action.choices)))]
    return ["1"] if action.type in (int, float) else ["x"]


def _with_positionals():
    for words, parser in _leaves(build_parser()):
        positionals = [a for a in parser._actions if not a.option_strings]
        if positionals:
            yield words, parser, positionals


CASES = list(_with_positionals())


def test_the_walk_finds_the_commands_with_positionals():
    found = {" ".join(w) for w, _, _ in CASES}
    assert {"record", "config check", "config init", "calibrate report", "calibrate export", "calibrate board",
            "model check"} <= found, found


@pytest.mark.parametrize("words,parser,positionals", CASES, ids=[" ".join(w) for w, _, _ in CASES])
def test_options_before_or_after_the_positionals_parse_the_same(words, parser, positionals):
    pos = [v for a in positionals for v in _value(a)]
    required = [v for a in parser._actions if a.option_strings and a.required
                for v in (a.option_strings[0], *([] if a.nargs == 0 else _value(a)))]
    flags = [a.option_strings[-1] for a in parser._actions
             if a.option_strings and a.nargs == 0 and not a.required and a.dest != "help"]
    assert flags, f"rig {' '.join(words)} has no flag to move around"
    forms = {
        "after": [*words, *pos, *required, *flags],
        "before": [*words, *flags, *required, *pos],
        "between": [*words, *pos[:1], *flags, *required, *pos[1:]],
    }
    parsed = {k: vars(build_parser().parse_args(v)) for k, v in forms.items()}
    for k, ns in parsed.items():
        ns.pop("func", None)
        assert all(ns[a.dest] is True for a in parser._actions if a.option_strings and a.option_strings[-1] in flags), (k, ns)
    assert parsed["before"] == parsed["after"] == parsed["between"]


def test_record_validate_and_repair_take_options_on_either_side(tmp_path):
    take = tmp_path / "take"
    assert run_rig("record", "-c", rig_file(tmp_path), "-o", take, "--sets", 3, "--json").returncode == 0
    outputs = []
    for argv in (["record", "validate", "--pixels", "--json", take], ["record", "validate", take, "--pixels", "--json"],
                 ["record", "validate", "--json", take, "--pixels"], ["record", "--json", "--pixels", "validate", take]):
        proc = run_rig(*argv)
        assert proc.returncode == 0 and proc.stderr == "", (argv, proc.stderr)
        outputs.append(json.loads(proc.stdout))
    assert all(o == outputs[0] for o in outputs) and outputs[0]["readable"] and outputs[0]["sets"] == 3
    for argv in (["record", "repair", "--json", take], ["record", "repair", take, "--json"]):
        proc = run_rig(*argv)
        assert proc.returncode == 0 and json.loads(proc.stdout)["kept_sets"] == 3, proc.stderr
    # still one line for what is really wrong
    proc = run_rig("record", "validate", "--json", take, "extra")
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == ["rig: error: unrecognized arguments: extra"]


def test_config_check_and_calibrate_report_take_options_on_either_side(tmp_path):
    from simulator.rig import arc_rig

    cfg = rig_file(tmp_path)
    calib = tmp_path / "calib.json"
    arc_rig([("left", 160, 90), ("right", 160, 90)]).save(calib)
    for a, b in ((["config", "check", "--json", cfg], ["config", "check", cfg, "--json"]),
                 (["calibrate", "report", "--json", calib], ["calibrate", "report", calib, "--json"])):
        first, second = run_rig(*a), run_rig(*b)
        assert first.returncode == second.returncode == 0, (first.stderr, second.stderr)
        assert json.loads(first.stdout) == json.loads(second.stdout)
    out = tmp_path / "colmap"
    proc = run_rig("calibrate", "export", "--format", "colmap", "-o", out, calib)
    assert proc.returncode == 0, proc.stderr
