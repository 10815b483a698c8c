"""Access to the product's HTTP servers (`rig live`, the camera daemons' control API): ASGI middleware
in front of every route and WebSocket.

With a token, every request must carry it (`?token=`, `Authorization: Bearer`, or the server's
cookie when it names one): else 401 and nothing else. Without a token the server answers on a
loopback address only: a request whose Host is not a loopback name gets 403 (DNS rebinding), and a
browser's WebSocket handshake must come from the server's own origin.
"""
from __future__ import annotations

import hmac
import ipaddress
import socket
from typing import Optional
from urllib.parse import parse_qs, urlsplit

from fastapi.responses import JSONResponse
from starlette.requests import cookie_parser

from common.net import listening_socket
from rig.errors import RigError


def _headers(scope) -> dict[str, str]:
    out: dict[str, str] = {}
    for k, v in scope.get("headers", []):
        out.setdefault(k.decode("latin-1").lower(), v.decode("latin-1"))
    return out


def _host_name(host_header: str) -> str:
    """'127.0.0.1:8080' -> '127.0.0.1', '[::1]:8080' -> '::1'."""
    host = host_header.strip().lower()
    if host.startswith("["):
        return host[1:].partition("]")[0]
    return host.rpartition(":")[0] if host.count(":") == 1 else host


def is_loopback_name(name: str) -> bool:
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def _same_origin(headers: dict[str, str]) -> bool:
    """A WebSocket handshake from a browser carries Origin: it must be this server's own page."""
    origin = headers.get("origin")
    if origin is None:
        return True  # not a browser (ffplay, a script): nothing to forge
    parts = urlsplit(origin)
    return parts.scheme in ("http", "https") and bool(parts.netloc) and parts.netloc.lower() == headers.get("host", "").lower()


def token_matches(candidate: Optional[str], token: str) -> bool:
    return candidate is not None and hmac.compare_digest(candidate.encode("utf-8", "surrogatepass"), token.encode("utf-8"))


def _candidates(scope, headers: dict[str, str], cookie_name: Optional[str]) -> list[str]:
    found = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token", [])[:4]
    auth = headers.get("authorization", "")
    scheme, _, value = auth.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        found.append(value.strip())
    cookie = cookie_parser(headers.get("cookie", "")).get(cookie_name) if cookie_name else None
    if cookie:
        found.append(cookie)
    return found


class AccessGuard:
    """ASGI middleware in front of every route, static files and the WebSocket included."""

    def __init__(self, app, token: Optional[str], cookie: Optional[str] = None):
        self.app = app
        self.token = token
        self.cookie = cookie

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = _headers(scope)
        if self.token is None:
            host = _host_name(headers.get("host", ""))
            if host and not is_loopback_name(host):  # (no Host at all: not a browser, nothing to rebind)
                return await self._deny(scope, receive, send, 403, "this server has no token and answers on a loopback address only")
        elif not any(token_matches(c, self.token) for c in _candidates(scope, headers, self.cookie)):
            return await self._deny(scope, receive, send, 401, "a valid token is needed (?token=, or Authorization: Bearer)")
        if scope["type"] == "websocket" and not _same_origin(headers):
            return await self._deny(scope, receive, send, 403, "WebSocket from another origin refused")
        return await self.app(scope, receive, send)

    @staticmethod
    async def _deny(scope, receive, send, status: int, reason: str) -> None:
        response = JSONResponse({"error": reason}, status_code=status,
                                headers={"WWW-Authenticate": "Bearer"} if status == 401 else None)
        if scope["type"] == "http":
            await response(scope, receive, send)
        elif "websocket.http.response" in scope.get("extensions", {}):
            await response(scope, receive, send)  # the handshake is answered with this HTTP response
        else:
            await send({"type": "websocket.close", "code": 1008, "reason": reason})  # before accept


def bind_socket(host: str, port: int, what: str) -> socket.socket:
    """A listening, non-blocking TCP socket for uvicorn (port 0: any free port); one-line RigError
    naming `what` when the address cannot be had."""
    try:
        return listening_socket(host, port)
    except OSError as exc:
        raise RigError(f"{what}: cannot listen on {host}:{port}: {exc.strerror or exc}") from None
