"""The detached-cluster detector against brute-force references, on synthetic and real data."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest

from algorithms.detached import (
    XY_SPACING_K,
    detect_detached,
    distinct_voxels,
    envelope_scores,
    first_lowest_per_key,
    floor_scores,
    ladder_pieces,
    lowest_per_cell,
    median_spacing,
    nearest_distance,
    nearest_first,
    pit_scores,
    reach_through,
    scale_of_ladder,
    small_clusters,
    small_ladder,
    strided_median,
    surface_scale,
    voxel_ladder,
    voxel_pieces,
    xy_kth_distance,
    xy_spacing,
)

AIRBORNE = Path(__file__).resolve().parents[1] / "data" / "airborne"


def slow_small_clusters(xyz: np.ndarray, link: float, max_cluster: int) -> np.ndarray:
    """Components of the full link graph by breadth-first search over explicit distances."""
    n = len(xyz)
    label = np.full(n, -1)
    current = 0
    for seed in range(n):
        if label[seed] >= 0:
            continue
        label[seed] = current
        queue = [seed]
        while queue:
            i = queue.pop()
            for j in range(n):
                if label[j] < 0 and np.sqrt(np.sum((xyz[i] - xyz[j]) ** 2)) <= link:
                    label[j] = current
                    queue.append(j)
        current += 1
    sizes = np.bincount(label)
    return sizes[label] <= max_cluster


def slow_envelope(xyz, candidate, k_surface, below, above):
    """One explicit least-squares plane per candidate (np.linalg.lstsq on the design matrix)."""
    surf = np.flatnonzero(~candidate)
    out = np.full(len(xyz), np.nan)
    for i in np.flatnonzero(candidate):
        d2 = np.sum((xyz[surf, :2] - xyz[i, :2]) ** 2, axis=1)
        nb = xyz[surf[np.argsort(d2, kind="stable")[:k_surface]]]
        c = nb.mean(axis=0)
        a_mat = np.c_[nb[:, 0] - c[0], nb[:, 1] - c[1], np.ones(len(nb))]
        coef = np.linalg.lstsq(a_mat, nb[:, 2] - c[2], rcond=None)[0]
        res = nb[:, 2] - c[2] - a_mat @ coef
        r = xyz[i, 2] - c[2] - np.array([xyz[i, 0] - c[0], xyz[i, 1] - c[1], 1.0]) @ coef
        out[i] = max((res.min() - r) / below, (r - res.max()) / above)
    return out


def rough_terrain(seed: int, n: int = 1500) -> np.ndarray:
    """A sloping, rough surface with a 3 m bump: real, never an outlier."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 40, (n, 2))
    z = 0.3 * xy[:, 0] - 0.1 * xy[:, 1] + 3.0 * np.exp(-((xy - 20) ** 2).sum(1) / 20)
    return np.c_[xy, z + rng.normal(0, 0.15, n)]


