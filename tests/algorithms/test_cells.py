"""Cell keys against explicit index arithmetic, also for grids that only fit once squeezed."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from algorithms.cells import KEY_LIMIT, cell_keys, forward_offsets, offset_keys


def cells_with_strays(seed: int, far: float) -> np.ndarray:
    """A few hundred cells in a small block plus a few very far along each axis."""
    rng = np.random.default_rng(seed)
    block = rng.integers(-4, 5, (300, 3))
    strays = np.array([[far, 0, 0], [0, -far, 3], [2, 1, far], [far, far, -far],
                       [far + 1, far, -far]], dtype=np.int64)
    return np.vstack([block, strays]).astype(np.int64)


@pytest.mark.parametrize("far", [20, 10 ** 9])  # plain keys; keys only after squeezing
@pytest.mark.parametrize("reach", [0, 1, 2])
def test_key_differences_are_exactly_the_neighbour_offsets(reach, far):
    ijk = cells_with_strays(reach, far)
    key, strides = cell_keys(ijk, reach)
    assert key.dtype == np.int64 and key.max() < KEY_LIMIT
    span = range(-reach, reach + 1)
    offsets = np.array(list(itertools.product(span, span, span)))
    step = dict(zip(offset_keys(offsets, strides).tolist(), map(tuple, offsets.tolist()),
                    strict=True))
    assert len(step) == len(offsets)  # no two offsets share a key step
    for a in range(len(ijk)):
        diff = ijk - ijk[a]
        near = np.abs(diff).max(axis=1) <= reach
        by_key = np.array([d in step for d in (key - key[a]).tolist()])
        np.testing.assert_array_equal(by_key, near)
        for b in np.flatnonzero(near):
            assert step[int(key[b] - key[a])] == tuple(diff[b])


def test_keys_sort_cells_as_their_indices():
    ijk = cells_with_strays(5, 10 ** 12)
    key = cell_keys(ijk, 1)[0]
    order = np.lexsort(ijk.T[::-1])
    assert np.all(np.diff(key[order]) >= 0)
    assert len(np.unique(key)) == len(np.unique(ijk, axis=0))


def test_grid_beyond_one_key_even_squeezed_is_refused():
    n = 1_700_000  # distinct, mutually distant indices on every axis: n^3 > 2^62
    ijk = np.repeat(np.arange(n, dtype=np.int64)[:, None] * 10, 3, axis=1)
    with pytest.raises(ValueError, match="larger cells"):
        cell_keys(ijk, 0)
    assert cell_keys(np.zeros((0, 3), dtype=np.int64), 1)[0].shape == (0,)


@pytest.mark.parametrize("reach", [1, 2])
def test_forward_offsets_are_one_of_each_opposite_pair(reach):
    forward = forward_offsets(reach)
    span = range(-reach, reach + 1)
    every = {o for o in itertools.product(span, span, span) if o != (0, 0, 0)}
    halves = {tuple(o) for o in forward.tolist()} | {tuple(o) for o in (-forward).tolist()}
    assert halves == every and len(forward) == len(every) // 2
