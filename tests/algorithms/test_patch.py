"""The `patch` detector (algorithm (b)): per-point quadric patches of the k nearest neighbours."""

from __future__ import annotations

import numpy as np
import pytest

from algorithms.errors import ParameterError
from algorithms.patch import detect_patch
from algorithms.stats import t_critical_value
from algorithms.tiles import grid_cells, group_by_cell, spatial_batches
from tests.algorithms.test_quadric import slow_fit


def gentle_surface(rng, n=3000, size=2.0, noise=0.005):
    """A smooth, gently curved surface sampled at random, 5 mm noise: (n, 3)."""
    xy = rng.uniform(0.0, size, (n, 2))
    z = 0.05 * np.sin(xy[:, 0]) + 0.03 * xy[:, 1] ** 2 + rng.normal(0.0, noise, n)
    return np.c_[xy, z]


def test_slow_reference_per_point():
    # Brute-force neighbours and the slow fit for a sample of points; the detector iterates
    # with acceleration to ||da|| < 1e-8, the reference plainly to 1e-12.
    rng = np.random.default_rng(1)
    xyz = gentle_surface(rng, n=600, size=1.0)
    res = detect_patch(xyz, k=40, sigma=0.005, alpha=0.001)
    agree = 0
    sample = rng.choice(len(xyz), 40, replace=False)
    for i in sample:
        d = np.linalg.norm(xyz - xyz[i], axis=1)
        nbr = np.argsort(d, kind="stable")[:40]
        assert nbr[0] == i
        _, _, T, _, _, ok = slow_fit(xyz[nbr], 0.005, max_iter=2000, tol=1e-12)
        if ok and not np.isnan(res.score[i]):
            agree += abs(res.score[i] - T[0]) < 1e-4
    assert agree >= 36


def test_ten_sigma_spike_is_flagged():
    rng = np.random.default_rng(2)
    xyz = gentle_surface(rng)
    spike = 1234
    xyz[spike, 2] += 10 * 0.005
    res = detect_patch(xyz, k=40, sigma=0.005, alpha=0.001)
    assert res.flagged[spike]
    assert res.score[spike] > res.critical_value
    assert res.critical_value == pytest.approx(t_critical_value(0.001, 31))
    # The clean surface: few false alarms and almost every point tested.
    assert res.flagged.sum() <= 1 + 0.005 * len(xyz)
    assert res.info["points_tested"] >= 0.98 * len(xyz)
    assert res.info["points_tested"] == int(res.tested.sum())


def test_shift_by_5e6_changes_nothing():
    rng = np.random.default_rng(3)
    # Coordinates on a 1/1024 m grid: the shifted values are exact, the large ones are shifted
    # back by a multiple of 65536 m (not to 0), so only the patch centroids round differently.
    xyz = np.round(gentle_surface(rng, n=1500) * 1024) / 1024
    xyz[100, 2] += 64 / 1024  # on the grid too
    a = detect_patch(xyz)
    b = detect_patch(xyz + np.array([5e6, 5e6, 300.0]))
    np.testing.assert_array_equal(a.flagged, b.flagged)
    np.testing.assert_allclose(a.score, b.score, atol=1e-5)
    assert a.flagged[100]


def test_a_part_of_the_cloud_gives_the_same_bits_as_the_whole():
    """Points of a millimetre grid (exact ties at the k-th neighbour everywhere): a point whose
    k nearest lie inside a part of the cloud gets the same patch and score from that part as
    from the whole cloud, in local and in projected coordinates."""
    g = np.stack(np.meshgrid(np.arange(40), np.arange(40)), -1).reshape(-1, 2) * 0.05
    z = 0.02 * np.sin(3 * g[:, 0]) + 0.01 * g[:, 1]
    xyz = np.round(np.column_stack([g, z]), 3)
    for offset in (np.zeros(3), np.array([600_000.0, 5_000_000.0, 50.0])):
        cloud = xyz + offset
        whole = detect_patch(cloud, k=30)
        part = (g[:, 0] > 0.6) & (g[:, 1] > 0.4)  # a corner cut off
        sub = detect_patch(cloud[part], k=30)
        inner = (g[part][:, 0] > 1.0) & (g[part][:, 1] > 0.8)  # 8 spacings from the cut
        np.testing.assert_array_equal(sub.score[inner], whole.score[part][inner])