def test_lowest_per_key_matches_a_loop_over_keys():
    rng = np.random.default_rng(31)
    for n in (1, 7, 2000):
        key = rng.integers(-3, max(2, n // 9), n)
        z = np.round(rng.random(n), 1)  # ties in z: the first in order wins
        slow = [int(np.flatnonzero(key == k)[np.argmin(z[key == k])]) for k in np.unique(key)]
        np.testing.assert_array_equal(first_lowest_per_key(key, z), slow)


def test_lowest_per_cell_takes_each_cells_lowest_point_of_the_index():
    rng = np.random.default_rng(32)
    xyz = np.column_stack([rng.random((500, 2)) * 2, np.round(rng.random(500), 1)])
    index = rng.permutation(500)[:400]  # any order: ties go to the first in it
    got = lowest_per_cell(xyz, index, 0.5, np.zeros(2))
    cells = [tuple(c) for c in np.floor(xyz[index, :2] / 0.5).astype(int)]
    slow = {}
    for i, c in zip(index, cells, strict=True):
        if c not in slow or xyz[i, 2] < xyz[slow[c], 2]:
            slow[c] = i
    np.testing.assert_array_equal(got, [slow[c] for c in sorted(slow)])


def test_small_clusters_matches_full_graph_components():
    rng = np.random.default_rng(5)
    ground = rough_terrain(5, 300)
    clumps = np.vstack([c + rng.normal(0, 0.4, (m, 3)) for c, m in
                        (([10, 10, 30], 3), ([30, 5, -20], 8), ([5, 30, 50], 12))])
    xyz = np.vstack([ground, clumps])
    for link, max_cluster in ((1.0, 5), (3.0, 10), (3.0, 12), (0.5, 1)):
        np.testing.assert_array_equal(small_clusters(xyz, link, max_cluster),
                                      slow_small_clusters(xyz, link, max_cluster))


def test_envelope_matches_explicit_least_squares():
    xyz = rough_terrain(6, 400)
    candidate = np.zeros(len(xyz), bool)
    candidate[::17] = True
    fast = envelope_scores(xyz, candidate, k_surface=25, below=1.0, above=2.0)
    slow = slow_envelope(xyz, candidate, 25, 1.0, 2.0)
    np.testing.assert_allclose(fast, slow, rtol=1e-7, atol=1e-7)
    assert np.isnan(fast[~candidate]).all()


def test_floating_and_sunken_clumps_are_found_rough_surface_raises_nothing():
    rng = np.random.default_rng(7)
    ground = rough_terrain(7)
    high = np.array([12.0, 14.0, 35.0]) + rng.normal(0, 0.3, (4, 3))
    low = np.array([25.0, 8.0, -15.0]) + rng.normal(0, 0.3, (3, 3))
    xyz = np.vstack([ground, high, low])
    res = detect_detached(xyz)
    assert res.flagged[len(ground):].all()
    assert not res.flagged[:len(ground)].any()
    assert not detect_detached(ground).flagged.any()


def test_median_spacing_matches_explicit_distances():
    xyz = rough_terrain(9, 300)
    slow = np.median([np.sort(np.sqrt(((xyz - p) ** 2).sum(1)))[1] for p in xyz])
    assert median_spacing(xyz) == pytest.approx(slow, rel=1e-12)
    assert median_spacing(xyz[:1]) == 0.0


def test_sparse_cloud_keeps_its_small_objects():
    """1.6 m spacing (an ISPRS-like airborne cloud): a 6 m tree of 5 points is no outlier."""
    rng = np.random.default_rng(10)
    ground = rough_terrain(10, 600)  # 40 m x 40 m, ~1.6 m spacing
    tree = np.array([20.0, 20.0, 9.0]) + rng.normal(0, 0.5, (5, 3))
    res = detect_detached(np.vstack([ground, tree]))
    assert res.info["link_used"] > 3.0
    assert not res.flagged.any()
    far = detect_detached(np.vstack([ground, tree + [0, 0, 30]]))
    assert far.flagged[len(ground):].all() and not far.flagged[:len(ground)].any()


def test_results_unchanged_by_a_5e6_shift():
    xyz = np.vstack([rough_terrain(8), [[20.0, 20.0, 40.0]]])
    a = detect_detached(xyz)
    b = detect_detached(xyz + np.array([5e6, 5e6, 1e3]))
    np.testing.assert_array_equal(a.flagged, b.flagged)
    np.testing.assert_allclose(a.score, b.score, rtol=1e-6, atol=1e-6)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="shape"):
        detect_detached(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="link"):
        detect_detached(np.zeros((3, 3)), link=0)
    assert detect_detached(np.zeros((0, 3))).flagged.shape == (0,)


def test_real_airborne_gross_outliers():
    """laspy's append-bug tile (BSD-2): the targets, recall >= 95 %, false alarms <= 0.1 %."""
    las = laspy.read(AIRBORNE / "laspy__append-bug.laz")
    with np.load(AIRBORNE / "laspy__append-bug.truth.npz") as t:
        gross = t["gross"].astype(bool)
        unlabelled = ~t["is_outlier"].astype(bool)
    res = detect_detached(np.c_[las.x, las.y, las.z])
    assert res.flagged[gross].mean() >= 0.95
    assert res.flagged[unlabelled].mean() <= 0.001


# --------------------------------------------------------------------------- under the surface


def slow_pieces(xyz: np.ndarray, size: float, origin: np.ndarray | None = None) -> np.ndarray:
    """Pieces by breadth-first search over explicit voxel indices (26 neighbours)."""
    ijk = np.floor((xyz - (xyz.min(axis=0) if origin is None else origin)) / size).astype(int)
    label = np.full(len(xyz), -1)
    current = 0
    for seed in range(len(xyz)):
        if label[seed] >= 0:
            continue
        label[seed] = current
        queue = [seed]
        while queue:
            i = queue.pop()
            near = np.flatnonzero((np.abs(ijk - ijk[i]).max(axis=1) <= 1) & (label < 0))
            label[near] = current
            queue.extend(near.tolist())
        current += 1
    return label


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    pairs = np.unique(np.c_[a, b], axis=0)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b))


