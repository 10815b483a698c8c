"""mDNS discovery of camera daemons (rig.cameras.discovery, `rig discover --network`), on loopback.

The advertisements come from another process (as from a daemon); no real daemon runs. Every test
uses rig names of its own, so daemons advertised by anything else on this host do not disturb it.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import subprocess
import sys
import threading
import time
import uuid

import pytest

from rig.cli import main
from rig.cameras.discovery import SERVICE_TYPE, DaemonInfo, advertise, browse, instance_name
from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig

LOOPBACK = ["127.0.0.1"]
RUN = uuid.uuid4().hex[:6]
ALPHA, BETA = f"alpha{RUN}", f"beta{RUN}"

DAEMONS = [
    DaemonInfo(rig=ALPHA, camera="cam0", role="main", uri="sim://left", model="SimCam 1", serial="S-001",
               shm=f"/dev/shm/rig/{ALPHA}/cam0", host="127.0.0.1", port=48101, pid=4242, token_required=False),
    DaemonInfo(rig=ALPHA, camera="cam 1/ü.x", role="witness", uri="aravis://192.0.2.7?x=1&y=2", model="",
               serial="GV01", shm=f"/dev/shm/rig/{ALPHA}/cam 1", host="127.0.0.1", port=48102, pid=4243,
               token_required=True),
    DaemonInfo(rig=BETA, camera="cam0", role="main", uri="sim://right", model="SimCam 2", serial="S-002",
               shm=f"/dev/shm/rig/{BETA}/cam0", host="127.0.0.1", port=48103, pid=4244, token_required=False),
]

# Services of the same type whose TXT records are not a daemon's: raw bytes that are no TXT strings,
# a v=1 record with a port that is no number, one that is not UTF-8, one without a version.
JUNK = [
    b"\x40short\xff\x00",
    {"v": "1", "rig": ALPHA, "camera": "junk1", "api": "x", "pid": "not-a-pid"},
    {b"v": b"1", b"rig": b"\xff\xfe" + ALPHA.encode(), b"camera": b"junk2"},
    {"rig": ALPHA, "camera": "junk3"},
]

ADVERTISER = r"""
import json, sys
from zeroconf import ServiceInfo, Zeroconf
from rig.cameras.discovery import SERVICE_TYPE, DaemonInfo, advertise
spec = json.loads(sys.argv[1])
ads = [advertise(DaemonInfo(**d), interfaces=["127.0.0.1"], wait=False) for d in spec["daemons"]]
zc = Zeroconf(interfaces=["127.0.0.1"])
for i, props in enumerate(spec["junk"]):
    props = bytes.fromhex(props) if isinstance(props, str) else {bytes.fromhex(k): bytes.fromhex(v) for k, v in props}
    zc.register_service(ServiceInfo(SERVICE_TYPE, f"junk{i}-{spec['run']}.{SERVICE_TYPE}", port=9, properties=props,
                                    server="junk.local.", parsed_addresses=["127.0.0.1"]),
                        cooperating_responders=True)  # no probing: unique names, and quicker
for ad in ads:
    ad.wait(10)
print("ready", flush=True)
sys.stdin.read()  # until the test closes our stdin
for ad in ads:
    ad.close()
zc.close()
"""


def _hexed(props):
    if isinstance(props, bytes):
        return props.hex()
    as_bytes = lambda x: x if isinstance(x, bytes) else x.encode()  # noqa: E731
    return [(as_bytes(k).hex(), as_bytes(v).hex()) for k, v in props.items()]


@pytest.fixture(scope="module")
def advertised():
    """DAEMONS and JUNK advertised on loopback by another process."""
    spec = {"run": RUN, "daemons": [dataclasses.asdict(d) for d in DAEMONS], "junk": [_hexed(j) for j in JUNK]}
    proc = subprocess.Popen([sys.executable, "-c", ADVERTISER, json.dumps(spec)], cwd=REPO, text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        line = []
        reader = threading.Thread(target=lambda: line.append(proc.stdout.readline()), daemon=True)
        reader.start()
        reader.join(30)
        if line != ["ready\n"]:
            proc.kill()
            pytest.fail(f"advertiser did not start: {line} {proc.stderr.read() if proc.poll() is not None else ''}")
        yield DAEMONS
    finally:
        if proc.poll() is None:
            try:
                proc.stdin.close()
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _discover(*args) -> tuple[int, dict, float]:
    out = io.StringIO()
    t0 = time.monotonic()
    with contextlib.redirect_stdout(out):
        rc = main(["discover", "--network", "--json", "--interface", "127.0.0.1", *args])
    took = time.monotonic() - t0
    assert out.getvalue().count("\n") == 1, out.getvalue()  # one JSON object
    return rc, json.loads(out.getvalue()), took


def _ours(daemons: list[dict]) -> list[dict]:
    return [d for d in daemons if d["rig"] in (ALPHA, BETA)]


def test_discover_network_finds_every_daemon_quickly_with_every_property(advertised):
    rc, out, took = _discover()
    assert rc == 0 and set(out) == {"daemons"}
    expected = sorted((d.to_dict() for d in advertised), key=lambda d: (d["rig"], d["camera"]))
    assert _ours(out["daemons"]) == expected  # the junk services are not listed
    assert took < 3.0, f"browse took {took:.2f} s"
    assert {d["api_url"] for d in _ours(out["daemons"])} == {"http://127.0.0.1:48101", "http://127.0.0.1:48102", "http://127.0.0.1:48103"}


def test_rig_filter(advertised):
    rc, out, _ = _discover("--rig", BETA)
    assert rc == 0 and out["daemons"] == [DAEMONS[2].to_dict()]
    assert browse(3.0, interfaces=LOOPBACK, rig=ALPHA) == [DAEMONS[1], DAEMONS[0]]  # by (rig, camera): "cam 1" < "cam0"


def test_browses_one_after_another_each_see_every_daemon_quickly(advertised):
    """A responder answers a multicast query for a record it multicast in the last second only a
    second later (RFC 6762 section 6); browse() also asks by legacy unicast, answered at once, so a
    browse right after another (daemon:// cameras opened in turn) neither waits nor misses one."""
    for _ in range(3):
        t0 = time.monotonic()
        found = browse(3.0, interfaces=LOOPBACK)
        took = time.monotonic() - t0
        assert [d for d in found if d.rig in (ALPHA, BETA)] == [DAEMONS[1], DAEMONS[0], DAEMONS[2]]
        assert took < 1.5, f"browse took {took:.2f} s (about 0.6 s expected)"


def test_text_output_has_one_line_per_daemon(advertised):
    proc = run_rig("discover", "--network", "--interface", "127.0.0.1", "--rig", ALPHA, timeout=30)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) == 2, proc.stdout
    assert lines[0].startswith(f"{ALPHA}/cam 1/ü.x") and "http://127.0.0.1:48102" in lines[0] and "token required" in lines[0]
    assert lines[1].startswith(f"{ALPHA}/cam0") and "sim://left" in lines[1] and "http://127.0.0.1:48101" in lines[1]
    assert lines[1].rstrip().endswith(f"/dev/shm/rig/{ALPHA}/cam0") and "token" not in lines[1]


