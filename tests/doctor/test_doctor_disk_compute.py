"""Disk and compute checks: a real write test in a temporary folder; fake programs for the rest."""
from __future__ import annotations

import json

import pytest

from rig.doctor import compute, disk
from rig.doctor.check import FAIL, OK, WARN
from rig.doctor.host import Host
from tests.doctor.fakehost import camera, needs_of, statuses

SMALL = [camera("left", "sim://left", role="left", width=64, height=48, fps=1.0),
         camera("right", "sim://right", role="right", width=64, height=48, fps=1.0)]
# 16384x16384 RGB8 at 10000 fps: 8 TB/s, no disk keeps up
HUGE = [camera("x", "sim://x", width=16384, height=16384, pixel_format="RGB8", fps=10000.0)]


def test_data_rate_is_cameras_times_size_times_fps_times_bytes_per_pixel():
    needs = needs_of([camera("a", "sim://a", width=1280, height=720, pixel_format="RGB8", fps=30.0),
                      camera("b", "sim://b", width=1280, height=720, pixel_format="BayerRG8", trigger="hardware")],
                     trigger={"uri": "sim://trigger", "rate_hz": 60.0})
    assert needs.data_rate == 1280 * 720 * 3 * 30 + 1280 * 720 * 1 * 60  # a Bayer frame is stored as its mosaic


def test_write_rate_is_measured_and_its_file_removed(tmp_path, fake):
    tmp_path = tmp_path / "out"
    tmp_path.mkdir()
    fake.program("df", f"Mounted on 1B-blocks Avail\n/data {10**12} {10**12}\n")
    checks = disk.checks(fake.host(), needs_of(SMALL), tmp_path, minutes=10, test_bytes=8 << 20)
    assert statuses(checks) == {f"free space {tmp_path}": OK, f"write rate {tmp_path}": OK}
    assert "8.0 MiB in" in checks[1].measured and list(tmp_path.iterdir()) == []
    checks = disk.checks(fake.host(), needs_of(HUGE), tmp_path / "takes", minutes=10, test_bytes=8 << 20)
    assert [c.status for c in checks] == [FAIL, FAIL] and "not made yet" in checks[1].name
    assert list(tmp_path.iterdir()) == []


def test_rate_and_free_space_verdicts():
    assert disk.rate_status(100e6, 50e6) == OK
    assert disk.rate_status(100e6, 90e6) == WARN  # within the recorder's headroom
    assert disk.rate_status(100e6, 101e6) == FAIL
    assert disk.free_status(30, 10) == OK and disk.free_status(15, 10) == WARN and disk.free_status(9, 10) == FAIL


def test_free_space_warn_and_fail_from_df(tmp_path, fake):
    needs = needs_of(SMALL)  # 2 x 64 x 48 bytes at 1 fps: 6144 B/s, 3.7 MB for 10 minutes
    fake.program("df", "Mounted on 1B-blocks Avail\n/data 100000000 5000000\n")
    c = disk.checks(fake.host(), needs, tmp_path, minutes=10, test_bytes=1 << 20)[0]
    assert c.status == WARN and "free room on /data" in c.note
    fake.program("df", "Mounted on 1B-blocks Avail\n/data 100000000 3000000\n")
    assert disk.checks(fake.host(), needs, tmp_path, minutes=10, test_bytes=1 << 20)[0].status == FAIL


def cpus(fake, online: str, quota: str | None = None):
    fake.file("sys/devices/system/cpu/online", online + "\n")
    if quota:
        fake.file("sys/fs/cgroup/cpu.max", quota + "\n")
    return compute._cpu_check(fake.host(), needs_of(SMALL))


def test_cpus_ok_warn_fail(fake):
    assert cpus(fake, "0-7").status == OK
    c = cpus(fake, "0-1")
    assert c.status == WARN and c.measured == "2"
    c = cpus(fake, "0-7", quota="100000 100000")  # a container allowed one CPU's time
    assert c.status == FAIL and c.measured.startswith("1 (cgroup quota")


@pytest.mark.parametrize("online", ["", "garbage", "0-"])
def test_an_unreadable_cpu_list_is_unreadable_not_one_cpu(fake, online):
    """An empty or garbled /sys/devices/system/cpu/online (or none under --root: a partial copy of a
    host's tree) counted as one CPU and failed the check ("on one core ...")."""
    c = cpus(fake, online)
    assert c.status == WARN and c.measured == "unreadable"
    assert compute.cpu_count(Host(fake.root.parent / "empty-root"))[0] is None


NO_GPU = {"torch": {"version": "2.13.0+cpu", "cuda": False, "devices": []},
          "onnxruntime": {"version": "1.32.0", "providers": ["CPUExecutionProvider"]}}


def test_gpu_ok_warn_fail(fake):
    fake.python_probe({**NO_GPU, "torch": {"version": "2.13.0", "cuda": True, "devices": ["NVIDIA H200"]}})
    c = compute._gpu_check(fake.host(), needs_of(SMALL))
    assert c.status == OK and "NVIDIA H200" in c.measured
    fake.python_probe({**NO_GPU, "onnxruntime": {"version": "1.20", "providers": ["CUDAExecutionProvider", "CPUExecutionProvider"]}})
    assert compute._gpu_check(fake.host(), needs_of(SMALL)).status == OK
    fake.python_probe(NO_GPU)
    assert compute._gpu_check(fake.host(), needs_of(SMALL)).status == WARN
    fake.program("nvidia-smi", "GPU 0: NVIDIA GeForce RTX 4090 (UUID: GPU-1234)\n")  # the driver sees one, the runtimes not
    c = compute._gpu_check(fake.host(), needs_of(SMALL))
    assert c.status == FAIL and "RTX 4090" in c.measured and c.fix == "python -m pip install onnxruntime-gpu"


