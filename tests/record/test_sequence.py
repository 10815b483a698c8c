"""Sequence writer, validation, repair and the dataset reader, on frames from simulated cameras."""
from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.camera import CameraModel, RigCalibration
from rig.cameras import open_camera
from rig.config import CameraConfig
from rig.storage.dataset import Sequence
from rig.storage.recorder import SequenceWriter
from rig.storage.layout import INDEX, SequenceError
from rig.storage.netpbm import read_netpbm
from rig.storage.repair import repair
from rig.storage.validate import validate
from sync.frames import FrameSet
from tests.rig.cli_helpers import assert_one_line_error, run_rig

CAMS = [
    CameraConfig(name="left", uri="sim://left", role="left", width=64, height=48, pixel_format="RGB8", trigger="software"),
    CameraConfig(name="right", uri="sim://right", role="right", width=64, height=48, pixel_format="Mono8", trigger="software"),
]


def capture_sets(n: int, drop_right_every: int = 0):
    cams = [open_camera(c) for c in CAMS]
    for c in cams:
        c.start()
    try:
        for i in range(n):
            frames = {}
            for c in cams:
                c.software_trigger()
                frames[c.name] = c.get_frame(1.0)
            if drop_right_every and i % drop_right_every == drop_right_every - 1:
                frames["right"] = None
            yield FrameSet(index=i, frames=frames, host_ts_ns=frames["left"].host_ts_ns)
    finally:
        for c in cams:
            c.close()


def write_sequence(root, n=12, calibration=None, **kw):
    w = SequenceWriter(root, CAMS, rig_name="t", rate_hz=30.0, calibration_file=calibration)
    sets = list(capture_sets(n, **kw))
    for fs in sets:
        assert w.write(fs)
    w.close()
    return sets


def calibration_file(tmp_path):
    cams = [CameraModel(c.name, c.width, c.height, [[50, 0, 31.5], [0, 50, 23.5], [0, 0, 1]], t=[0.1 * i, 0, 0])
            for i, c in enumerate(CAMS)]
    path = tmp_path / "calib.json"
    RigCalibration(cams).save(path)
    return path


def test_written_sequence_validates_and_reads_back(tmp_path):
    seq_dir = tmp_path / "seq"
    sets = write_sequence(seq_dir, n=12, calibration=calibration_file(tmp_path), drop_right_every=4)
    v = validate(seq_dir, check_pixels=True)
    assert v.readable and not v.errors, v.errors
    assert v.sets == 12 and v.complete_sets == 9
    assert v.frames == {"left": 12, "right": 9} and v.missing["right"] == 3
    assert v.calibrated
    rows = [json.loads(line) for line in (seq_dir / INDEX).read_text().splitlines()]
    first = rows[0]["frames"]["left"]
    assert np.array_equal(read_netpbm(seq_dir / first["file"]), sets[0].frames["left"].image)
    assert first["frame_id"] == sets[0].frames["left"].frame_id
    seq = Sequence(seq_dir)
    samples = list(seq.samples(cameras=["left", "right"], size=(32, 24)))
    assert len(samples) == 9  # sets where both cameras have a frame
    s = samples[0]
    assert s.images["left"].shape == (24, 32, 3) and s.images["right"].shape == (24, 32, 3)
    assert s.cameras["left"].fx == pytest.approx(25.0) and s.cameras["left"].cx == pytest.approx(15.5)
    assert s.depth["left"] is None  # not a simulator take


def test_torn_tail_is_reported_and_repaired(tmp_path):
    seq_dir = tmp_path / "seq"
    write_sequence(seq_dir, n=6)
    index = seq_dir / INDEX
    data = index.read_bytes()
    index.write_bytes(data + data.splitlines(keepends=True)[-1][:40])  # the recorder died mid-row
    v = validate(seq_dir)
    assert v.readable and v.torn_tail and v.sets == 6
    r = repair(seq_dir)
    assert r["kept_sets"] == 6 and r["removed_bytes"] == 40
    assert index.read_bytes() == data
    assert not validate(seq_dir).torn_tail


