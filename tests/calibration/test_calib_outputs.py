"""Where `rig calibrate` writes: an output that cannot be written is refused before the work (one
line, exit 2), an existing calibration is not replaced without --force, and a solve whose file
cannot be written after all is kept beside (never lost)."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.boards import CharucoSpec
from calibration.camera import RigCalibration, intrinsics_from_fov
from calibration.geometry import rodrigues
from calibration.synthetic import arc_rig, warp_board
from rig.cli import main
from rig.calibrate.run import save_keeping

REPO = Path(__file__).resolve().parents[2]
UNWRITABLE = "/proc/rig-calibrate-test"  # nobody, root included, can create anything under /proc
BOARD = CharucoSpec(7, 5, 0.03, 0.022)
BOARD_TOML = 'type = "charuco"\nsquares_x = 7\nsquares_y = 5\nsquare_size = 0.03\nmarker_size = 0.022\ndictionary = "DICT_5X5_100"\n'


def _quads() -> list[np.ndarray]:
    """One camera's views of the board: its square grid's corners (clockwise from the top-left) as a
    pinhole camera 0.45 m away sees them at varied tilts, so that one lens explains every view."""
    K = intrinsics_from_fov(640, 480, 60.0)
    w, h = BOARD.size_m
    grid = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]]) - [w / 2, h / 2, 0]
    quads = []
    for rx, ry, rz, dx, dy in [(0.3, 0, 0, 0, 0), (-0.35, 0.1, 0.1, 0.03, -0.02), (0, 0.4, -0.05, -0.03, 0.02),
                               (0.1, -0.4, 0.15, 0.02, 0.03), (0.45, 0.3, 0, -0.02, -0.03), (-0.2, -0.3, -0.1, 0.0, 0.02)]:
        pts = grid @ rodrigues(np.array([rx, ry, rz])).T + [dx, dy, 0.45]
        uv = pts[:, :2] / pts[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
        quads.append(uv.astype(np.float32))
    return quads


QUADS = _quads()


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


@pytest.fixture(scope="module")
def unusable_views(views) -> Path:
    """Views no lens explains: DIR/shifted (a stereo pair whose right images are filed one instant
    late, as cameras counting from different numbers leave them), DIR/bent (one camera's board under
    a wave no lens makes) beside DIR/bent/good (the same views unbent)."""
    root = views / "unusable"
    imgs = [cv2.imread(str(p)) for p in sorted((views / "imgs" / "cam").glob("*.png"))]
    yy, xx = np.mgrid[0 : imgs[0].shape[0], 0 : imgs[0].shape[1]].astype(np.float32)
    for i, img in enumerate(imgs):
        for folder, image in (("shifted/left", img), ("shifted/right", imgs[(i + 1) % len(imgs)]), ("bent/good", img),
                              ("bent/wavy", cv2.remap(img, xx + 12 * np.sin(yy / 25 + i), yy + 12 * np.sin(xx / 30 + 2 * i),
                                                      cv2.INTER_LINEAR, borderValue=(255, 255, 255)))):
            (root / folder).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / folder / f"{i:04d}.png"), image)
    return root


def test_a_rig_no_lens_explains_is_not_written_nor_replaces_a_calibration(views, unusable_views, tmp_path):
    """Each camera alone fits, the pair does not (its views are of different instants): the pairing
    check names the camera out of step; with its pairing kept as named (`--offset right=0`) the joint
    solve fits no lens: one line that says so, exit 2, the calibration already there kept, and no
    numpy warning on the way."""
    calib = tmp_path / "calib.json"
    arc_rig(2).save(calib)
    before = calib.read_text()
    proc = _rig("calibrate", "run", "--images", unusable_views / "shifted", "--board", views / "board.toml", "-o", calib, "--force", cwd=tmp_path)
    _one_line(proc, 2, "right's images fit best one instant later (", "--offset right=+1")
    assert calib.read_text() == before
    proc = _rig("calibrate", "run", "--images", unusable_views / "shifted", "--board", views / "board.toml", "-o", calib, "--force",
                "--offset", "right=0", cwd=tmp_path)
    line = _one_line(proc, 2, "unusable", "'left'", "'right'", "nothing was written", "share a name or number")
    assert "RuntimeWarning" not in proc.stderr, line
    assert calib.read_text() == before and "verdict: left unusable, right unusable" in proc.stdout  # the report says why
    proc = _rig("calibrate", "run", "--images", unusable_views / "shifted", "--board", views / "board.toml", "-o", "new.json", "--json",
                "--offset", "right=0", cwd=tmp_path)
    assert proc.returncode == 2 and json.loads(proc.stdout)["exit_code"] == 2 and not (tmp_path / "new.json").exists()


def test_intrinsics_list_a_camera_no_lens_explains_as_failed(views, unusable_views, tmp_path):
    proc = _rig("calibrate", "intrinsics", "--images", unusable_views / "bent", "--board", views / "board.toml", "-o", "lenses.json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "wavy: unusable: camera 'wavy': reprojection RMS" in proc.stdout and "the corners fit no lens model" in proc.stdout
    doc = json.loads((tmp_path / "lenses.json").read_text())
    assert list(doc["cameras"]) == ["good"] and list(doc["failed"]) == ["wavy"]
    shutil.rmtree(unusable_views / "bent" / "good")
    try:
        proc = _rig("calibrate", "intrinsics", "--images", unusable_views / "bent", "--board", views / "board.toml", "-o", "none.json", cwd=tmp_path)
        _one_line(proc, 2, "no camera could be calibrated", "the corners fit no lens model")
        assert not (tmp_path / "none.json").exists()
    finally:
        shutil.copytree(views / "imgs" / "cam", unusable_views / "bent" / "good")
