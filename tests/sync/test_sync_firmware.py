"""The firmware's C code, compiled on the host with g++: the shared protocol vectors, the board
logic on a simulated clock, and the firmware served on a pty to the real host driver."""
from __future__ import annotations

import os
import subprocess
import tty

from sync.protocol import BOARD, HOST, format_line, parse_line, pulse_offset_us


def run(exe, *args, stdin: str) -> list[str]:
    proc = subprocess.run([str(exe), *args], input=stdin, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()


def test_firmware_parser_passes_the_shared_vectors(firmware_host, vectors):
    for direction in (HOST, BOARD):
        cases = [v for v in vectors["valid"] + vectors["invalid"] if v["dir"] == direction]
        out = run(firmware_host, "parse", direction, stdin="".join(v["line"].encode("latin-1").hex() + "\n" for v in cases))
        assert len(out) == len(cases)
        for v, got in zip(cases, out):
            if "error" in v:
                assert got == f"ERR {v['error']}", (v, got)
            else:
                assert got == " ".join(["OK", v["kind"], *map(str, v["args"])]), (v, got)


def test_firmware_formatter_passes_the_shared_vectors(firmware_host, vectors):
    cases = [v for v in vectors["valid"] if v["canonical"]]
    out = run(firmware_host, "format", stdin="".join(f"{v['dir']} {v['kind']} {' '.join(map(str, v['args']))}\n" for v in cases))
    assert out == [v["line"] for v in cases]
    bad = [v for v in vectors["format_invalid"] if " " not in "".join(map(str, v["args"]))]  # the harness splits on spaces
    out = run(firmware_host, "format", stdin="".join(f"{v['dir']} {v['kind']} {' '.join(map(str, v['args']))}\n" for v in bad))
    assert out == ["ERR"] * len(bad)


def board_script(exe, steps: list[tuple[int, str | None]]) -> list[tuple[int, str, tuple]]:
    """Run the board logic on a simulated clock; returns (board_us, kind, args) of every line it sent."""
    text = "".join(f"@{t}" + (f" {format_line(*cmd, direction=HOST)}" if cmd else "") + "\n" for t, cmd in steps)
    out = []
    for line in run(exe, "script", "TB-TEST", stdin=text):
        t, sent = line.split(" ", 1)
        if sent.startswith("#"):
            out.append((int(t), sent, ()))
            continue
        msg = parse_line(sent, BOARD)
        out.append((int(t), msg.kind, msg.args))
    return out


def test_firmware_runs_a_pulse_train_on_its_schedule(firmware_host):
    sent = board_script(firmware_host, [(10, ("HELLO", 1)), (20, ("RATE", 2, 30000, 100)), (1000, ("START", 3, 5)), (400000, None)])
    assert sent[0][1:] == ("BOOT", (1, "1.0.0", "TB-TEST"))
    assert sent[1][1:] == ("ID", (1, 1, "1.0.0", "TB-TEST"))
    assert sent[2][1:] == ("OK", (2,)) and sent[3][1:] == ("OK", (3,))
    pulses = [args for _, kind, args in sent if kind == "PULSE"]
    start = 1000 + 2000  # START at 1000 us, first pulse 2 ms later
    assert pulses == [(k, start + pulse_offset_us(k, 30000)) for k in range(5)]
    assert sent[-1][1:] == ("DONE", (5,))


def test_firmware_refuses_bad_settings_and_answers_retries_once(firmware_host):
    sent = board_script(firmware_host, [
        (10, ("RATE", 1, 0, 100)),            # 0 Hz
        (20, ("RATE", 2, 30000, 40000)),      # pulse longer than the period
        (30, ("START", 3, 0)),
        (40, ("START", 3, 0)),                # the same request again (its reply was lost): not run twice
        (50, ("RATE", 4, 60000, 100)),        # busy while a train runs
        (60, ("STATUS", 5)),
        (100000, ("STOP", 6)),
        (100010, None),
    ])
    replies = [(k, a) for _, k, a in sent if k in ("OK", "ERR", "STATUS", "DONE")]
    assert replies[:5] == [("ERR", (1, "RANGE")), ("ERR", (2, "RANGE")), ("OK", (3,)), ("OK", (3,)), ("ERR", (4, "BUSY"))]
    assert replies[5][0] == "STATUS" and replies[5][1][:4] == (5, 1, 30000, 100)
    pulses = [a for _, k, a in sent if k == "PULSE"]
    assert [p[0] for p in pulses] == [0, 1, 2]  # one train: the retried START did not restart it
    assert replies[-2:] == [("OK", (6,)), ("DONE", (3,))]


def test_firmware_answers_garbage_with_an_error_and_keeps_going(firmware_host):
    text = "@5 HELLO 1*0000\n@6 TIME 1\n@7 " + format_line("TIME", 2, direction=HOST) + "\n@8 " + format_line("FLASH", 3, 250, direction=HOST) + "\n@250007\n@250008\n"
    out = [line.split(" ", 1) for line in run(firmware_host, "script", stdin=text)]
    lines = [(int(t), sent) for t, sent in out if not sent.startswith("#")]
    led = [(int(t), sent) for t, sent in out if sent.startswith("#LED")]
    msgs = [(t, parse_line(sent, BOARD)) for t, sent in lines]
    assert [(m.kind, m.args) for _, m in msgs[1:3]] == [("ERR", (0, "CHECKSUM"))] * 2
    assert [(m.kind, m.args) for _, m in msgs[3:]] == [("TIME", (2, 7)), ("OK", (3,)), ("FLASH", (8, 250))]
    assert led == [(8, "#LED 1"), (250008, "#LED 0")]  # on at 8 us for 250 ms


def test_host_driver_talks_to_the_compiled_firmware_over_a_pty(firmware_host, tmp_path):
    from sync.board import TriggerBoard

    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    link = tmp_path / "board"
    os.symlink(os.ttyname(slave), link)
    proc = subprocess.Popen([str(firmware_host), "serve", "TB-PTY"], stdin=master, stdout=master)
    os.close(master)
    pulses = []
    board = TriggerBoard(f"serial://{link}")
    try:
        info = board.connect()
        assert (info.board_id, info.firmware) == ("TB-PTY", "1.0.0")
        board.subscribe(on_pulse=pulses.append)
        board.set_rate(200.0, 50)
        board.warm_up(0.5)
        board.start(20)
        assert board.wait_done(5.0) == 20
        assert [p.index for p in pulses] == list(range(20))
        steps = [b.board_us - a.board_us for a, b in zip(pulses, pulses[1:])]
        assert set(steps) == {5000}
        # the firmware's clock is the host's monotonic clock in us: the model must map it nearly 1:1
        assert abs(board.clock.drift_ppm) < 200
        status = board.status()
        assert status["pulses"] == 20 and not status["running"]
        assert board.report()["corrupt_lines"] == 0
    finally:
        board.close()
        proc.terminate()
        proc.wait(timeout=5)
        os.close(slave)
