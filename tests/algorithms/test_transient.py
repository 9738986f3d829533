"""transient: the vectorised steps against per-point loops, and a scene with a moving arm."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from algorithms.errors import ParameterError
from algorithms.linked import radius_components
from algorithms.transient import (
    cluster_decisions,
    detect_transient,
    floating_clusters,
    neighbour_table,
    persistent_points,
    point_facts,
    scan_line_neighbours,
    scan_line_sides,
    stream_scan_lines,
    touching_persistent,
)
from tests.algorithms.test_detached import same_partition


def slow_floating(xyz, t, radius, min_dt, k, source=None):
    """Per-point loops over explicit distance matrices (k nearest by a full sort): persistent
    points, floating single-epoch points, and those of them in revisited clusters."""
    n = len(xyz)
    dist = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)
    nbrs = []
    for i in range(n):
        order = [j for j in np.argsort(dist[i], kind="stable") if j != i][:k]
        nbrs.append([j for j in order if dist[i, j] <= radius])
    persistent = np.array([any(abs(t[j] - t[i]) >= min_dt for j in nbrs[i]) for i in range(n)])
    single = [i for i in range(n) if not persistent[i]]
    # flood fill of single-epoch points with links <= radius
    label = {}
    for s in single:
        if s in label:
            continue
        label[s] = s
        stack = [s]
        while stack:
            a = stack.pop()
            for b in single:
                if b not in label and dist[a, b] <= radius:
                    label[b] = s
                    stack.append(b)
    attached = {label[i] for i in single if any(persistent[j] for j in nbrs[i])}
    floating = np.array([i in label and label[i] not in attached for i in range(n)])
    src = np.zeros(n, int) if source is None else source
    revisited = {}
    for c in set(label.values()):
        members = [i for i in single if label[i] == c]
        flanks = []
        for i in members:  # the same scanner's previous and next return in time
            mine = sorted((j for j in range(n) if src[j] == src[i]), key=lambda j: (t[j], j))
            pos = mine.index(i)
            flanks += [mine[p] for p in (pos - 1, pos + 1)
                       if 0 <= p < len(mine) and label.get(mine[p]) != c]
        beside = bool(flanks) and 2 * sum(persistent[j] for j in flanks) >= len(flanks)
        covered = [any(persistent[j] and np.hypot(*(xyz[j, :2] - xyz[i, :2])) <= radius
                       for j in range(n)) for i in members]
        revisited[c] = beside and 2 * sum(covered) >= len(members)
    flagged = np.array([bool(floating[i]) and revisited[label[i]] for i in range(n)])
    return persistent, floating, flagged


def street(rng: np.random.Generator):
    """Ground seen on two passes (t ~ 0-1 s and 20-21 s), a box seen once (attached to the
    ground), and a floating arm seen once: returns xyz, t and the arm's index."""
    g = rng.uniform(0, 4, (1500, 2))
    ground = np.column_stack([g, rng.normal(0, 0.003, 1500)])
    t_ground = np.where(rng.random(1500) < 0.5, rng.uniform(0, 1, 1500),
                        rng.uniform(20, 21, 1500))
    # a box face standing on the ground, seen once (occluded on the other pass)
    f = rng.uniform(0, 1, (300, 2))
    face = np.column_stack([1 + f[:, 0], np.full(300, 2.0), 0.02 + 0.8 * f[:, 1]])
    t_face = rng.uniform(0.40, 0.45, 300)
    # an arm 1.2 m above the ground, seen once
    s = rng.uniform(0, 1.5, 120)
    arm = np.column_stack([np.full(120, 3.0), 0.5 + s, np.full(120, 1.2)])
    arm += rng.normal(0, 0.01, arm.shape)
    t_arm = rng.uniform(0.70, 0.72, 120)
    xyz = np.vstack([ground, face, arm])
    t = np.concatenate([t_ground, t_face, t_arm])
    return xyz, t + 4e5, np.arange(1800, 1920)


