"""The batched quadric fit (eqs. 18-31) against a slow reference written from the equations."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from algorithms.fit_outcome import CONVERGED, DOF_LOSS, can_flag, min_patch_size
from algorithms.quadric import (
    fit_masked,
    fit_quadrics,
    interleaved_order,
    moved_frame,
    weighted_moments,
)

# ---------------------------------------------------------------------------------------------
# Slow reference: one patch at a time, explicit matrices, the Lagrange-bordered normal equations.
# ---------------------------------------------------------------------------------------------


def ref_design_matrix(p: np.ndarray) -> np.ndarray:
    """B of eq. 23, one row per point: (n, 10)."""
    x, y, z = p.T
    return np.stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z, np.ones_like(x)], axis=1)


def ref_gradient(a: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(a_x, a_y, a_z) of eqs. 25-27 per point: (n, 3)."""
    x, y, z = p.T
    return np.stack(
        [
            2 * a[0] * x + a[3] * y + a[4] * z + a[6],
            2 * a[1] * y + a[3] * x + a[5] * z + a[7],
            2 * a[2] * z + a[4] * x + a[5] * y + a[8],
        ],
        axis=1,
    )


def slow_fit(points, sigma=0.005, max_iter=100, tol=1e-10):
    """Gauss-Helmert adjustment with equivalent single measurements, one point at a time, each
    bordered system solved with np.linalg.solve; the plain iteration a <- a + da, then restarts
    from the algebraic start with steps a <- a + 0.5 da and a <- a + 0.25 da, max_iter shared
    40 / 30 / 30 %.

    Returns (a, v, T, sigma0, iterations, converged) in the frame of the points' centroid.
    """
    p = np.asarray(points, dtype=np.float64)
    p = p - p.mean(axis=0)
    n = len(p)
    D = np.diag(np.broadcast_to(np.asarray(sigma, dtype=np.float64), (3,)) ** 2)
    B = ref_design_matrix(p)
    _, vecs = np.linalg.eigh(B.T @ B)
    start = vecs[:, 0].copy()  # algebraic start
    budgets = [int(0.4 * max_iter), int(0.3 * max_iter)]
    budgets.append(max_iter - sum(budgets))
    iterations = 0
    for damping, budget in zip((1.0, 0.5, 0.25), budgets, strict=True):
        a = start.copy()
        for _ in range(budget):
            iterations += 1
            g = ref_gradient(a, p)
            var = np.array([g[i] @ D @ g[i] for i in range(n)])  # eq. 30
            P = np.diag(1.0 / var)
            w = B @ a  # eq. 24
            N = B.T @ P @ B
            u = B.T @ P @ w
            M = np.zeros((11, 11))
            M[:10, :10] = N
            M[:10, 10] = a
            M[10, :10] = a
            rhs = np.concatenate([-u, [(1.0 - a @ a) / 2.0]])
            da = np.linalg.solve(M, rhs)[:10]
            Q = np.linalg.inv(M)[:10, :10]
            v = B @ da + w  # eq. 29
            Qvv = np.linalg.inv(P) - B @ Q @ B.T
            sigma0 = np.sqrt(v @ P @ v / (n - 9))
            T = np.abs(v) / (sigma0 * np.sqrt(np.diag(Qvv)))  # eq. 31
            if np.linalg.norm(da) < tol:
                return a + da, v, T, sigma0, iterations, True
            a = a + damping * da
    return a, v, T, sigma0, iterations, False


