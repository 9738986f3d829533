"""Every file of the format corpus is processed faithfully or refused with one line, via the CLI.

Each file runs through ``lidar-outliers detect`` in a subprocess with a timeout (a hang fails the
test instead of blocking the suite). Files with usable GPS times run ``temporal``, the others
``section``: cheap detectors, because the subject here is the I/O, not the detection.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers.pipeline import usable_gps_time

DATA = Path(__file__).resolve().parents[1] / "data" / "formats"
FILES = sorted(p.name for p in DATA.glob("*.la[sz]"))
ROOT = Path(__file__).resolve().parents[2]

#: Files that must be refused, with a piece of the expected one-line message.
REFUSED = {
    "pdal__las__garbage_nVariableLength.las": "claims 1069128089 VLRs",
    "pdal__las__bad_vlr_count.las": "claims 3 VLRs but only 2 fit",
    "ign-pdal-tools__Semis_2022_0906_6665_LA93_IGN69_nok.laz": "header size 0",
    "pdal__las__permutations__1.2-no-points.las": "truncated",
    "pdal__laz__simple-laszip-compressor-version-1.2r0.laz": "LAZ compressor 1",
}
#: VLRs a result does not carry over on purpose (laspy writes its own LASzip VLR, the
#: ExtraBytes VLR is rewritten to describe the new dimensions, COPC layout no longer applies).
_REWRITTEN = {("laszip encoded", 22204), ("LASF_Spec", 4)}


def _kept(vlrs) -> list[tuple[str, int, bytes]]:
    return [
        (v.user_id, v.record_id, bytes(v.record_data_bytes()))
        for v in vlrs
        if (v.user_id, v.record_id) not in _REWRITTEN and v.user_id != "copc"
    ]


def _run(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "lidar_outliers.cli", *args],
        capture_output=True, text=True, timeout=timeout, cwd=ROOT,
    )


def test_corpus_present():
    assert len(FILES) >= 40 and set(REFUSED) <= set(FILES)


@pytest.mark.parametrize("name", FILES)
def test_file_processed_faithfully_or_refused(tmp_path, name):
    src = DATA / name
    out_dir = tmp_path / "out"
    out = out_dir / name
    stats = out_dir / "stats.json"
    detector = "section"
    if name not in REFUSED:
        las = laspy.read(src)
        gps = np.asarray(las.gps_time) if "gps_time" in las.point_format.dimension_names else None
        detector = "temporal" if usable_gps_time(gps)[0] else "section"
    # --no-classify: the records must come back byte for byte (classify is tested elsewhere).
    result = _run("detect", str(src), "-o", str(out), "--stats", str(stats), "-q",
                  "--no-classify", "--detector", detector)

    if name in REFUSED:
        assert result.returncode == 1, result.stderr
        lines = result.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("lidar-outliers: error: "), result.stderr
        assert REFUSED[name] in lines[0]
        assert not out_dir.exists() or list(out_dir.iterdir()) == []
        return

    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert sorted(p.name for p in out_dir.iterdir()) == sorted([name, "stats.json"])
    after = laspy.read(out)
    n = len(las.points)
    assert len(after.points) == n
    # Every original byte of every record, in the same order, then the new dimensions.
    width = las.points.array.dtype.itemsize
    before_bytes = las.points.array.view(np.uint8).reshape(n, width)
    after_bytes = after.points.array.view(np.uint8).reshape(n, -1)[:, :width] if n else before_bytes
    np.testing.assert_array_equal(after_bytes, before_bytes)
    assert after.header.point_format.id == las.header.point_format.id
    np.testing.assert_array_equal(after.header.scales, las.header.scales)
    np.testing.assert_array_equal(after.header.offsets, las.header.offsets)
    assert _kept(after.header.vlrs) == _kept(las.header.vlrs)
    assert _kept(after.header.evlrs or []) == _kept(las.header.evlrs or [])
    assert {"outlier_flags", f"{detector}_score"} <= set(after.point_format.extra_dimension_names)
    report = json.loads(stats.read_text())
    assert report["input"]["points"] == n
    assert report["stages"][0]["detector"] == detector
    flagged = np.asarray(after["outlier_flags"]) != 0
    assert report["overall"]["points_flagged"] == int(flagged.sum())