def test_voxel_pieces_match_breadth_first_search():
    rng = np.random.default_rng(11)
    xyz = np.vstack([rough_terrain(11, 300), rng.normal([20, 20, -15], 0.5, (20, 3)),
                     rng.normal([5, 35, 30], 2.0, (15, 3))])
    for size in (0.7, 1.5, 4.0):
        assert same_partition(voxel_pieces(xyz, size), slow_pieces(xyz, size))
    assert voxel_pieces(np.zeros((0, 3)), 1.0).shape == (0,)


def test_reach_through_matches_every_pair():
    rng = np.random.default_rng(5)
    local = rng.uniform(0, 10, (400, 3))
    reach = np.where(rng.random(400) < 0.3, rng.uniform(0.1, 2.0, 400), 0.0)
    points = rng.choice(400, 60, replace=False)
    radius = rng.uniform(0.2, 3.0, 60)
    expected = radius.copy()
    for i, p in enumerate(points):
        for q in np.flatnonzero(reach > 0):
            d = float(np.hypot(*(local[q, :2] - local[p, :2])))
            if d <= radius[i]:
                expected[i] = max(expected[i], d + reach[q])
    assert np.allclose(reach_through(local, points, radius, reach), expected, rtol=0, atol=1e-12)
    assert reach_through(local, points[:0], radius[:0], reach).shape == (0,)
    assert np.array_equal(reach_through(local, points, radius, np.zeros(400)), radius)


def slow_ladder(local: np.ndarray, piece_points: int, start: float):
    """Bits and reach of every ladder size, each from its own breadth-first pieces of the
    points and explicit XY bounds of each small piece's points."""
    bits = np.zeros(len(local), dtype=np.int64)
    reach = np.zeros(len(local))
    for i, size in enumerate(voxel_ladder(start)):
        label = slow_pieces(local, size, np.zeros(3))
        for piece in np.unique(label):
            members = label == piece
            if members.sum() < piece_points:
                bits[members] |= 1 << i
                lo, hi = local[members, :2].min(axis=0), local[members, :2].max(axis=0)
                extent = np.hypot(*(hi - lo)) + 3 * size
                reach[members] = np.maximum(reach[members], extent)
    return bits.astype(np.float64), reach


def test_ladder_cut_on_voxels_matches_pieces_of_the_points_at_every_size():
    rng = np.random.default_rng(12)
    local = np.vstack([rough_terrain(12, 400), rng.normal([20, 20, 2], 0.3, (12, 3)),
                       rng.normal([5, 35, 30], 1.5, (8, 3))])
    local[:, 2] += 20  # the grid's corner at 0 lies below and beside every point
    for piece_points, start in ((30, 0.3), (200, 0.9), (1000, 0.0)):
        bits, reach = ladder_pieces(local, piece_points, start)
        slow_bits, slow_reach = slow_ladder(local, piece_points, start)
        np.testing.assert_array_equal(bits, slow_bits)
        np.testing.assert_allclose(reach, slow_reach, rtol=1e-12)
    empty = ladder_pieces(np.zeros((0, 3)), 30, 0.3)
    assert empty[0].shape == empty[1].shape == (0,)