def canonical(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    return a if a[np.argmax(np.abs(a))] > 0 else -a


def quadric_vector(A: np.ndarray, b: np.ndarray, c: float, shift: np.ndarray) -> np.ndarray:
    """Eq. 18 parameters of x^T A x + b.x + c = 0 written in the frame x = x' + shift."""
    b2 = 2.0 * A @ shift + b
    c2 = shift @ A @ shift + b @ shift + c
    vec = [A[0, 0], A[1, 1], A[2, 2], 2 * A[0, 1], 2 * A[0, 2], 2 * A[1, 2], *b2, c2]
    return canonical(np.array(vec))


def random_patches(rng, m, k, kind, noise=0.005, radius=0.3):
    xy = rng.uniform(-radius, radius, (m, k, 2))
    x, y = xy[..., 0], xy[..., 1]
    if kind == "curved":
        z = 0.8 * x**2 - 0.4 * y**2 + 0.3 * x * y + 0.1 * x
    elif kind == "flat":
        z = 0.03 * x - 0.01 * y
    else:
        raise ValueError(kind)
    z = z + rng.normal(0.0, noise, (m, k))
    return np.concatenate([xy, z[..., None]], axis=2)


# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["curved", "flat"])
@pytest.mark.parametrize("sigma", [0.005, (0.004, 0.006, 0.005)])
def test_batched_fit_matches_slow_reference(kind, sigma):
    rng = np.random.default_rng(7)
    patches = random_patches(rng, 12, 40, kind)
    patches[3, 5, 2] += 0.08  # one gross outlier in one patch
    fit = fit_quadrics(patches, sigma, max_iter=60, tol=1e-10, accelerate=False)
    # Flat patches are ill-conditioned (the quadric tends to a double plane): the reference
    # disagrees with itself by 2e-9 in T when the same points are merely listed in another order,
    # so 1e-9 is only meaningful for curved patches.
    rtol = 1e-9 if kind == "curved" else 1e-8
    for j in range(len(patches)):
        a, v, T, sigma0, it, ok = slow_fit(patches[j], sigma, max_iter=60, tol=1e-10)
        assert fit.iterations[j] == it
        assert fit.converged[j] == ok
        np.testing.assert_allclose(fit.t_stat[j], T, rtol=rtol, atol=rtol * T.max())
        sign = np.sign(canonical(a) @ a)
        np.testing.assert_allclose(
            fit.residuals[j], sign * v, rtol=rtol, atol=1e-9 * np.abs(v).max()
        )
        assert fit.sigma0[j] == pytest.approx(sigma0, rel=rtol)
        np.testing.assert_allclose(fit.params[j], canonical(a), atol=rtol)
        np.testing.assert_allclose(fit.centroid[j], patches[j].mean(axis=0), rtol=1e-12)


def test_t_first_only_gives_the_same_first_t():
    rng = np.random.default_rng(3)
    patches = random_patches(rng, 30, 40, "curved")
    full = fit_quadrics(patches, 0.005, max_iter=40, tol=1e-9)
    first = fit_quadrics(patches, 0.005, max_iter=40, tol=1e-9, t_first_only=True)
    np.testing.assert_allclose(first.t_stat[:, 0], full.t_stat[:, 0], rtol=1e-11)
    assert np.isnan(first.t_stat[:, 1:]).all()


def test_acceleration_reaches_the_same_fixed_point():
    # Anderson acceleration only changes the path. On these strongly curved small patches a few
    # have several stationary points and the paths may end in different ones; we accept 5 %.
    rng = np.random.default_rng(11)
    patches = random_patches(rng, 200, 40, "curved", radius=0.15)
    plain = fit_quadrics(patches, 0.005, max_iter=3000, tol=1e-12, accelerate=False)
    fast = fit_quadrics(patches, 0.005, max_iter=1000, tol=1e-12, accelerate=True)
    both = plain.converged & fast.converged
    assert both.mean() > 0.97
    same = np.nanmax(np.abs(plain.t_stat - fast.t_stat), axis=1)[both] < 1e-6
    assert same.mean() >= 0.95
    assert fast.iterations[both].mean() < 0.7 * plain.iterations[both].mean()


def test_t_never_exceeds_sqrt_redundancy():
    rng = np.random.default_rng(5)
    patches = random_patches(rng, 50, 20, "curved")
    patches[:, 0, 2] += rng.uniform(0.05, 5.0, 50)  # gross outliers of all sizes
    fit = fit_quadrics(patches, 0.005)
    t = fit.t_stat[fit.converged]
    assert np.nanmax(t) <= np.sqrt(20 - DOF_LOSS) + 1e-9
    assert np.nanmax(t) > 2.0  # the outliers do stand out as far as the bound allows


def _surface_points(kind, rng, n, noise):
    """Points of a known quadric x^T A x + b.x + c = 0 plus Gaussian noise along its normal."""
    if kind == "sphere":  # radius 2 centred at (0.3, -0.2, 2.1): a cap near the origin
        centre = np.array([0.3, -0.2, 2.1])
        theta = rng.uniform(0, 0.9, n)
        phi = rng.uniform(0, 2 * np.pi, n)
        d = np.c_[np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)]
        pts = centre + 2.0 * d
        normal = d
        A, b, c = np.eye(3), -2 * centre, centre @ centre - 4.0
    elif kind == "cylinder":  # axis along y, radius 0.5
        ang = rng.uniform(-1.3, 1.3, n)
        y = rng.uniform(-0.3, 0.3, n)
        normal = np.c_[np.sin(ang), np.zeros(n), np.cos(ang)]
        pts = np.c_[0.5 * np.sin(ang), y, 0.5 * np.cos(ang)]
        A, b, c = np.diag([1.0, 0.0, 1.0]), np.zeros(3), -0.25
    elif kind == "paraboloid":  # z = x^2 + 0.5 y^2
        x, y = rng.uniform(-0.4, 0.4, (2, n))
        pts = np.c_[x, y, x**2 + 0.5 * y**2]
        normal = np.c_[2 * x, y, -np.ones(n)]
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        A, b, c = np.diag([1.0, 0.5, 0.0]), np.array([0.0, 0.0, -1.0]), 0.0
    else:
        raise ValueError(kind)
    pts = pts + normal * rng.normal(0, noise, (n, 1))
    return pts, (A, b, c)


