"""The frame ring (rig.daemon.ring) between real processes: round trips, no torn frame ever handed out
at full write speed, a reader's death leaves the ring alone, bad files and frames refused in one line,
the writer's liveness, and atomic creation."""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

from rig.daemon.ring import (HEADER_SIZE, FrameNotReady, FrameOverwritten, FrameRing, RingError, RingLayoutError,
                             RingReader, default_path)
from sync.frames import Frame

CTX = mp.get_context("spawn")  # children share nothing with the test process but the ring file
VARIANTS = 7  # frame f shows image f % 7: coprime to the ring sizes used, so a slot's next frame always differs
ID0 = 1000  # frame_id = ID0 + sequence: a frame id is not its sequence number


def images(shape, dtype=np.uint8) -> list[np.ndarray]:
    """The frames' contents: a fixed random pattern, rolled and offset per variant."""
    base = np.random.default_rng(0).integers(0, np.iinfo(dtype).max + 1, size=shape, dtype=dtype)
    return [np.roll(base, 37 * j, axis=1) + dtype(j) for j in range(VARIANTS)]


def make_frame(k: int, imgs: list[np.ndarray], **meta) -> Frame:
    return Frame(image=imgs[(ID0 + k) % VARIANTS], camera="ignored", frame_id=ID0 + k, device_ts_ns=10 * k,
                 host_ts_ns=time.monotonic_ns(), pixel_format="RGB8", **meta)


def attach_when_there(path, timeout: float = 60.0) -> RingReader:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return RingReader.attach(path)
        except RingLayoutError:
            raise
        except RingError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.01)


def create(path, shape=(48, 64, 3), slots=4, dtype="uint8", pixel_format="RGB8") -> FrameRing:
    return FrameRing.create(path, slots=slots, height=shape[0], width=shape[1], channels=shape[2] if len(shape) == 3 else 1,
                            dtype=dtype, pixel_format=pixel_format, camera="cam0")


# --- child processes -------------------------------------------------------------------------------

def burst_writer(path: str, n: int, shape, slots: int, go, results) -> None:
    """Writes n frames as fast as it can once the reader is attached."""
    imgs = images(shape)
    ring = create(path, shape, slots)
    go.wait(60)
    t0 = time.perf_counter()
    for k in range(n):
        ring.write(make_frame(k, imgs))
    results.put(("writer", time.perf_counter() - t0))
    ring.close(unlink=False)


def checking_reader(path: str, go, results) -> None:
    """Reads without pause until the writer closes, alternating the newest frame and the oldest still
    there (the next one to be overwritten), and checks every frame it gets against its frame id."""
    reader = attach_when_there(path)
    crcs = [zlib.crc32(im) for im in images(reader.shape)]
    out = np.empty(reader.shape, reader.dtype)
    counts = {"good": 0, "torn": 0, "not_ready": 0, "gone_before": 0, "gone_during": 0}
    distinct, turn = set(), 0
    go.set()
    while not reader.closed:
        latest = reader.latest()
        if latest == 0:
            time.sleep(0.0005)
            continue
        # the newest frame, the one being written (a streaming read behind the writer), the oldest still there
        k = (latest - 1, latest, max(0, latest - reader.slots))[turn % 3]
        turn += 1
        try:
            frame = reader.read_into(k, out)
        except FrameNotReady:
            counts["not_ready"] += 1
            continue
        except FrameOverwritten as exc:
            counts["gone_during" if "while it was read" in str(exc) else "gone_before"] += 1
            continue
        if frame.frame_id != ID0 + k or zlib.crc32(frame.image) != crcs[frame.frame_id % VARIANTS]:
            counts["torn"] += 1
        else:
            counts["good"] += 1
            distinct.add(k)
    counts["distinct"] = len(distinct)
    counts["streamed"] = reader.streamed
    results.put(("reader", counts))


def steady_writer(path: str, shape, stop) -> None:
    """Writes about a frame a millisecond until told to stop, then closes (and removes) the ring."""
    imgs = images(shape)
    ring = create(path, shape, slots=4)
    k = 0
    while not stop.is_set():
        ring.write(make_frame(k, imgs))
        k += 1
        time.sleep(0.001)
    ring.close()


def looping_reader(path: str, reading, forever: bool) -> None:
    reader = attach_when_there(path)
    n = 0
    while forever or n < 50:
        try:
            reader.read(reader.latest() - 1)
            n += 1
        except (FrameNotReady, FrameOverwritten):
            pass
        if n == 20:
            reading.set()
    reader.close()


