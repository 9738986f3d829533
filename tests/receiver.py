"""A real HTTP server on 127.0.0.1 that receives callbacks: it records each POST (path and
JSON body) and answers the statuses it is told to, then 200."""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any


class Receiver:
    def __init__(self, fail_first: int = 0, fail_status: int = 503) -> None:
        self.received: list[tuple[str, Any]] = []
        self.fail_left = fail_first
        self.fail_status = fail_status
        self.lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - the http.server name
                body = self.rfile.read(int(self.headers.get("content-length", 0)))
                with receiver.lock:
                    receiver.received.append((self.path, json.loads(body or b"null")))
                    failing = receiver.fail_left > 0
                    receiver.fail_left -= failing
                self.send_response(receiver.fail_status if failing else 200)
                self.send_header("content-length", "0")
                self.end_headers()

            def log_message(self, *_: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}"

    def posts(self, path: str) -> list[Any]:
        with self.lock:
            return [body for p, body in self.received if p == path]

    def wait_for(self, path: str, count: int = 1, timeout: float = 60.0) -> list[Any]:
        """The bodies posted to ``path`` once there are ``count`` of them (or fail)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            bodies = self.posts(path)
            if len(bodies) >= count:
                return bodies
            time.sleep(0.05)
        raise AssertionError(f"{count} POST(s) to {path} expected, got {self.posts(path)}")

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