def test_a_ladder_from_a_later_start_is_the_bits_of_the_finest_shifted():
    """The ladder of any start is a suffix of the ladder from its finest size: the bits cut
    from 0 and shifted are those cut from the start, and they choose the same voxel size."""
    rng = np.random.default_rng(14)
    local = np.vstack([rough_terrain(14, 3000), rng.normal([20, 20, 2], 0.3, (40, 3))])
    local[:, 2] += 20
    finest = ladder_pieces(local, 200, 0.0)[0]
    for start in (0.0, 0.1, 0.13, 0.3, 0.9, 5.0, 16.0):
        cut = ladder_pieces(local, 200, start)[0]
        shift = len(voxel_ladder(0.0)) - len(voxel_ladder(start))
        np.testing.assert_array_equal(finest.astype(np.int64) >> shift, cut.astype(np.int64))
        assert (scale_of_ladder([finest[:1000], finest[1000:]], 200, start, cut_from=0.0)
                == scale_of_ladder([cut], 200, start)
                == (surface_scale(local, 200, start, np.zeros(3))[0] or 0.0))
    with pytest.raises(ValueError, match="holds no ladder"):
        scale_of_ladder([finest], 200, 0.05, cut_from=0.1)


def test_ladder_sizes_double_every_second_step():
    sizes = voxel_ladder(0.3)
    assert sizes[0] >= 0.3 > sizes[0] / np.sqrt(2) * 1.0001
    assert all(b == 2 * a for a, b in zip(sizes[:-2], sizes[2:], strict=True))
    np.testing.assert_allclose(np.diff(np.log(sizes)), np.log(np.sqrt(2)))


def test_distinct_voxels_are_numpys_unique_rows():
    ijk = np.random.default_rng(3).integers(-5, 5, (500, 3))
    voxels, inverse = distinct_voxels(ijk)
    expected, expected_inverse = np.unique(ijk, axis=0, return_inverse=True)
    np.testing.assert_array_equal(voxels, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.ravel())
    far = np.vstack([ijk, [[10 ** 9, -10 ** 9, 10 ** 9]]])  # one key only once squeezed
    voxels, inverse = distinct_voxels(far)
    expected, expected_inverse = np.unique(far, axis=0, return_inverse=True)
    np.testing.assert_array_equal(voxels, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.ravel())


def test_voxel_pieces_with_a_stray_point_far_away():
    """A return at the projection's origin beside a survey 500 km east: the same pieces."""
    xyz = np.vstack([rough_terrain(13, 200) + [500_000.0, 5_400_000.0, 0.0], [[0.0, 0.0, 0.0]]])
    for size in (1e-6, 0.7):
        assert same_partition(voxel_pieces(xyz, size), slow_pieces(xyz, size))


def test_xy_spacing_of_a_regular_grid():
    g = np.arange(0, 60, 0.5)
    xx, yy = np.meshgrid(g, g)
    xyz = np.c_[xx.ravel(), yy.ravel(), np.zeros(xx.size)]
    # 1 / sqrt(density) = 0.5 m; the k-th neighbour ring makes it approximate
    assert xy_spacing(xyz) == pytest.approx(0.5, rel=0.15)
    assert xy_spacing(xyz[:5]) == 0.0


def test_surface_scale_joins_the_surface_and_leaves_clumps_apart():
    rng = np.random.default_rng(12)
    ground = rough_terrain(12, 6000)  # 40 m x 40 m, 0.5 m spacing
    clump = rng.normal([20, 20, -20], 0.5, (50, 3))
    size, small = surface_scale(np.vstack([ground, clump]), piece_points=1000)
    assert size is not None and size < 2.0
    assert small[len(ground):].all() and small[:len(ground)].mean() <= 0.01
    assert surface_scale(ground[:500], piece_points=1000)[0] is None  # no piece can be large


def test_whole_cloud_estimates_from_every_points_value_in_pieces():
    """What a run tile by tile gathers (each point's value, in order, in uneven pieces) gives
    the whole cloud's spacings and voxel size exactly, subsample included."""
    rng = np.random.default_rng(13)
    xyz = np.vstack([rough_terrain(13, 5000), rng.normal([20, 20, -20], 0.5, (50, 3))])
    cuts = [0, 7, 1200, 1201, 3900, len(xyz)]

    def pieces(values: np.ndarray) -> list[np.ndarray]:
        return [values[a:b] for a, b in zip(cuts[:-1], cuts[1:], strict=True)]

    assert strided_median(pieces(nearest_distance(xyz)), 300) == median_spacing(xyz, 300)
    xy = strided_median(pieces(xy_kth_distance(xyz)), 300) * np.sqrt(np.pi / XY_SPACING_K)
    assert xy == xy_spacing(xyz, max_points=300)
    corner = xyz.min(axis=0)
    bits = small_ladder(xyz, 1000, start=0.3, origin=corner)
    assert scale_of_ladder(pieces(bits), 1000, 0.3) == surface_scale(xyz, 1000, 0.3, corner)[0]
    assert scale_of_ladder(pieces(bits), 0, 0.3) == 0.0  # the test off


