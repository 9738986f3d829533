"""Parsing of the Range header (RFC 9110, section 14); the responses themselves are tested over
real HTTP in tests/e2e/test_deployments.py."""

from __future__ import annotations

import pytest

from lidar_outliers.jobs.storage import ObjectInfo
from service.downloads import (
    MAX_RANGES,
    ByteRange,
    RangeNotSatisfiable,
    _if_range_holds,
    parse_range,
)


@pytest.mark.parametrize(
    ("header", "expected"),
    [
        (None, None),
        ("", None),
        ("items=0-5", None),  # another unit: the whole object
        ("bytes=0-0", [(0, 0)]),
        ("bytes=0-99", [(0, 99)]),
        ("BYTES = 10-", [(10, 999)]),
        ("bytes=990-5000", [(990, 999)]),  # clipped to the object
        ("bytes=-10", [(990, 999)]),
        ("bytes=-5000", [(0, 999)]),
        ("bytes=0-9,20-29", [(0, 9), (20, 29)]),
        ("bytes=20-29, 0-9", [(0, 9), (20, 29)]),  # sorted
        ("bytes=0-9,5-19,20-24", [(0, 24)]),  # overlapping and adjacent: merged
        ("bytes=0-9,,", [(0, 9)]),  # empty list elements are allowed
        ("bytes=5000-,0-1", [(0, 1)]),  # one unsatisfiable range among others
    ],
)
def test_satisfiable_ranges(header: str | None, expected: list | None) -> None:
    got = parse_range(header, 1000)
    assert (None if got is None else [(r.first, r.last) for r in got]) == expected


@pytest.mark.parametrize(
    "header",
    ["bytes=1000-", "bytes=1000-1001", "bytes=-0", "bytes=abc", "bytes=5-2", "bytes=1-2-3",
     "bytes=-", "bytes=", "bytes=,", "bytes", "bytes=0x10-20", "bytes=+1-2",
     "bytes=\u00b2-3",
     "bytes=" + ",".join(["0-1"] * (MAX_RANGES + 1))],
)
def test_invalid_or_unsatisfiable(header: str) -> None:
    with pytest.raises(RangeNotSatisfiable):
        parse_range(header, 1000)


def test_an_empty_object_satisfies_no_range() -> None:
    with pytest.raises(RangeNotSatisfiable):
        parse_range("bytes=-5", 0)
    assert parse_range(None, 0) is None


def test_if_range() -> None:
    info = ObjectInfo(size=10, etag='"abc"', modified=1_700_000_000.0)
    assert _if_range_holds(None, info)
    assert _if_range_holds('"abc"', info)
    assert not _if_range_holds('"abd"', info)
    assert not _if_range_holds('W/"abc"', info)  # weak validators never allow a range
    assert _if_range_holds("Tue, 14 Nov 2023 22:13:20 GMT", info)
    assert not _if_range_holds("Tue, 14 Nov 2023 22:13:21 GMT", info)
    assert not _if_range_holds("not a date", info)
    assert ByteRange(3, 7).length == 5
