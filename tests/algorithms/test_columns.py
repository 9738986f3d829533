from __future__ import annotations

import numpy as np
import pytest

from algorithms.columns import column_max, column_min


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int64, np.int32])
@pytest.mark.parametrize("shape", [(1, 3), (1000, 3), (257, 2)])
def test_columns_give_numpys_axis_reductions(dtype, shape):
    a = (np.random.default_rng(4).normal(size=shape) * 100).astype(dtype)
    for fast, slow in ((column_min(a), a.min(axis=0)), (column_max(a), a.max(axis=0))):
        assert fast.dtype == slow.dtype
        np.testing.assert_array_equal(fast, slow)


def test_columns_of_a_strided_view():
    a = np.arange(60.0).reshape(20, 3)[::3, :2]
    np.testing.assert_array_equal(column_min(a), a.min(axis=0))
    np.testing.assert_array_equal(column_max(a), a.max(axis=0))
