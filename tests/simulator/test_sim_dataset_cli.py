"""`rig sim dataset`: simulated takes rendered offline, read back as recorded takes."""
from __future__ import annotations

import json

from rig.cli import main
from rig.storage.dataset import Sequence
from rig.storage.validate import validate


def test_rig_sim_dataset_writes_takes_the_reader_and_validate_accept(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["sim", "dataset", "-o", str(out), "--takes", "2", "--seconds", "0.1", "--size", "160x90", "--seed", "3", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["take_seeds"] == [3000, 3001] and summary["sets_per_take"] == 3
    for name in summary["takes"]:
        assert validate(out / name).readable
        take = Sequence(out / name)
        sample = next(iter(take.samples()))
        assert sorted(sample.images) == ["left", "right", "sup1", "sup2", "sup3", "sup4"]
        assert sample.images["left"].shape == (90, 160, 3)


def test_rig_sim_dataset_refuses_bad_input_in_one_line(tmp_path, capsys):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("keep me")
    assert main(["sim", "dataset", "-o", str(tmp_path / "full"), "--takes", "1", "--seconds", "1"]) == 2
    assert main(["sim", "dataset", "-o", str(tmp_path / "new"), "--takes", "1", "--seconds", "1", "--size", "big"]) == 2
    assert main(["sim", "dataset", "-o", str(tmp_path / "new"), "--takes", "0", "--seconds", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("rig: error: ") for line in err)
    assert (tmp_path / "full" / "x").read_text() == "keep me"