@pytest.mark.parametrize("kind", ["sphere", "cylinder", "paraboloid"])
def test_known_surfaces_are_recovered(kind):
    rng = np.random.default_rng(21)
    noise = 1e-4
    pts, (A, b, c) = _surface_points(kind, rng, 200, noise)
    fit = fit_quadrics(pts[None], noise, max_iter=200, tol=1e-12)
    assert fit.converged[0]
    expected = quadric_vector(A, b, c, fit.centroid[0])
    sign = np.sign(fit.params[0] @ expected)  # eq. 19 fixes the scale, not the sign
    np.testing.assert_allclose(sign * fit.params[0], expected, atol=5e-3)
    # sigma_0 ~ 1: the residuals are the size of the noise that was put in.
    assert 0.75 < fit.sigma0[0] < 1.25
    assert np.nanmax(fit.t_stat[0]) < 4.5


def test_plane_is_recovered_as_its_zero_set():
    # A plane has no unique general quadric (any second plane times it fits as well); what must
    # hold is that the fitted surface passes through the points with the plane's normal.
    rng = np.random.default_rng(4)
    noise = 0.002
    normal = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    uv = rng.uniform(-0.5, 0.5, (300, 2))
    e1 = np.cross(normal, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    pts = uv[:, :1] * e1 + uv[:, 1:] * e2 + normal * rng.normal(0, noise, (300, 1))
    fit = fit_quadrics(pts[None], noise, max_iter=500, tol=1e-10)
    a = fit.params[0]
    local = pts - fit.centroid[0]
    F = ref_design_matrix(local) @ a
    g = ref_gradient(a, local)
    gn = np.linalg.norm(g, axis=1)
    distance = np.abs(F) / gn  # first-order distance to the zero set
    assert np.sqrt(np.mean(distance**2)) < 1.5 * noise
    cosines = np.abs(g @ normal) / gn
    assert np.median(cosines) > 0.999


def test_fit_masked_equals_fit_of_the_subset():
    rng = np.random.default_rng(9)
    pts = random_patches(rng, 1, 80, "curved")[0]
    active = rng.random(80) < 0.6
    params = np.empty(10)
    centroid = np.empty(3)
    v = np.full(80, np.nan)
    t = np.full(80, np.nan)
    var = np.full(3, 0.005**2)
    s0, it, status = fit_masked(pts, active, var, 100, 1e-10, params, centroid, v, t, False)
    ok = status == CONVERGED
    a, v_ref, T_ref, s0_ref, it_ref, ok_ref = slow_fit(pts[active], 0.005, 100, 1e-10)
    assert (it, ok) == (it_ref, ok_ref)
    np.testing.assert_allclose(t[active], T_ref, rtol=1e-9)
    assert np.isnan(t[~active]).all()
    assert s0 == pytest.approx(s0_ref, rel=1e-9)


def test_moved_frame_is_the_same_surface():
    rng = np.random.default_rng(21)
    a = rng.normal(size=10)
    d = rng.normal(size=3) * 5.0
    out = np.empty(10)
    moved_frame(a, d, out)
    x = rng.normal(size=(50, 3)) * 3.0
    before = ref_design_matrix(x) @ a  # F_a at x
    after = ref_design_matrix(x - d) @ out  # F_out at the same points in the moved frame
    scale = (before @ after) / (after @ after)  # out is scaled to unit norm
    np.testing.assert_allclose(after * scale, before, rtol=1e-9, atol=1e-9)
    assert np.linalg.norm(out) == pytest.approx(1.0)


def test_fit_masked_from_an_earlier_fit_in_another_frame_converges_at_once():
    rng = np.random.default_rng(22)
    pts = random_patches(rng, 1, 200, "curved")[0]
    var = np.full(3, 0.005**2)
    every = np.ones(200, dtype=bool)
    first, c_first = np.empty(10), np.empty(3)
    v, t = np.full(200, np.nan), np.full(200, np.nan)
    _, it_first, status = fit_masked(pts, every, var, 500, 1e-10, first, c_first, v, t)
    assert status == CONVERGED
    fewer = every.copy()
    fewer[:20] = False  # a refit without some points: another centroid
    algebraic, warm = np.empty(10), np.empty(10)
    c_alg, c_warm = np.empty(3), np.empty(3)
    _, _, st_alg = fit_masked(pts, fewer, var, 500, 1e-10, algebraic, c_alg, v, t)
    _, it_warm, st_warm = fit_masked(pts, fewer, var, 500, 1e-10, warm, c_warm, v, t, True,
                                     first, c_first)
    assert st_alg == st_warm == CONVERGED
    np.testing.assert_array_equal(c_alg, c_warm)
    np.testing.assert_allclose(warm, algebraic, atol=1e-7)  # the same fixed point
    assert it_warm <= it_first


@pytest.mark.parametrize("n", [1, 40, 256, 257, 1000])
def test_weighted_moments_match_a_plain_sum(n):
    # The blocked, vectorised sums against sum_i w_i x^ex y^ey z^ez written out per monomial.
    rng = np.random.default_rng(n)
    xyz = rng.normal(0.0, 2.0, (n, 3))
    weight = rng.random(n) * (rng.random(n) < 0.8)  # some rows weigh nothing (inactive)
    out = np.empty(35)
    weighted_moments(xyz, weight, 35, out)
    exponents = [(i, j, d - i - j) for d in range(5) for i in range(d, -1, -1)
                 for j in range(d - i, -1, -1)]  # fmt: skip
    x, y, z = xyz.T
    expected = [np.sum(weight * x**ex * y**ey * z**ez) for ex, ey, ez in exponents]
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    first10 = np.full(35, np.nan)
    weighted_moments(xyz, weight, 10, first10)
    np.testing.assert_allclose(first10[:10], out[:10], rtol=1e-12, atol=1e-12)



def test_block_weights_equal_the_equations_point_by_point():
    # The vectorised w_i (eq. 24) and p_i (eq. 30) bit for bit against the same expressions
    # evaluated one point at a time; inactive rows weigh nothing and do not fail the block.
    from algorithms.quadric import _block_monomials, _block_weights, equivalent_variance, gradient

    rng = np.random.default_rng(3)
    n = 40
    xyz = rng.normal(0.0, 0.3, (n, 3))
    active = rng.random(n) < 0.8
    a = rng.normal(size=10)
    var = np.array([0.004, 0.006, 0.005]) ** 2
    mono = np.empty((35, n))
    _block_monomials(xyz, 0, n, mono)
    w, p_w, p_b, pw_b = (np.full(n, np.nan) for _ in range(4))
    assert _block_weights(mono, n, active, var, a, w, p_w, p_b, pw_b)
    for i in range(n):
        x, y, z = xyz[i]
        wi = (a[0] * (x * x) + a[1] * (y * y) + a[2] * (z * z) + a[3] * x * y + a[4] * x * z
              + a[5] * y * z + a[6] * x + a[7] * y + a[8] * z + a[9])  # fmt: skip
        ax, ay, az = gradient(a, x, y, z)
        pi = 1.0 / equivalent_variance(ax, ay, az, var[0], var[1], var[2])
        assert w[i] == wi and p_w[i] == pi
        assert p_b[i] == (pi if active[i] else 0.0)
        assert pw_b[i] == (pi * wi if active[i] else 0.0)
    flat = np.zeros(10)
    flat[9] = 1.0  # F = 1 everywhere: zero gradient, sigma_i^2 = 0
    assert not _block_weights(mono, n, active, var, flat, w, p_w, p_b, pw_b)
    assert _block_weights(mono, n, np.zeros(n, dtype=bool), var, flat, w, p_w, p_b, pw_b)

def test_fit_masked_on_a_section_of_several_blocks_matches_slow_reference():
    # Sections are fitted block by block (256 points); 1,000 points with holes span four blocks.
    rng = np.random.default_rng(21)
    pts = random_patches(rng, 1, 1000, "curved", radius=2.0)[0]
    pts[17, 2] += 0.5
    active = rng.random(1000) < 0.9
    params, centroid = np.empty(10), np.empty(3)
    v, t = np.full(1000, np.nan), np.full(1000, np.nan)
    var = np.full(3, 0.005**2)
    s0, it, status = fit_masked(pts, active, var, 100, 1e-10, params, centroid, v, t, False)
    ok = status == CONVERGED
    a, v_ref, T_ref, s0_ref, it_ref, ok_ref = slow_fit(pts[active], 0.005, 100, 1e-10)
    assert (it, ok) == (it_ref, ok_ref) and ok
    np.testing.assert_allclose(t[active], T_ref, rtol=1e-9)
    assert s0 == pytest.approx(s0_ref, rel=1e-9)


def test_shift_by_5e6_changes_nothing():
    rng = np.random.default_rng(2)
    patches = random_patches(rng, 20, 40, "curved")
    shifted = patches + np.array([5e6, 5e6, 1e3])
    a = fit_quadrics(patches, 0.005, max_iter=1000, tol=1e-9)
    b = fit_quadrics(shifted, 0.005, max_iter=1000, tol=1e-9)
    ok = a.converged & b.converged
    # Strongly curved 0.6 m patches: some never converge (the plain iteration settles in a
    # 2-cycle); they are reported as such in both frames.
    assert ok.sum() >= 12
    assert (a.converged == b.converged).mean() >= 0.9
    np.testing.assert_allclose(b.t_stat[ok], a.t_stat[ok], rtol=1e-5, atol=1e-6)


def test_min_patch_size_is_where_sqrt_dof_exceeds_t():
    for alpha in (0.05, 0.01, 0.001, 1e-5):
        n = min_patch_size(alpha)
        crit = stats.t.isf(alpha / 2, np.arange(1, 400))
        first = 1 + int(np.argmax(np.sqrt(np.arange(1, 400)) > crit))
        assert n == first + DOF_LOSS
        assert can_flag(n, alpha) and not can_flag(n - 1, alpha)
    assert min_patch_size(0.001) == 26


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="shape"):
        fit_quadrics(np.zeros((3, 10)))
    with pytest.raises(ValueError, match="at least 10"):
        fit_quadrics(np.zeros((2, 9, 3)))
    with pytest.raises(ValueError, match="sigma"):
        fit_quadrics(np.zeros((2, 12, 3)), sigma=0.0)