def test_nearest_in_order_is_the_brute_force_order():
    from scipy.spatial import cKDTree

    from algorithms.neighbours import nearest_in_order

    g = np.stack(np.meshgrid(np.arange(12), np.arange(12)), -1).reshape(-1, 2) * 0.1
    xyz = np.column_stack([g, np.zeros(len(g))])
    got = nearest_in_order(cKDTree(xyz), xyz, np.arange(len(xyz)), 13)
    for i in range(len(xyz)):
        d2 = np.sum((xyz - xyz[i]) ** 2, axis=1)
        near = np.lexsort((np.arange(len(xyz)), d2))[:13]  # by distance, ties by index
        assert got[i, 0] == i and list(got[i, 1:]) == sorted(near[1:])


def test_nearest_in_order_with_copies_follows_the_points_not_the_tree():
    # A scanner standing still repeats points: every copy of a point gets the same row, its
    # lowest-index copy first, and the rows are the same from any k-d tree build.
    from scipy.spatial import cKDTree

    from algorithms.neighbours import nearest_in_order, neighbour_tree

    rng = np.random.default_rng(11)
    base = rng.random((300, 3))
    xyz = np.concatenate([base, base[:40], base[:40], base[rng.choice(300, 60)]])
    query = np.arange(len(xyz))
    rows = [
        nearest_in_order(tree, xyz, query, 20)
        for tree in (cKDTree(xyz), neighbour_tree(xyz), cKDTree(xyz, leafsize=2))
    ]
    np.testing.assert_array_equal(rows[0], rows[1])
    np.testing.assert_array_equal(rows[0], rows[2])
    got = rows[0]
    for i in range(len(xyz)):
        d2 = np.sum((xyz - xyz[i]) ** 2, axis=1)
        near = np.lexsort((np.arange(len(xyz)), d2))[:20]  # by distance, ties by index
        assert got[i, 0] == near[0] and list(got[i, 1:]) == sorted(near[1:])
        assert np.array_equal(xyz[got[i, 0]], xyz[i])
        copies = np.flatnonzero(np.all(xyz == xyz[i], axis=1))
        assert all(np.array_equal(got[c], got[i]) for c in copies)


def test_shift_without_exact_grid_changes_nothing_measurable():
    rng = np.random.default_rng(4)
    xyz = gentle_surface(rng, n=1500)
    a = detect_patch(xyz)
    b = detect_patch(xyz + np.array([4.9e6, 5.1e6, 123.456]))
    both = a.tested & b.tested
    assert both.mean() > 0.98
    np.testing.assert_allclose(b.score[both], a.score[both], atol=1e-4)
    assert (a.flagged != b.flagged).sum() <= 1


def test_tiny_tiles_equal_one_tile():
    rng = np.random.default_rng(5)
    xyz = gentle_surface(rng, n=2000)
    xyz[::97, 2] += 0.05
    one = detect_patch(xyz, batch_points=10**9)
    tiny = detect_patch(xyz, batch_points=37, tile_size=0.05)
    np.testing.assert_array_equal(one.score, tiny.score)
    np.testing.assert_array_equal(one.flagged, tiny.flagged)


def test_k_too_small_for_alpha_is_refused():
    xyz = gentle_surface(np.random.default_rng(6), n=200)
    with pytest.raises(ParameterError, match=r"k=20 .*alpha=0.001.*k >= 26"):
        detect_patch(xyz, k=20, alpha=0.001)
    with pytest.raises(ParameterError, match="k=10"):
        detect_patch(xyz, k=10, alpha=0.01)
    # The same k is fine with a larger alpha: sqrt(11) > t(11) at 0.05.
    res = detect_patch(xyz, k=20, alpha=0.05)
    assert res.info["k"] == 20


def test_bad_input_is_refused_with_one_line():
    with pytest.raises(ParameterError, match="shape"):
        detect_patch(np.zeros((10, 2)))
    bad = gentle_surface(np.random.default_rng(7), n=100)
    bad[3, 1] = np.nan
    with pytest.raises(ParameterError, match="NaN"):
        detect_patch(bad)
    with pytest.raises(ParameterError, match="sigma"):
        detect_patch(gentle_surface(np.random.default_rng(7), n=100), sigma=-1.0)


