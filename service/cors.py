"""CORS for the origins in ``CORS_ORIGINS``: browser scripts of those portals may call the API.

An allowed origin gets ``Access-Control-Allow-Origin`` (its own origin, never ``*`` unless the
setting is ``*``) on every answer, errors included, and the headers a portal reads exposed
(``Location`` of a new job, ``Preference-Applied``, ``Content-Range`` of a partial download ...).
A preflight (``OPTIONS`` with ``Origin`` and ``Access-Control-Request-Method``) from an allowed
origin is answered here with 204. Any other origin gets no CORS header at all: its preflight
falls through to the routes (405) and the browser keeps its script out.

The API authenticates with a bearer key, not cookies: credentials are not allowed.
"""

from __future__ import annotations

from starlette.datastructures import Headers, MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

METHODS = "GET, HEAD, POST, PUT, PATCH, DELETE, OPTIONS"
EXPOSED = ", ".join([
    "Location", "Preference-Applied", "Content-Range", "Content-Length", "Content-Disposition",
    "Accept-Ranges", "ETag", "Last-Modified", "Link", "Retry-After", "WWW-Authenticate",
])
#: How long a browser may cache a preflight's answer (seconds).
MAX_AGE = "600"


class CORSMiddleware:
    """Pure ASGI middleware (streams and background answers pass untouched)."""

    def __init__(self, app: ASGIApp, origins: list[str]) -> None:
        self.app = app
        self.any = "*" in origins
        self.origins = {o.rstrip("/") for o in origins if o != "*"}

    def allowed(self, origin: str | None) -> bool:
        return bool(origin) and (self.any or origin in self.origins)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        origin = headers.get("origin")
        if not self.allowed(origin):
            await self.app(scope, receive, send)
            return
        assert origin is not None
        if scope["method"] == "OPTIONS" and "access-control-request-method" in headers:
            await self.preflight(origin, headers, send)
            return

        async def send_with_cors(message: Message) -> None:
            if message["type"] == "http.response.start":
                out = MutableHeaders(scope=message)
                out["Access-Control-Allow-Origin"] = "*" if self.any else origin
                out["Access-Control-Expose-Headers"] = EXPOSED
                if not self.any:
                    out.add_vary_header("Origin")
            await send(message)

        await self.app(scope, receive, send_with_cors)

    async def preflight(self, origin: str, headers: Headers, send: Send) -> None:
        answer = [
            (b"access-control-allow-origin", ("*" if self.any else origin).encode("latin-1")),
            (b"access-control-allow-methods", METHODS.encode()),
            (b"access-control-max-age", MAX_AGE.encode()),
            (b"vary", b"Origin, Access-Control-Request-Headers"),
            (b"content-length", b"0"),
        ]
        requested = headers.get("access-control-request-headers")
        if requested:  # whatever the allowed portal's script sends (Authorization, Prefer ...)
            answer.append((b"access-control-allow-headers", requested.encode("latin-1")))
        await send({"type": "http.response.start", "status": 204, "headers": answer})
        await send({"type": "http.response.body", "body": b""})
