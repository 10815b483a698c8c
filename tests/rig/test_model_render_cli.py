"""`rig model render` on a short simulator take: a PNG at a point of the arc and at a supervision
camera, an orbit video with one frame per set, and one-line errors (exit 2) for bad input.

The model is the session's exported tiny model of tests/inference/conftest.py (`_export`: one
export per test run, shared through the run's temp folder, also with the inference tests), not a
new export."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from simulator.takes import write_take
from tests.rig.cli_helpers import assert_one_line_error, run_rig

SIZE = (320, 180)  # the test-size model's output


@pytest.fixture(scope="module")
def model(tiny_onnx) -> Path:
    return tiny_onnx.path  # the session's test-size export (tests/conftest.py), made once per run


@pytest.fixture(scope="module")
def take(tmp_path_factory) -> Path:
    return Path(write_take(tmp_path_factory.mktemp("render") / "take", seed=321, seconds=0.3, fps=10, size=SIZE)["out"])


def _render(*args, timeout: float = 300):
    return run_rig("model", "render", *args, timeout=timeout)


def _image(path: Path):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return img


def test_renders_a_png_halfway_and_at_a_supervision_camera(model, take, tmp_path):
    half = tmp_path / "half.png"
    r = _render("--model", model, "--sequence", take, "--set", 1, "--view", 0.5, "-o", half, "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["output"] == str(half) and out["kind"] == "image" and out["sets"] == [1] and out["frames"] == 1
    assert out["sources"] == ["left", "right"] and out["size"] == list(SIZE)
    assert out["viewpoints"] == [{"t": 0.5, "yaw": 0.0, "pitch": 0.0, "zoom": 1.0}]
    assert out["model_ms_median"] > 0
    img = _image(half)
    assert img.shape == (SIZE[1], SIZE[0], 3) and img.std() > 1

    sup = tmp_path / "sup2.png"
    r = _render("--model", model, "--sequence", take, "--view", "sup2", "-o", sup)
    assert r.returncode == 0, r.stderr
    assert f"wrote {sup}" in r.stdout and "sup2" in r.stdout
    assert _image(sup).shape == (SIZE[1], SIZE[0], 3)
    assert not (_image(sup) == img).all()  # another viewpoint (and set), another image

    orbit = tmp_path / "orbit.png"  # orbit options on top of a view
    r = _render("--model", model, "--sequence", take, "--view", 0.5, "--yaw", 10, "--pitch", -5, "--zoom", 1.5, "-o", orbit, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["viewpoints"] == [{"t": 0.5, "yaw": 10.0, "pitch": -5.0, "zoom": 1.5}]


def test_orbit_video_has_one_frame_per_set(model, take, tmp_path):
    av = pytest.importorskip("av")
    video = tmp_path / "orbit.mp4"
    r = _render("--model", model, "--sequence", take, "--orbit", "--frames", 3, "-o", video, "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["kind"] == "video" and out["frames"] == 3 and out["sets"] == [0, 1, 2]
    assert [v["t"] for v in out["viewpoints"]] == [0.0, 0.5, 1.0]
    assert out["codec"] in ("libx264", "h264", "mpeg4") and out["fps"] == 10.0  # the take's rate
    with av.open(str(video)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == ("mpeg4" if out["codec"] == "mpeg4" else "h264")
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 3 and frames[0].shape == (SIZE[1], SIZE[0], 3)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left behind

    # default --frames: every set from --set to the end; text mode names the codec
    rest = tmp_path / "rest.mp4"
    r = _render("--model", model, "--sequence", take, "--orbit", "--set", 1, "--fps", 5, "-o", rest)
    assert r.returncode == 0, r.stderr
    assert "2 frames at 5 fps" in r.stdout and ("H.264" in r.stdout or "MPEG-4" in r.stdout)
    with av.open(str(rest)) as container:
        assert sum(1 for _ in container.decode(video=0)) == 2


def test_bad_input_is_one_line_and_exit_2(model, take, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    png = tmp_path / "v.png"
    cases = [
        (["--view", "sup9", "-o", png], "no camera 'sup9'"),
        (["--view", "1.5", "-o", png], "between 0 and 1"),
        (["--view", "nan", "-o", png], "finite"),
        (["--set", 3, "--view", 0.5, "-o", png], "--set 3: out of range"),
        (["--set", -1, "--view", 0.5, "-o", png], "--set must be 0 or more"),
        (["--view", 0.5, "-o", blocker / "v.png"], "is a file, not a folder"),
        (["--view", 0.5, "-o", tmp_path], "is a folder"),
        (["--view", 0.5, "-o", tmp_path / "v.mp4"], "must end in .png"),
        (["--orbit", "-o", png], "must end in .mp4"),
        (["--orbit", "--set", 1, "--frames", 3, "-o", tmp_path / "o.mp4"], "has only 2 sets from there"),
        (["--view", 0.5, "--frames", 3, "-o", png], "--frames is for --orbit"),
        (["--view", 0.5, "--zoom", 1e9, "-o", png], "zoom must be between"),
    ]
    for args, fragment in cases:
        r = _render("--model", model, "--sequence", take, *args, timeout=120)
        assert_one_line_error(r, fragment)
    assert not png.exists()
    r = _render("--model", model, "--sequence", tmp_path / "no-such-take", "--view", 0.5, "-o", png)
    assert_one_line_error(r, "no-such-take", "no such sequence folder")
    r = _render("--model", tmp_path / "missing.onnx", "--sequence", take, "--view", 0.5, "-o", png)
    assert_one_line_error(r, "missing.onnx")
    r = _render("--sequence", take, "-o", png)  # neither --view nor --orbit
    assert_one_line_error(r, "--view")


def test_without_a_shipped_model_it_asks_for_model(take, tmp_path, monkeypatch, capsys):
    import inference.runtime.shipped as shipped
    from rig.cli import main

    monkeypatch.setattr(shipped, "MODELS", tmp_path / "no-models")
    rc = main(["model", "render", "--sequence", str(take), "--view", "0.5", "-o", str(tmp_path / "v.png")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--model" in err[0], err
