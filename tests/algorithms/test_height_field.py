"""height_field: the numba kernels against slow explicit-matrix references, and scene properties."""

from __future__ import annotations

import numpy as np
import pytest

from algorithms.detached import lowest_per_cell
from algorithms.errors import ParameterError
from algorithms.height_field import (
    FLOOR_NEIGHBOURS,
    LOW_MAX_SLOPE,
    ONE_SIDED_NZ,
    detect_height_field,
    floor_cells,
    full_residuals,
    neighbours,
)
from algorithms.height_field_fits import (
    MIN_HALF_POINTS,
    all_terms,
    height_field_fit,
    scores_from_terms,
)

# --------------------------------------------------------------------------------------------
# Slow references, straight from the formulas


def slow_fit(uvw: np.ndarray, p: np.ndarray) -> tuple[float, float, float]:
    """w = a + b u + c v by lstsq; residual of p, leverage x_p^T (X^T X)^-1 x_p, rms."""
    x = np.column_stack([np.ones(len(uvw)), uvw[:, 0], uvw[:, 1]])
    beta, *_ = np.linalg.lstsq(x, uvw[:, 2], rcond=None)
    xp = np.array([1.0, p[0], p[1]])
    lev = xp @ np.linalg.inv(x.T @ x) @ xp
    rss = np.sum((uvw[:, 2] - x @ beta) ** 2)
    return p[2] - xp @ beta, lev, np.sqrt(rss / (len(uvw) - 3))


def slow_terms(xyz: np.ndarray, nbr_row: np.ndarray, i: int) -> np.ndarray:
    """(5, 4) terms of point i: explicit frame, explicit fits, halves by coordinate sign."""
    idx = [j for j in nbr_row if j != i and j >= 0]
    pts = xyz[idx]
    c = pts.mean(axis=0)
    scatter = sum(np.outer(q - c, q - c) for q in pts)
    _, vec = np.linalg.eigh(scatter)
    w = vec[:, 0] if vec[2, 0] >= 0 else -vec[:, 0]
    frame = np.column_stack([vec[:, 2], vec[:, 1], w])  # u, v, w
    uvw = (pts - c) @ frame
    p = (xyz[i] - c) @ frame
    out = np.full((5, 4), np.nan)
    out[0, :3] = slow_fit(uvw, p)
    for f, (axis, sign) in enumerate([(0, 1), (0, -1), (1, 1), (1, -1)]):
        half = uvw[sign * (uvw[:, axis] - p[axis]) > 0]
        if len(half) >= MIN_HALF_POINTS:
            out[f + 1, :3] = slow_fit(half, p)
    out[:, 3] = w[2]
    return out


def slow_score(terms: np.ndarray, sigma: float, rms_weight: float, nz: float,
               half_gate: float, max_leverage: float) -> float:
    def term(r, lev, rms, wz):
        if np.isnan(r) or lev > max_leverage:
            return np.inf
        r = 0.0 if (r < 0 and wz >= nz) else r
        return max(abs(r) / (sigma * np.sqrt(1 + lev)), rms_weight * rms / sigma)

    fits = terms if not terms[0, 2] <= half_gate * sigma else terms[:1]
    best = min(term(*f) for f in fits)
    return best if np.isfinite(best) else np.nan


def _sorted_halves(terms: np.ndarray) -> np.ndarray:
    """The u/v axes' signs are arbitrary, so the four halves are compared as a set."""
    halves = np.nan_to_num(terms[1:5, :3], nan=-1.0)
    return halves[np.lexsort(halves.T[::-1])]


# --------------------------------------------------------------------------------------------
# Scenes


def rough_road(rng: np.random.Generator, size: float = 3.0, spacing: float = 0.02,
               noise: float = 0.002) -> np.ndarray:
    """Jittered grid on a crowned, graded road with mm texture and Gaussian noise."""
    g = np.arange(0.0, size, spacing)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    x = x + rng.uniform(-0.3, 0.3, x.size) * spacing
    y = y + rng.uniform(-0.3, 0.3, y.size) * spacing
    z = 0.005 * x - 0.01 * (y - size / 2) ** 2 + 0.001 * np.sin(x / 0.05) * np.cos(y / 0.07)
    return np.column_stack([x, y, z + rng.normal(0.0, noise, x.size)])


