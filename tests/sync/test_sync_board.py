"""The host driver against the emulated board, over a real pty pair and a loopback socket."""
from __future__ import annotations

import os
import threading
import time
import tty

import pytest

from simulator.trigger_board import TriggerBoardEmulator
from sync.board import TriggerBoard
from sync.errors import TriggerBoardError


@pytest.mark.parametrize("transport", ["pty", "socket"])
def test_handshake_rate_and_a_pulse_train(transport):
    with TriggerBoardEmulator({"transport": transport, "drift_ppm": 50, "clock_offset_us": 10**9}) as emu:
        edges = []
        emu.add_pulse_output(lambda index, host_ns: edges.append((index, host_ns)))
        with TriggerBoard(emu.url) as board:
            info = board.connect()
            assert info.board_id == "SIM-TB-0001" and info.protocol == 1
            pulses = []
            board.subscribe(on_pulse=pulses.append)
            board.set_rate(100.0, 200.0)
            board.warm_up(0.5)
            board.start(25)
            assert board.wait_done(5.0) == 25
            time.sleep(0.05)
            assert [p.index for p in pulses] == list(range(25))
            assert [i for i, _ in edges] == list(range(25))
            # the board reports each edge at its scheduled board time; the outputs got its host time
            for p, (_, host_ns) in zip(pulses, edges):
                assert emu.truth_host_ns(p.board_us) == host_ns
                assert abs(board.clock.board_to_host_ns(p.board_us) - host_ns) < 1_000_000  # within 1 ms at 0.5 s warm-up
            assert board.status() == {"running": False, "rate_hz": 100.0, "pulse_width_us": 200, "pulses": 25, "bad_lines": 0}


def test_the_board_refuses_settings_it_cannot_do(board):
    with pytest.raises(TriggerBoardError, match="shorter than the period"):
        board.set_rate(100.0, 20000.0)
    board.start(0)
    with pytest.raises(TriggerBoardError, match="BUSY"):
        board.start(0)
    board.stop()
    assert board.wait_done(2.0) is not None


def test_flash_drives_the_led_output_and_reports_its_board_time(emulator, board):
    led = []
    emulator.add_led_output(lambda on, host_ns: led.append((on, host_ns)))
    event = board.flash(30)
    assert event is not None and event.values["ms"] == 30
    time.sleep(0.1)
    truth = emulator.flashes[-1]
    assert event.values["board_us"] == truth.board_us
    assert led == [(True, truth.host_start_ns), (False, truth.host_end_ns)]
    assert truth.host_end_ns - truth.host_start_ns == pytest.approx(30e6, abs=2)


def test_corrupt_and_delayed_lines_are_counted_and_survived():
    opts = {"corrupt_rate": 0.1, "delay_rate": 0.1, "delay_ms": 30.0, "seed": 5}
    with TriggerBoardEmulator(opts) as emu, TriggerBoard(emu.url, retries=6) as board:
        board.connect(timeout=5.0)
        pulses = []
        board.subscribe(on_pulse=pulses.append)
        board.set_rate(200.0, 100.0)  # requests get through: retries answer lost or garbled lines
        board.start(200)
        assert board.wait_done(5.0) is not None or board.status()["pulses"] == 200
        time.sleep(0.2)
        report = board.report()
        assert report["corrupt_lines"] > 0
        assert report["out_of_order_lines"] > 0 and report["late_pulses"] > 0
        received = {p.index for p in pulses}
        assert received | set(range(200)) == set(range(200))
        # every pulse report either arrived (in order or late) or is counted as missing
        assert len(received) + report["missing_pulse_reports"] == 200
        assert report["missing_pulse_reports"] > 0
        assert sum(report["board_errors"].values()) > 0 or report["retries"] > 0


def test_dropped_pulses_never_reach_the_cameras():
    with TriggerBoardEmulator({"drop_pulse_rate": 0.3, "seed": 2}) as emu, TriggerBoard(emu.url) as board:
        edges = []
        emu.add_pulse_output(lambda index, host_ns: edges.append(index))
        board.connect()
        board.set_rate(200.0, 100.0)
        board.start(100)
        board.wait_done(3.0)
        time.sleep(0.05)
        dropped = set(emu.dropped_pulses())
        assert 10 < len(dropped) < 50
        assert set(edges) == set(range(100)) - dropped


@pytest.mark.parametrize("transport", ["pty", "socket"])
def test_unplug_mid_run_is_reported_and_the_driver_reconnects(transport):
    with TriggerBoardEmulator({"transport": transport}) as emu:
        events = []
        got_event = threading.Condition()

        def on_event(e):
            with got_event:
                events.append(e)
                got_event.notify_all()

        with TriggerBoard(emu.url, reconnect_interval=0.1) as board:
            board.connect()
            pulses = []
            board.subscribe(on_pulse=pulses.append, on_event=on_event)
            board.set_rate(100.0, 100.0)
            board.start(0)
            time.sleep(0.3)
            emu.unplug()
            with got_event:
                assert got_event.wait_for(lambda: any(e.kind == "disconnected" for e in events), 3.0)
            assert not board.connected
            lost = next(e for e in events if e.kind == "disconnected")
            assert "disconnected" in lost.detail
            with pytest.raises(TriggerBoardError, match="not connected"):
                board.start(0)
            n_before = len(pulses)
            assert n_before > 10
            time.sleep(0.3)
            assert len(pulses) == n_before  # the train stopped with the board
            emu.replug()
            with got_event:
                assert got_event.wait_for(lambda: any(e.kind == "connected" and e.values.get("reconnect") for e in events), 5.0)
            assert board.connected and board.counters.reconnects == 1
            board.start(5)  # a fresh board: indices from 0 again
            assert board.wait_done(3.0) == 5
            assert [p.index for p in pulses[n_before:]] == [0, 1, 2, 3, 4]


def test_ports_without_a_board_are_reported(tmp_path):
    with pytest.raises(TriggerBoardError, match="cannot open"):
        TriggerBoard(f"serial://{tmp_path}/nothing").connect()
    with pytest.raises(TriggerBoardError, match="rig.capture.session"):
        TriggerBoard("sim://trigger").connect()
    master, slave = os.openpty()  # a port where nobody speaks the protocol
    tty.setraw(slave)
    try:
        with pytest.raises(TriggerBoardError, match="no trigger board answers"):
            TriggerBoard(os.ttyname(slave)).connect(timeout=0.5)
    finally:
        os.close(master)
        os.close(slave)
