"""Bad input to the model-side commands (rig model, rig train): one line on stderr, exit 2, nothing
written. Found by trying them as a user would (trial-model)."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig

LIVE = REPO / "models" / "splat-sap-live.onnx"
pytestmark = pytest.mark.slow  # an export among them: a minute in all, started early


def _copy_model(dst: Path) -> Path:
    """The shipped live model and its parts and data file, copied together."""
    for f in LIVE.resolve().parent.glob(LIVE.name.replace(".onnx", ".*")):
        shutil.copy(f, dst / f.name)
    return dst / LIVE.name


def test_model_with_its_data_file_cut_short_is_one_line(tmp_path):
    # ONNX Runtime printed its own multi-line error log before the one line
    model = _copy_model(tmp_path)
    (data,) = tmp_path.glob(LIVE.name + ".*.data")
    with open(data, "r+b") as f:
        f.truncate(data.stat().st_size // 2)
    proc = run_rig("model", "check", model)
    assert_one_line_error(proc, str(model), data.name, "shorter than the model needs")


@pytest.fixture(scope="module")
def take(tmp_path_factory) -> Path:
    from simulator.takes import write_take

    return Path(write_take(tmp_path_factory.mktemp("trial") / "take", seed=5, seconds=0.2, fps=10, size=(320, 180))["out"])


@pytest.fixture
def empty_take(take, tmp_path) -> Path:
    """A take's sequence.json with no frame set recorded."""
    empty = tmp_path / "empty-take"
    empty.mkdir()
    shutil.copy(take / "sequence.json", empty / "sequence.json")
    (empty / "index.jsonl").write_text("")
    return empty


def test_render_into_a_folder_not_made_yet(take, tmp_path):
    # the output was checked writable up front, then the image write failed after the render (exit 1)
    out = tmp_path / "new" / "deeper" / "view.png"
    proc = run_rig("model", "render", "--model", LIVE, "--sequence", take, "--set", "0", "--view", "0.5", "-o", out, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert out.is_file()


def test_eval_of_an_empty_take_is_refused(empty_take):
    # printed an empty table and exited 0
    proc = run_rig("model", "eval", "--model", REPO / "models" / "splat-sap-preview.pt", "--sequence", empty_take)
    assert_one_line_error(proc, str(empty_take), "no frame set to evaluate")


@pytest.mark.parametrize("command", ["train", "eval"])
def test_a_file_given_as_the_sequence(command, tmp_path):
    # "rig.toml/sequence.json: Not a directory (the work stopped here)", exit 1
    f = tmp_path / "rig.toml"
    f.write_text("[rig]\n")
    if command == "train":
        proc = run_rig("train", f, "-o", tmp_path / "run", "--size", "test")
    else:
        proc = run_rig("model", "eval", "--model", REPO / "models" / "splat-sap-preview.pt", "--sequence", f)
    assert_one_line_error(proc, str(f), "is a file, not a sequence folder")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("damage", ["torn", "missing"])
def test_train_on_a_damaged_take_is_refused_before_anything_is_written(take, tmp_path, damage):
    # stopped with exit 2 at the first batch that read the frame, leaving a run folder with
    # metrics and no checkpoint (which a second try then refused as a run that kept nothing)
    bad = tmp_path / "bad-take"
    shutil.copytree(take, bad)
    frame = sorted((bad / "frames" / "left").iterdir())[1]
    if damage == "torn":
        with open(frame, "r+b") as f:
            f.truncate(100)
    else:
        frame.unlink()
    out = tmp_path / "run"
    proc = run_rig("train", bad, "-o", out, "--size", "test", "--stage1-steps", "2", "--stage2-steps", "0", "--batch", "1")
    assert_one_line_error(proc, str(bad), frame.name, "damaged", "rig record repair")
    assert not out.exists()


@pytest.mark.parametrize("name", ["model.onnx", "model.view.onnx"])
def test_export_does_not_replace_an_onnx_named_file_that_is_no_export(tmp_path, name):
    # `-o model.onnx` replaced any file of that name (or of its parts' names), exports or not
    kept = tmp_path / name
    kept.write_bytes(b"a file the user keeps")
    proc = run_rig("model", "export", "--backbone", "stereo", "--size", "test", "-o", tmp_path / "model.onnx")
    assert_one_line_error(proc, str(kept), "not a model rig model export wrote", "nothing was overwritten")
    assert kept.read_bytes() == b"a file the user keeps"
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_export_replaces_an_earlier_export(tmp_path):
    out = _copy_model(tmp_path)  # an earlier export and its parts
    # (any backbone replaces it alike: the oracle's, without a network, exports in the least time)
    proc = run_rig("model", "export", "--backbone", "oracle", "--size", "test", "-o", out, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "wrote" in proc.stdout


def test_check_refuses_a_tolerance_that_is_no_bound():
    # --tolerance -1 ran the whole comparison and reported MISMATCH, exit 1
    for value in ("-1", "nan"):
        assert_one_line_error(run_rig("model", "check", LIVE, "--tolerance", value), "--tolerance")


@pytest.mark.parametrize("command", ["render", "live"])
def test_a_checkpoint_given_as_the_onnx_model(command, take, tmp_path):
    # render: "ONNX Runtime cannot load it (... INVALID_PROTOBUF ...)"; live: "model.stage1.onnx: no such file"
    ckpt = REPO / "models" / "splat-sap-preview.pt"
    if command == "render":
        proc = run_rig("model", "render", "--model", ckpt, "--sequence", take, "--set", "0", "--view", "0.5", "-o", tmp_path / "v.png")
    else:
        from rig.config import dump_config, parse_config
        from rig.sim.rig_config import sim_rig_config

        cfg = tmp_path / "rig.toml"
        cfg.write_text(dump_config(parse_config(sim_rig_config(2, 320, 180, fps=15.0))))
        proc = run_rig("live", "-c", cfg, "--model", ckpt, "--port", "0", "--seconds", "1")
    assert_one_line_error(proc, str(ckpt), "a checkpoint, not an ONNX model", "rig model export --checkpoint")