def heartbeat_writer(path: str, ready) -> None:
    ring = create(path)
    ready.set()
    while True:
        ring.heartbeat()
        time.sleep(0.01)


def creation_watcher(path: str, started, stop, results) -> None:
    """Attaches to the ring path over and over while rings are created onto it."""
    ok = missing = 0
    bad = []
    attach_when_there(path).close()
    started.set()
    while not stop.is_set():
        try:
            RingReader.attach(path).close()
            ok += 1
        except RingLayoutError as exc:
            bad.append(str(exc))
        except RingError:
            missing += 1
    results.put((ok, missing, bad))


def start(target, *args):
    proc = CTX.Process(target=target, args=args, daemon=True)
    proc.start()
    return proc


def finish(proc, timeout: float = 60.0) -> None:
    proc.join(timeout)
    if proc.is_alive():
        proc.kill()
        proc.join()
        raise AssertionError(f"{proc.name} did not finish within {timeout} s")
    assert proc.exitcode == 0, f"{proc.name} exited with {proc.exitcode}"


# --- tests -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape,dtype,fmt", [((30, 40), np.uint8, "Mono8"), ((30, 40, 3), np.uint8, "RGB8"),
                                             ((30, 40), np.uint16, "Mono16")])
def test_round_trip(tmp_path, shape, dtype, fmt):
    path = tmp_path / "rig" / "cam0"
    before = time.time_ns()
    with create(path, shape, slots=3, dtype=dtype, pixel_format=fmt) as ring, RingReader.attach(path) as reader:
        assert (ring.path, ring.slots, ring.shape, ring.dtype, ring.camera) == (path, 3, shape, np.dtype(dtype), "cam0")
        assert (reader.slots, reader.shape, reader.dtype, reader.pixel_format, reader.camera, reader.pid) == (
            3, shape, np.dtype(dtype), fmt, "cam0", os.getpid())
        assert before <= reader.created_ns <= time.time_ns()
        assert (reader.write_seq, reader.latest(), reader.closed) == (0, 0, False)
        imgs = images(shape, dtype)
        sent = []
        for k in range(5):
            meta = dict(trigger_index=k, exposure_us=125.5 * k, sim_time_s=k / 30) if k % 2 else {}
            frame = make_frame(k, imgs, **meta)
            frame.pixel_format = fmt if k < 4 else "BayerGR8"  # the frame's own format travels with it
            hb = reader.heartbeat_ns
            assert ring.write(frame) == k
            assert reader.heartbeat_ns >= hb and reader.latest() == k + 1
            sent.append(frame)
        with pytest.raises(FrameOverwritten):
            reader.read(1)  # 3 slots: frames 2, 3, 4 are there
        with pytest.raises(FrameNotReady):
            reader.read(5)
        for k in (2, 3, 4):
            got, want = reader.read(k), sent[k]
            assert got.image.dtype == np.dtype(dtype) and np.array_equal(got.image, want.image)
            assert got.camera == "cam0"
            for field in ("frame_id", "device_ts_ns", "host_ts_ns", "pixel_format", "exposure_us", "trigger_index",
                          "sim_time_s"):
                assert getattr(got, field) == getattr(want, field), field
        assert reader.read(2).trigger_index is None and reader.read(2).exposure_us is None
        assert reader.read(2).sim_time_s is None and reader.read(3).trigger_index == 3
        kept = reader.read(4)
        out = np.zeros(shape, dtype)
        assert reader.read_into(3, out).image is out and np.array_equal(out, sent[3].image)
        for k in range(5, 8):  # the slots are reused: what was read is a copy and stays as it was
            ring.write(make_frame(k, imgs))
        assert np.array_equal(kept.image, sent[4].image) and kept.image.flags.writeable
    assert not path.exists()