def test_live_rate_ok_warn_fail():
    needs = needs_of(SMALL)  # the pair runs at 1 set/s
    assert compute._live_check(needs, None, None).status == WARN
    bench = {"preset": "preview", "ort_ms": {"total": 400.0}, "torch_ms": {"total": 900.0}}
    c = compute._live_check(needs, bench, "bench.json")
    assert c.status == OK and c.measured.startswith("2.5 sets/s (ort 400 ms")
    bench["ort_ms"]["total"] = 2000.0  # the faster of the two totals counts: torch's 900 ms still make it
    assert compute._live_check(needs, bench, "bench.json").status == OK
    bench["torch_ms"]["total"] = 1500.0
    assert compute._live_check(needs, bench, "bench.json").status == FAIL
    with pytest.raises(ValueError):
        compute.bench_rate({"ort_ms": {}})
    no_pair = needs_of([camera("s", "sim://s")])
    assert compute._live_check(no_pair, None, None).status == OK


def test_time_source_ok_warn_fail(fake):
    assert compute._clock_check(fake.host()).status == WARN  # nothing installed, nothing readable
    fake.program("timedatectl", "no\n")
    c = compute._clock_check(fake.host())
    assert c.status == FAIL and c.fix == "sudo timedatectl set-ntp true"
    fake.program("timedatectl", "yes\n")
    assert compute._clock_check(fake.host()).status == OK
    fake.program("chronyc", "Reference ID    : 7F7F0101 ()\nStratum         : 10\n"
                            "System time     : 0.000000003 seconds fast of NTP time\nLeap status     : Not synchronised\n")
    assert compute._clock_check(fake.host()).status == FAIL  # chrony's word comes first
    fake.program("chronyc", "Reference ID    : C0A80101 (192.168.1.1)\nSystem time     : 0.000012500 seconds slow of NTP time\n"
                            "Leap status     : Normal\n")
    c = compute._clock_check(fake.host())
    assert c.status == OK and c.measured == "chrony: Normal, 0.013 ms slow"
    (fake.bin / "chronyc").unlink()
    fake.file("proc/4242/comm", "ptp4l\n")
    fake.program("pmc", "sending: GET TIME_STATUS_NP\n\tmaster_offset -35\n\tgmPresent true\n")
    assert compute._clock_check(fake.host()).measured.startswith("PTP: grandmaster present, offset -35 ns")
    fake.program("pmc", "sending: GET TIME_STATUS_NP\n\tmaster_offset 0\n\tgmPresent false\n")
    assert compute._clock_check(fake.host()).status == FAIL


def test_gpu_probe_runs_in_the_rigs_python_for_real(fake):
    """The probe itself, in this interpreter: it answers for this host's torch and onnxruntime."""
    from rig.doctor.host import Host

    seen = compute.runtime_gpus(Host(fake.root))
    assert "version" in seen["onnxruntime"] and isinstance(seen["onnxruntime"]["providers"], list)


def test_write_test_takes_at_most_a_tenth_of_the_free_room_and_says_when_it_cannot_measure(tmp_path, fake):
    out = tmp_path / "out"
    out.mkdir()
    fake.program("df", f"Mounted on 1B-blocks Avail\n/data {10**9} {20 << 20}\n")  # 20 MiB free
    checks = disk.checks(fake.host(), needs_of(SMALL), out, minutes=10, test_bytes=256 << 20)
    assert "2.0 MiB in" in checks[1].measured  # a tenth of it (it took 4 MiB, a fifth)
    fake.program("df", f"Mounted on 1B-blocks Avail\n/data {10**9} {5 << 20}\n")  # a tenth is under the test's megabyte
    rate = disk.checks(fake.host(), needs_of(SMALL), out, minutes=10, test_bytes=256 << 20)[1]
    # before: "0.0 MB/s (0.0 MiB in 0.00 s)", a failure saying the disk cannot keep up
    assert rate.status == WARN and rate.measured.startswith("not measured") and "cannot keep up" not in rate.note
    assert list(out.iterdir()) == []


def test_the_doctor_counts_the_data_rate_that_rig_record_checks():
    """A software-triggered camera gets a trigger per board pulse, so it runs at the board's rate, as
    `rig record`'s disk check counts it; the doctor counted its fps (here half the rate)."""
    from rig.config import parse_config
    from rig.doctor.needs import rig_needs
    from rig.storage.disk import rig_data_rate

    cams = [camera("a", "sim://a", width=640, height=360, pixel_format="RGB8", fps=30.0, trigger="hardware"),
            camera("b", "sim://b", width=640, height=360, pixel_format="Mono16", fps=30.0, trigger="software"),
            camera("c", "sim://c", width=320, height=180, pixel_format="BayerRG8", fps=25.0, trigger="free")]
    cfg = parse_config({"rig": {"name": "venue"}, "cameras": cams, "trigger": {"uri": "sim://trigger", "rate_hz": 60.0}})
    needs = rig_needs(cfg)
    assert {c.name: c.rate_hz for c in needs.cameras} == {"a": 60.0, "b": 60.0, "c": 25.0}
    assert needs.data_rate == rig_data_rate(cfg)
