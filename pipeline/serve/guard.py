"""ASGI middleware in front of every route: the bearer token and the request-body size limit.

The body limit is checked twice: against ``Content-Length`` before anything is read, and while the body
streams in (chunked uploads name no length), so no request makes the server buffer more than the limit.
"""

from __future__ import annotations

import hmac
import json

from starlette.exceptions import HTTPException

#: paths that answer without a token: the page, liveness and the API description hold no store data
OPEN_PATHS = frozenset({"/", "/health", "/docs", "/openapi.json", "/docs/oauth2-redirect"})


class BodyTooLarge(HTTPException):
    """Raised from ``receive`` when the streamed body passes the limit (an HTTPException, so the app's
    body parser re-raises it and its handler answers 413 JSON)."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body is larger than the limit of {limit} bytes")


class GuardMiddleware:
    def __init__(self, app, *, max_body_bytes: int, token: str | None = None) -> None:
        self.app = app
        self.max_body_bytes = int(max_body_bytes)
        self.token = token.encode() if token else None

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        if self.token is not None and scope.get("path") not in OPEN_PATHS:
            given = headers.get(b"authorization", b"")
            if not hmac.compare_digest(given, b"Bearer " + self.token):
                return await _reply(
                    send, 401, "missing or wrong bearer token", [(b"www-authenticate", b"Bearer")]
                )
        length = headers.get(b"content-length")
        if length is not None:
            try:
                too_big = int(length) > self.max_body_bytes
            except ValueError:
                return await _reply(send, 400, "bad Content-Length header")
            if too_big:
                return await _reply(send, 413, BodyTooLarge(self.max_body_bytes).detail)
        seen = 0
        started = False

        async def counted_receive():
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_body_bytes:
                    raise BodyTooLarge(self.max_body_bytes)
            return message

        async def tracking_send(message):
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counted_receive, tracking_send)
        except BodyTooLarge as exc:
            if not started:
                await _reply(send, 413, exc.detail)


async def _reply(send, status: int, message: str, extra_headers: list | None = None) -> None:
    body = json.dumps({"error": message}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": status, "headers": headers + (extra_headers or [])})
    await send({"type": "http.response.body", "body": body})