def test_ties_at_the_kth_neighbour_go_to_the_first_point():
    """On a grid many points lie at the k-th distance: the first of them in the cloud's order
    are taken, whatever else the tree holds (a tile holds fewer points than the cloud)."""
    from scipy.spatial import cKDTree

    g = np.arange(0.0, 6.0)
    xy = np.c_[np.repeat(g, 6), np.tile(g, 6)]
    _, idx = nearest_first(cKDTree(xy), np.array([[2.0, 2.0]]), 3)
    assert idx[0].tolist() == [14, 8, 13]  # itself, then the first two of its four at 1 m
    near = np.flatnonzero(np.abs(xy - 2).max(axis=1) <= 2)
    _, sub = nearest_first(cKDTree(xy[near]), np.array([[2.0, 2.0]]), 3)
    assert near[sub[0]].tolist() == idx[0].tolist()


def test_nearest_first_matches_sorting_every_distance():
    """The k nearest by (distance, index), from all distances, on a grid with duplicates (ties
    at the k-th distance everywhere) and on scattered points (none)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(5)
    g = np.arange(0.0, 8.0, 0.5)
    grid = np.c_[np.repeat(g, g.size), np.tile(g, g.size), np.zeros(g.size ** 2)]
    grid = np.vstack([grid, grid[rng.choice(len(grid), 40)]])[rng.permutation(len(grid) + 40)]
    for xyz in (grid, rng.uniform(0.0, 8.0, (300, 3))):
        for k in (1, 5, 7):
            dist, idx = nearest_first(cKDTree(xyz), xyz, k)
            d = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)
            slow = np.array([np.lexsort((np.arange(len(xyz)), row))[:k] for row in d])
            assert idx.tolist() == slow.tolist()
            np.testing.assert_allclose(dist, np.take_along_axis(d, slow, axis=1), atol=1e-12)


def test_floor_matches_explicit_least_squares():
    xyz = rough_terrain(13, 500)
    reference = np.arange(0, 500, 2)
    candidate = np.zeros(500, bool)
    candidate[1::10] = True
    fast = floor_scores(xyz, candidate, reference, k_floor=20, quantile=0.1, below=0.5)
    for i in np.flatnonzero(candidate):
        d2 = np.sum((xyz[reference, :2] - xyz[i, :2]) ** 2, axis=1)
        nb = xyz[reference[np.argsort(d2, kind="stable")[:20]]]
        c = nb.mean(axis=0)
        a_mat = np.c_[nb[:, :2] - c[:2], np.ones(20)]
        coef = np.linalg.lstsq(a_mat, nb[:, 2] - c[2], rcond=None)[0]
        res = nb[:, 2] - c[2] - a_mat @ coef
        lower = res <= np.median(res)
        coef = np.linalg.lstsq(a_mat[lower], nb[lower, 2] - c[2], rcond=None)[0]
        res = nb[:, 2] - c[2] - a_mat @ coef
        r = xyz[i, 2] - c[2] - np.r_[xyz[i, :2] - c[:2], 1.0] @ coef
        assert fast[i] == pytest.approx((np.quantile(res, 0.1) - r) / 0.5, abs=1e-7)
    assert np.isnan(fast[~candidate]).all()
    assert np.isnan(floor_scores(xyz, candidate, reference, reach=0.0)[candidate]).sum() > 0


def test_floor_slope_guard_matches_explicit_gradient():
    """Where the lower refit plane's gradient (from an explicit least-squares fit) exceeds
    ``max_slope`` the candidate is compared with the lowest reference point around instead."""
    xyz = rough_terrain(15, 500)
    xyz[:, 2] += 0.8 * xyz[:, 0]  # a slope near the limit: some planes pass, some not
    reference = np.arange(0, 500, 2)
    candidate = np.zeros(500, bool)
    candidate[1::5] = True
    limit = 0.8
    free = floor_scores(xyz, candidate, reference, k_floor=12, quantile=0.1, below=0.5)
    guarded = floor_scores(xyz, candidate, reference, k_floor=12, quantile=0.1, below=0.5,
                           max_slope=limit)
    steep = []
    for i in np.flatnonzero(candidate):
        d2 = np.sum((xyz[reference, :2] - xyz[i, :2]) ** 2, axis=1)
        nb = xyz[reference[np.argsort(d2, kind="stable")[:12]]]
        a_mat = np.c_[nb[:, :2] - nb[:, :2].mean(axis=0), np.ones(12)]
        coef = np.linalg.lstsq(a_mat, nb[:, 2], rcond=None)[0]
        res = nb[:, 2] - a_mat @ coef
        lower = res <= np.median(res)
        coef = np.linalg.lstsq(a_mat[lower], nb[lower, 2], rcond=None)[0]
        gradient = np.hypot(coef[0], coef[1])
        if abs(gradient - limit) < 1e-9:
            continue
        steep.append(gradient > limit)
        want = (nb[:, 2].min() - xyz[i, 2]) / 0.5 if steep[-1] else free[i]
        assert guarded[i] == pytest.approx(want, abs=1e-7)
    assert 0 < sum(steep) < len(steep)  # the scene tests both sides


def test_pit_scores_match_brute_force():
    rng = np.random.default_rng(14)
    xyz = rough_terrain(14, 800)
    xyz[::97, 2] -= rng.uniform(1, 4, len(xyz[::97]))
    radius = 4.0
    fast = pit_scores(xyz, radius, below=1.0, min_points=8)
    cell = radius / 3
    ij = np.floor((xyz[:, :2] - xyz[:, :2].min(axis=0)) / cell).astype(int)
    for i in np.flatnonzero(np.isfinite(fast)):
        same = np.flatnonzero((ij == ij[i]).all(axis=1))
        assert xyz[i, 2] == xyz[same, 2].min()  # the lowest of its cell
        block = np.flatnonzero(np.abs(ij - ij[i]).max(axis=1) <= 3)
        block = block[block != i]
        assert fast[i] == pytest.approx(xyz[block, 2].min() - xyz[i, 2])
    assert np.isfinite(fast).sum() > 50


def test_low_noise_clumps_pits_and_real_low_ground():
    """A 60-return clump 20 m under the ground (too big for a cluster) and a lone return 1.5 m
    under it are found; a 3 m deep ramp joined to the ground and ground seen under a roof are
    kept."""
    rng = np.random.default_rng(15)
    xy = rng.uniform(0, 60, (20000, 2))  # 5.6 points per m2
    z = 0.05 * xy[:, 0] + rng.normal(0, 0.03, len(xy))
    ramp = (xy[:, 0] > 20) & (xy[:, 0] < 32) & (np.abs(xy[:, 1] - 30) < 2)
    z[ramp] -= 3.0 * (xy[ramp, 0] - 20) / 12  # down to 3 m under the street, then a wall
    roof_xy = rng.uniform([40, 40], [52, 52], (900, 2))
    roof = np.c_[roof_xy, 0.05 * roof_xy[:, 0] + 4.0]
    under = (xy[:, 0] > 41) & (xy[:, 0] < 51) & (xy[:, 1] > 41) & (xy[:, 1] < 51)
    keep = ~under | (rng.random(len(xy)) < 0.05)  # the roof hides most of the ground
    ground = np.c_[xy, z][keep]
    clump = rng.normal([15, 45, -20], [2.0, 2.0, 0.3], (60, 3))
    pit = np.array([[45.0, 15.0, 0.05 * 45 - 1.5]])
    xyz = np.vstack([ground, roof, clump, pit])
    res = detect_detached(xyz)
    n_real = len(ground) + len(roof)
    assert res.flagged[n_real:].all()
    assert res.flagged[:n_real].sum() <= 2
    assert res.info["pieces"]["points_flagged"] >= 60 and res.info["pits"]["points_flagged"] >= 1