@pytest.mark.parametrize("seed", [1, 4])
def test_steps_match_slow_loops(seed):
    rng = np.random.default_rng(seed)
    xyz, t, _ = street(rng)
    xyz, t = np.vstack([xyz, hidden_box(rng)[0]]), np.concatenate([t, hidden_box(rng)[1]])
    sub = rng.choice(len(xyz), 500, replace=False)
    xyz, t = xyz[sub], t[sub]
    source = rng.integers(1, 3, len(t))
    k, radius, min_dt = 12, 0.25, 0.5
    idx, near = neighbour_table(xyz, k, radius)
    persistent = persistent_points(t, idx, near, min_dt)
    clusters = floating_clusters(xyz, persistent, touching_persistent(idx, near, persistent),
                                 radius, scan_line_sides(scan_line_neighbours(t, source),
                                                         persistent))
    floating, fast = clusters.floating, clusters.flagged
    slow_p, slow_fl, slow_f = slow_floating(xyz, t, radius, min_dt, k, source)
    np.testing.assert_array_equal(persistent, slow_p)
    np.testing.assert_array_equal(floating, slow_fl)
    np.testing.assert_array_equal(fast, slow_f)
    # single-epoch points of every kind: attached, floating but not revisited, flagged
    assert slow_f.any() and (slow_fl & ~slow_f).any() and (~slow_p & ~slow_fl).any()


def hidden_box(rng: np.random.Generator):
    """The top of a static box 1.5 m up at x 5-6, seen once, with no ground seen under or
    around it (one scanner's look over an occluded spot): xyz and t."""
    f = rng.uniform(0, 1, (200, 2))
    top = np.column_stack([5 + f[:, 0], 1 + f[:, 1], np.full(200, 1.5)])
    return top, 4e5 + rng.uniform(0.2, 0.25, 200)


def test_scan_line_neighbours():
    t = np.array([3.0, 1.0, 2.0, 1.5, 0.5])
    src = np.array([1, 1, 1, 2, 2])
    before, after = scan_line_neighbours(t, src)
    assert before.tolist() == [2, -1, 1, 4, -1] and after.tolist() == [-1, 2, 0, -1, 3]


def test_scan_lines_stream_over_a_file_in_time_order_per_scanner():
    """Two scanners' returns interleaved, each in time order (ties too), some points left out:
    the pass in chunks gives the sort's neighbours; a return out of order stops it."""
    rng = np.random.default_rng(6)
    n = 1000
    source = rng.integers(1, 3, n)
    t = np.round(np.cumsum(rng.uniform(0, 1e-3, n)), 4) + 100 * source  # per scanner in order
    use = rng.random(n) < 0.8
    before, after = np.zeros(n, np.int64), np.zeros(n, np.int64)
    assert stream_scan_lines(t, source, use, before, after, chunk=97)
    rows = np.flatnonzero(use)
    for got, want in zip((before, after), scan_line_neighbours(t[rows], source[rows]),
                         strict=True):
        assert np.all(got[~use] == -1)
        np.testing.assert_array_equal(got[rows], np.where(want >= 0, rows[want], -1))
    t[700], t[701] = t[701] + 1.0, t[700]  # one return later than the next of its scanner
    source[700:702] = 1
    assert not stream_scan_lines(t, source, np.ones(n, bool), before, after, chunk=97)


def test_surface_seen_once_on_a_single_pass_is_not_flagged():
    """One scanner, one pass: every static surface is seen once, so nothing is persistent
    and being seen once says nothing about motion."""
    rng = np.random.default_rng(5)
    x = np.repeat(np.arange(0, 6, 0.3), 60)  # scan lines 0.3 m apart (fast, slow mirror)
    y = np.tile(np.linspace(-3, 3, 60), len(x) // 60)
    z = np.where(np.abs(y) > 2.5, 1 + np.abs(y), 0.0) + rng.normal(0, 0.003, len(x))
    t = 4e5 + np.arange(len(x)) * 1e-4
    res = detect_transient(np.column_stack([x, y, z]), t, np.ones(len(x), int))
    assert not res.flagged.any() and res.info["floating_not_revisited"] > 0


def test_neighbours_equally_far_are_taken_in_index_order_in_any_part():
    """On a lattice many points lie as far as the k-th: the table of a block of the lattice with
    the points within radius around it is the whole lattice's (and takes the lowest indices)."""
    g = np.arange(12) * 0.125  # exact in binary: the ties are exact
    xyz = np.stack(np.meshgrid(g, g, g[:4], indexing="ij"), axis=-1).reshape(-1, 3)
    k, radius = 4, 0.2
    idx, near = neighbour_table(xyz, k, radius)
    xy = xyz[:, :2]
    for lo in (0.0, 0.5):
        block = np.flatnonzero(np.all((xy >= lo - radius) & (xy <= lo + 0.5 + radius), axis=1))
        core = np.flatnonzero(np.all((xy[block] >= lo) & (xy[block] <= lo + 0.5), axis=1))
        part_idx, part_near = neighbour_table(xyz[block], k, radius, rows=core)
        whole = block[core]
        np.testing.assert_array_equal(np.sort(block[part_idx], axis=1), np.sort(idx[whole], axis=1))
        np.testing.assert_array_equal(part_near.sum(axis=1), near[whole].sum(axis=1))
    dist = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)
    np.fill_diagonal(dist, np.inf)
    for p in range(len(xyz)):  # every row: by distance, then index, as brute force
        first = np.lexsort((np.arange(len(xyz)), dist[p]))[:k]
        assert sorted(idx[p]) == sorted(first)
        np.testing.assert_array_equal(np.sort(dist[p, idx[p]]), np.sort(dist[p, first]))
        assert near[p].sum() == np.count_nonzero(dist[p, first] <= radius)


