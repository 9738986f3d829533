"""Every way the project writes a LAS/LAZ file keeps VLRs, EVLRs, the CRS and extra bytes.

The paths: a result written in memory and streamed, a conversion between LAS and LAZ, a
filtered download (inliers / outliers) and an in-memory ``LasData`` (the simulator's). Each is
run on the LAS 1.4 file with an EVLR of ``tests/data/formats/`` and read back with laspy.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers import lasio
from lidar_outliers.errors import LasFormatError
from lidar_outliers.output import FLAGS_DIMENSION
from lidar_outliers.process import process_file

EVLR_FILE = Path(__file__).resolve().parents[1] / "data" / "formats" / "laspy__1_4_w_evlr.las"
#: Records a writer replaces by design: the LASzip description and the extra-bytes layout.
REWRITTEN = {("laszip encoded", 22204), ("LASF_Spec", 4)}


def records(vlrs) -> list[tuple[str, int, bytes]]:
    kept = []
    for vlr in vlrs or []:
        key = (vlr.user_id.strip("\0").strip(), vlr.record_id)
        if key not in REWRITTEN:
            kept.append((*key, bytes(vlr.record_data_bytes())))
    return kept


def assert_same_records(before: laspy.LasData, after: laspy.LasData) -> None:
    assert records(after.header.vlrs) == records(before.header.vlrs)
    assert records(after.header.evlrs) == records(before.header.evlrs)
    assert records(before.header.evlrs), "the input has an EVLR"
    for name in before.point_format.extra_dimension_names:
        assert name in after.point_format.extra_dimension_names


@pytest.fixture
def source(tmp_path: Path) -> Path:
    path = tmp_path / "evlr.las"
    shutil.copyfile(EVLR_FILE, path)
    return path


@pytest.mark.parametrize("streaming", [False, True])
@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_results_keep_every_record(source: Path, tmp_path: Path, streaming: bool,
                                   suffix: str) -> None:
    out = tmp_path / f"result{suffix}"
    params = {"pipeline": [{"detector": "temporal", "sigma": 0.01}], "classify": False}
    stats = process_file(source, out, params, laz=suffix == ".laz", streaming=streaming)
    assert stats["mode"] == ("streaming" if streaming else "in memory")
    before, after = laspy.read(source), laspy.read(out)
    assert_same_records(before, after)
    assert after.header.point_count == before.header.point_count
    assert np.asarray(after[FLAGS_DIMENSION]).dtype == np.uint16
    np.testing.assert_array_equal(after.X, before.X)


def test_conversions_keep_every_record(source: Path, tmp_path: Path) -> None:
    laz, back = tmp_path / "c.laz", tmp_path / "c.las"
    lasio.convert(source, laz, laz=True)
    lasio.convert(laz, back, laz=False)
    before = laspy.read(source)
    for path in (laz, back):
        after = laspy.read(path)
        assert_same_records(before, after)
        np.testing.assert_array_equal(after.points.array, before.points.array)


@pytest.mark.parametrize("keep", ["inliers", "outliers"])
def test_filtered_downloads_keep_every_record(source: Path, tmp_path: Path, keep: str) -> None:
    result = tmp_path / "result.las"
    process_file(source, result, {"pipeline": [{"detector": "temporal", "sigma": 0.001}]})
    flagged = np.asarray(laspy.read(result)[FLAGS_DIMENSION]) != 0
    assert 0 < flagged.sum() < flagged.size
    out = tmp_path / f"{keep}.laz"
    written = lasio.write_filtered(result, out, keep, laz=True)
    assert written == (flagged.sum() if keep == "outliers" else (~flagged).sum())
    assert_same_records(laspy.read(result), laspy.read(out))


def test_in_memory_clouds_keep_every_record(source: Path, tmp_path: Path) -> None:
    las = laspy.read(source)
    for name in ("copy.las", "copy.laz"):
        lasio.write_las_data(las, tmp_path / name)
        after = laspy.read(tmp_path / name)
        assert_same_records(las, after)
        assert not list(tmp_path.glob(".*.part*")), "a temporary file was left behind"


def test_lossy_laz_is_refused_on_every_path(tmp_path: Path) -> None:
    """lazrs does not keep point formats 9 and 10's waveform fields: no path writes them."""
    header = laspy.LasHeader(point_format=9, version="1.4")
    las = laspy.LasData(header)
    las.x = las.y = las.z = np.arange(5.0)
    plain = tmp_path / "wave.las"
    lasio.write_las_data(las, plain)
    with pytest.raises(LasFormatError, match="point format 9"):
        lasio.write_las_data(las, tmp_path / "wave.laz")
    with pytest.raises(LasFormatError, match="point format 9"):
        lasio.convert(plain, tmp_path / "converted.laz", laz=True)
    result = tmp_path / "result.las"
    process_file(plain, result, {"pipeline": [{"detector": "temporal", "sigma": 0.01}]})
    with pytest.raises(LasFormatError, match="point format 9"):
        lasio.write_filtered(result, tmp_path / "kept.laz", "inliers", laz=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.las", "wave.las"]