def test_missing_image_is_an_error_and_repair_marks_only_that_frame_missing(tmp_path):
    seq_dir = tmp_path / "seq"
    write_sequence(seq_dir, n=6)
    rows = [json.loads(line) for line in (seq_dir / INDEX).read_text().splitlines()]
    (seq_dir / rows[4]["frames"]["left"]["file"]).unlink()
    proc = run_rig("record", "validate", seq_dir, "--json")
    assert proc.returncode == 1
    out = json.loads(proc.stdout)
    assert out["readable"] is False and out["readable_sets"] == 4 and "missing" in out["errors"][0]
    r = repair(seq_dir)
    assert r["kept_sets"] == 6 and r["frames_marked_missing"] == 1
    again = validate(seq_dir)
    assert again.readable and again.sets == 6 and again.missing == {"left": 1, "right": 0}


def test_validate_rejects_a_folder_that_is_not_a_sequence(tmp_path):
    assert_one_line_error(run_rig("record", "validate", tmp_path), "not a sequence")
    assert_one_line_error(run_rig("record", "validate", tmp_path / "nope"), "no such sequence folder")


def test_a_file_read_as_a_sequence_is_a_sequence_error_for_every_caller(tmp_path):
    # the commands each said so; a caller of the library got NotADirectoryError (exit 1 through rig)
    from rig.storage.layout import SequenceError, SequenceMeta

    notes = tmp_path / "notes.txt"
    notes.write_text("not a sequence\n")
    with pytest.raises(SequenceError, match="is a file, not a sequence folder") as err:
        SequenceMeta.load(notes)
    assert err.value.exit_code == 2


def test_writer_refuses_to_overwrite(tmp_path):
    seq_dir = tmp_path / "seq"
    write_sequence(seq_dir, n=2)
    from rig.errors import StorageError

    with pytest.raises(StorageError, match="already holds a sequence"):
        SequenceWriter(seq_dir, CAMS)


def test_bayer_cameras_are_stored_as_their_mosaic_and_read_back_identical(tmp_path):
    cams = [CameraConfig(name="left", uri="sim://left", role="left", width=64, height=48, pixel_format="BayerRG8", trigger="software")]
    cam = open_camera(cams[0])
    cam.start()
    cam.software_trigger()
    frame = cam.get_frame(1.0)
    cam.close()
    seq_dir = tmp_path / "seq"
    w = SequenceWriter(seq_dir, cams, calibration_file=calibration_file(tmp_path))
    w.write(FrameSet(0, {"left": frame}, frame.host_ts_ns))
    w.close()
    stored = read_netpbm(seq_dir / json.loads((seq_dir / INDEX).read_text())["frames"]["left"]["file"])
    assert stored.shape == (48, 64)  # one sample per pixel: a third of the RGB bytes
    sample = next(Sequence(seq_dir).samples(cameras=["left"]))
    assert np.array_equal(sample.images["left"], frame.image)
    assert validate(seq_dir).readable


def test_a_damaged_image_header_is_reported_not_a_crash(tmp_path):
    seq_dir = tmp_path / "seq"
    write_sequence(seq_dir, n=4, calibration=calibration_file(tmp_path))
    rows = [json.loads(line) for line in (seq_dir / INDEX).read_text().splitlines()]
    image = seq_dir / rows[2]["frames"]["left"]["file"]
    data = image.read_bytes()
    image.write_bytes(data.replace(b"64 48", b"6x 48", 1))  # same size: the header tells
    rel = rows[2]["frames"]["left"]["file"]
    for v in (validate(seq_dir), validate(seq_dir, check_pixels=True)):  # what repair marks missing (it passed)
        assert not v.readable and v.readable_sets == 2 and v.errors == [f"set 2: {rel}: damaged image header"]
    with pytest.raises(SequenceError, match="damaged PPM/PGM header"):
        list(Sequence(seq_dir).samples(cameras=["left"]))


def test_repair_removes_a_camera_the_sequence_does_not_record_and_keeps_the_set(tmp_path):
    """A row naming a camera the sequence does not record is damage to both, so repair leaves a clean take."""
    seq_dir = tmp_path / "seq"
    write_sequence(seq_dir, n=6)
    index = seq_dir / INDEX
    lines = index.read_text().splitlines(keepends=True)
    row = json.loads(lines[3])
    row["frames"]["ghost"] = None
    lines[3] = json.dumps(row) + "\n"
    index.write_text("".join(lines))
    v = validate(seq_dir)
    assert v.errors == ["set 3: unknown camera 'ghost'"] and v.readable_sets == 3
    r = repair(seq_dir)
    assert r["kept_sets"] == 6 and [(c["what"], c["camera"]) for c in r["dropped"]] == [("camera", "ghost")]
    again = validate(seq_dir)
    assert again.readable and again.sets == 6 and again.complete_sets == 6
