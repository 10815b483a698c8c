"""`rig record repair` keeps every good set of a damaged take: a bad index line is dropped, a missing
or torn image marks only that frame missing, the original index is kept beside, and `--json` says
what was dropped and why. Issue 11 point 1: it used to cut the take at the first damage, with no backup
(40 of 94 sets kept after one garbage line at set 41; 20 of 94 after one missing image at set 20)."""
from __future__ import annotations

import hashlib
import json
import shutil
import tomllib

import pytest

from rig.storage.layout import INDEX
from rig.storage.repair import BACKUP_PREFIX
from tests.record.test_record import rig_file
from tests.rig.cli_helpers import run_rig

SETS = 94


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """One 94-set take of the simulated rig, recorded as a user does; each test damages a copy."""
    base = tmp_path_factory.mktemp("take")
    proc = run_rig("record", "-c", rig_file(base), "-o", base / "take", "--sets", SETS, "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["complete_sets"] == SETS
    return base / "take"


@pytest.fixture
def take(recorded, tmp_path):
    copy = tmp_path / "take"
    shutil.copytree(recorded, copy)
    return copy


def lines_of(take) -> list[bytes]:
    return (take / INDEX).read_bytes().splitlines(keepends=True)


def row(take, n: int) -> dict:
    return json.loads(lines_of(take)[n])


def images(take) -> dict[str, str]:
    return {str(p.relative_to(take)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted((take / "frames").rglob("*"))
            if p.is_file()}


def backups(take) -> list:
    return sorted(take.glob(f"{BACKUP_PREFIX}*"))


def repair_json(take) -> dict:
    proc = run_rig("record", "repair", take, "--json")
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    return json.loads(proc.stdout)


def validate_json(take, *extra) -> dict:
    proc = run_rig("record", "validate", take, "--json", *extra)
    out = json.loads(proc.stdout)
    assert proc.returncode == 0 and out["readable"], out["errors"]
    return out


def test_a_garbage_line_at_set_41_drops_that_line_only(take):
    lines = lines_of(take)
    good = [json.loads(x) for i, x in enumerate(lines) if i != 41]
    lines[41] = b'{"set": 41, "frames": {"left": \x00\x17garbage\n'
    (take / INDEX).write_bytes(b"".join(lines))
    damaged = (take / INDEX).read_bytes()
    before = images(take)

    r = repair_json(take)
    assert r["changed"] and r["sets_before"] == SETS and r["kept_sets"] == SETS - 1
    assert r["dropped_lines"] == 1 and r["frames_marked_missing"] == 0
    assert r["dropped"] == [{"what": "line", "line": 42, "bytes": len(lines[41]), "reason": "not JSON (corrupt line)"}]
    assert [json.loads(x) for x in lines_of(take)] == good  # every other set, as it was
    # the original index beside the repaired one, byte for byte; no image touched
    assert backups(take) == [take / r["backup"].rsplit("/", 1)[1]]
    assert (take / r["backup"].rsplit("/", 1)[1]).read_bytes() == damaged
    assert images(take) == before
    v = validate_json(take, "--pixels")
    assert v["sets"] == SETS - 1 and v["complete_sets"] == SETS - 1 and v["errors"] == []


def test_a_missing_image_at_set_20_marks_that_frame_missing_and_keeps_every_set(take):
    lost = row(take, 20)["frames"]["left"]["file"]
    (take / lost).unlink()
    right_before = row(take, 20)["frames"]["right"]

    r = repair_json(take)
    assert r["kept_sets"] == SETS and r["dropped_lines"] == 0 and r["frames_marked_missing"] == 1
    assert r["dropped"] == [{"what": "frame", "line": 21, "set": 20, "camera": "left", "file": lost, "reason": "image file missing"}]
    assert row(take, 20)["frames"] == {"left": None, "right": right_before}
    v = validate_json(take)
    assert v["sets"] == SETS and v["complete_sets"] == SETS - 1 and v["missing"] == {"left": 1, "right": 0}


def test_torn_image_damaged_header_and_torn_tail(take):
    torn = take / row(take, 5)["frames"]["right"]["file"]
    torn.write_bytes(torn.read_bytes()[:1000])
    header = take / row(take, 7)["frames"]["left"]["file"]
    data = header.read_bytes()
    header.write_bytes(data.replace(b"160 90", b"16x 90", 1))  # same size: only the header tells
    index = take / INDEX
    index.write_bytes(index.read_bytes() + lines_of(take)[-1][:50])  # the recorder died mid-row

    r = repair_json(take)
    assert r["kept_sets"] == SETS
    reasons = {(c["what"], c.get("set"), c.get("camera")): c["reason"] for c in r["dropped"]}
    assert reasons == {("frame", 5, "right"): f"torn image (1000 of {len(data)} bytes)",
                       ("frame", 7, "left"): "damaged image header",
                       ("line", None, None): "torn last line (the recording was interrupted mid-row)"}
    v = validate_json(take, "--pixels")
    assert not v["torn_tail"] and v["sets"] == SETS and v["missing"] == {"left": 1, "right": 1}


def test_repairing_twice_is_harmless_and_never_overwrites_a_backup(take):
    (take / row(take, 3)["frames"]["left"]["file"]).unlink()
    first = repair_json(take)
    repaired = (take / INDEX).read_bytes()
    first_backup = take / first["backup"].rsplit("/", 1)[1]
    kept_copy = first_backup.read_bytes()

    again = repair_json(take)
    assert not again["changed"] and again["backup"] is None and again["dropped"] == []
    assert (take / INDEX).read_bytes() == repaired and backups(take) == [first_backup]

    (take / row(take, 9)["frames"]["right"]["file"]).unlink()  # new damage, repaired within the same second
    third = repair_json(take)
    assert third["changed"] and third["backup"] != first["backup"]
    assert len(backups(take)) == 2 and first_backup.read_bytes() == kept_copy
    assert (take / third["backup"].rsplit("/", 1)[1]).read_bytes() == repaired
    assert validate_json(take)["missing"] == {"left": 1, "right": 1}


def test_repair_says_what_it_dropped_in_words(take):
    lines = lines_of(take)
    lines[60] = b"\x00\x00\x00\n"
    (take / INDEX).write_bytes(b"".join(lines))
    proc = run_rig("record", "repair", take)
    assert proc.returncode == 0 and proc.stderr == ""
    out = proc.stdout
    assert f"kept {SETS - 1} of {SETS} sets" in out and "line 61: dropped (not JSON (corrupt line))" in out
    assert "the original index is kept as" in out and BACKUP_PREFIX in out and f"next: rig record validate {take}" in out
    # the copied config is untouched, and the take reads as a take
    assert tomllib.loads((take / "rig.toml").read_text())["rig"]["name"] == "sim-2cam"
