"""A port closed under the reader thread (close() during a read, or the board dropped) ends the read
quietly, whatever pyserial raises for it: on socket:// it is a ValueError from select on fd -1."""
from __future__ import annotations

import socket
import threading
import time

from sync.link import SerialLink


def test_closing_a_socket_port_under_the_reader_raises_nothing_in_its_thread():
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    port = server.getsockname()[1]
    errors = []
    old = threading.excepthook
    threading.excepthook = lambda args: errors.append(args.exc_value)
    try:
        lost = []
        link = SerialLink(f"socket://127.0.0.1:{port}", on_message=lambda m, t: None, on_lost=lost.append)
        serial_port = link.open()
        conn, _ = server.accept()
        # the moment of the race: another thread has closed the port's socket (its fd is -1) and
        # pyserial still counts the port open; the reader's next read selects on fd -1
        serial_port._socket.close()
        link.start()
        deadline = time.monotonic() + 5
        while not lost and not errors and time.monotonic() < deadline:
            time.sleep(0.01)
        link.close()
        conn.close()
    finally:
        threading.excepthook = old
        server.close()
    assert errors == [], errors[:3]
    assert len(lost) == 1  # the link says the port is lost, once