def test_a_closed_advertisement_says_goodbye():
    """A browser that saw the daemon sees it removed (goodbye packets: zeroconf drops the records 1 s
    later), and a later browse no longer finds it."""
    from zeroconf import ServiceBrowser, Zeroconf

    rig = f"gone{RUN}"
    info = DaemonInfo(rig=rig, camera="c", role="main", uri="sim://left", model="", serial="", shm="/x",
                      host="127.0.0.1", port=48110)
    events: dict[str, threading.Event] = {"Added": threading.Event(), "Removed": threading.Event()}
    expected_name = f"{instance_name(rig, 'c')}.{SERVICE_TYPE}"

    def on_change(zeroconf, service_type, name, state_change):
        if name == expected_name and state_change.name in events:
            events[state_change.name].set()

    zc = Zeroconf(interfaces=LOOPBACK)
    browser = ServiceBrowser(zc, SERVICE_TYPE, handlers=[on_change])
    try:
        ad = advertise(info, interfaces=LOOPBACK)  # waits for the registration
        try:
            assert ad.ready.is_set() and ad.error is None and ad.name == expected_name
            assert events["Added"].wait(5)
            assert browse(3.0, interfaces=LOOPBACK, rig=rig) == [info]
        finally:
            t0 = time.monotonic()
            ad.close()
            ad.close()  # idempotent
            closing = time.monotonic() - t0
        assert closing < 2.0
        assert events["Removed"].wait(5), "no goodbye seen within 5 s"
    finally:
        browser.cancel()
        zc.close()
    assert browse(1.0, interfaces=LOOPBACK, rig=rig) == []


def test_advertise_without_waiting_returns_at_once_and_closes_cleanly():
    info = DaemonInfo(rig=f"q{RUN}", camera="c", role="main", uri="sim://left", model="", serial="", shm="/x",
                      host="127.0.0.1", port=48111)
    t0 = time.monotonic()
    with advertise(info, interfaces=LOOPBACK, wait=False) as ad:
        assert time.monotonic() - t0 < 0.5 and not ad.ready.is_set()  # probing takes ~1.5 s
    assert time.monotonic() - t0 < 3.0  # closed while probing: cancelled, nothing to withdraw
    assert ad.ready.is_set() and ad.error is not None
    ad.close()


@pytest.mark.parametrize("rig, camera, expected", [
    ("studio", "cam0", "studio-cam0"),
    ("Studio A", "cam 1/ü", "Studio-A-cam-1"),
    ("ü", "ß", "rig-camera"),
    ("x" * 80, "y", "x" * 56),
])
def test_instance_names_are_ascii_dns_labels(rig, camera, expected):
    assert instance_name(rig, camera) == expected


@pytest.mark.parametrize("args, fragment", [
    (["--network", "--timeout", "-1"], "--timeout -1"),
    (["--network", "--timeout", "nan"], "--timeout nan"),
    (["--network", "--interface", "eth0"], "--interface eth0"),
    (["--rig", "x"], "--network"),
])
def test_bad_arguments_exit_2_with_one_line(args, fragment):
    assert_one_line_error(run_rig("discover", *args, timeout=30), fragment)


def test_advertised_addresses():
    import ipaddress

    from rig.cameras.discovery import _addresses

    assert _addresses("127.0.0.1", None) == ["127.0.0.1"]
    assert _addresses("0.0.0.0", ["127.0.0.1"]) == ["127.0.0.1"]  # wildcard API, advertised on loopback only
    machine = _addresses("0.0.0.0", None)  # the machine's addresses, loopback only when it has no other
    assert machine and (machine == ["127.0.0.1"] or not any(ipaddress.ip_address(a).is_loopback for a in machine))
    assert _addresses("", None) == machine
