"""/app: the job page for people, and /app/static: its scripts, styles and the vendored three.js.

The page talks to the API like any client (Bearer key, no cookies) and loads nothing from
elsewhere: its Content-Security-Policy allows this origin only, so it works offline.
"""

from __future__ import annotations

import base64
import hashlib
import os
import re
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

STATIC = Path(__file__).resolve().parents[1] / "static"
PAGE = (STATIC / "app.html").read_text(encoding="utf-8")


def _inline_script_hashes(html: str) -> list[str]:
    """CSP sources of the page's inline scripts (its import map), by their SHA-256."""
    return [f"'sha256-{base64.b64encode(hashlib.sha256(body.encode()).digest()).decode()}'"
            for body in re.findall(r"<script[^>]*>(.*?)</script>", html, flags=re.DOTALL)
            if body]


CSP = "; ".join([
    "default-src 'none'",
    "script-src 'self' " + " ".join(_inline_script_hashes(PAGE)),
    "style-src 'self'",
    "img-src 'self' data: blob:",
    "connect-src 'self'",
    "base-uri 'none'",
    "form-action 'none'",
    "frame-ancestors 'none'",
])
HEADERS = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",
}

router = APIRouter(include_in_schema=False)


@router.get("/app", response_class=HTMLResponse)
def job_page() -> HTMLResponse:
    return HTMLResponse(PAGE, headers=HEADERS)


class _Assets(StaticFiles):
    """The page's scripts, styles and icon; the page itself only at /app, with its policy."""

    def lookup_path(self, path: str) -> tuple[str, os.stat_result | None]:
        if path.endswith(".html"):
            return "", None
        return super().lookup_path(path)


def static_files() -> StaticFiles:
    """The page's files, mounted at /app/static."""
    return _Assets(directory=STATIC)
