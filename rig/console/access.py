"""Who may do what on the console: ASGI middleware in front of every route and WebSocket.

- No tokens: the console answers on a loopback address only (a request whose Host is not a
  loopback name is refused, 403: no DNS rebinding), and whoever reaches it is the operator.
- With tokens (any non-loopback address needs an operator token; `rig console` makes one):
  every request carries one (`?token=`, `Authorization: Bearer`, or the cookie the page sets);
  the operator token may change things, a viewer token may only watch; none: 401.
- Every WebSocket handshake and every state-changing request (POST, PUT, PATCH, DELETE) that
  carries an Origin must come from the console's own origin (403 otherwise); a viewer's
  state-changing request is 403; a body over MAX_BODY bytes is 413.
The role lands in the request's `scope["state"]["role"]`.
"""
from __future__ import annotations

from typing import Optional

from fastapi.responses import JSONResponse

from rig.http_access import _candidates, _headers, _host_name, _same_origin, is_loopback_name, token_matches

COOKIE = "rig_console_token"
MAX_BODY = 16 * 1024
CHANGES = {"POST", "PUT", "PATCH", "DELETE"}
OPERATOR, VIEWER = "operator", "viewer"


class ConsoleGuard:
    def __init__(self, app, operator_token: Optional[str], viewer_token: Optional[str] = None):
        if viewer_token is not None and operator_token is None:
            raise ValueError("a viewer token needs an operator token too")
        if operator_token is not None and viewer_token is not None and operator_token == viewer_token:
            raise ValueError("the viewer token must differ from the operator token")
        self.app = app
        self.operator = operator_token
        self.viewer = viewer_token

    def role(self, scope, headers: dict[str, str]) -> Optional[str]:
        if self.operator is None:
            return OPERATOR
        found = _candidates(scope, headers, COOKIE)
        if any(token_matches(c, self.operator) for c in found):
            return OPERATOR
        if self.viewer is not None and any(token_matches(c, self.viewer) for c in found):
            return VIEWER
        return None

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = _headers(scope)
        if self.operator is None:
            host = _host_name(headers.get("host", ""))
            if host and not is_loopback_name(host):
                return await _deny(scope, receive, send, 403, "this console has no token and answers on a loopback address only")
        role = self.role(scope, headers)
        if role is None:
            return await _deny(scope, receive, send, 401, "a valid token is needed (?token=, or Authorization: Bearer)")
        changes = scope["type"] == "http" and scope.get("method", "GET").upper() in CHANGES
        if (scope["type"] == "websocket" or changes) and not _same_origin(headers):
            return await _deny(scope, receive, send, 403, "a request from another origin is refused")
        if changes and role != OPERATOR:
            return await _deny(scope, receive, send, 403, "a viewer token can watch only; this needs the operator token")
        if changes:
            try:
                size = int(headers.get("content-length", "0") or 0)
            except ValueError:
                size = MAX_BODY + 1
            if size > MAX_BODY:
                return await _deny(scope, receive, send, 413, f"a request body is limited to {MAX_BODY} bytes")
        scope.setdefault("state", {})["role"] = role
        return await self.app(scope, receive, send)


async def _deny(scope, receive, send, status: int, reason: str) -> None:
    response = JSONResponse({"error": reason}, status_code=status, headers={"WWW-Authenticate": "Bearer"} if status == 401 else None)
    if scope["type"] == "http" or "websocket.http.response" in scope.get("extensions", {}):
        await response(scope, receive, send)
    else:
        await send({"type": "websocket.close", "code": 1008, "reason": reason})
