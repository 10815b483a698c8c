"""The live server (rig/live/server.py) and its wire format (rig/live/protocol.py), on a real uvicorn
bound to 127.0.0.1 port 0, with the `websockets` client and http.client."""
from __future__ import annotations

import http.client
import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from rig.errors import RigError
from rig.live import protocol
from rig.live.api import LiveFrame
from rig.live.server import COOKIE, CREDIT, LiveServer, WS_MAX_SIZE
from tests.live.conftest import start_server, wait_until

REPO = Path(__file__).resolve().parents[2]
TOKEN = "s3cret-token-for-tests"


# --- helpers ------------------------------------------------------------------------------------------------
def get(server, path: str, headers: dict | None = None, timeout: float = 10.0):
    """(status, headers, body) of a GET."""
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=timeout)
    try:
        conn.request("GET", path, headers=headers or {})
        resp = conn.getresponse()
        return resp.status, {k.lower(): v for k, v in resp.getheaders()}, resp.read()
    finally:
        conn.close()


def ws_url(server, query: str = "") -> str:
    return f"ws://127.0.0.1:{server.port}/ws{query}"


class Client:
    """A WebSocket viewer: frames and JSON messages, acked or not."""

    def __init__(self, server, query: str = "", headers: dict | None = None, ack: bool = False):
        self.ws = connect(ws_url(server, query), additional_headers=headers, open_timeout=10, max_size=None).__enter__()
        self.ack = ack
        self.frames: list[tuple[float, LiveFrame]] = []
        self.texts: list[dict] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def recv(self, timeout: float = 5.0):
        data = self.ws.recv(timeout=timeout)
        if isinstance(data, bytes):
            frame = protocol.unpack_frame(data)
            self.frames.append((time.monotonic(), frame))
            if self.ack:
                self.send({"type": "ack", "set": frame.set_index, "viewpoint": frame.viewpoint_id})
            return frame
        msg = json.loads(data)
        self.texts.append(msg)
        return msg

    def send(self, message) -> None:
        self.ws.send(message if isinstance(message, (str, bytes)) else json.dumps(message))

    def next_text(self, *types: str, timeout: float = 5.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"no {types} message within {timeout} s")
            msg = self.recv(timeout=left)
            if isinstance(msg, dict) and msg.get("type") in types:
                return msg

    def next_frame(self, timeout: float = 5.0) -> LiveFrame:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"no frame within {timeout} s")
            msg = self.recv(timeout=left)
            if isinstance(msg, LiveFrame):
                return msg

    def pump(self, seconds: float) -> None:
        """Receive (and ack, if acking) for this long."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                self.recv(timeout=left)
            except TimeoutError:
                return

    def pump_in_background(self) -> "Client":
        def run():
            while not self._stop.is_set():
                try:
                    self.recv(timeout=0.1)
                except TimeoutError:
                    continue
                except ConnectionClosed:
                    return

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()
        return self

    def frames_between(self, t0: float, t1: float) -> list[float]:
        return [t for t, _ in list(self.frames) if t0 <= t <= t1]

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
        self.ws.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def jpeg_rgb(jpeg: bytes, fx: float = 0.5, fy: float = 0.5) -> tuple[int, int, int]:
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None, "not an image"
    h, w = img.shape[:2]
    b, g, r = img[int(fy * (h - 1)), int(fx * (w - 1))]
    return int(r), int(g), int(b)


def close_to(rgb, expected, tol: int = 8) -> bool:
    return all(abs(int(a) - int(b)) <= tol for a, b in zip(rgb, expected))


# --- the wire format ----------------------------------------------------------------------------------------
@given(set_index=st.integers(0, 2 ** 64 - 1), vid=st.integers(0, 2 ** 32 - 1),
       capture_ns=st.integers(-(2 ** 63), 2 ** 63 - 1), jpeg=st.binary(max_size=64))
def test_frame_round_trip(set_index, vid, capture_ns, jpeg):
    data = protocol.pack_frame(LiveFrame(set_index, vid, capture_ns, jpeg))
    assert data[:4] == b"RLVF" and len(data) == protocol.HEADER_LEN + len(jpeg) == 32 + len(jpeg)
    assert protocol.unpack_frame(data) == LiveFrame(set_index, vid, capture_ns, jpeg)


def test_frame_header_layout_and_growth():
    data = protocol.pack_frame(LiveFrame(7, 3, 1_700_000_000_123_456_789, b"\xff\xd8jpeg"))
    assert data[:8] == b"RLVF" + (1).to_bytes(2, "little") + (32).to_bytes(2, "little")
    assert int.from_bytes(data[8:16], "little") == 7
    assert int.from_bytes(data[16:20], "little") == 3
    assert int.from_bytes(data[24:32], "little", signed=True) == 1_700_000_000_123_456_789
    # a later header with more fields: an old reader finds the JPEG at header_len
    grown = data[:6] + (40).to_bytes(2, "little") + data[8:32] + b"newfield" + b"\xff\xd8jpeg"
    assert protocol.unpack_frame(grown).jpeg == b"\xff\xd8jpeg"
    for bad in (b"", data[:31], b"XXXX" + data[4:], data[:4] + (2).to_bytes(2, "little") + data[6:],
                data[:6] + (31).to_bytes(2, "little") + data[8:], data[:6] + (999).to_bytes(2, "little") + data[8:]):
        with pytest.raises(protocol.ProtocolError):
            protocol.unpack_frame(bad)
    with pytest.raises(ValueError):
        protocol.pack_frame(LiveFrame(-1, 0, 0, b""))


def test_client_messages():
    assert protocol.parse_client_message('{"type":"ack","set":5,"viewpoint":2}') == protocol.Ack(5, 2)
    assert protocol.parse_client_message('{"type":"ack","set":5.0,"viewpoint":2}') == protocol.Ack(5, 2)
    vp = protocol.parse_client_message('{"type":"viewpoint","t":0.25,"yaw":-3}')
    assert vp == protocol.Viewpoint({"type": "viewpoint", "t": 0.25, "yaw": -3})
    # "seq" is the client's: echoed in the reply, never passed on
    assert protocol.parse_client_message('{"type":"viewpoint","t":1,"seq":9}') == protocol.Viewpoint({"type": "viewpoint", "t": 1}, 9)
    assert protocol.parse_client_message('{"type":"ack","set":1,"viewpoint":2,"seq":3}') == protocol.Ack(1, 2, 3)
    with pytest.raises(protocol.ProtocolError) as err:
        protocol.parse_client_message('{"type":"ack","set":-1,"viewpoint":2,"seq":3}')
    assert err.value.seq == 3
    bad = ['{"type":"viewpoint","t":1,"seq":-1}', '{"type":"viewpoint","t":1,"seq":1.5}', '{"type":"viewpoint","seq":"1"}',
           b'{"type":"ack","set":1,"viewpoint":1}', "", "nope", "[1,2]", '"viewpoint"', "{}", '{"type":"hello"}',
           '{"type":5}', '{"type":"viewpoint","t":NaN}', '{"type":"viewpoint","t":Infinity}', '{"type":"viewpoint","t":1e999}',
           '{"type":"viewpoint","t":' + "9" * 30 + "}", '{"type":"viewpoint","t":' + "9" * 5000 + "}",
           '{"type":"ack","set":-1,"viewpoint":1}', '{"type":"ack","set":1.5,"viewpoint":1}', '{"type":"ack","set":true,"viewpoint":1}',
           '{"type":"ack","set":1}', '{"type":"ack","set":1,"viewpoint":1,"x":0}', '{"type":"ack","set":"1","viewpoint":1}',
           '{"type":"ack","set":1,"viewpoint":4294967296}', '{"type":"viewpoint","x":' + "[" * 100 + "]" * 100 + "}",
           "[" * 4000, '{"type":"viewpoint","pad":"' + "x" * 5000 + '"}']
    for text in bad:
        with pytest.raises(protocol.ProtocolError) as err:
            protocol.parse_client_message(text)
        assert "\n" not in str(err.value) and len(str(err.value)) < 200


def test_outgoing_json_is_strict():
    text = protocol.status_message({"fps": float("nan"), "x": np.float32(1.5), "n": np.int64(3), "a": np.arange(2),
                                    "t": (1, float("inf"))}, viewer_id=4)
    assert json.loads(text) == {"type": "status", "viewer": 4, "fps": None, "x": 1.5, "n": 3, "a": [0, 1], "t": [1, None]}


# --- access -------------------------------------------------------------------------------------------------
ROUTES = ["/", "/status", "/snapshot.png?t=0.5", "/mjpeg?t=0.5", "/static/viewer.js", "/no-such-page"]


def test_token_required_everywhere(live_rig):
    with start_server(live_rig.engine, token=TOKEN, snapshot_timeout=3.0) as srv:
        for path in ROUTES:
            for headers in ({}, {"Authorization": "Bearer wrong-token"}, {"Cookie": f"{COOKIE}=wrong"}):
                status, hdrs, body = get(srv, path, headers)
                assert status == 401, (path, headers)
                assert json.loads(body) == {"error": "a valid token is needed (?token=, or Authorization: Bearer)"}
            sep = "&" if "?" in path else "?"
            assert get(srv, f"{path}{sep}token=wrong")[0] == 401
            assert get(srv, f"{path}{sep}token={TOKEN[:-1]}")[0] == 401
        for query, headers in (("", {}), ("?token=nope", {}), ("", {"Authorization": "Bearer nope"})):
            with pytest.raises(InvalidStatus) as err:
                connect(ws_url(srv, query), additional_headers=headers, open_timeout=5).__enter__()
            assert err.value.response.status_code == 401
        assert live_rig.engine.viewers == [] and live_rig.engine.snapshots == []  # nothing reached the engine

        # the right token: query, bearer header, or the cookie the page sets
        for path in ("/", "/status", "/static/viewer.js", "/static/viewer.css", "/snapshot.png?t=0.5"):
            sep = "&" if "?" in path else "?"
            assert get(srv, f"{path}{sep}token={TOKEN}")[0] == 200, path
            assert get(srv, path, {"Authorization": f"Bearer {TOKEN}"})[0] == 200, path
        status, hdrs, body = get(srv, f"/?token={TOKEN}")
        assert b"<canvas" in body and hdrs["content-type"].startswith("text/html")
        cookie = hdrs["set-cookie"]
        assert cookie.startswith(f"{COOKIE}={TOKEN};") and "HttpOnly" in cookie and "SameSite=strict" in cookie
        assert "set-cookie" not in get(srv, "/", {"Authorization": f"Bearer {TOKEN}"})[1]
        assert get(srv, "/status", {"Cookie": f"{COOKIE}={TOKEN}"})[0] == 200
        for query, headers in ((f"?token={TOKEN}", {}), ("", {"Authorization": f"Bearer {TOKEN}"}),
                               ("", {"Cookie": f"{COOKIE}={TOKEN}"})):
            with Client(srv, query, headers) as c:
                assert c.next_text("hello")["viewer"] >= 1
        # MJPEG with the token: the first part comes
        conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=10)
        conn.request("GET", f"/mjpeg?t=0.5&token={TOKEN}")
        resp = conn.getresponse()
        assert resp.status == 200 and resp.getheader("content-type").startswith("multipart/x-mixed-replace")
        assert resp.read(100).startswith(b"--")
        conn.close()


def test_without_token_loopback_names_and_same_origin_only(live_rig, server):
    assert get(server, "/status")[0] == 200
    assert get(server, "/status", {"Host": "localhost:1234"})[0] == 200
    assert get(server, "/status", {"Host": "[::1]:1234"})[0] == 200
    status, _, body = get(server, "/status", {"Host": "evil.example:80"})  # DNS rebinding
    assert status == 403 and b"loopback" in body
    host = f"127.0.0.1:{server.port}"
    with pytest.raises(InvalidStatus) as err:
        connect(ws_url(server), origin="http://evil.example", open_timeout=5).__enter__()
    assert err.value.response.status_code == 403
    with Client(server, headers={"Origin": f"http://{host}"}) as c:  # the page's own origin
        assert c.next_text("hello")


def test_create_app_refuses_an_empty_token(live_rig):
    from rig.live.server import create_app

    with pytest.raises(ValueError):
        create_app(live_rig.engine, "")


# --- the WebSocket viewer --------------------------------------------------------------------------------------
def test_hello_status_frames_and_viewpoint(live_rig, server):
    with Client(server, ack=True) as c:
        hello = c.next_text("hello")
        assert hello["presets"] == live_rig.presets and hello["protocol"] == 1
        status = c.next_text("status")
        assert status["viewer"] == hello["viewer"] and "health" in status and "fps_in" in status
        t0 = time.monotonic()
        c.next_text("status")
        c.next_text("status")
        assert time.monotonic() - t0 < 2.5  # about twice a second
        frame = c.next_frame()
        assert frame.jpeg[:2] == b"\xff\xd8"
        if live_rig.expected_rgb:
            assert close_to(jpeg_rgb(frame.jpeg), live_rig.expected_rgb(None))
        # a viewpoint message reaches the engine; frames at its id follow
        c.send({"type": "viewpoint", "t": 0.1})
        vid = c.next_text("viewpoint")["viewpoint"]
        viewer = live_rig.engine.viewers[-1]
        assert viewer.messages[-1] == {"type": "viewpoint", "t": 0.1} and viewer.ids[-1] == vid
        while (frame := c.next_frame()).viewpoint_id != vid:
            pass
        if live_rig.expected_rgb:
            assert close_to(jpeg_rgb(frame.jpeg), live_rig.expected_rgb({"type": "viewpoint", "t": 0.1}))
        # the engine's reason for a bad viewpoint comes back; nothing changes
        c.send({"type": "viewpoint", "t": 7, "seq": 12})
        err = c.next_text("error")
        assert err["seq"] == 12 and err["message"].startswith("viewpoint: ") and len(err["message"]) < 300
        c.send({"type": "viewpoint", "t": 0.1, "seq": 13})
        assert c.next_text("viewpoint") == {"type": "viewpoint", "viewpoint": vid, "seq": 13}
        assert viewer.messages[-1] == {"type": "viewpoint", "t": 0.1}
        assert c.next_frame().viewpoint_id == vid
        wait_until(lambda: viewer.acks, what="acks reaching the engine")
    wait_until(lambda: viewer.id in live_rig.engine.removed, what="the viewer to be removed at disconnect")


def test_credit_slow_viewer_gets_two_frames_other_keeps_its_rate(live_rig, server):
    with Client(server, ack=False) as slow, Client(server, ack=True) as fast:
        fast.next_frame()
        t0 = time.monotonic()
        fast.pump_in_background()
        slow.pump(2.0)
        t1 = time.monotonic()
        assert len(slow.frames) == CREDIT == 2
        got = len(fast.frames_between(t0, t1))
        fps = live_rig.engine.status()["fps_in"]
        assert got >= 0.5 * fps * (t1 - t0), (got, fps)
        # one ack: exactly one more frame
        f = slow.frames[0][1]
        slow.send({"type": "ack", "set": f.set_index, "viewpoint": f.viewpoint_id})
        slow.pump(1.0)
        assert len(slow.frames) == 3
        # an ack for a frame never sent, or acked twice, gives no credit
        slow.send({"type": "ack", "set": f.set_index, "viewpoint": f.viewpoint_id})
        assert "no such frame" in slow.next_text("error")["message"]
        slow.pump(0.5)
        assert len(slow.frames) == 3


# hypothesis: messages that must all be refused with an error reply
_numbers = ["NaN", "Infinity", "-Infinity", "1e999", "-1e999", "1e308", "-5", "2", '"0.5"', "true", "null", "[]", "{}",
            str(2 ** 53 + 1), str(-(2 ** 64)), "9" * 40]
bad_messages = st.one_of(
    st.text(max_size=80).filter(lambda s: not s.lstrip().startswith("{")),  # not an object (or not JSON)
    st.builds(lambda k: json.dumps({"type": k}), st.text(max_size=20).filter(lambda k: k not in ("viewpoint", "ack"))),
    st.builds(lambda n: '{"type":"viewpoint","t":%s}' % n, st.sampled_from(_numbers)),
    st.builds(lambda n: '{"type":"ack","set":%s,"viewpoint":4294967295}' % n, st.sampled_from(_numbers + ["1.5", "-1", "1", "3"])),
    st.builds(lambda s, v: json.dumps({"type": "ack", "set": s, "viewpoint": v}),
              st.integers(10 ** 9, 2 ** 53), st.integers(0, 2 ** 32 - 1)),  # well formed, never sent
    st.builds(lambda d: json.dumps({"type": "ack", **d}), st.dictionaries(st.text(max_size=5), st.integers(), max_size=3)),
    st.builds(lambda n: '{"type":"viewpoint","pad":"' + "x" * n + '"}', st.integers(4100, 30000)),  # over 4 KB
    st.builds(lambda n: "[" * n, st.integers(1000, 4000)),
    st.binary(max_size=200),
)


@pytest.mark.timeout(120)
def test_fuzzed_messages_get_an_error_reply_and_never_disturb_another_viewer(live_rig, server):
    with Client(server, ack=True) as watcher, Client(server, ack=False) as fuzz:
        watcher.next_frame()
        watcher.pump_in_background()
        fuzz.next_text("hello")
        t0 = time.monotonic()

        @settings(max_examples=400, deadline=None, suppress_health_check=list(HealthCheck), database=None)
        @given(message=bad_messages)
        def refused(message):
            fuzz.send(message)
            reply = fuzz.next_text("error", "viewpoint", timeout=5)
            assert reply["type"] == "error", (message, reply)
            assert isinstance(reply["message"], str) and 0 < len(reply["message"]) <= 300

        refused()
        t1 = time.monotonic()
        # the fuzzing connection still works
        fuzz.send({"type": "viewpoint", "t": 0.9})
        assert fuzz.next_text("viewpoint", "error")["type"] == "viewpoint"
        assert get(server, "/status")[0] == 200
        # the other viewer kept receiving the whole time
        times = [t0] + watcher.frames_between(t0, t1) + [t1]
        fps = live_rig.engine.status()["fps_in"]
        assert len(times) - 2 >= 0.3 * fps * (t1 - t0), (len(times), fps, t1 - t0)
        assert max(b - a for a, b in zip(times, times[1:])) < 1.5


def test_oversize_message_closes_only_that_connection(live_rig, server):
    with Client(server, ack=True) as watcher, Client(server) as big:
        big.next_text("hello")
        watcher.next_frame()
        big.send("x" * (WS_MAX_SIZE + 1))
        with pytest.raises(ConnectionClosed) as err:
            big.pump(5.0)
            big.recv(timeout=0.1)
        assert err.value.rcvd is not None and err.value.rcvd.code == 1009
        n = len(watcher.frames)
        watcher.pump(0.5)
        assert len(watcher.frames) > n


def test_engine_failure_in_set_viewpoint_is_reported_not_fatal(colour_engine, server):
    with Client(server, ack=True) as c:
        c.next_frame()
        colour_engine.raise_in_set_viewpoint = True
        c.send({"type": "viewpoint", "t": 0.2})
        assert "deliberate failure" in c.next_text("error")["message"]
        colour_engine.raise_in_set_viewpoint = False
        c.send({"type": "viewpoint", "t": 0.2})
        assert c.next_text("viewpoint", "error")["type"] == "viewpoint"
        c.next_frame()


def test_viewer_cap(live_rig):
    with start_server(live_rig.engine, max_viewers=1) as srv, Client(srv) as first:
        first.next_text("hello")
        with Client(srv) as second:
            assert "too many viewers" in second.next_text("error")["message"]
            with pytest.raises(ConnectionClosed) as err:
                second.pump(3.0)
                second.recv(timeout=0.1)
            assert err.value.rcvd.code == 1013
        assert get(srv, "/mjpeg")[0] == 503
        first.next_text("status")


# --- HTTP routes ---------------------------------------------------------------------------------------------
def test_status_route_is_strict_json(colour_engine, server):
    colour_engine.extra_status = {"nan_figure": float("nan"), "np_figure": np.float64(2.5)}
    status, hdrs, body = get(server, "/status")
    assert status == 200 and hdrs["content-type"] == "application/json"
    s = json.loads(body, parse_constant=lambda c: pytest.fail(f"{c} in /status"))
    assert s["nan_figure"] is None and s["np_figure"] == 2.5 and s["health"]["ok"] is True


def test_snapshot(live_rig, server):
    status, hdrs, body = get(server, "/snapshot.png?t=0.25")
    assert status == 200 and hdrs["content-type"] == "image/png" and body[:8] == b"\x89PNG\r\n\x1a\n"
    assert live_rig.engine.snapshots[-1] == {"type": "viewpoint", "t": 0.25}
    if live_rig.expected_rgb:
        assert close_to(jpeg_rgb(body), live_rig.expected_rgb({"type": "viewpoint", "t": 0.25}), tol=1)
    status, _, body = get(server, f"/snapshot.png?preset={live_rig.supervision}")
    assert status == 200 and live_rig.engine.snapshots[-1] == {"type": "viewpoint", "preset": live_rig.supervision}
    if live_rig.expected_rgb:
        assert close_to(jpeg_rgb(body), live_rig.expected_rgb({"type": "viewpoint", "preset": live_rig.supervision}), tol=1)
    assert get(server, "/snapshot.png")[0] == 200 and live_rig.engine.snapshots[-1] is None  # default: halfway
    for query in ("t=7", "t=nan", "t=inf", "preset=no-such-camera", "t=abc"):
        status, hdrs, body = get(server, f"/snapshot.png?{query}")
        assert status == 400 and json.loads(body)["error"].startswith("viewpoint: "), query


def test_snapshot_503_before_any_frame_set(live_rig):
    if live_rig.kind != "colour":
        pytest.skip("needs an engine that has no frame set yet")
    live_rig.inner.paused = True
    live_rig.inner.set_index = 0
    with start_server(live_rig.engine, snapshot_timeout=0.3) as srv:
        status, hdrs, body = get(srv, "/snapshot.png?t=0.5")
        assert status == 503 and hdrs["content-type"] == "application/json"
        assert json.loads(body) == {"error": "no frame set arrived within 0.3 s"}


def read_mjpeg_part(resp) -> bytes:
    line = resp.readline()  # (the body is chunked: read through the response, not its socket)
    while line in (b"\r\n", b""):
        line = resp.readline()
    assert line.startswith(b"--"), line
    headers = {}
    while (line := resp.readline()) not in (b"\r\n", b""):
        k, _, v = line.decode().partition(":")
        headers[k.strip().lower()] = v.strip()
    assert headers["content-type"] == "image/jpeg"
    return resp.read(int(headers["content-length"]))


def test_mjpeg_stream_and_client_going_away(live_rig, server):
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    conn.request("GET", "/mjpeg?t=0.75")
    resp = conn.getresponse()
    boundary = resp.getheader("content-type").split("boundary=")[1]
    assert resp.status == 200 and boundary
    t0 = time.monotonic()
    parts = [read_mjpeg_part(resp) for _ in range(5)]
    assert time.monotonic() - t0 < 5
    for jpeg in parts:
        assert jpeg[:2] == b"\xff\xd8"
        if live_rig.expected_rgb:
            assert close_to(jpeg_rgb(jpeg), live_rig.expected_rgb({"type": "viewpoint", "t": 0.75}))
    viewer = live_rig.engine.viewers[-1]
    assert viewer.id not in live_rig.engine.removed
    conn.sock.shutdown(socket.SHUT_RDWR)
    conn.close()
    wait_until(lambda: viewer.id in live_rig.engine.removed, timeout=5, what="the MJPEG viewer to be removed")
    assert get(server, "/mjpeg?t=2")[0] == 400


def test_mjpeg_plays_in_ffmpeg(live_rig, server):
    """What ffplay and VLC do: FFmpeg's HTTP client and mpjpeg demuxer (through PyAV)."""
    av = pytest.importorskip("av")
    with av.open(f"http://127.0.0.1:{server.port}/mjpeg?t=0.25", timeout=10) as container:
        assert container.format.name == "mpjpeg"
        images = []
        for frame in container.decode(video=0):
            images.append(frame.to_ndarray(format="rgb24"))
            if len(images) == 3:
                break
    assert all(img.ndim == 3 and img.shape[2] == 3 for img in images)
    if live_rig.expected_rgb:
        h, w = images[-1].shape[:2]
        assert close_to(images[-1][h // 2, w // 2], live_rig.expected_rgb({"type": "viewpoint", "t": 0.25}))
    wait_until(lambda: len(live_rig.engine.removed) == len(live_rig.engine.viewers), what="the MJPEG viewer removed")


# --- running and stopping -----------------------------------------------------------------------------------------
def test_stop_with_viewers_connected(live_rig):
    srv = start_server(live_rig.engine)
    ws = Client(srv, ack=True)
    ws.next_frame()
    conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=10)
    conn.request("GET", "/mjpeg")
    resp = conn.getresponse()
    read_mjpeg_part(resp)
    t0 = time.monotonic()
    srv.stop()
    assert time.monotonic() - t0 < 5 and not srv.running
    with pytest.raises(ConnectionClosed):
        ws.pump(3.0)
        ws.recv(timeout=0.1)
    resp.read()  # the stream ended
    conn.close()
    ws.close()
    wait_until(lambda: len(live_rig.engine.removed) == len(live_rig.engine.viewers), what="every viewer removed")
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", srv.port), timeout=1).close()


def test_port_in_use_is_a_rig_error(live_rig, server):
    with pytest.raises(RigError, match=f"cannot listen on 127.0.0.1:{server.port}"):
        LiveServer(live_rig.engine, "127.0.0.1", server.port)


SIGINT_SCRIPT = """
import sys
sys.path[:0] = [{repo!r}]
from tests.live.conftest import ColourEngine
from rig.live.server import LiveServer
engine = ColourEngine().start()
srv = LiveServer(engine, "127.0.0.1", 0)
print(srv.port, flush=True)
srv.run()
engine.stop()
print("stopped", flush=True)
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_run_stops_cleanly_on_signal(sig):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", SIGINT_SCRIPT.format(repo=str(REPO))], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)
    try:
        port = int(proc.stdout.readline())

        class S:
            pass

        srv = S()
        srv.port = port
        wait_until(lambda: _answers(srv), timeout=10, what="the server to answer")
        with Client(srv, ack=True) as c:
            c.next_frame()
            proc.send_signal(sig)
            out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        assert out.strip() == "stopped" and "Traceback" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _answers(srv) -> bool:
    try:
        return get(srv, "/status", timeout=2)[0] == 200
    except OSError:
        return False