def road_with_curb_and_lid(rng: np.random.Generator) -> np.ndarray:
    """A road whose y > 2.2 half is a 15 cm curb/sidewalk, with a 2 cm raised lid of r = 0.3 m."""
    xyz = rough_road(rng)
    x, y = xyz[:, 0], xyz[:, 1]
    xyz[y > 2.2, 2] += 0.15
    xyz[(x - 1.2) ** 2 + (y - 1.2) ** 2 < 0.3**2, 2] += 0.02
    # the curb face: a vertical strip of points between the road and the sidewalk
    xf = np.arange(0.0, 3.0, 0.02)
    zf = np.arange(0.01, 0.15, 0.02)
    fx, fz = (a.ravel() for a in np.meshgrid(xf, zf))
    base = 0.005 * fx - 0.01 * (2.2 - 1.5) ** 2
    face = np.column_stack([fx, np.full(fx.size, 2.2) + rng.normal(0, 0.002, fx.size),
                            base + fz])
    return np.vstack([xyz, face])


# --------------------------------------------------------------------------------------------
# Kernels against the references


def test_height_field_fit_matches_lstsq():
    rng = np.random.default_rng(1)
    for _ in range(20):
        m = int(rng.integers(6, 40))
        uvw = rng.normal(size=(m, 3)) * [0.1, 0.05, 0.003]
        p = rng.normal(size=3) * [0.05, 0.05, 0.01]
        fast = height_field_fit(uvw, np.arange(m), m, p[0], p[1], p[2])
        np.testing.assert_allclose(fast, slow_fit(uvw, p), rtol=1e-9, atol=1e-15)


def test_collinear_patch_is_singular():
    uvw = np.column_stack([np.linspace(0, 1, 10), np.zeros(10), np.zeros(10)])
    assert np.isnan(height_field_fit(uvw, np.arange(10), 10, 0.5, 0.0, 0.0)[0])


def test_all_terms_match_explicit_reference():
    rng = np.random.default_rng(2)
    xyz = rough_road(rng, size=0.6)
    xyz = np.vstack([xyz, [[0.3, 0.3, 0.05]], rng.normal(0.3, 0.05, (20, 3))])
    nbr = neighbours(xyz, 16)
    terms = all_terms(xyz, nbr)
    for i in rng.choice(len(xyz), 60, replace=False).tolist() + [len(xyz) - 21]:
        ref = slow_terms(xyz, nbr[i], i)
        np.testing.assert_allclose(terms[i, 0], ref[0], rtol=1e-7, atol=1e-12)
        np.testing.assert_allclose(_sorted_halves(terms[i]), _sorted_halves(ref), rtol=1e-7,
                                   atol=1e-12)


def test_scores_match_slow_loop():
    rng = np.random.default_rng(3)
    terms = rng.normal(size=(200, 5, 4)) * [0.01, 0.0, 0.003, 1.0]
    terms[:, :, 2] = np.abs(terms[:, :, 2])
    terms[:, :, 1] = rng.uniform(0, 2, (200, 5))
    terms[:, :, 3] = rng.uniform(-1, 1, (200, 1))
    terms[rng.random((200, 5)) < 0.3, 0] = np.nan
    terms[0, :, 0] = np.nan
    terms[rng.random((200, 5)) < 0.1, 1] = 50.0  # beyond the leverage limit
    fast = scores_from_terms(terms, 0.002, 0.5, ONE_SIDED_NZ, 2.0, 10.0)
    slow = np.array([slow_score(t, 0.002, 0.5, ONE_SIDED_NZ, 2.0, 10.0) for t in terms])
    np.testing.assert_allclose(fast, slow, rtol=1e-12)
    assert np.isnan(fast[0])
    assert (terms[:, 0, 2] <= 0.004).any() and (terms[:, 0, 2] > 0.004).any()  # both branches


# --------------------------------------------------------------------------------------------
# Properties on synthetic scenes


