"""`RequestLimits`: an ASGI middleware that bounds what a client can make the daemon hold in memory: the request
body (413 above `max_body_bytes`, whether or not Content-Length is sent) and the query string (414)."""
from __future__ import annotations

import json

__all__ = ["RequestLimits", "MAX_QUERY_BYTES"]

MAX_QUERY_BYTES = 2048


class RequestLimits:
    def __init__(self, app, max_body_bytes: int) -> None:
        self.app = app
        self.max_body_bytes = int(max_body_bytes)

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if len(scope.get("query_string", b"")) > MAX_QUERY_BYTES:
            await _problem(send, 414, f"query string longer than {MAX_QUERY_BYTES} bytes")
            return
        length = dict(scope.get("headers", ())).get(b"content-length")
        if length is not None:
            if not length.isdigit():
                await _problem(send, 400, "invalid Content-Length")
                return
            if int(length) > self.max_body_bytes:
                await _problem(send, 413, f"request body larger than {self.max_body_bytes} bytes")
                return
        if scope.get("method") not in ("POST", "PUT", "PATCH"):
            await self.app(scope, receive, send)
            return
        # read the whole (small) body here, within the limit, then hand it on in one message
        body, more = bytearray(), True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            body += message.get("body", b"")
            more = message.get("more_body", False)
            if len(body) > self.max_body_bytes:
                await _problem(send, 413, f"request body larger than {self.max_body_bytes} bytes")
                return
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": bytes(body), "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


async def _problem(send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})
