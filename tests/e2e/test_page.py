"""The job page in a real headless Chromium against the real stack (API, Redis, a worker).

Debian's Chromium (``/usr/bin/chromium``, or ``$CHROMIUM``) is driven by Playwright. Without it
every test here fails when ``CI`` is set and is skipped otherwise, saying why. Any request the
page makes to a host other than 127.0.0.1 is refused and fails the test: the page must work
offline. Set ``LIDAR_OUTLIERS_SCREENSHOTS=docs`` to keep the two screenshots the README shows.
"""

from __future__ import annotations

import io
import json
import os
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn
from urllib.parse import urlsplit

import numpy as np
import pytest

from lidar_outliers.tools.simulator import simulate, write_simulation
from tests.e2e.stack import RedisServer, Stack, running_stack

CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
    # WebGL on the CPU: no GPU here, and Chromium no longer falls back to SwiftShader unasked
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    # a name lookup for any other host fails inside the browser, whatever asks for it
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
]
BACKGROUND = np.array([0x16, 0x19, 0x1D])  # the viewer's clear colour
TEMPORAL_RED = np.array([0xE6, 0x19, 0x4B])  # the colour of bit 1 in viewer.js
PIPELINE = {"pipeline": [{"detector": "temporal", "sigma": 0.02}, {"detector": "patch"}]}


