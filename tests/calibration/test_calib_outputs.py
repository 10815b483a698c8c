"""Where `rig calibrate` writes: an output that cannot be written is refused before the work (one
line, exit 2), an existing calibration is not replaced without --force, and a solve whose file
cannot be written after all is kept beside (never lost)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from calibration.boards import CharucoSpec
from calibration.camera import RigCalibration
from calibration.synthetic import arc_rig, warp_board
from rig.cli import main
from rig.commands.calibrate import save_keeping

REPO = Path(__file__).resolve().parents[2]
UNWRITABLE = "/proc/rig-calibrate-test"  # nobody, root included, can create anything under /proc
BOARD = CharucoSpec(7, 5, 0.03, 0.022)
BOARD_TOML = 'type = "charuco"\nsquares_x = 7\nsquares_y = 5\nsquare_size = 0.03\nmarker_size = 0.022\ndictionary = "DICT_5X5_100"\n'
# One camera's views of the board: quads (clockwise from the grid's top-left) seen at varied tilts.
QUADS = [
    [[120, 100], [500, 120], [480, 380], [130, 360]],
    [[100, 80], [520, 60], [540, 400], [90, 380]],
    [[160, 120], [460, 90], [500, 420], [140, 390]],
    [[80, 140], [420, 100], [440, 360], [100, 420]],
    [[200, 60], [560, 110], [520, 360], [180, 420]],
    [[140, 90], [520, 100], [460, 400], [190, 380]],
]


def _rig(*args, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig", *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=300)


def _one_line(proc, code: int, *fragments: str) -> str:
    assert proc.returncode == code, (proc.returncode, proc.stdout[-2000:], proc.stderr)
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rig"), proc.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def views(tmp_path_factory) -> Path:
    """DIR/cam/NNNN.png: six views of the board for one camera, and the board file."""
    root = tmp_path_factory.mktemp("views")
    (root / "imgs" / "cam").mkdir(parents=True)
    for i, quad in enumerate(QUADS):
        img, _ = warp_board(BOARD, quad, size=(640, 480), ppm=4000)
        cv2.imwrite(str(root / "imgs" / "cam" / f"{i:04d}.png"), img)
    (root / "board.toml").write_text(BOARD_TOML)
    return root


def test_run_into_an_unwritable_output_is_refused_before_the_solve(views):
    proc = _rig("calibrate", "run", "--images", "imgs", "--board", "board.toml", "-o", f"{UNWRITABLE}/calib.json", cwd=views)
    _one_line(proc, 2, UNWRITABLE, "cannot write")
    assert "detecting" not in proc.stderr and proc.stdout == ""  # nothing was solved only to be lost


def test_run_does_not_replace_an_existing_calibration_without_force(views, tmp_path):
    calib = tmp_path / "calib.json"
    calib.write_text("keep me\n")
    proc = _rig("calibrate", "run", "--images", views / "imgs", "--board", views / "board.toml", "-o", calib, cwd=tmp_path)
    _one_line(proc, 2, str(calib), "already exists")
    assert calib.read_text() == "keep me\n"
    proc = _rig("calibrate", "run", "--images", views / "imgs", "--board", views / "board.toml", "-o", calib, "--force", "--json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["output"] == str(calib) and RigCalibration.load(calib).names == ["cam"]


def test_a_solve_that_cannot_be_written_is_kept_beside(tmp_path, monkeypatch):
    """The write can still fail after the check (a disk that filled up during the solve): the result
    goes to NAME.unsaved-TIME in the working folder, and the caller is told where."""
    monkeypatch.chdir(tmp_path)
    rig = arc_rig(2)
    written, why = save_keeping(rig, Path(UNWRITABLE) / "calib.json")
    assert why and written is not None and written.parent == tmp_path and written.name.startswith("calib.json.unsaved-")
    assert RigCalibration.load(written).to_dict()["cameras"] == rig.to_dict()["cameras"]
    written, why = save_keeping(rig, tmp_path / "ok.json")
    assert (written, why) == (tmp_path / "ok.json", None)


def test_board_into_an_unwritable_output(tmp_path):
    (tmp_path / "board.toml").write_text(BOARD_TOML)
    _one_line(_rig("calibrate", "board", "board.toml", "-o", f"{UNWRITABLE}/b.png", cwd=tmp_path), 2, UNWRITABLE)


@pytest.mark.parametrize("fmt", ["opencv", "colmap", "easymocap"])
def test_export_into_an_unwritable_output_or_onto_a_file(tmp_path, fmt):
    arc_rig(2).save(tmp_path / "calib.json")
    _one_line(_rig("calibrate", "export", "calib.json", "--format", fmt, "-o", f"{UNWRITABLE}/x", cwd=tmp_path), 2, UNWRITABLE)
    (tmp_path / "notes.txt").write_text("mine\n")
    _one_line(_rig("calibrate", "export", "calib.json", "--format", fmt, "-o", "notes.txt", cwd=tmp_path), 2, "notes.txt")
    assert (tmp_path / "notes.txt").read_text() == "mine\n"


def test_run_rejects_a_non_positive_outlier_limit(views, capsys):
    rc = main(["calibrate", "run", "--images", str(views / "imgs"), "--board", str(views / "board.toml"), "-o", "x.json", "--outlier-px", "0"])
    assert rc == 2 and "--outlier-px" in capsys.readouterr().err