def test_no_torn_frame_at_full_speed(tmp_path):
    """A writer process fills a 4-slot ring with 720p RGB frames as fast as it can; a reader process
    reads all the while, including the slot about to be overwritten and the frame being written
    (streamed out behind the writer). Every frame it gets is whole."""
    n, shape, path = 3000, (720, 1280, 3), str(tmp_path / "cam0")
    imgs = images(shape)
    torn = imgs[0].copy()
    torn[:360] = imgs[4][:360]  # half of one frame over another: the check below sees it
    assert zlib.crc32(torn) not in {zlib.crc32(im) for im in imgs}
    go, results = CTX.Event(), CTX.Queue()
    procs = [start(burst_writer, path, n, shape, 4, go, results), start(checking_reader, path, go, results)]
    got = dict(results.get(timeout=120) for _ in procs)
    for proc in procs:
        finish(proc)
    counts = got["reader"]
    print(f"{n} frames written in {got['writer']:.2f} s; reader: {counts}")
    assert counts["torn"] == 0, counts
    assert counts["distinct"] > n // 30, counts  # it kept up with a good share of the frames
    assert counts["gone_before"] + counts["gone_during"] > 0, counts  # overwritten frames raised, not returned
    assert counts["streamed"] > 0, counts  # frames read while they were written, band by band behind the writer
    with RingReader.attach(path) as reader:
        assert reader.latest() == n and reader.closed


def test_reader_killed_mid_read_leaves_ring_intact(tmp_path):
    shape, path = (240, 320, 3), str(tmp_path / "cam0")
    stop, reading = CTX.Event(), CTX.Event()
    writer = start(steady_writer, path, shape, stop)
    try:
        done = CTX.Event()  # (held here until the child has it)
        finish(start(looping_reader, path, done, False))  # a reader that exits cleanly
        assert Path(path).exists()
        victim = start(looping_reader, path, reading, True)
        assert reading.wait(60)
        time.sleep(0.1)
        os.kill(victim.pid, signal.SIGKILL)
        victim.join(10)
        assert victim.exitcode == -signal.SIGKILL
        assert Path(path).exists()
        with RingReader.attach(path) as reader:
            assert reader.writer_alive()
            crcs = [zlib.crc32(im) for im in images(shape)]
            first, good = reader.latest(), 0
            while good < 30:
                k = reader.latest()
                assert reader.wait(k, 10)
                try:
                    frame = reader.read(k)
                except FrameOverwritten:
                    continue
                assert frame.frame_id == ID0 + k and zlib.crc32(frame.image) == crcs[frame.frame_id % VARIANTS]
                good += 1
            assert reader.latest() > first  # the writer kept writing
    finally:
        stop.set()
        finish(writer)
    assert not Path(path).exists()  # removed by its writer, and only by it