def test_degenerate_patch_is_not_converged_not_a_crash():
    pts = np.zeros((1, 12, 3))  # every point identical: no surface
    fit = fit_quadrics(pts, 0.005)
    assert not fit.converged[0]


def test_nearly_collinear_points_stop_at_once():
    # A scan line repeated by a scanner standing still: every quadric through the line fits.
    rng = np.random.default_rng(12)
    t = rng.uniform(-0.2, 0.2, (2, 40))
    line = np.stack([t, 0.3 * t, 0.1 * t], axis=2) + rng.normal(0, 1e-5, (2, 40, 3))
    line[1, :, 1] += rng.normal(0, 0.01, 40)  # the second is a thin strip, 5 % wide: fitted
    fit = fit_quadrics(line, 0.005)
    assert not fit.converged[0] and fit.iterations[0] == 0 and np.isnan(fit.t_stat[0]).all()
    assert fit.iterations[1] > 0


def test_degenerate_patches_are_untested_not_flagged():
    """Regression: 40-point patches of simulated cloud A (vehicle standing still, one scan line
    repeated) once gave T_i up to 5e8, beyond the bound sqrt(n - 9) that holds in exact
    arithmetic; cancellation in q_vv = 1/p_i - B_i Q_aa B_i^T must leave them untested."""
    patches = np.load(Path(__file__).parent.parent / "data" / "quadric" / "degenerate_patches.npy")
    fit = fit_quadrics(patches, 0.005)
    t = fit.t_stat
    bound = np.sqrt(patches.shape[1] - DOF_LOSS) * (1 + 1e-6)  # rounding slack of t_statistic
    assert np.all(np.isnan(t) | (t <= bound))
    assert np.isnan(t[:, 0]).any()  # the originally flagged points are now untested


