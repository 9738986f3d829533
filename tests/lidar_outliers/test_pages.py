"""Pages of memory-mapped columns given back: the content stays, the resident set shrinks."""

from __future__ import annotations

import mmap
import sys

import numpy as np
import pytest

from lidar_outliers.pages import Releaser, filled, gathered, release, releasing, scattered

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux")
                                or not hasattr(mmap, "MADV_DONTNEED"),
                                reason="RssFile and MADV_DONTNEED are Linux's")


def rss_file_bytes() -> int:
    """This process's resident file pages (``RssFile`` of /proc/self/status)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("RssFile:"):
                return int(line.split()[1]) * 1024
    raise AssertionError("no RssFile line")


def test_written_pages_survive_the_release(tmp_path):
    arr = np.lib.format.open_memmap(tmp_path / "a.npy", mode="w+", dtype=np.float64,
                                    shape=(1_000_000,))
    arr[:] = np.arange(1_000_000)
    release(arr[10:20])  # a view finds its map
    assert arr[123_456] == 123_456.0
    del arr
    again = np.load(tmp_path / "a.npy")
    np.testing.assert_array_equal(again, np.arange(1_000_000, dtype=np.float64))


@linux_only
def test_release_shrinks_the_resident_set(tmp_path):
    n = 8_000_000  # 64 MB
    arr = np.lib.format.open_memmap(tmp_path / "a.npy", mode="w+", dtype=np.float64, shape=(n,))
    arr[:] = 1.0
    mapped = rss_file_bytes()
    release(arr)
    assert mapped - rss_file_bytes() > 0.9 * n * 8
    assert float(arr.sum()) == n  # read back from the page cache


def test_copy_on_write_maps_and_plain_arrays_are_left_alone(tmp_path):
    np.save(tmp_path / "a.npy", np.zeros(1000))
    private = np.load(tmp_path / "a.npy", mmap_mode="c")
    private[:] = 7.0  # changes live only in this process's pages
    plain = np.ones(10)
    release(private, plain, None)
    assert np.all(private == 7.0) and np.all(plain == 1.0)


def test_filled_and_releasing(tmp_path):
    arr = np.lib.format.open_memmap(tmp_path / "a.npy", mode="w+", dtype=np.float32,
                                    shape=(5_000_001,))
    filled(arr, np.nan)
    assert np.isnan(arr).all()
    releaser = Releaser([arr], every=3)
    results = [{"index": np.arange(k, k + 2)} for k in (0, 2, 4)]
    seen = []
    for res in releasing(results, releaser):
        arr[res["index"]] = 1.0
        seen.append(releaser.pending)
    assert seen == [0, 2, 0]  # counted after each result: released at 4 points and at the end
    assert releaser.pending == 0
    assert np.count_nonzero(arr == 1.0) == 6


def test_gathered_and_scattered_by_spans_equal_fancy_indexing(tmp_path):
    rng = np.random.default_rng(3)
    arr = np.lib.format.open_memmap(tmp_path / "a.npy", mode="w+", dtype=np.float64,
                                    shape=(10_007, 2))
    arr[:] = rng.normal(size=(10_007, 2))
    rows = np.sort(rng.choice(10_007, 900, replace=False))
    np.testing.assert_array_equal(gathered(arr, rows, every=1000), arr[rows])
    assert gathered(arr, rows[:0], every=1000).shape == (0, 2)
    values = rng.normal(size=(900, 2))
    expected = np.array(arr)
    expected[rows] = values
    scattered(arr, rows, values, every=333)
    np.testing.assert_array_equal(arr, expected)