def test_bad_files_and_frames(tmp_path):
    def refused(path, kind):
        with pytest.raises(kind) as err:
            RingReader.attach(path)
        message = str(err.value)
        assert str(path) in message and "\n" not in message and err.value.exit_code == 2
        return message

    assert "no frame ring" in refused(tmp_path / "missing", RingError)
    assert "cannot open" in refused(tmp_path, RingError)  # a folder
    (tmp_path / "empty").write_bytes(b"")
    assert "empty" in refused(tmp_path / "empty", RingLayoutError)
    (tmp_path / "other").write_bytes(b"NOTARING" + bytes(4096))
    assert "wrong magic" in refused(tmp_path / "other", RingLayoutError)

    path = tmp_path / "cam0"
    ring = create(path, (48, 64, 3), slots=4)
    data = path.read_bytes()
    (tmp_path / "v9").write_bytes(data[:8] + (9).to_bytes(4, "little") + data[12:])
    assert "version 9" in refused(tmp_path / "v9", RingLayoutError)
    for cut in (100, len(data) // 2, len(data) - 1):
        (tmp_path / "cut").write_bytes(data[:cut])
        assert "truncated" in refused(tmp_path / "cut", RingLayoutError)

    imgs = images((48, 64, 3))
    for image in (np.zeros((64, 48, 3), np.uint8), np.zeros((48, 64), np.uint8), np.zeros((48, 64, 3), np.uint16)):
        with pytest.raises(RingError) as err:
            ring.write(Frame(image, "cam0", 1, 0, 0, "RGB8"))
        assert str(image.shape) in str(err.value) and "(48, 64, 3)" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(RingError, match="pixel format"):
        ring.write(Frame(imgs[0], "cam0", 1, 0, 0, "YUV422"))
    assert ring.write(make_frame(0, imgs)) == 0  # still usable, nothing consumed by the refusals
    with RingReader.attach(path) as reader:
        assert reader.latest() == 1 and np.array_equal(reader.read(0).image, imgs[ID0 % VARIANTS])
    with pytest.raises(RingError, match="dtype"):
        create(tmp_path / "f32", dtype="float32")
    ring.close()


def test_writer_alive(tmp_path):
    path = str(tmp_path / "cam0")
    ready = CTX.Event()
    proc = start(heartbeat_writer, path, ready)
    assert ready.wait(60)
    with RingReader.attach(path) as reader:
        assert reader.pid == proc.pid
        assert reader.writer_alive(stale_s=1.0)
        os.kill(proc.pid, signal.SIGKILL)  # not joined yet: its pid still exists, its heartbeat stops
        deadline = time.monotonic() + 10
        while reader.writer_alive(stale_s=0.3) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not reader.writer_alive(stale_s=0.3) and not reader.closed
        proc.join(10)
        assert not reader.writer_alive(stale_s=3600)  # reaped: no such pid, however fresh the heartbeat
        assert Path(path).exists()  # a crashed writer leaves its ring (the next one replaces it)

    ring = create(path)  # replaces the dead writer's ring
    with RingReader.attach(path) as reader:
        assert reader.pid == os.getpid() and reader.writer_alive(stale_s=1.0)
        ring.close(unlink=False)
        assert reader.closed and not reader.writer_alive(stale_s=1.0)
        ring.close()  # idempotent, and a closed ring is not removed
        assert Path(path).exists()
        cpu = time.process_time()
        assert not reader.wait(reader.latest(), 0.3)
        assert time.process_time() - cpu < 0.1  # waiting sleeps, it does not spin


def test_atomic_creation(tmp_path):
    path = tmp_path / "a" / "b" / "cam0"
    shape, slots = (37, 51, 3), 5
    ring = create(path, shape, slots)
    assert sorted(os.listdir(path.parent)) == ["cam0"]  # no temporary file left behind
    stride = (128 + 37 * 51 * 3 + 63) // 64 * 64
    assert stride % 64 == 0 and path.stat().st_size == HEADER_SIZE + slots * stride
    assert oct(path.stat().st_mode & 0o777) == oct(0o644)

    # Rings created onto the same path while another process keeps attaching to it: it finds the old
    # ring or the new one, never a half-made file; closing the replaced ring leaves the new one alone.
    started, stop, results = CTX.Event(), CTX.Event(), CTX.Queue()
    watcher = start(creation_watcher, str(path), started, stop, results)
    assert started.wait(60)
    created, until = 0, time.monotonic() + 1.0
    while created < 200 or time.monotonic() < until:
        new = create(path, shape, slots)
        ring.close()
        ring = new
        created += 1
    stop.set()
    ok, missing, bad = results.get(timeout=60)
    finish(watcher)
    print(f"{created} rings created while another process attached {ok} times")
    assert bad == [] and missing == 0 and ok > 100
    assert sorted(os.listdir(path.parent)) == ["cam0"]
    ring.close()
    assert os.listdir(path.parent) == []


def test_default_path(monkeypatch):
    if not os.access("/dev/shm", os.W_OK):
        pytest.skip("/dev/shm is not writable here")
    monkeypatch.delenv("RIG_SHM_ROOT", raising=False)
    rig_name = f"test-ring-{os.getpid()}"
    path = default_path(rig_name, "cam 0")
    assert path == Path("/dev/shm/rig") / rig_name / "cam_0"
    root_was_there = path.parent.parent.exists()
    try:
        with create(path) as ring, RingReader.attach(path) as reader:
            ring.write(make_frame(0, images(ring.shape)))
            assert reader.read(0).frame_id == ID0
        assert not path.exists()
    finally:
        path.unlink(missing_ok=True)
        path.parent.rmdir()
        if not root_was_there:
            path.parent.parent.rmdir()


def test_started_is_called_once_the_slot_is_marked(tmp_path):
    """The writer's `started` callback (the daemon rings readers' doorbells from it) runs with the
    slot marked as being written, so a reader that looks then sees the frame coming, not done."""
    path = tmp_path / "rig" / "cam0"
    shape = (48, 64, 3)
    seen = []
    with create(path, shape, slots=2) as ring, RingReader.attach(path) as reader:
        imgs = images(shape, np.uint8)
        for k in range(3):
            ring.write(make_frame(k, imgs), started=lambda k=k: seen.append((reader.writing(k), reader.write_seq)))
            assert not reader.writing(k) and reader.write_seq == k + 1
    assert seen == [(True, 0), (True, 1), (True, 2)]
