"""The `section` detector (algorithm (c)): one quadric per XY section, fit and remove, repeat."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from algorithms.errors import ParameterError
from algorithms.section import balanced_buckets, detect_section
from tests.algorithms.test_quadric import slow_fit


def surface(rng, n, size=10.0, noise=0.005, plane=False):
    xy = rng.uniform(0.0, size, (n, 2))
    if plane:
        z = 0.01 * xy[:, 0] - 0.02 * xy[:, 1]
    else:
        z = 0.004 * xy[:, 0] ** 2 - 0.002 * xy[:, 1] ** 2 + 0.001 * xy[:, 0] * xy[:, 1]
    return np.c_[xy, z + rng.normal(0.0, noise, n)]


def slow_section(xyz, section_size, sigma, alpha, max_iterations):
    """Algorithm (c) written plainly: a Python loop over sections and refits, slow_fit inside."""
    n = len(xyz)
    score = np.full(n, np.nan)
    flagged = np.zeros(n, dtype=bool)
    origin = xyz[:, :2].min(axis=0)
    cell = np.floor((xyz[:, :2] - origin) / section_size).astype(int)
    dof = np.arange(1, 1000)
    min_points = 9 + int(dof[np.argmax(np.sqrt(dof) > stats.t.isf(alpha / 2, dof))])
    for key in np.unique(cell, axis=0):
        members = np.flatnonzero((cell == key).all(axis=1))
        active = members.copy()
        for _ in range(max_iterations):
            if len(active) < min_points:
                score[active] = np.nan
                break
            _, _, T, _, _, ok = slow_fit(xyz[active], sigma, max_iter=300, tol=1e-10)
            if not ok:
                score[active] = np.nan
                break
            crit = stats.t.isf(alpha / 2, len(active) - 9)
            score[active] = T
            out = T > crit
            flagged[active[out]] = True
            active = active[~out]
            if not out.any():
                break
    return score, flagged


def test_against_slow_reference():
    rng = np.random.default_rng(1)
    xyz = surface(rng, 1200, size=8.0)
    bad = rng.choice(1200, 12, replace=False)
    xyz[bad, 2] += rng.choice([-1, 1], 12) * rng.uniform(0.03, 2.0, 12)
    # The reference takes the plain path with damped restarts: so does the detector here (the
    # accelerated path may end in another stationary point of a refit).
    res = detect_section(xyz, section_size=4.0, sigma=0.005, alpha=0.001, max_iterations=10,
                         accelerate=False)
    score, flagged = slow_section(xyz, 4.0, 0.005, 0.001, 10)
    np.testing.assert_array_equal(res.flagged, flagged)
    np.testing.assert_array_equal(np.isnan(res.score), np.isnan(score))
    tested = ~np.isnan(score)
    # Some sections of this curved, contaminated surface never converge (in both
    # implementations alike): they are untested, not wrong.
    assert tested.mean() > 0.5
    # The detector stops at ||da|| < 1e-8, the reference at 1e-10.
    np.testing.assert_allclose(res.score[tested], score[tested], rtol=1e-4, atol=1e-4)


def test_gross_outliers_are_removed_iteratively():
    rng = np.random.default_rng(2)
    xyz = surface(rng, 4000)
    # In each 5 m section: one huge outlier that masks several moderate ones.
    huge = rng.choice(4000, 4, replace=False)
    moderate = rng.choice(np.setdiff1d(np.arange(4000), huge), 40, replace=False)
    xyz[huge, 2] += 20.0
    xyz[moderate, 2] += rng.choice([-1, 1], 40) * rng.uniform(0.04, 0.3, 40)
    res = detect_section(xyz, section_size=5.0)
    truth = np.zeros(4000, dtype=bool)
    truth[huge] = truth[moderate] = True
    assert res.flagged[truth].all()
    assert (res.flagged & ~truth).sum() <= 0.002 * 4000
    assert res.info["mean_fits_per_section"] > 2  # it took refits to find them all
    # A removed point keeps its score from the fit that removed it, above that fit's threshold.
    assert (res.score[truth] > 3.0).all()
    # A single fit (no refit) misses some of them: the iteration is what finds them.
    once = detect_section(xyz, section_size=5.0, max_iterations=1)
    assert once.flagged[truth].sum() < truth.sum()


def test_clean_surfaces_are_left_alone():
    rng = np.random.default_rng(3)
    for plane in (True, False):
        xyz = surface(rng, 4000, plane=plane)
        res = detect_section(xyz, section_size=5.0, alpha=0.001)
        assert res.info["points_tested"] == 4000, str(res.info)
        # alpha = 0.001 per test: a handful of chance exceedances at most, never a cascade.
        assert res.flagged.sum() <= 8
        assert np.nanmax(res.score) < 6.0


def test_sparse_section_is_untested():
    rng = np.random.default_rng(4)
    dense = surface(rng, 2000, size=5.0)
    sparse = surface(rng, 15, size=5.0) + np.array([5.0, 0.0, 0.0])  # 15 points: too few
    xyz = np.vstack([dense, sparse])
    res = detect_section(xyz, section_size=5.0)
    assert np.isnan(res.score[2000:]).all()
    assert not res.flagged[2000:].any()
    assert res.info["sections_untested"]["too_few_points"] == 1
    assert res.info["points_untested"] == {"did_not_converge": 0, "degenerate_geometry": 0,
                                           "too_few_points": 15}
    assert res.tested[:2000].all()


def test_shift_by_5e6_changes_nothing():
    rng = np.random.default_rng(5)
    xyz = np.round(surface(rng, 3000, plane=True) * 1024) / 1024  # exact in both frames
    xyz[::300, 2] += 0.25
    a = detect_section(xyz)
    b = detect_section(xyz + np.array([5e6, 5e6, 200.0]))
    np.testing.assert_array_equal(a.score, b.score)
    np.testing.assert_array_equal(a.flagged, b.flagged)
    assert a.flagged[::300].all(), str(a.info)


def test_info_reports_the_run():
    rng = np.random.default_rng(6)
    xyz = surface(rng, 3000, plane=True)
    res = detect_section(xyz, section_size=5.0, alpha=0.01, max_iterations=3)
    info = res.info
    assert info["sections"] == 4
    assert info["alpha"] == 0.01 and info["max_iterations"] == 3
    cells = np.floor((xyz[:, :2] - xyz[:, :2].min(axis=0)) / 5.0).astype(int)
    sizes = np.unique(cells, axis=0, return_counts=True)[1]
    assert info["critical_value"] == pytest.approx(stats.t.isf(0.005, int(np.median(sizes)) - 9))
    assert info["points_tested"] == int(res.tested.sum())
    assert info["sections_untested"]["did_not_converge"] == 0
    assert sum(info["points_untested"].values()) == 3000 - info["points_tested"]
    assert 1 <= info["mean_fits_per_section"] <= 3
    assert info["fits"] == round(info["mean_fits_per_section"] * 4)
    assert 1 <= info["max_fits_per_section"] <= 3


def test_each_point_is_flagged_against_the_critical_value_of_its_own_fit():
    # Removals shrink a section, so later fits use t(n - 9) of a smaller n: the critical value
    # is per point, and flagged == (score > critical) holds for every point.
    rng = np.random.default_rng(8)
    xyz = surface(rng, 2500, size=10.0)
    huge = rng.choice(2500, 4, replace=False)
    xyz[huge, 2] += 5.0
    moderate = rng.choice(np.setdiff1d(np.arange(2500), huge), 30, replace=False)
    xyz[moderate, 2] += rng.choice([-1, 1], 30) * rng.uniform(0.04, 0.2, 30)
    res = detect_section(xyz, section_size=5.0, max_iterations=20)
    critical = np.asarray(res.critical_value)
    assert critical.shape == (2500,)
    assert np.array_equal(np.isnan(critical), np.isnan(res.score))
    tested = res.tested
    np.testing.assert_array_equal(res.flagged[tested], res.score[tested] > critical[tested])
    assert not res.flagged[~tested].any()
    # Critical values are t(n - 9) of the fits' sizes: more than one distinct value per
    # section when a refit removed points.
    assert res.info["max_fits_per_section"] >= 2
    assert np.unique(critical[tested]).size > 4
    n_fit = 9 + np.round([_dof_of(c) for c in np.unique(critical[tested])])
    assert (n_fit >= 26).all()  # never below the size where eq. 31 can flag anything
    # The refitting stopped because a fit removed nothing, not at max_iterations.
    assert res.info["sections_stopped_at_max_iterations"] == 0


def _dof_of(critical: float, alpha: float = 0.001) -> float:
    """The degrees of freedom whose two-sided t critical value at alpha is ``critical``."""
    dof = np.arange(1, 5000)
    return float(dof[np.argmin(np.abs(stats.t.isf(alpha / 2, dof) - critical))])


@pytest.mark.parametrize(
    "kwargs, word",
    [
        ({"section_size": 0.0}, "section_size"),
        ({"section_size": float("nan")}, "section_size"),
        ({"alpha": 0.7}, "alpha"),
        ({"max_iterations": 0}, "max_iterations"),
        ({"sigma": 0.0}, "sigma"),
    ],
)
def test_bad_parameters_are_refused(kwargs, word):
    xyz = surface(np.random.default_rng(7), 100)
    with pytest.raises(ParameterError, match=word):
        detect_section(xyz, **kwargs)


def test_empty_cloud():
    res = detect_section(np.zeros((0, 3)))
    assert res.score.shape == (0,) and res.flagged.shape == (0,)


def test_balanced_buckets_share_every_section_once_by_size():
    sizes = np.array([313, 226, 216, 117, 112, 107, 2, 1])
    offsets, sections = balanced_buckets(sizes, 2)
    assert sorted(sections.tolist()) == list(range(8))
    loads = [int(sizes[sections[offsets[b]:offsets[b + 1]]].sum()) for b in range(2)]
    assert abs(loads[0] - loads[1]) <= sizes.max() and sum(loads) == sizes.sum()
    assert loads == [545, 549]  # greedy: {313, 117, 112, 2, 1} and {226, 216, 107}
    one = balanced_buckets(sizes, 1)
    assert one[0].tolist() == [0, 8]
    many = balanced_buckets(sizes[:3], 8)  # more threads than sections: one bucket per section
    assert many[0].tolist() == [0, 1, 2, 3]


def street_section() -> np.ndarray:
    """A real street section (road, walls, a vehicle), 31,247 points."""
    from pathlib import Path

    data = Path(__file__).resolve().parents[1] / "data" / "sections" / "street_section.npz"
    return np.load(data)["xyz_mm"] * 0.001


def test_a_street_section_is_tested_whole():
    """Its algebraic start and the best plane wander on some CPUs and converge on others (the
    iterations differ in the last bits with the instructions numba compiles to); where they
    wander, its quarters are fitted instead: either way every point is tested."""
    xyz = street_section()
    res = detect_section(xyz, section_size=5.0)  # one section
    assert res.info["sections"] == 1
    assert res.info["sections_cut_in_four"] in (0, 1)
    assert sum(res.info["points_untested"].values()) == 0
    assert 0 < res.flagged.sum() < 0.05 * len(xyz)


def test_a_first_fit_that_does_not_converge_starts_again_from_the_best_plane(monkeypatch):
    """With too few adjustments for any start to converge, the first fit starts again from
    the best plane (reported), the section is cut in four ``MAX_SPLITS`` times, and its points
    are reported untested."""
    import algorithms.section

    monkeypatch.setattr(algorithms.section, "FIT_MAX_ITER", 2)
    res = detect_section(street_section(), section_size=100.0)  # 5 m of points: one quarter
    assert res.info["sections_started_from_plane"] == 1 + algorithms.section.MAX_SPLITS
    assert res.info["sections_cut_in_four"] == algorithms.section.MAX_SPLITS
    assert res.info["smallest_section_size"] == 100.0 / 2**algorithms.section.MAX_SPLITS
    assert res.info["points_untested"]["did_not_converge"] == len(res.flagged)
    assert res.info["sections_untested"]["did_not_converge"] == 1


def test_a_section_that_does_not_converge_is_fitted_as_its_quarters(monkeypatch):
    """The result of a cut section is that of sections half as wide on the same grid."""
    import algorithms.section

    xyz = street_section()
    corner = xyz[:, :2].min(axis=0)
    quarters = detect_section(xyz, section_size=2.5, anchor=corner)
    real_fit = algorithms.section.fit_sections
    sizes = []

    def first_pass_wanders(local, size, *args):
        sizes.append(size)
        budget = algorithms.section.FIT_MAX_ITER
        if len(sizes) == 1:  # the whole section: no adjustment budget, so no convergence
            algorithms.section.FIT_MAX_ITER = 2
        try:
            return real_fit(local, size, *args)
        finally:
            algorithms.section.FIT_MAX_ITER = budget

    monkeypatch.setattr(algorithms.section, "fit_sections", first_pass_wanders)
    res = detect_section(xyz, section_size=5.0, anchor=corner)
    assert sizes == [5.0, 2.5]
    assert res.info["sections_cut_in_four"] == 1
    assert res.info["points_tested"] == quarters.info["points_tested"] > 0
    np.testing.assert_array_equal(res.flagged, quarters.flagged)
    np.testing.assert_array_equal(res.score, quarters.score)
    np.testing.assert_array_equal(res.critical_value, quarters.critical_value)


def test_the_best_plane_is_the_quadric_across_the_least_spread():
    from algorithms.section_fits import _plane

    rng = np.random.default_rng(5)
    xy = rng.uniform(-2, 2, (500, 2))
    xyz = np.c_[xy, 0.5 * xy[:, 0] - 0.2 * xy[:, 1] + 10.0]
    active = rng.random(500) < 0.9
    params, centroid = np.empty(10), np.empty(3)
    _plane(xyz, active, params, centroid)
    np.testing.assert_allclose(centroid, xyz[active].mean(axis=0))
    normal = np.array([0.5, -0.2, -1.0]) / np.linalg.norm([0.5, -0.2, -1.0])
    assert abs(abs(params[6:9] @ normal) - 1.0) < 1e-12
    assert np.all(params[:6] == 0.0) and params[9] == 0.0
    np.testing.assert_allclose((xyz - centroid) @ params[6:9], 0.0, atol=1e-12)