def test_neighbour_indices_give_the_same_fit_as_gathered_patches():
    # The patch detector passes the cloud and k-nearest-neighbour rows instead of a copy.
    rng = np.random.default_rng(12)
    cloud = random_patches(rng, 1, 600, "curved", radius=1.0)[0]
    nbr = np.argsort(np.linalg.norm(cloud[:50, None, :2] - cloud[None, :, :2], axis=2), axis=1)
    nbr = nbr[:, :40]
    gathered = fit_quadrics(cloud[nbr], 0.005, max_iter=60, tol=1e-9, t_first_only=True)
    indexed = fit_quadrics(cloud, 0.005, neighbours=nbr, max_iter=60, tol=1e-9, t_first_only=True)
    np.testing.assert_array_equal(indexed.t_stat[:, 0], gathered.t_stat[:, 0])
    np.testing.assert_array_equal(indexed.iterations, gathered.iterations)
    np.testing.assert_array_equal(indexed.centroid, gathered.centroid)


@pytest.mark.parametrize(("m", "parts"), [(0, 2), (1, 2), (7, 2), (10, 4), (5, 8), (9, 1)])
def test_interleaved_order_is_a_permutation(m, parts):
    order = interleaved_order(m, parts)
    assert sorted(order.tolist()) == list(range(m))
    if m > parts:
        assert order[:2].tolist() == [0, parts]  # the first thread's part takes every parts-th