def test_fewer_points_than_k_tests_nothing():
    xyz = gentle_surface(np.random.default_rng(8), n=30)
    res = detect_patch(xyz, k=40)
    assert np.isnan(res.score).all()
    assert not res.flagged.any()
    assert res.info["points_tested"] == 0


def test_per_axis_sigma_is_accepted():
    rng = np.random.default_rng(9)
    xyz = gentle_surface(rng, n=800)
    xyz[50, 2] += 0.08
    res = detect_patch(xyz, sigma=(0.01, 0.01, 0.005))
    assert res.info["sigma"] == [0.01, 0.01, 0.005]
    assert res.flagged[50]


def test_spatial_batches_cover_every_point_once():
    rng = np.random.default_rng(10)
    xy = rng.uniform(0.0, 30.0, (5000, 2))
    for batch_points, tile_size in [(1, None), (37, 0.5), (1000, None), (10**6, None)]:
        batches = list(spatial_batches(xy, batch_points, tile_size))
        assert all(1 <= len(b) <= batch_points for b in batches)
        np.testing.assert_array_equal(np.sort(np.concatenate(batches)), np.arange(5000))


def test_grid_cells_follow_the_cloud():
    rng = np.random.default_rng(11)
    xy = np.round(rng.uniform(0.0, 20.0, (1000, 2)) * 64) / 64
    cell, n_columns = grid_cells(xy, 5.0)
    shifted, n_columns_shifted = grid_cells(xy + np.array([5e6, 4e6]), 5.0)
    np.testing.assert_array_equal(cell, shifted)
    assert n_columns == n_columns_shifted == 4
    order, offsets = group_by_cell(cell)
    assert offsets[0] == 0 and offsets[-1] == 1000
    for j in range(len(offsets) - 1):
        members = cell[order[offsets[j] : offsets[j + 1]]]
        assert (members == members[0]).all()


def test_points_at_one_location_share_their_patch_exactly():
    # A vehicle standing still repeats points; each location is fitted once. The scores must
    # equal fitting every point's own patch.
    from scipy.spatial import cKDTree

    from algorithms.neighbours import nearest_in_order
    from algorithms.patch import FIT_MAX_ITER, FIT_TOL, distinct_locations, frame_shift
    from algorithms.quadric import fit_quadrics

    rng = np.random.default_rng(7)
    base = gentle_surface(rng, n=1500, size=1.0)
    xyz = np.concatenate([base, base[rng.choice(1500, 400)], base[:50]])  # 450 repeats
    first, location = distinct_locations(xyz)
    assert first.size == 1500 and np.array_equal(xyz[first[location]], xyz)
    res = detect_patch(xyz, k=40, sigma=0.005, alpha=0.001, batch_points=300)
    local = xyz - frame_shift(xyz)
    nbr = nearest_in_order(cKDTree(local), local, np.arange(len(local)), 40)
    fit = fit_quadrics(local, np.full(3, 0.005), neighbours=nbr, max_iter=FIT_MAX_ITER,
                       tol=FIT_TOL, t_first_only=True)
    expected = np.where(fit.converged, fit.t_stat[:, 0], np.nan)
    np.testing.assert_array_equal(res.score, expected)
    assert res.info["mean_iterations"] == pytest.approx(fit.iterations.mean())


