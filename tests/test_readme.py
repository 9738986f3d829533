"""The README and the detector pages say what the code does.

The README's Python example runs against a small LAS file; its ``outlier_flags`` table and the
parameter tables of ``docs/detectors/<name>.md`` are those `lidar-outliers detectors --json`
prints from the detector declarations.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers.cli.detectors import listing
from tests.lasfiles import write_las

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = ROOT / "docs" / "detectors"
DETECTORS = listing()["detectors"]


def first_python_block(markdown: str) -> str:
    match = re.search(r"^```python\n(.*?)^```", markdown, flags=re.MULTILINE | re.DOTALL)
    assert match, "README.md has no ```python block"
    return match.group(1)


def write_scan(path: Path, n: int = 3000, spikes: int = 10, seed: int = 0) -> np.ndarray:
    """A scanner sweeping a gently curved road along a straight track, in time order (LAS 1.4,
    point format 6, coordinates near a projected easting/northing), with ``spikes`` points lifted
    by 2 m. Returns the indices of the spikes."""
    rng = np.random.default_rng(seed)
    t = 400_000.0 + np.arange(n) * 1e-4
    phase = np.arange(n) * 0.05
    x = 500_000.0 + 10.0 * (t - t[0]) + 3.0 * np.cos(phase)
    y = 5_000_000.0 + 3.0 * np.sin(phase)
    z = 100.0 + 0.02 * np.sin(phase) + rng.normal(0.0, 0.003, n)
    lifted = np.sort(rng.choice(np.arange(20, n - 20), spikes, replace=False))
    z[lifted] += 2.0
    write_las(path, np.c_[x, y, z], point_format=6, offsets=(500_000.0, 5_000_000.0, 0.0),
              gps_time=t, point_source_id=np.ones(n, dtype=np.uint16), vlrs=())
    return lifted


def test_readme_python_example_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    spikes = write_scan(tmp_path / "scan.las")
    monkeypatch.chdir(tmp_path)
    code = compile(first_python_block(README.read_text()), str(README), "exec")
    exec(code, {"__name__": "readme_example"})
    out = capsys.readouterr().out

    las = laspy.read(tmp_path / "flagged.las")
    flagged = np.flatnonzero(las.outlier_flags != 0)
    assert set(spikes) <= set(flagged.tolist()), "a lifted point was not flagged"
    assert len(flagged) <= 2 * len(spikes)
    assert f"{len(flagged)} of {las.header.point_count} points flagged" in out
    assert f"{len(flagged)} points flagged in flagged.las" in out
    for name in DETECTORS:
        assert re.search(rf"^{name} ", out, flags=re.MULTILINE), f"{name} not listed"


def test_readme_flag_table_is_the_registry() -> None:
    rows = re.findall(r"^\| (\d+) \| `(\w+)` \| `(\w+)` \|", README.read_text(), re.MULTILINE)
    expected = [(str(d["outlier_flags_bit"]), name, d["score_dimension"])
                for name, d in DETECTORS.items() if d["kind"] == "outlier"]
    assert rows == expected


def parameter_table(name: str) -> str:
    """The markdown table of a detector's parameters, as its page shows it."""
    def cell(value: object) -> str:
        return str(value).replace("|", "\\|")

    rows = ["| parameter | type | default | range | meaning |",
            "| --- | --- | --- | --- | --- |"]
    for p in DETECTORS[name]["parameters"]:
        rows.append(f"| `{p['name']}` | `{cell(p['type'])}` | `{cell(json.dumps(p['default']))}` "
                    f"| {cell(p['range'] or '')} | {cell(p['description'])} |")
    return "\n".join(rows)


@pytest.mark.parametrize("name", list(DETECTORS))
def test_every_detector_has_a_page_with_its_parameters(name: str) -> None:
    page = PAGES / f"{name}.md"
    assert page.is_file(), f"docs/detectors/{name}.md is missing"
    table = parameter_table(name)
    assert table in page.read_text(), (
        f"the parameter table of {page.name} differs from `lidar-outliers detectors --json`; "
        f"it should be:\n{table}")
    assert f"](docs/detectors/{name}.md)" in README.read_text()
