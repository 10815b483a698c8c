"""`rig live` bad input found by trying it (trial-model): each one line, exit 2, before the cameras
and the model open. Before: an address in use or not of this host failed after the cameras opened
(exit 1); a --record-view that is not a viewpoint was a ValueError traceback; a calibration at
another size than the frames (a take of another rig) served forever with a preprocessing error
per frame set."""
from __future__ import annotations

import json
import socket
from pathlib import Path

import pytest

from calibration.camera import RigCalibration
from rig.config import dump_config, parse_config
from rig.sim.rig_config import sim_rig_config
from rig.storage.dataset import Sequence
from simulator.takes import write_take
from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig

pytestmark = [pytest.mark.timeout(300)]

MODEL = REPO / "models" / "splat-sap-live.onnx"


@pytest.fixture(scope="module")
def rig_toml(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("trial-live") / "rig.toml"
    path.write_text(dump_config(parse_config(sim_rig_config(3, 320, 180, fps=15.0))))
    return path


@pytest.fixture(scope="module")
def take(tmp_path_factory) -> Path:
    return Path(write_take(tmp_path_factory.mktemp("trial-live-take") / "take", seed=11, seconds=0.2, fps=10, size=(320, 180))["out"])


@pytest.fixture(scope="module")
def big_calibration(take, tmp_path_factory) -> Path:
    """The take's exact cameras at twice its size: the calibration of another rig."""
    truth = Sequence(take).ground_truth
    path = tmp_path_factory.mktemp("trial-live-calib") / "other-rig.json"
    path.write_text(json.dumps(RigCalibration.from_dict(
        {"version": 1, "cameras": [truth[n].scaled(2 * truth[n].width, 2 * truth[n].height).to_dict() for n in truth.names]}).to_dict()))
    return path


def _live(rig_toml, *args):
    return run_rig("live", "-c", rig_toml, "--model", MODEL, "--seconds", 2, *args, timeout=120)


def test_an_address_in_use_is_one_line_before_the_cameras_open(rig_toml):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        proc = _live(rig_toml, "--port", port)
    assert_one_line_error(proc, f"127.0.0.1:{port}", "in use")


def test_an_address_not_of_this_host_is_one_line(rig_toml):
    assert_one_line_error(_live(rig_toml, "--host", "999.1.1.1", "--port", 0), "999.1.1.1", "cannot listen")


@pytest.mark.parametrize("view, fragment", [("nosuchcam", "nosuchcam"), ("nan", "finite"), ("7", "between 0 and 1")])
def test_a_record_view_that_is_no_viewpoint(rig_toml, tmp_path, view, fragment):
    video = tmp_path / "out.mp4"
    proc = _live(rig_toml, "--port", 0, "--record-output", video, "--record-view", view)
    assert_one_line_error(proc, "--record-view", fragment)
    assert not video.exists()


def test_a_calibration_of_another_size_than_the_replayed_take(rig_toml, take, big_calibration):
    proc = _live(rig_toml, "--port", 0, "--replay", take, "--calibration", big_calibration)
    assert_one_line_error(proc, "camera 'left' is 320x180 in the take", "640x360 in --calibration")


def test_a_calibration_of_another_size_than_the_rig(rig_toml, big_calibration):
    proc = _live(rig_toml, "--port", 0, "--calibration", big_calibration)
    assert_one_line_error(proc, f"camera 'left' is 320x180 in {rig_toml}", "640x360 in --calibration")


def test_a_file_given_to_replay(rig_toml):
    # "rig.toml/sequence.json: Not a directory (the work stopped here)", exit 1
    assert_one_line_error(_live(rig_toml, "--port", 0, "--replay", rig_toml), "--replay", str(rig_toml), "is a file")
