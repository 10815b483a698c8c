"""`rig calibrate export` writes the images a nerfstudio (or COLMAP) folder points at: one set of a
recorded take (--take, --set), or a calibration view (--images, --view; by default the views the
calibration was made from), so that `ns-train` can start from the folder."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from rig.cli import main
from rig.storage.dataset import Sequence

pytestmark = pytest.mark.slow


def _cli(argv, capsys) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.fixture(scope="module")
def rig_folder(tmp_path_factory) -> Path:
    """A small simulated rig, a 3-set take of it, its exact calibration, and two calibration views."""
    from simulator.rig import arc_rig

    d = tmp_path_factory.mktemp("export-images")
    assert main(["config", "init", "--sim", "--width", "160", "--height", "96", str(d / "rig.toml")]) == 0
    assert main(["record", "-c", str(d / "rig.toml"), "-o", str(d / "take"), "--sets", "3"]) == 0
    arc_rig([("left", 160, 96), ("right", 160, 96)]).save(d / "calib.json")
    for cam, shade in (("left", 70), ("right", 140)):
        (d / "views" / cam).mkdir(parents=True)
        for view in ("0000", "0001"):
            cv2.imwrite(str(d / "views" / cam / f"{view}.png"), np.full((96, 160), shade + int(view), np.uint8))
    return d


def test_nerfstudio_from_a_take_writes_that_sets_frames(rig_folder, tmp_path, capsys):
    out = tmp_path / "ns"
    rc, text, err = _cli(["calibrate", "export", rig_folder / "calib.json", "--format", "nerfstudio", "-o", out,
                          "--take", rig_folder / "take", "--set", 1, "--json"], capsys)
    assert rc == 0, err
    files = json.loads(text)["files"]
    data = json.loads((out / "transforms.json").read_text())
    sample = next(s for s in Sequence(rig_folder / "take").samples(with_depth=False) if s.set == 1)
    for frame in data["frames"]:
        path = out / frame["file_path"]
        assert str(path) in files
        name = Path(frame["file_path"]).stem
        img = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        assert img.shape == (frame["h"], frame["w"], 3) and np.array_equal(img, sample.images[name])


def test_nerfstudio_from_calibration_views_named_or_by_default(rig_folder, tmp_path, capsys):
    rc, _, err = _cli(["calibrate", "export", rig_folder / "calib.json", "--format", "nerfstudio", "-o", tmp_path / "a",
                       "--images", rig_folder / "views", "--view", "0001"], capsys)
    assert rc == 0, err
    assert cv2.imread(str(tmp_path / "a" / "images" / "right.png"), cv2.IMREAD_UNCHANGED)[0, 0] == 141
    # A calibration made by `rig calibrate run` remembers its views: they are the default.
    calib = json.loads((rig_folder / "calib.json").read_text())
    calib["images"] = str(rig_folder / "views")
    (tmp_path / "calib.json").write_text(json.dumps(calib))
    rc, _, err = _cli(["calibrate", "export", tmp_path / "calib.json", "--format", "nerfstudio", "-o", tmp_path / "b"], capsys)
    assert rc == 0, err
    assert cv2.imread(str(tmp_path / "b" / "images" / "left.png"), cv2.IMREAD_UNCHANGED)[0, 0] == 70


def test_colmap_with_a_take_gets_the_images_its_model_names(rig_folder, tmp_path, capsys):
    rc, _, err = _cli(["calibrate", "export", rig_folder / "calib.json", "--format", "colmap", "-o", tmp_path, "--take", rig_folder / "take"], capsys)
    assert rc == 0, err
    names = [line.split()[-1] for line in (tmp_path / "images.txt").read_text().splitlines() if line and not line.startswith("#")]
    assert names == ["left.png", "right.png"] and all((tmp_path / "images" / n).is_file() for n in names)


@pytest.mark.parametrize("extra, fragment", [
    ([], "needs one image per camera"),  # no source, and the calibration names no views
    (["--take", "TAKE", "--set", "99"], "no set 99"),
    (["--images", "VIEWS", "--view", "0009"], "no view '0009'"),
    (["--set", "1"], "--take"),
])
def test_nerfstudio_without_usable_images_is_refused_before_writing(rig_folder, tmp_path, capsys, extra, fragment):
    extra = [str(rig_folder / "take") if a == "TAKE" else str(rig_folder / "views") if a == "VIEWS" else a for a in extra]
    rc, _, err = _cli(["calibrate", "export", rig_folder / "calib.json", "--format", "nerfstudio", "-o", tmp_path / "out", *extra], capsys)
    assert rc == 2 and err.count("\n") == 1 and fragment in err, err
    assert not (tmp_path / "out").exists()


def test_image_sources_are_refused_for_formats_without_images(rig_folder, tmp_path, capsys):
    rc, _, err = _cli(["calibrate", "export", rig_folder / "calib.json", "--format", "opencv", "-o", tmp_path, "--take", rig_folder / "take"], capsys)
    assert rc == 2 and "--take" in err
