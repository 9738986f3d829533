"""The job page's files: everything it names exists, nothing comes from another host, and the
vendored three.js is the release pinned in web/. tests/e2e/test_page.py fetches them from the
running API and drives the page in a real browser."""

from __future__ import annotations

import base64
import hashlib
import json
import re
from pathlib import Path

import pytest

from service.routes import pages

ROOT = Path(__file__).resolve().parents[2]
STATIC = ROOT / "service" / "static"
VENDOR = STATIC / "vendor" / "three"
OWN_FILES = sorted(STATIC.glob("*.*"))
HTML = (STATIC / "app.html").read_text()


def import_map() -> str:
    match = re.search(r'<script type="importmap">(.*?)</script>', HTML, flags=re.DOTALL)
    assert match, "app.html has no import map"
    return match.group(1)


def page_files() -> set[str]:
    """Every path under /app/static that the page, its scripts, styles and import map name."""
    names: set[str] = set(json.loads(import_map())["imports"].values())
    for own in OWN_FILES:
        names |= set(re.findall(r"""["'(](/app/static/[^"')]+)["')]""", own.read_text()))
    return names


def test_the_policy_allows_the_import_map_and_this_origin_only() -> None:
    csp = dict(part.strip().split(" ", 1) for part in pages.CSP.split(";"))
    digest = base64.b64encode(hashlib.sha256(import_map().encode()).digest()).decode()
    assert csp["script-src"] == f"'self' 'sha256-{digest}'"
    assert csp["default-src"] == "'none'" and csp["connect-src"] == "'self'"


def test_every_file_the_page_names_exists() -> None:
    names = page_files()
    assert {"/app/static/vendor/three/three.module.js", "/app/static/vendor/three/OrbitControls.js",
            "/app/static/app.js", "/app/static/viewer.js"} <= names
    for name in names:
        assert (STATIC / name.removeprefix("/app/static/")).is_file(), name


@pytest.mark.parametrize("path", OWN_FILES, ids=lambda p: p.name)
def test_the_page_names_no_other_host(path: Path) -> None:
    text = path.read_text().replace('xmlns="http://www.w3.org/2000/svg"', "")  # a name only
    assert not re.search(r"https?://", text), f"{path.name} names another host"


def test_vendored_modules_import_only_each_other() -> None:
    for module in VENDOR.glob("*.js"):
        specifiers = re.findall(r"""^(?:import|export)\b[^;]*?\bfrom\s*['"]([^'"]+)['"]""",
                                module.read_text(), flags=re.MULTILINE)
        assert set(specifiers) <= {"three", "./three.core.js"}, (module.name, set(specifiers))


def test_vendored_three_is_the_pinned_release() -> None:
    pinned = json.loads((ROOT / "web" / "package.json").read_text())["dependencies"]["three"]
    lock = json.loads((ROOT / "web" / "package-lock.json").read_text())
    assert re.fullmatch(r"\d+\.\d+\.\d+", pinned), "pin an exact version"
    assert lock["packages"]["node_modules/three"]["version"] == pinned
    assert (VENDOR / "VERSION").read_text().splitlines()[0] == f"three {pinned}"
    revision = re.search(r"const REVISION = '(\d+)'", (VENDOR / "three.core.js").read_text())
    assert revision and revision.group(1) == pinned.split(".")[1]
    assert "MIT License" in (VENDOR / "LICENSE").read_text()