def unavailable(reason: str) -> NoReturn:
    message = f"the job page tests need Chromium: {reason}"
    if os.environ.get("CI"):
        pytest.fail(message, pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if not os.access(CHROMIUM, os.X_OK):
        unavailable(f"{CHROMIUM} not found (install it with `apt-get install chromium`)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        unavailable("the Python package playwright is missing (pip install -e '.[test]')")
    with sync_playwright() as playwright:
        try:
            chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        except Exception as exc:
            unavailable(f"{CHROMIUM} did not start: {exc}")
        yield chromium
        chromium.close()


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory,
          compiled_detectors: None) -> Iterator[Stack]:
    with running_stack(tmp_path_factory.mktemp("data"), redis_server.new_url()) as s:
        yield s


@pytest.fixture(scope="module")
def keys(stack: Stack) -> dict[str, str]:
    return {name: stack.add_user(name) for name in ("alice", "bob")}


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A stretch of the paper's condition A: a road with a wall, cars and exhaust spikes."""
    return write_simulation(simulate("A", 3, 0.02), tmp_path_factory.mktemp("sim"))


class Browsing:
    """A browser context that refuses, and records, every request leaving 127.0.0.1, and
    records uncaught script errors and Content-Security-Policy refusals."""

    def __init__(self, browser: Any) -> None:
        self.outside: list[str] = []
        self.errors: list[str] = []
        self.context = browser.new_context(viewport={"width": 1400, "height": 1000},
                                           accept_downloads=True, service_workers="block")
        self.context.route("**/*", self._route)

    def _route(self, route: Any) -> None:
        url = route.request.url
        if urlsplit(url).hostname == "127.0.0.1":
            route.continue_()
        else:
            self.outside.append(url)
            route.abort()

    def page(self) -> Any:
        page = self.context.new_page()
        page.set_default_timeout(60_000)
        page.on("pageerror", lambda error: self.errors.append(f"uncaught: {error}"))
        page.on("console", lambda msg: self.errors.append(msg.text)
                if "Content Security Policy" in msg.text else None)
        return page


@pytest.fixture
def browsing(browser: Any) -> Iterator[Callable[[], Browsing]]:
    opened: list[Browsing] = []

    def new() -> Browsing:
        opened.append(Browsing(browser))
        return opened[-1]

    yield new
    for b in opened:
        assert b.context.cookies() == []  # the key travels as a header, never as a cookie
        b.context.close()
        assert b.outside == [], f"the page asked for hosts other than 127.0.0.1: {b.outside}"
        assert b.errors == []


@pytest.fixture(scope="module")
def screenshots(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = os.environ.get("LIDAR_OUTLIERS_SCREENSHOTS")
    return Path(folder) if folder else tmp_path_factory.mktemp("screenshots")


def sign_in(page: Any, stack: Stack, key: str) -> None:
    page.goto(f"{stack.url}/app")
    page.fill("#key", key)
    page.click("#sign-in-form button")
    page.wait_for_selector("#signed-in:not([hidden])")


def pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def near(image: np.ndarray, colour: np.ndarray, tolerance: int) -> int:
    return int((np.abs(image - colour).sum(axis=-1) <= tolerance).sum())


@pytest.fixture(scope="module")
def finished_job() -> dict[str, Any]:
    """The job the first test runs through the page, for the tests after it."""
    return {}


def test_the_page_and_every_file_it_names_are_served(stack: Stack) -> None:
    from tests.service.test_pages import page_files

    with stack.client() as http:
        page = http.get("/app")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert page.headers["content-security-policy"].startswith("default-src 'none'")
        assert "/app" in [link["href"] for link in http.get("/").json()["links"]]
        for name in sorted(page_files()):
            answer = http.get(name)
            assert answer.status_code == 200, name
            assert answer.headers["content-type"].split(";")[0] in (
                "text/javascript", "application/javascript", "text/css", "image/svg+xml"), name
        assert http.get("/app/static/..%2Froutes%2Fpages.py").status_code == 404
        assert http.get("/app/static/app.html").status_code == 404  # only /app, with its policy


def test_wrong_key_shows_the_401_problem(stack: Stack, browsing) -> None:
    page = browsing().page()
    page.goto(f"{stack.url}/app")
    page.fill("#key", "not-a-key")
    page.click("#sign-in-form button")
    page.wait_for_selector("#problem:not([hidden])")
    assert page.inner_text("#problem") == ("401 Missing or wrong API key: the API key is wrong "
                                           "or revoked")
    assert page.is_hidden("#signed-in")
    assert page.evaluate("sessionStorage.length") == 0


def test_upload_follow_view_statistics_and_download(stack: Stack, keys: dict[str, str],
                                                    browsing, survey: Path, screenshots: Path,
                                                    finished_job: dict[str, Any]) -> None:
    page = browsing().page()
    sign_in(page, stack, keys["alice"])
    assert page.evaluate("sessionStorage.length") == 1

    page.set_input_files("#file", str(survey))
    page.click("#new-job summary")
    page.fill("#inputs", json.dumps(PIPELINE))
    page.click("#submit")
    page.wait_for_url(re.compile(r"#/jobs/[0-9a-f]+$"))
    job_id = page.url.rsplit("/", 1)[-1]
    row = page.locator(f"#job-table tr[data-job='{job_id}']")
    row.wait_for()
    assert row.locator("progress").count() == 1 and survey.name in row.inner_text()
    assert page.get_attribute("#upload-progress", "value") == "100"

    # live progress: the page polls until the worker is done
    page.wait_for_selector("#job[data-status=successful]", timeout=240_000)
    assert page.get_attribute("#job-progress", "value") == "100"
    page.wait_for_function(f"document.querySelector(\"#job-table tr[data-job='{job_id}']\")"
                           ".innerText.includes('100 %')")
    assert "successful" in row.inner_text()

    with stack.client(keys["alice"]) as http:
        stats = http.get(f"/jobs/{job_id}/results/statistics").json()
        cloud = http.get(f"/jobs/{job_id}/results/cloud").content

    # the 3-D view: every point drawn (fewer than the page's budget), the canvas not blank
    page.wait_for_selector("#viewer[data-drawn]")
    assert int(page.get_attribute("#viewer", "data-drawn")) == stats["overall"]["points"]
    canvas = page.locator("#viewer canvas")
    image = pixels(canvas.screenshot())
    lit = image.shape[0] * image.shape[1] - near(image, BACKGROUND, 24)
    assert lit > 0.02 * image.shape[0] * image.shape[1], f"only {lit} pixels drawn"
    red = near(image, TEMPORAL_RED, 60)
    assert red > 0, "no point in temporal's colour"
    page.screenshot(path=str(screenshots / "page-jobs.png"))
    page.locator("#job").screenshot(path=str(screenshots / "page-view.png"))

    # a toggle per detector that flagged something; hiding temporal hides its points
    toggles = page.locator("#legend input[data-detector]")
    flagged = {name for name, n in stats["overall"]["flagged_by_bit"].items() if n}
    assert {toggles.nth(i).get_attribute("data-detector") for i in range(toggles.count())} \
        == flagged
    before = int(page.get_attribute("#viewer", "data-drawn"))
    page.uncheck("#legend input[data-detector=temporal]")
    page.wait_for_function(f"Number(document.querySelector('#viewer').dataset.drawn) < {before}")
    assert near(pixels(canvas.screenshot()), TEMPORAL_RED, 60) == 0
    page.check("#legend input[data-detector=temporal]")

    # the statistics as tables: per stage, and flagged by bit
    stages = page.locator("#stage-table tbody tr")
    assert stages.count() == len(stats["stages"]) == 2
    for i, stage in enumerate(stats["stages"]):
        cells = stages.nth(i).locator("td").all_inner_texts()
        assert cells[1] == stage["detector"]
        assert cells[3] == f"{stage['points_tested']:,}"
        assert cells[4] == f"{stage['points_flagged']:,}"
        assert f"sigma={stage['params']['sigma']}" in cells[5]
    flag_rows = page.locator("#flag-table tbody tr").all_inner_texts()
    assert any(r.startswith("1\ttemporal\t") for r in flag_rows), flag_rows
    assert flag_rows[-1].startswith(f"any\tall detectors\t{stats['overall']['points_flagged']:,}")

    # the download link saves exactly the file the API serves
    with page.expect_download() as download:
        page.click("#download-cloud")
    assert Path(download.value.path()).read_bytes() == cloud
    assert download.value.suggested_filename == f"{job_id}.las"
    page.wait_for_selector("#download-text:has-text('saved')")
    finished_job["id"] = job_id

    page.click("#sign-out")
    page.wait_for_selector("#sign-in:not([hidden])")
    assert page.evaluate("sessionStorage.length") == 0


def test_another_users_job_is_not_reachable(stack: Stack, keys: dict[str, str], browsing,
                                            finished_job: dict[str, Any]) -> None:
    if "id" not in finished_job:
        pytest.fail("needs the job of the test before it", pytrace=False)
    job_id = finished_job["id"]
    page = browsing().page()
    sign_in(page, stack, keys["bob"])
    page.wait_for_selector("#no-jobs:not([hidden])")  # bob's list is empty
    page.goto(f"{stack.url}/app#/jobs/{job_id}")
    page.wait_for_selector("#problem:not([hidden])")
    assert page.inner_text("#problem") == f"404 Unknown job: no job '{job_id}' of yours"
    assert page.is_hidden("#job")
    assert page.locator(f"#job-table tr[data-job='{job_id}']").count() == 0
    with stack.client(keys["bob"]) as http:
        assert http.get(f"/jobs/{job_id}/results/points").status_code == 404

    # its owner deletes it from the page; it stays listed as dismissed
    page = browsing().page()
    sign_in(page, stack, keys["alice"])
    page.goto(f"{stack.url}/app#/jobs/{job_id}")
    page.wait_for_selector("#job[data-status=successful]")
    page.click("#dismiss")
    page.wait_for_url(re.compile(r"#/jobs$"))
    page.wait_for_selector(f"#job-table tr[data-job='{job_id}'] .status.dismissed")
    assert page.is_hidden("#job")
