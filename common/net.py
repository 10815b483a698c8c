"""Sockets the servers share (the live server, the daemons' APIs, the emulators)."""
from __future__ import annotations

import socket


def listening_socket(host: str, port: int) -> socket.socket:
    """A listening, non-blocking TCP socket on host:port (port 0: any free port), for uvicorn to
    serve on; OSError when the address cannot be had."""
    family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(128)
    except OSError:
        sock.close()
        raise
    sock.setblocking(False)
    return sock