def test_coincident_points_exclude_only_themselves():
    xyz = np.zeros((5, 3))
    idx, near = neighbour_table(xyz, 3, 0.1)
    assert all(i not in idx[i] for i in range(5)) and near.all()


def test_arm_is_flagged_and_occluded_face_is_not():
    rng = np.random.default_rng(2)
    xyz, t, arm = street(rng)
    top, t_top = hidden_box(rng)
    res = detect_transient(np.vstack([xyz, top]), np.concatenate([t, t_top]), radius=0.25)
    assert res.flagged[arm].all()
    assert not np.delete(res.flagged, arm).any()  # the hidden box's top floats unrevisited
    assert res.info["floating_not_revisited"] == len(top)
    face = set(np.unique(res.score[1500:1800]))  # single epoch and attached (1), or persistent
    assert 1.0 in face and 2.0 not in face  # where it meets the ground seen twice (0)


def test_shift_invariance():
    rng = np.random.default_rng(3)
    xyz, t, _ = street(rng)
    a = detect_transient(xyz, t, radius=0.25)
    b = detect_transient(xyz + [5e5, 5e6, 100.0], t + 1e5, radius=0.25)
    np.testing.assert_array_equal(a.score, b.score)


def test_bad_input_is_refused():
    with pytest.raises(ParameterError, match="shape"):
        detect_transient(np.zeros((4, 3)), np.zeros(3))
    with pytest.raises(ParameterError, match="NaN"):
        detect_transient(np.zeros((4, 3)), np.full(4, np.nan))
    with pytest.raises(ParameterError, match="radius"):
        detect_transient(np.zeros((4, 3)), np.zeros(4), radius=0.0)


def test_tiny_clouds():
    assert detect_transient(np.zeros((0, 3)), np.zeros(0)).score.shape == (0,)
    res = detect_transient(np.zeros((2, 3)), np.array([0.0, 10.0]))
    assert res.score.tolist() == [0.0, 0.0]


def test_cluster_wider_than_max_extent_is_static():
    """The arm is 1.5 m long: flagged while max_extent allows it, static scene once wider."""
    rng = np.random.default_rng(2)
    xyz, t, arm = street(rng)
    narrow = detect_transient(xyz, t, radius=0.25, max_extent=1.0)
    wide = detect_transient(xyz, t, radius=0.25, max_extent=2.0)
    assert wide.flagged[arm].all() and wide.info["single_epoch_wide"] == 0
    assert not narrow.flagged.any()
    assert narrow.info["single_epoch_wide"] >= len(arm)
    np.testing.assert_array_equal(narrow.score[arm], 1.0)