def smooth_surface_with_displaced_points(seed, n=400, displacement=0.05):
    """A smooth surface over 2 m x 2 m (5 mm noise) with 6 points moved by +-displacement
    vertically, away from the border: (xyz (n, 3), displaced (6,))."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0.0, 2.0, (2, n))
    z = 0.1 * np.sin(1.5 * x) + 0.05 * np.cos(2 * y) + 0.02 * x * y + rng.normal(0, 0.005, n)
    inner = np.flatnonzero((x > 0.3) & (x < 1.7) & (y > 0.3) & (y < 1.7))
    displaced = rng.choice(inner, 6, replace=False)
    z[displaced] += rng.choice([-1, 1], 6) * displacement
    return np.c_[x, y, z], displaced


def test_every_fit_of_a_smooth_surface_converges_and_finds_the_displaced_points():
    # The plain iteration stops at 100 adjustments on many of these patches (2-cycles and slow
    # valleys) and leaves their points untested; the staged iteration converges on all 400.
    xyz, displaced = smooth_surface_with_displaced_points(26)
    res = detect_patch(xyz, k=40, sigma=0.005, alpha=0.001)
    assert res.info["points_untested"] == {"did_not_converge": 0, "degenerate_geometry": 0,
                                           "too_few_points": 0}
    assert res.tested.all()
    assert res.flagged[displaced].all()
    assert res.flagged.sum() == 6  # no false flags


def test_untested_points_are_rare_on_smooth_surfaces_and_counted_by_reason():
    untested = 0
    for seed in range(5):
        xyz, _ = smooth_surface_with_displaced_points(seed)
        res = detect_patch(xyz, k=40, sigma=0.005, alpha=0.001)
        reasons = res.info["points_untested"]
        assert sum(reasons.values()) == 400 - res.info["points_tested"]
        untested += 400 - res.info["points_tested"]
    assert untested <= 0.005 * 5 * 400


def test_too_few_points_and_collinear_patches_are_counted_as_untested():
    rng = np.random.default_rng(13)
    few = detect_patch(gentle_surface(rng, n=30), k=40)
    assert few.info["points_untested"]["too_few_points"] == 30
    # A scan line repeated while standing still: every patch of the line is collinear.
    t = np.linspace(0.0, 1.0, 60)
    line = np.c_[t, 0.3 * t, 0.1 * t] + rng.normal(0.0, 1e-6, (60, 3))
    res = detect_patch(line, k=40)
    assert res.info["points_untested"]["degenerate_geometry"] == 60
    assert res.info["points_tested"] == 0


def test_points_on_two_rounding_levels_are_tested_a_priori_and_pass():
    """A flat road recorded at 1 mm: every point lies on z = 0 or z = 1 mm. A pair of planes (a
    quadric) holds all of them and sigma_0 vanishes: eq. 31 would be rounding noise over
    rounding noise, so the residuals are normalised with the a-priori variance factor (Baarda's
    w), which is near 0: every point is tested and none is flagged. A point 5 cm up breaks the
    exact fit of its neighbours' patches and is flagged by eq. 31 as usual."""
    rng = np.random.default_rng(21)
    xy = np.round(rng.uniform(0.0, 1.5, (800, 2)), 3)
    z = np.where(rng.random(800) < 0.5, 0.0, 0.001)  # the LAS millimetre
    res = detect_patch(np.c_[xy, z], k=40, sigma=0.005, alpha=0.001)
    assert not res.flagged.any()
    assert res.info["points_tested"] == res.info["points_tested_a_priori"] == 800
    assert sum(res.info["points_untested"].values()) == 0
    assert np.nanmax(res.score) < 1e-3
    spiked = z.copy()
    spiked[100] = 0.05
    res = detect_patch(np.c_[xy, spiked], k=40, sigma=0.005, alpha=0.001)
    assert res.flagged[100] and res.flagged.sum() == 1
    assert res.info["points_tested_a_priori"] < 800
    # the same road with its true noise is tested by eq. 31
    noisy = detect_patch(np.c_[xy, rng.normal(0.0, 0.003, 800)], k=40, sigma=0.005, alpha=0.001)
    assert noisy.info["points_untested"]["degenerate_geometry"] == 0
    assert noisy.info["points_tested_a_priori"] == 0
    assert noisy.info["points_tested"] >= 0.99 * 800


def test_rows_by_distance_then_index_equal_lexsort():
    from algorithms.neighbours import by_distance_then_index

    rng = np.random.default_rng(8)
    dist = np.round(rng.random((500, 17)), 1)  # many ties
    idx = rng.permutation(500 * 17).reshape(500, 17).astype(np.int64)
    dist = np.sort(dist, axis=1)  # as a k-d tree returns them: by distance, ties in any order
    order = np.lexsort((idx, dist), axis=-1)
    want_d, want_i = np.take_along_axis(dist, order, 1), np.take_along_axis(idx, order, 1)
    by_distance_then_index(dist, idx)
    np.testing.assert_array_equal(dist, want_d)
    np.testing.assert_array_equal(idx, want_i)
