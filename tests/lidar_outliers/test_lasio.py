"""lasio: header validation, reading into local-origin arrays, faithful result writing."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import laspy
import numpy as np
import pytest

from lidar_outliers import lasio
from lidar_outliers.errors import LasFormatError
from lidar_outliers.output import result_dimensions
from tests.lasfiles import WKT, scan_line_cloud, write_las


def _records(vlrs) -> list[tuple[str, int, bytes]]:
    """User id, record id and payload of every VLR a result file must keep.

    The ExtraBytes VLR is rewritten on purpose (it describes the new dimensions too) and laspy
    writes its own LASzip VLR, so both are left out of the comparison.
    """
    out = []
    for v in vlrs:
        if v.user_id in ("laszip encoded",) or (v.user_id == "LASF_Spec" and v.record_id == 4):
            continue
        out.append((v.user_id, v.record_id, bytes(v.record_data_bytes())))
    return out


@pytest.mark.parametrize("laz", [False, True], ids=["las", "laz"])
@pytest.mark.parametrize("point_format", range(11))
def test_round_trip_keeps_every_dimension_vlr_evlr_and_crs(tmp_path, rng, point_format, laz):
    n = 600
    xyz, t, _ = scan_line_cloud(n, rng)
    extra = {"reflectance": rng.normal(size=n), "ring": rng.integers(0, 64, n).astype(np.uint16)}
    suffix = "laz" if laz and point_format not in lasio.LAZ_LOSSY_FORMATS else "las"
    src = write_las(tmp_path / f"in.{suffix}", xyz + [512_000.0, 5_400_000.0, 80.0],
                    point_format=point_format, offsets=(512_000.0, 5_400_000.0, 0.0),
                    extra=extra, random_dims=True, crs=True, evlr=point_format >= 6,
                    seed=point_format)
    flags = rng.integers(0, 8, n).astype(np.uint8)
    score = rng.normal(size=n)
    score[::7] = np.nan
    out = tmp_path / f"out.{'laz' if laz else 'las'}"
    if laz and point_format in lasio.LAZ_LOSSY_FORMATS:
        # lazrs does not round-trip the waveform fields of formats 9 and 10: refused, no file.
        with pytest.raises(LasFormatError, match="waveform"):
            lasio.write_result(src, out, flags=flags, scores={}, laz=True)
        assert list(tmp_path.iterdir()) == [src]
        return

    lasio.write_result(src, out, flags=flags, scores={"temporal": score, "patch": -score},
                       classification=None, chunk_points=250, laz=laz)

    before, after = laspy.read(src), laspy.read(out)
    assert after.header.point_format.id == point_format
    assert lasio.inspect_las(out).compressed is laz
    for dim in before.point_format.dimension_names:
        np.testing.assert_array_equal(np.asarray(after[dim]), np.asarray(before[dim]), err_msg=dim)
    np.testing.assert_array_equal(after["outlier_flags"], flags)
    np.testing.assert_array_equal(after["temporal_score"], score.astype(np.float32))
    np.testing.assert_array_equal(after["patch_score"], (-score).astype(np.float32))
    assert after["temporal_score"].dtype == np.float32
    assert _records(after.header.vlrs) == _records(before.header.vlrs)
    assert _records(after.header.evlrs or []) == _records(before.header.evlrs or [])
    if point_format >= 6:
        assert _records(after.header.evlrs) != []
    assert lasio.inspect_las(out).crs == WKT
    np.testing.assert_array_equal(after.header.scales, before.header.scales)
    np.testing.assert_array_equal(after.header.offsets, before.header.offsets)


def test_existing_extra_bytes_kept_and_our_dimensions_replaced(tmp_path, rng):
    # an earlier result's dimension (same name and type) is overwritten in place; one of
    # another type (scores cut to uint8, NaN to 0) keeps its bytes under <name>_input
    n = 300
    xyz, t, _ = scan_line_cloud(n, rng)
    extra = {"outlier_flags": np.full(n, 9, np.uint8), "height": rng.normal(size=n),
             "temporal_score": np.full(n, 7.0, np.float32)}
    src = write_las(tmp_path / "in.las", xyz, gps_time=t, extra=extra)
    out = tmp_path / "out.las"
    flags = np.zeros(n, np.uint16)
    flags[5] = 1 << 9
    scores = np.full(n, np.nan)
    scores[3] = 2.5
    lasio.write_result(src, out, flags=flags, scores={"temporal": scores})
    after = laspy.read(out)
    assert list(after.point_format.extra_dimension_names) == [
        "outlier_flags_input", "height", "temporal_score", "outlier_flags"
    ]
    assert after["outlier_flags"].dtype == np.uint16
    np.testing.assert_array_equal(after["outlier_flags"], flags)
    np.testing.assert_array_equal(after["outlier_flags_input"], extra["outlier_flags"])
    np.testing.assert_array_equal(after["height"], extra["height"])
    np.testing.assert_array_equal(after["temporal_score"], scores.astype(np.float32))


def test_classification_written_only_when_given(tmp_path, rng):
    n = 200
    xyz, t, _ = scan_line_cloud(n, rng)
    cls = np.full(n, 1, np.uint8)
    src = write_las(tmp_path / "in.las", xyz, gps_time=t, classification=cls)
    new = cls.copy()
    new[[3, 4]] = 7
    lasio.write_result(src, tmp_path / "a.las", flags=np.zeros(n, np.uint8), scores={},
                       classification=new)
    lasio.write_result(src, tmp_path / "b.las", flags=np.zeros(n, np.uint8), scores={})
    np.testing.assert_array_equal(laspy.read(tmp_path / "a.las").classification, new)
    np.testing.assert_array_equal(laspy.read(tmp_path / "b.las").classification, cls)


def test_read_cloud_local_origin_keeps_precision_far_from_origin(tmp_path, rng):
    n = 1000
    xyz, t, _ = scan_line_cloud(n, rng)
    far = np.array([4_999_990.0, 5_000_010.0, 250.0])
    near_file = write_las(tmp_path / "near.las", xyz, gps_time=t, point_format=1)
    far_file = write_las(tmp_path / "far.las", xyz + far, gps_time=t + 500_000.0,
                         point_format=1, offsets=tuple(far))
    near, farc = lasio.read_cloud(near_file), lasio.read_cloud(far_file)
    # Same integer coordinates relative to each file's grid: identical local coordinates
    # (up to the choice of the origin, a whole number of grid steps).
    np.testing.assert_allclose((farc.xyz - farc.xyz.mean(0)), (near.xyz - near.xyz.mean(0)),
                               rtol=0, atol=1e-9)
    # Local coordinates are small: polynomial arithmetic on them keeps its precision.
    assert np.abs(farc.xyz).max() < 50
    # World coordinates are recovered to the file's resolution.
    las = laspy.read(far_file)
    np.testing.assert_allclose(farc.xyz + farc.origin, np.column_stack([las.x, las.y, las.z]),
                               rtol=0, atol=1e-6)
    np.testing.assert_array_equal(farc.gps_time, np.asarray(las.gps_time))


def test_read_cloud_fields_and_chunking(tmp_path, rng):
    n = 1234
    xyz, t, _ = scan_line_cloud(n, rng)
    psid = rng.integers(1, 4, n).astype(np.uint16)
    cls = rng.integers(0, 20, n).astype(np.uint8)
    src = write_las(tmp_path / "in.laz", xyz, gps_time=t, point_format=6, classification=cls,
                    point_source_id=psid)
    seen = []
    cloud = lasio.read_cloud(src, chunk_points=100, progress=lambda f, m: seen.append(f))
    assert len(cloud) == n
    np.testing.assert_array_equal(cloud.point_source_id, psid)
    np.testing.assert_array_equal(cloud.classification, cls)
    np.testing.assert_allclose(cloud.xyz + cloud.origin, xyz, atol=6e-4)
    assert len(seen) == 13 and seen[-1] == pytest.approx(1.0) and seen == sorted(seen)
    sub = cloud.subset(np.array([5, 1, 9]))
    np.testing.assert_array_equal(sub.gps_time, cloud.gps_time[[5, 1, 9]])


def test_write_filtered_splits_inliers_and_outliers(tmp_path, rng):
    n = 500
    xyz, t, _ = scan_line_cloud(n, rng)
    src = write_las(tmp_path / "in.las", xyz, gps_time=t, crs=True)
    flags = (rng.random(n) < 0.1).astype(np.uint8) * 2
    result = tmp_path / "result.las"
    lasio.write_result(src, result, flags=flags, scores={"patch": rng.normal(size=n)})
    n_in = lasio.write_filtered(result, tmp_path / "in_only.laz", "inliers", True)
    n_out = lasio.write_filtered(result, tmp_path / "out_only.las", "outliers", False)
    assert (n_in, n_out) == (int((flags == 0).sum()), int((flags != 0).sum()))
    inl, outl, full = (laspy.read(tmp_path / f) for f in ("in_only.laz", "out_only.las",
                                                         "result.las"))
    np.testing.assert_array_equal(inl.gps_time, full.gps_time[flags == 0])
    np.testing.assert_array_equal(outl.patch_score, full.patch_score[flags != 0])
    assert lasio.inspect_las(tmp_path / "in_only.laz").crs == WKT
    with pytest.raises(LasFormatError, match="no outlier_flags"):
        lasio.write_filtered(src, tmp_path / "x.las", "inliers", False)


def test_failed_write_leaves_no_file(tmp_path, rng):
    n = 1000
    xyz, t, _ = scan_line_cloud(n, rng)
    src = write_las(tmp_path / "in.las", xyz, gps_time=t)
    out = tmp_path / "out" / "result.las"

    class Stop(Exception):
        pass

    def progress(fraction: float, message: str) -> None:
        if fraction > 0.5:
            raise Stop

    with pytest.raises(Stop):
        lasio.write_result(src, out, flags=np.zeros(n, np.uint8), scores={}, chunk_points=100,
                           progress=progress)
    assert list(out.parent.iterdir()) == []


def test_a_write_that_fails_on_the_writer_thread_raises_and_leaves_no_file(tmp_path, rng):
    xyz, t, _ = scan_line_cloud(500, rng)
    src = write_las(tmp_path / "in.las", xyz, gps_time=t)
    out = tmp_path / "out" / "result.las"
    out.parent.mkdir()
    with pytest.raises(laspy.errors.LaspyException, match="[Ii]ncompatible"):
        with lasio.ResultWriter(src, out, result_dimensions(["temporal"])) as writer:
            for chunk in lasio.iter_chunks(src, 100):
                writer.write(chunk)  # the input's record lacks the result's dimensions
    assert list(out.parent.iterdir()) == []
    # and closed: a removed file that stays open keeps its space on the disk
    assert not [f for f in _open_files() if f.startswith(str(out.parent))]


def _open_files() -> list[str]:
    """The paths this process holds open (Linux)."""
    paths = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            paths.append(os.readlink(f"/proc/self/fd/{fd}"))
        except FileNotFoundError:  # the listing's own descriptor, closed since
            pass
    return paths


# --------------------------------------------------------------------------- header refusals


def _good_file(tmp_path: Path, rng: np.random.Generator, **kw) -> bytes:
    xyz, t, _ = scan_line_cloud(50, rng)
    return write_las(tmp_path / "good.las", xyz, gps_time=t, **kw).read_bytes()


def _patched(data: bytes, offset: int, fmt: str, value) -> bytes:
    buf = bytearray(data)
    struct.pack_into(fmt, buf, offset, value)
    return bytes(buf)


def _cases(good: bytes) -> dict[str, tuple[bytes, str]]:
    header_size, offset = struct.unpack_from("<HI", good, 94)
    return {
        "empty": (b"", "not a LAS/LAZ file"),
        "zip": (b"PK\x03\x04" + good[4:], "not a LAS/LAZ file"),
        "short header": (good[:120], "truncated"),
        "version 2.2": (_patched(good, 24, "<B", 2), "version 2.2 is not supported"),
        "version 1.7": (_patched(good, 25, "<B", 7), "version 1.7 is not supported"),
        "point format 12": (_patched(good, 104, "<B", 12), "point format 12 is not supported"),
        "record too short": (_patched(good, 105, "<H", 20), "record length 20 is below"),
        "header size 0": (_patched(good, 94, "<H", 0), "header size 0"),
        "offset past end": (_patched(good, 96, "<I", 10**9), "offset to point data"),
        "garbage vlr count": (_patched(good, 100, "<I", 1_069_128_089), "claims 1069128089 VLRs"),
        "vlr past points": (_patched(good, 100, "<I", 2), "VLRs"),
        "points cut off": (good[: offset + 10 * 34], "truncated"),
        "count too high": (_patched(good, 107, "<I", 51), "header says 51 points"),
        "laz bit without laszip vlr": (_patched(good, 104, "<B", 3 | 0x80), "no LASzip VLR"),
        "zero scale": (_patched(good, 131, "<d", 0.0), "scale factors"),
    }


@pytest.mark.parametrize("case", list(_cases(b"\0" * 400)))
def test_inspect_refuses_bad_headers_with_one_line(tmp_path, rng, case):
    good = _good_file(tmp_path, rng)
    data, expected = _cases(good)[case]
    bad = tmp_path / "bad.las"
    bad.write_bytes(data)
    with pytest.raises(LasFormatError) as err:
        lasio.inspect_las(bad)
    message = str(err.value)
    assert expected in message
    assert "\n" not in message and message.startswith("bad.las")


def test_inspect_refuses_a_laz_file_cut_short(tmp_path, rng):
    # an interrupted upload or copy: the chunk table the points point to is past the end
    xyz, t, _ = scan_line_cloud(3000, rng)
    whole = write_las(tmp_path / "whole.laz", xyz, gps_time=t).read_bytes()
    lasio.inspect_las(tmp_path / "whole.laz")
    for keep in (len(whole) // 2, len(whole) - 9):
        cut = tmp_path / "cut.laz"
        cut.write_bytes(whole[:keep])
        with pytest.raises(LasFormatError, match=rf"^cut.laz is truncated: .* has {keep} bytes"):
            lasio.inspect_las(cut)


def test_inspect_facts(tmp_path, rng):
    xyz, t, _ = scan_line_cloud(50, rng)
    path = write_las(tmp_path / "f.laz", xyz, gps_time=t, point_format=7, crs=True,
                     extra={"amp": np.ones(50, np.float32)}, offsets=(1.0, 2.0, 3.0))
    facts = lasio.inspect_las(path)
    assert facts.points == 50 and facts.las_version == "1.4" and facts.point_format == 7
    assert facts.compressed and facts.has_gps_time and facts.extra_dimensions == ["amp"]
    assert facts.crs == WKT and facts.offsets == [1.0, 2.0, 3.0]
    assert facts.record_length == 36 + 4
    assert facts.to_dict()["bounds"]["min"][0] == pytest.approx(xyz[:, 0].min(), abs=1e-3)
    plain = write_las(tmp_path / "g.las", xyz, point_format=0)
    assert lasio.inspect_las(plain).has_gps_time is False