@pytest.mark.parametrize("strip", [0.8, 2.5])
def test_facts_of_strips_and_clusters_over_the_file_decide_as_the_whole_cloud(strip):
    """Each point's facts from a strip with 2 x radius around it, the clusters joined over
    the file in small blocks: the scores of the whole cloud's run, though the arm, the rail and
    the ground's single-epoch patches cross the strips' edges and the blocks'."""
    rng = np.random.default_rng(4)
    xyz, t, _ = street(rng)
    top, t_top = hidden_box(rng)
    s = rng.uniform(0.2, 3.8, 300)  # a rail 3.6 m long over the street, seen once: wide
    rail = np.column_stack([s, np.full(300, 3.5), np.full(300, 1.2)])
    t_rail = 4e5 + rng.uniform(0.5, 0.95, 300)  # between the ground's returns
    xyz, t = np.vstack([xyz, top, rail]), np.concatenate([t, t_top, t_rail])
    source = rng.integers(1, 3, len(t))
    k, radius, min_dt, max_extent = 12, 0.25, 0.5, 1.6
    whole = detect_transient(xyz, t, source, k=k, radius=radius, min_dt=min_dt,
                             max_extent=max_extent, centre=False)
    assert whole.flagged.any() and whole.info["single_epoch_wide"] > 0
    facts = {name: np.zeros(len(t), dtype=bool) for name in ("persistent", "touches", "covered")}
    for x0 in np.arange(xyz[:, 0].min(), xyz[:, 0].max() + strip, strip):
        rows = np.flatnonzero(np.abs(xyz[:, 0] - (x0 + strip / 2)) <= strip / 2 + 2 * radius)
        core = (xyz[rows, 0] >= x0) & (xyz[rows, 0] < x0 + strip)
        part = point_facts(xyz[rows], t[rows], k=k, radius=radius, min_dt=min_dt)
        for name, values in part.items():
            facts[name][rows[core]] = values[core]
    single = np.flatnonzero(~facts["persistent"])
    where = np.full(len(t), -1)
    where[single] = np.arange(single.size)
    sides = [type(side)(side.present[single], np.where(side.row[single] >= 0,
                                                        where[side.row[single]], -1),
                        side.persistent[single])
             for side in scan_line_sides(scan_line_neighbours(t, source), facts["persistent"])]
    clusters, n_comp = cluster_decisions(
        xyz[single], {name: facts[name][single] for name in ("touches", "covered")},
        tuple(sides), radius=radius, max_extent=max_extent)
    score = np.zeros(len(t))
    score[single] = np.where(clusters.flagged, 2.0, 1.0)
    np.testing.assert_array_equal(score, whole.score)
    assert n_comp > 1 and int(clusters.wide.sum()) == whole.info["single_epoch_wide"]


def pair_components(xyz: np.ndarray, radius: float) -> tuple[int, np.ndarray]:
    """Components of the explicit list of every link (a k-d tree's pairs within radius)."""
    pairs = cKDTree(xyz).query_pairs(radius, output_type="ndarray")
    m = len(xyz)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
    return connected_components(graph, directed=False)


@pytest.mark.parametrize("radius", [0.05, 0.12, 0.4])
def test_components_without_the_list_of_links_are_those_of_every_link(radius):
    """Cells, joins and early stops: the same partition as one connected-components pass over
    every link, on sparse points, a dense pile (a vehicle standing still) and a thin chain."""
    rng = np.random.default_rng(9)
    xyz = np.vstack([rng.uniform(0, 6, (1500, 3)) * [1, 1, 0.1],
                     rng.normal([3, 3, 2], 0.05, (400, 3)),  # dense: many links a point
                     np.column_stack([np.linspace(0, 6, 200), np.full(200, 3.0),
                                      np.full(200, 0.05)])])
    n_ref, ref = pair_components(xyz, radius)
    n_got, got = radius_components(xyz, radius)
    assert n_got == n_ref and 1 < n_ref < len(xyz)
    assert same_partition(ref, got)


def test_points_exactly_one_radius_apart_are_linked():
    xyz = np.array([[0.0, 0, 0], [0.25, 0, 0], [0.5, 0, 0], [2.0, 0, 0]])
    n, label = radius_components(xyz, 0.25)
    assert n == 2 and label[0] == label[1] == label[2] != label[3]
    assert radius_components(np.zeros((0, 3)), 0.3)[0] == 0


def test_components_with_a_stray_point_far_away():
    """Fine cells and one return kilometres off (a point at the projection's origin): keys that
    would overflow int64 are squeezed, the partition is still that of every link."""
    rng = np.random.default_rng(4)
    xyz = np.vstack([rng.uniform(0, 2, (600, 3)) + [500_000.0, 5_400_000.0, 100.0],
                     [[0.0, 0.0, 0.0]]])
    n_ref, ref = pair_components(xyz, 0.02)
    n_got, got = radius_components(xyz, 0.02)
    assert n_got == n_ref and ref[-1] not in ref[:-1]
    assert same_partition(ref, got)