def test_floating_clump_above_a_road_is_found():
    rng = np.random.default_rng(4)
    road = rough_road(rng)
    clump = np.column_stack([rng.uniform(1.0, 1.6, 150), rng.uniform(1.0, 1.6, 150),
                             rng.uniform(0.1, 0.6, 150)])
    res = detect_height_field(np.vstack([road, clump]))
    assert res.flagged[len(road):].mean() >= 0.8  # 86 % here: clumped droplets hide a few
    assert res.flagged[: len(road)].sum() == 0


def mirror_scene(rng: np.random.Generator) -> tuple[np.ndarray, int, int]:
    """A 6 m road with a puddle (no returns from the water, 0.8 m wide), mirror returns 0.3-0.7 m
    under it (the image of a car body), and a wall seen only above 0.9 m (its foot
    hidden): xyz, index of the first mirror return and of the first wall point."""
    road = rough_road(rng, size=6.0, spacing=0.04)
    puddle = np.hypot(road[:, 0] - 3.0, road[:, 1] - 3.0) < 0.4
    road = road[~puddle]
    n_img = 300  # the image of a car's roof and side: surfaces of their own
    img = np.column_stack([rng.uniform(2.75, 3.25, n_img), rng.uniform(2.75, 3.25, n_img),
                           np.full(n_img, -0.7)])
    img[::2, 0] = 2.75
    img[::2, 2] = rng.uniform(-0.7, -0.3, n_img // 2)
    img += rng.normal(0, 0.002, img.shape)
    wx, wz = (a.ravel() for a in np.meshgrid(np.arange(0.5, 1.5, 0.04),
                                             np.arange(0.9, 1.6, 0.04)))
    wall = np.column_stack([wx, np.full(wx.size, 6.5), wz])
    wall += rng.normal(0, 0.002, wall.shape)
    return np.vstack([road, img, wall]), len(road), len(road) + n_img


def test_half_patches_fitted_only_where_scores_read_them():
    """Scores equal those from every point's full and half patches (the slow way)."""
    rng = np.random.default_rng(13)
    xyz, _, _ = mirror_scene(rng)
    local = xyz - xyz.mean(axis=0)
    terms = all_terms(local, neighbours(xyz - xyz.min(axis=0), 24))
    for sigma in (0.001, 0.003, 0.02):
        expected = scores_from_terms(terms, sigma, 0.5, ONE_SIDED_NZ, 2.0, 10.0)
        got = detect_height_field(xyz, sigma=sigma, low=False)
        np.testing.assert_allclose(got.score, expected, rtol=1e-9, atol=0.0)
    one_surface = terms[:, 0, 2] <= 2.0 * np.array([[0.001], [0.02]])
    assert not one_surface[0].all() and one_surface[1].all()  # halves needed, then none


def test_wanted_points_get_the_scores_of_the_whole_run():
    rng = np.random.default_rng(12)
    xyz, first_img, _ = mirror_scene(rng)
    wanted = rng.random(len(xyz)) < 0.3
    wanted[first_img:first_img + 20] = True
    whole = detect_height_field(xyz, sigma=0.003)
    part = detect_height_field(xyz, sigma=0.003, wanted=wanted)
    np.testing.assert_array_equal(part.score[wanted], whole.score[wanted])
    assert np.array_equal(part.flagged[wanted], whole.flagged[wanted])
    assert part.flagged[wanted].any()
    auto = full_residuals(xyz, 24)
    np.testing.assert_array_equal(full_residuals(xyz, 24, wanted=wanted)[wanted], auto[wanted])
    assert np.isnan(full_residuals(xyz, 24, wanted=wanted)[~wanted]).all()


def test_mirror_returns_under_the_road_are_low():
    rng = np.random.default_rng(11)
    xyz, first_img, first_wall = mirror_scene(rng)
    res = detect_height_field(xyz)
    assert res.flagged[first_img:first_wall].mean() >= 0.9
    assert not res.flagged[:first_img].any() and not res.flagged[first_wall:].any()
    assert res.info["low_test"]["points_flagged"] >= 0.9 * (first_wall - first_img)
    off = detect_height_field(xyz, low=False)
    assert off.flagged[first_img:first_wall].mean() < 0.1 and "low_test" not in off.info


def slow_floor_cells(local: np.ndarray, cell: float) -> np.ndarray:
    """Per cell: its lowest return, kept when at least FLOOR_NEIGHBOURS of the 8 neighbour
    cells' lowest returns continue its plane."""
    cells: dict[tuple[int, int], int] = {}
    for i, key in enumerate(map(tuple, np.floor((local[:, :2] - local[:, :2].min(axis=0))
                                                / cell).astype(int))):
        if key not in cells or local[i, 2] < local[cells[key], 2]:
            cells[key] = i
    keep = []
    for (a, b), i in cells.items():
        support = 0
        for da in (-1, 0, 1):
            for db in (-1, 0, 1):
                j = cells.get((a + da, b + db))
                if (da or db) and j is not None and (
                        abs(local[j, 2] - local[i, 2]) <= LOW_MAX_SLOPE * cell * np.hypot(da, db)):
                    support += 1
        if support >= FLOOR_NEIGHBOURS:
            keep.append(i)
    return np.sort(np.array(keep, dtype=np.int64))


def test_floor_cells_match_slow_loop_and_leave_out_a_walls_foot():
    rng = np.random.default_rng(12)
    road = rough_road(rng, size=3.0, spacing=0.05)
    road[road[:, 0] > 2.0, 2] += 0.3  # a step: cells across it do not continue each other
    wx, wz = (a.ravel() for a in np.meshgrid(np.arange(0, 3, 0.05), np.arange(1.5, 3, 0.05)))
    wall = np.column_stack([wx, np.full(wx.size, 4.0), wz])  # foot hidden: lowest z 1.5 m
    local = np.vstack([road, wall])
    cell = 0.2
    lowest = lowest_per_cell(local, np.arange(len(local)), cell)
    fast = floor_cells(local, np.arange(len(local)), cell)
    np.testing.assert_array_equal(fast, slow_floor_cells(local, cell))
    assert not np.isin(fast, np.arange(len(road), len(local))).any()  # no wall cell
    assert np.isin(lowest[lowest < len(road)], fast).mean() > 0.7  # the road's cells stay


def test_rough_surface_with_curb_and_lid_raises_nothing():
    rng = np.random.default_rng(5)
    xyz = road_with_curb_and_lid(rng)
    res = detect_height_field(xyz)
    assert res.info["points_tested"] == len(xyz)
    assert res.flagged.sum() == 0, xyz[res.flagged]


def test_near_surface_spike_is_one_sided():
    rng = np.random.default_rng(6)
    road = rough_road(rng)
    spikes = np.array([[1.5, 1.5, 0.0], [2.0, 0.7, 0.0], [0.8, 2.0, 0.0], [2.3, 2.3, 0.0]])
    for p in spikes:
        near = np.argmin(np.sum((road[:, :2] - p[:2]) ** 2, axis=1))
        p[2] = road[near, 2]
    spikes[:, 2] += [0.04, 0.04, -0.04, -0.04]  # 20 sigma: half patches extrapolate (h ~ 1)
    res = detect_height_field(np.vstack([road, spikes]))
    assert res.flagged[-4:].tolist() == [True, True, False, False]
    two_sided = detect_height_field(np.vstack([road, spikes]), one_sided=False)
    assert two_sided.flagged[-4:].all()


def test_scores_survive_large_coordinates():
    rng = np.random.default_rng(7)
    xyz = road_with_curb_and_lid(rng)
    a = detect_height_field(xyz)
    b = detect_height_field(xyz + [5e5, 5e6, 100.0])
    np.testing.assert_allclose(a.score, b.score, rtol=1e-5, atol=1e-3)
    assert a.info["sigma"] == pytest.approx(b.info["sigma"], rel=1e-5)


def test_given_sigma_is_used():
    rng = np.random.default_rng(8)
    res = detect_height_field(rough_road(rng, size=1.0), sigma=0.01)
    assert res.info["sigma"] == 0.01 and res.info["sigma_source"] == "given"


@pytest.mark.parametrize(
    "kwargs, words",
    [({"k": 4}, "k must"), ({"sigma": -1.0}, "sigma must"), ({"sigma": "big"}, "sigma must"),
     ({"threshold": 0.0}, "threshold must"), ({"rms_weight": -1.0}, "rms_weight must")],
)
def test_bad_parameters_are_refused(kwargs, words):
    with pytest.raises(ParameterError, match=words):
        detect_height_field(np.zeros((50, 3)), **kwargs)


def test_bad_arrays_are_refused():
    with pytest.raises(ParameterError, match="shape"):
        detect_height_field(np.zeros((5, 2)))
    with pytest.raises(ParameterError, match="NaN"):
        detect_height_field(np.full((5, 3), np.nan))


def test_empty_and_tiny_clouds():
    assert detect_height_field(np.zeros((0, 3))).score.shape == (0,)
    res = detect_height_field(np.random.default_rng(9).normal(size=(4, 3)))
    assert np.isnan(res.score).all() and not res.flagged.any()


def _crown_and_dust():
    """Ground and a sparse tree crown each recorded on two passes 10 s apart, and a dust clump
    recorded once: (xyz, gps_time, label 0 ground, 1 crown, 2 dust)."""
    rng = np.random.default_rng(4)
    g = rng.uniform(0, 20, (20000, 2))
    ground = np.c_[g, rng.normal(0, 0.005, 20000)]
    c = rng.normal(0, 1, (3000, 3))
    c *= rng.uniform(0, 2, (3000, 1)) / np.linalg.norm(c, axis=1)[:, None]
    dust = rng.normal(0, 0.15, (300, 3)) + [4, 4, 1.0]
    xyz = np.r_[ground, c + [10, 10, 5], dust]
    passes = np.where(rng.random(23000) < 0.5, 0.0, 10.0) + rng.random(23000)
    t = np.r_[passes, 5.0 + rng.random(300) * 0.2]
    label = np.r_[np.zeros(20000), np.ones(3000), np.full(300, 2)]
    return xyz, t, label


def test_a_scatter_seen_again_is_not_flagged_and_one_seen_once_is():
    """Times alone (no foliage test): the crown seen on both passes, the dust once."""
    xyz, t, label = _crown_and_dust()
    off = detect_height_field(xyz, gps_time=t, low=False, static_dt=0.0, foliage_reach=0.0)
    on = detect_height_field(xyz, gps_time=t, low=False, static_dt=0.5, foliage_reach=0.0)
    assert off.info["points_static"] == 0 and on.info["points_static"] > 1000
    crown, dust = label == 1, label == 2
    assert on.flagged[crown].mean() < 0.5 * off.flagged[crown].mean()
    np.testing.assert_array_equal(on.flagged[dust], off.flagged[dust])
    assert on.flagged[dust].any()
    assert not (on.flagged & ~off.flagged).any()
    # without times nothing is seen again
    assert detect_height_field(xyz, low=False, static_dt=0.5,
                               foliage_reach=0.0).info["points_static"] == 0


def test_seen_again_equals_a_loop_over_the_neighbours():
    from algorithms.height_field_fits import seen_again

    rng = np.random.default_rng(2)
    xyz = rng.random((400, 3))
    t = rng.choice([0.0, 0.3, 1.0, np.nan], 400)
    nbr = np.argsort(np.linalg.norm(xyz[:, None] - xyz[None], axis=2), axis=1)[:, :8]
    points = np.arange(400)
    got = seen_again(xyz, t, nbr, points, 0.15, 0.5)
    want = [any(np.linalg.norm(xyz[j] - xyz[p]) <= 0.15 and abs(t[j] - t[p]) >= 0.5
                for j in nbr[p]) for p in points]
    np.testing.assert_array_equal(got, want)
    assert 0 < np.count_nonzero(got) < len(points)


def test_a_scatter_seen_again_near_the_road_is_still_flagged():
    """A mist over the road recorded on both passes is seen again as a crown is, but it hangs
    within ``static_above`` of the road: only the crown, metres up, is taken for vegetation."""
    xyz, t, label = _crown_and_dust()
    rng = np.random.default_rng(5)
    mist = np.c_[rng.uniform(14, 17, (600, 2)), rng.uniform(0.05, 0.8, 600)]
    xyz = np.r_[xyz, mist]
    t = np.r_[t, np.where(rng.random(600) < 0.5, 0.0, 10.0) + rng.random(600)]
    label = np.r_[label, np.full(600, 3)]
    off = detect_height_field(xyz, gps_time=t, low=False, static_dt=0.0, foliage_reach=0.0)
    on = detect_height_field(xyz, gps_time=t, low=False, foliage_reach=0.0)  # 0.5 s, 2 m
    crown, mist = label == 1, label == 3
    assert on.info["points_seen_again_near_ground"] > 100
    assert off.flagged[mist].mean() > 0.5
    np.testing.assert_array_equal(on.flagged[mist], off.flagged[mist])
    assert on.flagged[crown].mean() < 0.5 * off.flagged[crown].mean()
    everywhere = detect_height_field(xyz, gps_time=t, low=False, static_above=0.0,
                                     foliage_reach=0.0)
    assert everywhere.flagged[mist].mean() < 0.5 * off.flagged[mist].mean()


def _crown_seen_once():
    """Ground, a dense crown 4-6 m up seen on one pass (no times), a sparse scatter of returns
    in the air at the same height (rain) and a dense dust clump 0.5-1.5 m over the road:
    (xyz, label 0 ground, 1 crown, 2 rain, 3 dust)."""
    rng = np.random.default_rng(6)
    g = rng.uniform(0, 20, (20000, 2))
    ground = np.c_[g, rng.normal(0, 0.005, 20000)]
    c = rng.normal(0, 1, (6000, 3))
    crown = c * rng.uniform(0, 1, (6000, 1)) / np.linalg.norm(c, axis=1)[:, None] + [10, 10, 5]
    rain = np.c_[rng.uniform(2, 18, (90, 2)), rng.uniform(4, 6, 90)]
    rain = rain[np.linalg.norm(rain - [10, 10, 5], axis=1) > 2.0][:60]  # not in the crown
    dust = rng.normal(0, 0.15, (400, 3)) + [4, 15, 1.0]
    label = np.r_[np.zeros(20000), np.ones(6000), np.full(60, 2), np.full(400, 3)]
    return np.r_[ground, crown, rain, dust], label


def test_a_dense_scatter_high_above_the_ground_is_foliage_even_seen_once():
    xyz, label = _crown_seen_once()
    off = detect_height_field(xyz, low=False, foliage_reach=0.0)
    on = detect_height_field(xyz, low=False)  # the defaults: 0.5 m, 2 m
    crown, rain, dust = label == 1, label == 2, label == 3
    assert off.flagged[crown].sum() > 100 and not on.flagged[crown].any()
    assert on.info["points_in_foliage"] > 1000 and off.info["points_in_foliage"] == 0
    for kind in (rain, dust):  # sparse, or near the road: tested as before
        assert off.flagged[kind].sum() > 40
        np.testing.assert_array_equal(on.flagged[kind], off.flagged[kind])
    assert not (on.flagged & ~off.flagged).any()


def test_dense_scatter_equals_a_loop_over_the_neighbours():
    from algorithms.height_field import dense_scatter, neighbours

    rng = np.random.default_rng(3)
    local = np.r_[rng.normal(0, 0.1, (200, 3)), rng.uniform(-3, 3, (200, 3))]
    points = np.arange(0, 400, 2)
    nbr = neighbours(local, 12, points)
    got = dense_scatter(local, nbr, points, 0.25)
    want = [p for p in points
            if np.sort(np.linalg.norm(local - local[p], axis=1))[12] <= 0.25]
    np.testing.assert_array_equal(got, want)
    assert 0 < got.size < points.size


def test_height_above_lowest_equals_a_loop_over_the_cells():
    from algorithms.height_field import height_above_lowest

    rng = np.random.default_rng(8)
    local = np.c_[rng.uniform(0, 6, (500, 2)), rng.normal(0, 2, 500)]
    local[:40, :2] = np.floor(local[:40, :2])  # points on cell edges
    rows = np.arange(0, 500, 3)
    got = height_above_lowest(local, rows, 0.7)
    cell = np.floor(local[:, :2] / 0.7)
    want = [local[r, 2] - local[np.all(np.abs(cell - cell[r]) <= 1, axis=1), 2].min()
            for r in rows]
    np.testing.assert_allclose(got, want, rtol=0, atol=0)
    assert (got >= 0).all() and (got > 0).any()
    assert height_above_lowest(local, np.zeros(0, np.int64)).shape == (0,)
