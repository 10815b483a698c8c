"""Commands that write never overwrite or append to what is recorded (issue 11 point 2: `rig grab -o
DIR` into an earlier grab appended to its frames.jsonl and overwrote 000000.png).

Recorded frames (grab, record) go only into a new or empty folder; a snapshot, which can be made
again, writes into a folder with files only with --force; `model export` replaces an earlier .onnx
export (atomically) but nothing else, and refuses before the slow part."""
from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import pytest

from rig.errors import StorageError
from rig.storage.recorder import SequenceWriter
from tests.record.test_record import rig_file
from tests.record.test_sequence import CAMS
from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig


def checksums(folder) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_grab_into_an_earlier_grab_is_refused_and_changes_nothing(tmp_path):
    cfg = rig_file(tmp_path)
    out = tmp_path / "grab"
    assert run_rig("grab", "-c", cfg, "-n", 2, "-o", out, "--json").returncode == 0
    before = checksums(out)
    assert "frames.jsonl" in before and "left/000000.png" in before
    assert_one_line_error(run_rig("grab", "-c", cfg, "-n", 2, "-o", out), str(out), "not empty", "nothing was overwritten")
    assert checksums(out) == before
    # a folder with anything else in it is refused too; an empty one is fine
    other = tmp_path / "notes"
    other.mkdir()
    (other / "readme.txt").write_text("mine\n")
    assert_one_line_error(run_rig("grab", "-c", cfg, "-n", 1, "-o", other, "--json"), "not empty")
    assert checksums(other) == {"readme.txt": hashlib.sha256(b"mine\n").hexdigest()}
    empty = tmp_path / "empty"
    empty.mkdir()
    assert run_rig("grab", "-c", cfg, "-n", 1, "-o", empty, "--json").returncode == 0


def test_record_into_an_occupied_folder_is_refused_and_changes_nothing(tmp_path):
    cfg = rig_file(tmp_path)
    take = tmp_path / "take"
    assert run_rig("record", "-c", cfg, "-o", take, "--sets", 2, "--json").returncode == 0
    before = checksums(take)
    assert_one_line_error(run_rig("record", "-c", cfg, "-o", take, "--sets", 2), str(take), "nothing was overwritten")
    assert checksums(take) == before
    # the folder of a grab (or anything) would get a take's files mixed into it
    other = tmp_path / "notes"
    other.mkdir()
    (other / "rig.toml").write_text("# my own notes\n")
    assert_one_line_error(run_rig("record", "-c", cfg, "-o", other, "--sets", 2), "not empty")
    assert sorted(p.name for p in other.iterdir()) == ["rig.toml"] and (other / "rig.toml").read_text() == "# my own notes\n"


def test_the_sequence_writer_itself_never_writes_over_a_take_file(tmp_path):
    folder = tmp_path / "seq"
    folder.mkdir()
    (folder / "rig.toml").write_text("# not ours\n")
    config = tmp_path / "other.toml"
    config.write_text("# the rig being recorded\n")
    with pytest.raises(StorageError, match="already holds rig.toml"):
        SequenceWriter(folder, CAMS, config_file=config)
    assert sorted(p.name for p in folder.iterdir()) == ["rig.toml"] and (folder / "rig.toml").read_text() == "# not ours\n"


def test_sim_snapshot_into_a_folder_with_files_needs_force(tmp_path):
    cfg = rig_file(tmp_path)
    take = tmp_path / "take"
    assert run_rig("record", "-c", cfg, "-o", take, "--sets", 2, "--json").returncode == 0
    before = checksums(take)
    assert_one_line_error(run_rig("sim", "snapshot", "-c", cfg, "-t", 0, "-o", take), str(take), "--force")
    assert checksums(take) == before
    snap = tmp_path / "snap"
    assert run_rig("sim", "snapshot", "-c", cfg, "-t", 0, "-o", snap, "--json").returncode == 0
    assert_one_line_error(run_rig("sim", "snapshot", "-c", cfg, "-t", 1, "-o", snap), "--force")
    proc = run_rig("sim", "snapshot", "-c", cfg, "-t", 1, "-o", snap, "--force", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads((snap / "cameras.json").read_text())["time_s"] == 1.0  # the earlier snapshot replaced


def _export_in_process(tmp_path, *argv) -> tuple[int, bool, str]:
    """(exit status, whether torch was loaded, stderr) of `rig model export ...` in a fresh interpreter."""
    code = ("import sys; from rig.cli import main; rc = main(sys.argv[1:]); "
            "print(rc, 'torch' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code, "model", "export", *map(str, argv)], capture_output=True, text=True,
                          cwd=REPO, timeout=120)
    rc, torch_loaded = proc.stdout.split()
    return int(rc), torch_loaded == "True", proc.stderr


def test_model_export_refuses_to_replace_anything_but_a_model_before_loading_torch(tmp_path):
    config = tmp_path / "rig.toml"
    config.write_text("[rig]\nname = 'keep me'\n")
    rc, torch_loaded, err = _export_in_process(tmp_path, "--size", "test", "-o", config)
    assert rc == 2 and not torch_loaded and err.count("\n") == 1 and "must end in .onnx" in err
    assert config.read_text() == "[rig]\nname = 'keep me'\n"
    weights = tmp_path / "trained.onnx"
    weights.write_bytes(b"weights that took a week")
    rc, torch_loaded, err = _export_in_process(tmp_path, "--checkpoint", weights, "-o", weights)
    assert rc == 2 and not torch_loaded and "is the checkpoint being exported" in err
    assert weights.read_bytes() == b"weights that took a week"
    rc, torch_loaded, err = _export_in_process(tmp_path, "--size", "test", "-o", "/proc/rig-test/m.onnx")
    assert rc == 2 and not torch_loaded and "/proc" in err
