"""Least-squares fit of the general quadric surface, eqs. 18-31 of Leslar, Wang & Hu (2010).

The model is the implicit quadric of eq. 18,

    F(a, x, y, z) = a1 x^2 + a2 y^2 + a3 z^2 + a4 xy + a5 xz + a6 yz + a7 x + a8 y + a9 z + a10 = 0,

under the constraint of eq. 19, ||a|| = 1. Every point gives one *equivalent single measurement*
(eqs. 28-29): its residual v_i = B_i da + w_i, with B_i the design row of eq. 23, w_i = F(a0, x_i)
(eq. 24), and variance sigma_i^2 = g_i^T D_ii g_i (eq. 30), g_i the gradient of F (eqs. 25-27).
Together with the linearised constraint this is a parametric adjustment with a constraint; each
iteration solves the Lagrange-bordered normal equations

    [ N     a0 ] [ da ]   [ -u              ]
    [ a0^T  0  ] [ k  ] = [ (1 - a0.a0) / 2 ],   N = B^T P B,  u = B^T P w,  P = diag(1/sigma_i^2),

i.e. eq. 19 is linearised as 2 a0.da = 1 - a0.a0 and the parameters are *not* renormalised between
iterations (the linearised constraint pulls ||a|| back to 1 by itself; at convergence ||a|| = 1 to
the tolerance).

Choices that fix what the paper leaves open (the fitted surface depends on the frame because of
eq. 19):

* every surface is fitted in the frame of its own centroid (coordinates minus the mean of the
  points used, no scaling), so coordinates near 5e6 m lose nothing;
* the start is the algebraic fit: the unit eigenvector of the smallest eigenvalue of B^T B;
* the linearisation is at the observed coordinates (eqs. 24-27), as in the paper;
* iteration stops when ||da|| < tol; if it has not after a stage's share of ``max_iter``, it
  restarts from the algebraic start with another path (Anderson-accelerated, plain, damped by 0.5,
  damped by 0.25; see the iteration section below), and after ``max_iter`` adjustments in all the
  fit reports ``status`` NOT_CONVERGED;
* the reported residuals, sigma_0 and T_i are those of the last adjustment solved:
  sigma_0^2 = v^T P v / (n - 9) and T_i = |v_i| / (sigma_0 sqrt(q_vv_i)) (eq. 31) with
  Q_vv = P^-1 - B Q_aa B^T, Q_aa the 10 x 10 block of the inverse bordered matrix.

Facts of this model that matter to its users:

* T_i <= sqrt(n - 9) always (a studentised residual with the internal sigma_0 cannot exceed the
  square root of the redundancy), so a patch of k points can only flag anything when sqrt(k - 9)
  exceeds the critical value of t(k - 9) (:func:`algorithms.fit_outcome.min_patch_size`; 26
  points at alpha = 0.001).
* On flat ground the z^2 column of B is tiny, the algebraic start is already a pair of nearly
  coincident planes (a3 ~ 1) and the iteration converges linearly and slowly (contraction ~0.6 per
  step) towards a double plane; the noise is shared between the two sheets, so sigma_0 comes out
  near 0.5 for a correct sigma. T_i is self-normalised and unaffected in scale.
* The plain iteration a <- a + da does not always converge: some patches settle in a 2-cycle
  (an eigenvalue of the iteration's Jacobian near -1) or crawl along a flat valley with a step
  near 1e-6 .. 1e-3 for hundreds of iterations (a seventh of the k = 40 patches of a smooth but
  strongly curved surface stopped at 100 plain iterations). Damping, a <- a + s da with s = 0.5
  or 0.25, has the same fixed points and turns the 2-cycle into a contraction; Anderson
  acceleration takes most patches there in about ten adjustments. Which fixed point is reached
  can depend on the path when a patch has several (rare: about 1 % of random curved patches).
* Fits that cannot give a T_i say why (``status``): too few points, nearly collinear points, a
  singular system, or no convergence within ``max_iter``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from algorithms.fit_outcome import (
    COLLINEAR,
    CONVERGED,
    DOF_LOSS,
    N_PARAMS,
    NOT_CONVERGED,
    SINGULAR,
    TOO_FEW_POINTS,
)
from algorithms.jit import njit, prange

#: Relative rounding allowed above the bound T_i <= sqrt(n - 9) before a T_i is distrusted.
_T_BOUND_SLACK = 1e-6
#: sigma_0 (the a-posteriori standard deviation of unit weight, eq. 30's weights) at or below
#: which a fit holds its points exactly: a quadric through every point to within a millionth
#: of their stated noise (points on two coordinate-rounding levels 1 mm apart make a pair of
#: planes, which eq. 18 includes, with sigma_0 ~ 1e-18; a vehicle standing still gives such
#: patches by the thousand). Eq. 31 would divide rounding noise by rounding noise; such a fit
#: tests its points with the a-priori variance factor instead (:func:`t_statistic`).
EXACT_FIT_SIGMA0 = 1e-6


@dataclass
class QuadricFit:
    """Result of :func:`fit_quadrics` for m surfaces of k points each.

    Attributes
    ----------
    params : (m, 10) float64
        a1..a10 of eq. 18 in each surface's centroid frame, ||a|| = 1 (eq. 19), sign chosen so
        that the component of largest magnitude is positive.
    centroid : (m, 3) float64
        The frame origin of each surface (mean of its points).
    residuals : (m, k) float64
        v_i of eq. 29 (the equivalent single measurement residual, units of F), signed for the
        reported params.
    t_stat : (m, k) float64
        T_i of eq. 31.
    sigma0 : (m,) float64
        Posterior standard deviation of unit weight.
    iterations : (m,) int64
        Adjustments solved.
    converged : (m,) bool
        ||da|| < tol reached within max_iter (``status == CONVERGED``).
    status : (m,) int64
        CONVERGED, NOT_CONVERGED (max_iter reached), COLLINEAR (nearly collinear points; 0
        iterations), SINGULAR (the normal equations could not be solved) or TOO_FEW_POINTS.
    """

    params: np.ndarray
    centroid: np.ndarray
    residuals: np.ndarray
    t_stat: np.ndarray
    sigma0: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    status: np.ndarray


# ---------------------------------------------------------------------------------------------
# The equations, one point at a time (inlined by numba).
# ---------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def design_row(x: float, y: float, z: float, out: np.ndarray) -> None:
    """B_i of eq. 23 written into ``out`` (10,)."""
    out[0] = x * x
    out[1] = y * y
    out[2] = z * z
    out[3] = x * y
    out[4] = x * z
    out[5] = y * z
    out[6] = x
    out[7] = y
    out[8] = z
    out[9] = 1.0


@njit(cache=True, inline="always")
def gradient(a: np.ndarray, x: float, y: float, z: float) -> tuple[float, float, float]:
    """(a_x, a_y, a_z) of eqs. 25-27: the gradient of F at the observed point for parameters a."""
    ax = 2.0 * a[0] * x + a[3] * y + a[4] * z + a[6]
    ay = 2.0 * a[1] * y + a[3] * x + a[5] * z + a[7]
    az = 2.0 * a[2] * z + a[4] * x + a[5] * y + a[8]
    return ax, ay, az


@njit(cache=True, inline="always")
def equivalent_variance(
    ax: float, ay: float, az: float, var_x: float, var_y: float, var_z: float
) -> float:
    """sigma_i^2 of eq. 30 for a diagonal D_ii = diag(var_x, var_y, var_z)."""
    return ax * ax * var_x + ay * ay * var_y + az * az * var_z


@njit(cache=True, inline="always")
def t_statistic(v: float, sigma0: float, q_vv: float, redundancy: int) -> float:
    """T_i of eq. 31: |v_i| / (sigma_0 sqrt(q_vv_i)); NaN when it cannot be trusted.

    A fit through every point (sigma_0 at or below EXACT_FIT_SIGMA0) normalises the residual
    with the a-priori variance factor 1 instead of sigma_0 (Baarda's w_i = |v_i| / sqrt(q_vv_i),
    the weights of eq. 30 from the declared sigma): it is as small as the points' agreement, so
    the point is tested and passes, where eq. 31 would be rounding noise over rounding noise.

    In exact arithmetic v_i^2 / q_vv_i never exceeds v^T P v = sigma_0^2 redundancy, so T_i <=
    sqrt(redundancy) and w_i <= sigma_0 sqrt(redundancy). A larger value, or q_vv not positive,
    means q_vv = 1/p_i - B_i Q_aa B_i^T was lost to cancellation (a nearly degenerate patch):
    the point is left untested instead of flagged.
    """
    if q_vv <= 0.0 or not sigma0 >= 0.0:
        return math.nan
    exact = not sigma0 > EXACT_FIT_SIGMA0
    t = abs(v) / ((1.0 if exact else sigma0) * math.sqrt(q_vv))
    if t > math.sqrt(redundancy) * (EXACT_FIT_SIGMA0 if exact else 1.0) * (1.0 + _T_BOUND_SLACK):
        return math.nan
    return t


# ---------------------------------------------------------------------------------------------
# Normal equations from weighted moments: N[p, q] = sum_i p_i B_ip B_iq, and every product of two
# entries of eq. 23 is one of the 35 monomials x^i y^j z^l with i + j + l <= 4. The monomials of a
# block of points are formed once per fit (each is a lower one times x, y or z), and every
# adjustment sums them with its weights (loops the compiler vectorises): 35 multiply-adds per
# point instead of the 55 distinct entries of N. At most _BLOCK x 35 numbers are held.
# ---------------------------------------------------------------------------------------------

#: Exponents (x, y, z) of the 10 entries of B_i (eq. 23), in parameter order a1..a10.
_ROW_EXPONENTS = np.array(
    [[2, 0, 0], [0, 2, 0], [0, 0, 2], [1, 1, 0], [1, 0, 1], [0, 1, 1],
     [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]], dtype=np.int64,
)  # fmt: skip
#: Exponents of the 35 monomials of degree <= 4.
_MONOMIALS = np.array(
    [[i, j, d - i - j] for d in range(5) for i in range(d, -1, -1) for j in range(d - i, -1, -1)],
    dtype=np.int64,
)
_N_MONO = _MONOMIALS.shape[0]
#: N_INDEX[p, q]: which monomial is B_ip * B_iq.
_N_INDEX = np.array(
    [
        [
            int(np.flatnonzero((_MONOMIALS == _ROW_EXPONENTS[p] + _ROW_EXPONENTS[q]).all(1))[0])
            for q in range(N_PARAMS)
        ]
        for p in range(N_PARAMS)
    ],
    dtype=np.int64,
)


#: Each monomial of degree >= 1 as a lower monomial times one coordinate: _PARENT[j] is the
#: row of the lower one, _FACTOR[j] the row of x, y or z (monomials 1, 2, 3).
_PARENT = np.zeros(_N_MONO, dtype=np.int64)
_FACTOR = np.zeros(_N_MONO, dtype=np.int64)
for _j in range(1, _N_MONO):
    _axis = int(np.flatnonzero(_MONOMIALS[_j])[0])  # lower the first exponent that is not 0
    _lower = _MONOMIALS[_j].copy()
    _lower[_axis] -= 1
    _PARENT[_j] = int(np.flatnonzero((_MONOMIALS == _lower).all(1))[0])
    _FACTOR[_j] = 1 + _axis
del _j, _axis, _lower
#: Rows of x, y, z, x^2, y^2, z^2 among the monomials (what eqs. 24-27 read).
_X, _Y, _Z = 1, 2, 3
_XX, _YY, _ZZ = (int(np.flatnonzero((_MONOMIALS == e).all(1))[0])
                 for e in ([2, 0, 0], [0, 2, 0], [0, 0, 2]))  # fmt: skip

#: Points per block of the moment sums: the block's monomials (35 x 256 floats, 70 kB) are
#: formed once and summed by every adjustment.
_BLOCK = 256


@njit(cache=True)
def _block_monomials(xyz: np.ndarray, start: int, nb: int, mono: np.ndarray) -> None:
    """mono[j, i] = monomial j of point start + i (x^ex_j y^ey_j z^ez_j), for the nb points of
    one block; each row is a lower row times x, y or z, so every loop is contiguous."""
    for i in range(nb):
        mono[0, i] = 1.0
        mono[_X, i] = xyz[start + i, 0]
        mono[_Y, i] = xyz[start + i, 1]
        mono[_Z, i] = xyz[start + i, 2]
    for j in range(_Z + 1, _N_MONO):
        lower = mono[_PARENT[j]]
        factor = mono[_FACTOR[j]]
        row = mono[j]
        for i in range(nb):
            row[i] = lower[i] * factor[i]


@njit(cache=True, fastmath={"reassoc", "contract"})
def _block_moments(
    mono: np.ndarray, weight: np.ndarray, nb: int, count: int, out: np.ndarray
) -> None:
    """out[j] += sum_i weight[i] * mono[j, i], over the nb points of one block.

    ``reassoc`` lets the compiler split each sum into vector lanes (the order of the additions
    is the only difference from a plain loop).
    """
    for j in range(count):
        row = mono[j]
        acc = 0.0
        for i in range(nb):
            acc += weight[i] * row[i]
        out[j] += acc


@njit(cache=True)
def weighted_moments(xyz: np.ndarray, weight: np.ndarray, count: int, out: np.ndarray) -> None:
    """out[j] = sum_i weight_i x_i^ex_j y_i^ey_j z_i^ez_j for the first ``count`` monomials.

    The monomials are ordered by degree, so ``count`` 35 gives the entries of N = B^T P B and
    ``count`` 10 those of B^T u (the entries of eq. 23). Rows with weight 0 add nothing. The
    monomials are formed per block of points; only the order of the additions differs from a
    plain loop over the points.
    """
    mono = np.empty((_N_MONO, _BLOCK))
    out[:count] = 0.0
    for start in range(0, xyz.shape[0], _BLOCK):
        nb = min(_BLOCK, xyz.shape[0] - start)
        _block_monomials(xyz, start, nb, mono)
        _block_moments(mono, weight[start:start + nb], nb, count, out)


# ---------------------------------------------------------------------------------------------
# Small dense linear algebra without LAPACK calls (a call per patch would dominate the cost).
# ---------------------------------------------------------------------------------------------


@njit(cache=True)
def _solve(m: np.ndarray, r: np.ndarray) -> bool:
    """Solve m x = r in place (r (s, c) becomes x): Gaussian elimination, partial pivoting.

    m is destroyed. Returns False when a pivot is exactly zero or not finite (singular system).
    """
    return _eliminate(m, r, m.shape[0], r.shape[1])


@njit(cache=True)
def _solve_bordered(m: np.ndarray, r: np.ndarray) -> bool:
    """:func:`_solve` for the (11, 11) bordered normal equations and one right-hand side r
    (11, 1): the same operations, with sizes the compiler knows (the loops unroll; a third of
    an adjustment's time otherwise)."""
    return _eliminate(m, r, N_PARAMS + 1, 1)


@njit(cache=True, inline="always")
def _eliminate(m: np.ndarray, r: np.ndarray, s: int, c: int) -> bool:
    """Gaussian elimination with partial pivoting of the leading s x s of m against the c
    columns of r, in place (r becomes the solution); False on a pivot zero or not finite."""
    for col in range(s):
        piv = col
        best = abs(m[col, col])
        for i in range(col + 1, s):
            if abs(m[i, col]) > best:
                best = abs(m[i, col])
                piv = i
        if not (best > 0.0 and best < math.inf):
            return False
        if piv != col:
            for j in range(col, s):
                m[col, j], m[piv, j] = m[piv, j], m[col, j]
            for j in range(c):
                r[col, j], r[piv, j] = r[piv, j], r[col, j]
        inv = 1.0 / m[col, col]
        for i in range(col + 1, s):
            f = m[i, col] * inv
            if f == 0.0:
                continue
            for j in range(col + 1, s):
                m[i, j] -= f * m[col, j]
            for j in range(c):
                r[i, j] -= f * r[col, j]
    for i in range(s - 1, -1, -1):
        inv = 1.0 / m[i, i]
        for j in range(c):
            acc = r[i, j]
            for q in range(i + 1, s):
                acc -= m[i, q] * r[q, j]
            r[i, j] = acc * inv
    return True


@njit(cache=True)
def _lu_factor(m: np.ndarray, piv: np.ndarray) -> bool:
    """In-place LU factorisation with partial pivoting of the 10 x 10 m; row swaps into piv.

    The size is the constant N_PARAMS so that the compiler unrolls the short loops (a quarter
    of the algebraic start's time)."""
    s = N_PARAMS
    for col in range(s):
        p = col
        best = abs(m[col, col])
        for i in range(col + 1, s):
            if abs(m[i, col]) > best:
                best = abs(m[i, col])
                p = i
        piv[col] = p
        if not (best > 0.0 and best < math.inf):
            return False
        if p != col:
            for j in range(s):
                m[col, j], m[p, j] = m[p, j], m[col, j]
        inv = 1.0 / m[col, col]
        for i in range(col + 1, s):
            m[i, col] *= inv
            f = m[i, col]
            if f != 0.0:
                for j in range(col + 1, s):
                    m[i, j] -= f * m[col, j]
    return True


@njit(cache=True)
def _lu_solve(lu: np.ndarray, piv: np.ndarray, x: np.ndarray) -> None:
    """Solve with the factors of :func:`_lu_factor`; x (10,) is the right-hand side, overwritten."""
    s = N_PARAMS
    for i in range(s):
        p = piv[i]
        if p != i:
            x[i], x[p] = x[p], x[i]
    for i in range(s):
        acc = x[i]
        for j in range(i):
            acc -= lu[i, j] * x[j]
        x[i] = acc
    for i in range(s - 1, -1, -1):
        acc = x[i]
        for j in range(i + 1, s):
            acc -= lu[i, j] * x[j]
        x[i] = acc / lu[i, i]


@njit(cache=True)
def _algebraic_start(moments: np.ndarray, out: np.ndarray) -> None:
    """Unit eigenvector of the smallest eigenvalue of B^T B (active rows), into ``out`` (10,),
    from the 35 unweighted monomial sums of the active rows (:func:`weighted_moments`).

    Inverse iteration with one LU factorisation (no LAPACK call per patch): the smallest
    eigenvalue of B^T B is the algebraic fit's residual and lies well below the next one
    (typically by a factor 10 on the k = 40 patches of a mobile cloud), so about ten solves
    reach START_TOL. Where the two smallest eigenvalues are close (flat patches: every plane
    pair through the plane fits) the eigenvector is ill-determined anyway and the vector after
    INVERSE_ITERATIONS solves is the start: the adjustment's own iteration (an inverse
    iteration with the weighted N) goes on from there. np.linalg.eigh is the fallback only when
    B^T B cannot be factorised.
    """
    btb = np.empty((N_PARAMS, N_PARAMS))
    trace = 0.0
    for p in range(N_PARAMS):
        for q in range(N_PARAMS):
            btb[p, q] = moments[_N_INDEX[p, q]]
        trace += btb[p, p]
    lu = btb.copy()
    for p in range(N_PARAMS):
        lu[p, p] += 1e-15 * trace  # keeps an exactly singular B^T B (noise-free data) solvable
    piv = np.empty(N_PARAMS, dtype=np.int64)
    x = np.empty(N_PARAMS)
    for p in range(N_PARAMS):
        out[p] = 1.0 / (1.0 + p)  # generic start, not orthogonal to any eigenvector in practice
    norm = 0.0
    if _lu_factor(lu, piv):
        for _ in range(INVERSE_ITERATIONS):
            x[:] = out
            _lu_solve(lu, piv, x)
            norm = 0.0
            dot = 0.0
            for p in range(N_PARAMS):
                norm += x[p] * x[p]
                dot += x[p] * out[p]
            norm = math.sqrt(norm)
            if not (norm > 0.0 and norm < math.inf):
                break
            sign = 1.0 if dot >= 0.0 else -1.0
            change = 0.0
            for p in range(N_PARAMS):
                new = sign * x[p] / norm
                change = max(change, abs(new - out[p]))
                out[p] = new
            if change < START_TOL:
                return
        if norm > 0.0 and norm < math.inf:
            return
    _, vecs = np.linalg.eigh(btb)
    for p in range(N_PARAMS):
        out[p] = vecs[p, 0]


#: Inverse iterations for the algebraic start at most, and the change of the unit vector (largest
#: component) at which it stops.
INVERSE_ITERATIONS = 40
START_TOL = 1e-12


# ---------------------------------------------------------------------------------------------
# One surface: the iterative adjustment.
# ---------------------------------------------------------------------------------------------


@njit(cache=True)
def _adjust(
    xyz: np.ndarray,
    active: np.ndarray,
    var: np.ndarray,
    a: np.ndarray,
    m: np.ndarray,
    rhs: np.ndarray,
    w: np.ndarray,
    p_w: np.ndarray,
    mono: np.ndarray,
    block_w: np.ndarray,
    acc: np.ndarray,
) -> bool:
    """One adjustment linearised at ``a`` (10,): da into rhs[:10, 0]; False if it cannot be solved.

    Leaves the 35 monomial sums of N in acc[:35] (:func:`_bordered_matrix` rebuilds the bordered
    matrix from them and ``a``) and w_i (eq. 24), p_i = 1/sigma_i^2 (eq. 30) of the active rows
    in ``w`` and ``p_w``, for the residuals and cofactors of the last adjustment.
    N = B^T P B and u = B^T P w are summed block by block from the points' monomials
    (:func:`_block_moments`). Scratch: ``m`` (11, 11); ``mono`` (35, min(n, _BLOCK)), which
    holds the monomials of all points already when n <= _BLOCK (the caller forms them once per
    fit), ``block_w`` (2, _BLOCK) and ``acc`` (45,).
    """
    acc[:] = 0.0
    n_mono, u = acc[:_N_MONO], acc[_N_MONO:]
    p_b, pw_b = block_w[0], block_w[1]
    for start in range(0, xyz.shape[0], _BLOCK):
        nb = min(_BLOCK, xyz.shape[0] - start)
        if xyz.shape[0] > _BLOCK:
            _block_monomials(xyz, start, nb, mono)
        if not _block_weights(
            mono, nb, active[start:], var, a, w[start:], p_w[start:], p_b, pw_b
        ):
            return False
        _block_moments(mono, p_b, nb, _N_MONO, n_mono)  # N as 35 weighted monomial sums
        _block_moments(mono, pw_b, nb, N_PARAMS, u)  # B^T P w: eq. 23's entries are the first 10
    _bordered_matrix(n_mono, a, m)
    aa = 0.0
    for p in range(N_PARAMS):
        rhs[p, 0] = -u[_N_INDEX[p, 9]]
        aa += a[p] * a[p]
    rhs[N_PARAMS, 0] = 0.5 * (1.0 - aa)  # eq. 19 linearised: 2 a0.da = 1 - a0.a0
    return _solve_bordered(m, rhs)


@njit(cache=True)
def _bordered_matrix(n_mono: np.ndarray, a: np.ndarray, m: np.ndarray) -> None:
    """The bordered matrix [N a; a^T 0] (11, 11) into ``m``, from the 35 monomial sums of N and
    the parameters a (10,) the adjustment is linearised at."""
    for p in range(N_PARAMS):
        for q in range(N_PARAMS):
            m[p, q] = n_mono[_N_INDEX[p, q]]
        m[p, N_PARAMS] = a[p]
        m[N_PARAMS, p] = a[p]
    m[N_PARAMS, N_PARAMS] = 0.0


@njit(cache=True, error_model="numpy")  # 1/0 of an inactive row: inf, unused, not an exception
def _block_weights(
    mono: np.ndarray,
    nb: int,
    active: np.ndarray,
    var: np.ndarray,
    a: np.ndarray,
    w: np.ndarray,
    p_w: np.ndarray,
    p_b: np.ndarray,
    pw_b: np.ndarray,
) -> bool:
    """w_i = F(a, x_i) (eq. 24) and p_i = 1/sigma_i^2 (eqs. 25-27, 30) of the nb points of one
    block into ``w`` and ``p_w``, and the weights of N and u into ``p_b`` (p_i) and ``pw_b``
    (p_i w_i), 0 for inactive rows; False if an active row's sigma_i^2 is zero or not finite.

    Written as loops without branches over a's entries read once, so that the compiler
    vectorises them; each number is the same expression, evaluated in the same order, as for
    one point at a time (:func:`gradient`, :func:`equivalent_variance`).
    """
    a0, a1, a2, a3, a4 = a[0], a[1], a[2], a[3], a[4]
    a5, a6, a7, a8, a9 = a[5], a[6], a[7], a[8], a[9]
    vx, vy, vz = var[0], var[1], var[2]
    x, y, z = mono[_X], mono[_Y], mono[_Z]
    xx, yy, zz = mono[_XX], mono[_YY], mono[_ZZ]
    for i in range(nb):
        w[i] = (
            a0 * xx[i] + a1 * yy[i] + a2 * zz[i] + a3 * x[i] * y[i] + a4 * x[i] * z[i]
            + a5 * y[i] * z[i] + a6 * x[i] + a7 * y[i] + a8 * z[i] + a9
        )  # fmt: skip
        ax = 2.0 * a0 * x[i] + a3 * y[i] + a4 * z[i] + a6
        ay = 2.0 * a1 * y[i] + a3 * x[i] + a5 * z[i] + a7
        az = 2.0 * a2 * z[i] + a4 * x[i] + a5 * y[i] + a8
        p_w[i] = ax * ax * vx + ay * ay * vy + az * az * vz  # sigma_i^2 until the last loop
    for i in range(nb):
        if active[i] and not (p_w[i] > 0.0 and p_w[i] < math.inf):
            return False
    for i in range(nb):
        pi = 1.0 / p_w[i]
        p_w[i] = pi
        p_b[i] = pi if active[i] else 0.0
        pw_b[i] = pi * w[i] if active[i] else 0.0
    return True


#: Points whose spread across their main direction is below this fraction of the spread along it
#: lie on a line as far as a quadric is concerned: every quadric through the line fits them, the
#: adjustment has no unique solution, and the iteration wanders (a mobile scanner standing still
#: repeats its scan line; 11 % of the simulated cloud A). Such fits stop at once, not converged.
COLLINEAR_RATIO = 1e-3


@njit(cache=True)
def _nearly_collinear(xyz: np.ndarray, active: np.ndarray) -> bool:
    """True when the second principal spread of the centred active rows is < COLLINEAR_RATIO x
    the first (from the scatter matrix's trace and the sum of its 2 x 2 principal minors, which
    is ~ lambda_1 lambda_2 when lambda_3 is the smallest)."""
    sxx = syy = szz = sxy = sxz = syz = 0.0
    for i in range(xyz.shape[0]):
        if active[i]:
            x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
            sxx += x * x
            syy += y * y
            szz += z * z
            sxy += x * y
            sxz += x * z
            syz += y * z
    trace = sxx + syy + szz
    minors = (sxx * syy - sxy * sxy) + (sxx * szz - sxz * sxz) + (syy * szz - syz * syz)
    return not minors > (COLLINEAR_RATIO * trace) ** 2


# ---------------------------------------------------------------------------------------------
# The iteration. Each adjustment maps the approximate parameters a0 to a0 + da (eqs. 20-29 with
# the linearised eq. 19); the fit is the fixed point, where da = 0. The plain iteration
# a <- a + da converges linearly, and on some patches not at all: it settles in a 2-cycle (an
# eigenvalue of the map's Jacobian near -1) or crawls along a flat valley. The fixed points do not
# depend on the path, so the path is chosen for robustness and speed:
#
#   stage 0  Anderson acceleration (depth ANDERSON_DEPTH) of a <- a + da, safeguarded: when
#            ||da|| grows beyond twice the smallest seen, the history is dropped and a damped
#            step a + s da is taken (s = 0.5, then 0.25 while it keeps growing);
#   stage 1  restart from the algebraic start, plain steps a <- a + da;
#   stage 2  restart, damped steps a <- a + 0.5 da (a 2-cycle of the plain map becomes a fixed
#            point's contraction: eigenvalue -1 of the Jacobian turns into 0);
#   stage 3  restart, damped steps a <- a + 0.25 da.
#
# Each stage has a share of ``max_iter`` (:func:`stage_budget`); the first ||da|| < tol ends the
# fit. Without acceleration stage 0 is skipped.
# ---------------------------------------------------------------------------------------------

#: Step factors of the stages after the accelerated one (plain, then damped restarts).
DAMPING = (1.0, 0.5, 0.25)
#: Iterates kept by Anderson acceleration.
ANDERSON_DEPTH = 3
#: Share of max_iter per stage: accelerated, plain, 0.5, 0.25 (with acceleration; first row) or
#: plain, 0.5, 0.25 (without; second row); the last stage also gets what the rounding leaves.
_SHARES = np.array([[0.4, 0.2, 0.2, 0.2], [0.4, 0.3, 0.3, 0.0]])


@njit(cache=True)
def stage_budget(max_iter: int, stage: int, accelerate: bool) -> int:
    """Adjustments allowed in ``stage`` (0-based; stage 0 is the accelerated one only when
    ``accelerate``). The budgets add up to ``max_iter``."""
    row = 0 if accelerate else 1
    last = 3 if accelerate else 2
    used = 0
    for k in range(last + 1):
        b = max_iter - used if k == last else int(max_iter * _SHARES[row, k])
        if k == stage:
            return b
        used += b
    return 0


@njit(cache=True)
def _anderson(
    a: np.ndarray,
    da: np.ndarray,
    dx: np.ndarray,
    dr: np.ndarray,
    count: int,
    out: np.ndarray,
    g_buf: np.ndarray,
    r_buf: np.ndarray,
) -> None:
    """Anderson-accelerated iterate from a, its step da = G(a) - a and the last ``count``
    differences of iterates dx and of steps dr (rows): out = a + da - (dX + dR) gamma, gamma the
    least-squares solution of dR gamma ~ da (regularised normal equations). Scratch: ``g_buf``
    (ANDERSON_DEPTH, ANDERSON_DEPTH), ``r_buf`` (ANDERSON_DEPTH, 1)."""
    g = g_buf[:count, :count]
    r = r_buf[:count]
    trace = 0.0
    for i in range(count):
        acc = 0.0
        for q in range(N_PARAMS):
            acc += dr[i, q] * da[q]
        r[i, 0] = acc
        for j in range(count):
            acc = 0.0
            for q in range(N_PARAMS):
                acc += dr[i, q] * dr[j, q]
            g[i, j] = acc
        trace += g[i, i]
    for i in range(count):
        g[i, i] += 1e-12 * trace  # the differences may be nearly dependent near convergence
    for q in range(N_PARAMS):
        out[q] = a[q] + da[q]
    if not _solve(g, r):
        return
    for i in range(count):
        for q in range(N_PARAMS):
            out[q] -= r[i, 0] * (dx[i, q] + dr[i, q])


@njit(cache=True)
def _fit_one(
    xyz: np.ndarray,
    active: np.ndarray,
    var: np.ndarray,
    max_iter: int,
    tol: float,
    t_first_only: bool,
    accelerate: bool,
    a: np.ndarray,
    v_out: np.ndarray,
    t_out: np.ndarray,
    given_start: np.ndarray,
) -> tuple[float, int, int]:
    """Fit one quadric to the active rows of ``xyz`` (n, 3), already centred.

    ``var`` (3,) is diag(D_ii). ``a`` (10,) receives the parameters; ``v_out`` and ``t_out`` (n,)
    receive v_i (eq. 29) and T_i (eq. 31) of the active rows (inactive rows are left untouched;
    with ``t_first_only`` only row 0 gets T). ``given_start`` (10,): where every stage starts,
    in this frame; NaN: the algebraic start. Returns (sigma0, iterations, status), status one
    of CONVERGED, NOT_CONVERGED, COLLINEAR, SINGULAR, TOO_FEW_POINTS; sigma0 is NaN when the
    last adjustment could not be solved. ``iterations`` counts adjustments over all stages.
    The residuals and T are those of the last adjustment solved.
    """
    n = xyz.shape[0]
    n_act = 0
    for i in range(n):
        if active[i]:
            n_act += 1
    if n_act <= DOF_LOSS:
        return math.nan, 0, TOO_FEW_POINTS
    if _nearly_collinear(xyz, active):
        return math.nan, 0, COLLINEAR
    mono = np.empty((_N_MONO, min(n, _BLOCK)))
    block_w = np.empty((2, _BLOCK))
    acc = np.empty(_N_MONO + N_PARAMS)
    if n <= _BLOCK:
        _block_monomials(xyz, 0, n, mono)  # fixed for the whole fit
        for i in range(n):
            block_w[0, i] = 1.0 if active[i] else 0.0
        acc[:_N_MONO] = 0.0
        _block_moments(mono, block_w[0], n, _N_MONO, acc)  # as weighted_moments does
    else:
        weighted_moments(xyz, active.astype(np.float64), _N_MONO, acc)
    start = np.empty(N_PARAMS)
    if given_start[0] == given_start[0]:
        start[:] = given_start
    else:
        _algebraic_start(acc, start)

    s = N_PARAMS + 1
    m = np.empty((s, s))
    rhs = np.empty((s, 1))
    da = np.zeros(N_PARAMS)
    a_prev = np.empty(N_PARAMS)
    da_prev = np.empty(N_PARAMS)
    a_lin = np.empty(N_PARAMS)  # where the last adjustment was linearised
    dx = np.empty((ANDERSON_DEPTH, N_PARAMS))
    dr = np.empty((ANDERSON_DEPTH, N_PARAMS))
    g_buf = np.empty((ANDERSON_DEPTH, ANDERSON_DEPTH))
    r_buf = np.empty((ANDERSON_DEPTH, 1))
    w = np.empty(n)
    p_w = np.empty(n)

    iterations = 0
    status = NOT_CONVERGED
    solved = False  # the last adjustment could be solved (a_lin, acc, w, p_w, da are its)
    first_stage = 0 if accelerate else 1
    for stage in range(first_stage, 1 + len(DAMPING)):
        a[:] = start
        budget = stage_budget(max_iter, stage - first_stage, accelerate)
        damping = 1.0 if stage == 0 else DAMPING[stage - 1]
        count = 0  # Anderson history held
        head = 0
        have_prev = False
        best = math.inf
        guard = 0.5
        for _ in range(budget):
            iterations += 1
            a_lin[:] = a
            solved = _adjust(xyz, active, var, a, m, rhs, w, p_w, mono, block_w, acc)
            if not solved:
                break
            step = 0.0
            for q in range(N_PARAMS):
                da[q] = rhs[q, 0]
                step += da[q] * da[q]
            step = math.sqrt(step)
            if not step < math.inf:
                solved = False
                break
            if step < tol:
                for q in range(N_PARAMS):
                    a[q] += da[q]
                status = CONVERGED
                break
            if stage > 0:
                for q in range(N_PARAMS):
                    a[q] += damping * da[q]
                continue
            if step > 2.0 * best:
                # The step grew: drop the history (this iterate becomes its base) and take a
                # damped step.
                count = 0
                a_prev[:] = a
                da_prev[:] = da
                have_prev = True
                for q in range(N_PARAMS):
                    a[q] += guard * da[q]
                guard = max(0.25, 0.5 * guard)
                continue
            best = min(best, step)
            guard = 0.5
            if have_prev:
                for q in range(N_PARAMS):
                    dx[head, q] = a[q] - a_prev[q]
                    dr[head, q] = da[q] - da_prev[q]
                head = (head + 1) % ANDERSON_DEPTH
                count = min(count + 1, ANDERSON_DEPTH)
            a_prev[:] = a
            da_prev[:] = da
            have_prev = True
            if count == 0:
                for q in range(N_PARAMS):
                    a[q] += da[q]
            else:
                _anderson(a_prev, da_prev, dx[:count], dr[:count], count, a, g_buf, r_buf)
        if status == CONVERGED:
            break
    if not solved:
        return math.nan, iterations, SINGULAR

    # Residuals (eq. 29) and their cofactors from the last adjustment solved.
    vpv = 0.0
    b = np.empty(N_PARAMS)
    for i in range(n):
        if not active[i]:
            continue
        design_row(xyz[i, 0], xyz[i, 1], xyz[i, 2], b)
        vi = w[i]
        for q in range(N_PARAMS):
            vi += b[q] * da[q]  # eq. 29: v_i = B_i da + w_i
        v_out[i] = vi
        vpv += p_w[i] * vi * vi
    sigma0 = math.sqrt(vpv / (n_act - DOF_LOSS))
    # Q_aa b_i for the rows tested: one solve with the bordered matrix, rhs (b_i; 0) per row.
    n_rows = 1 if t_first_only else n
    cols = np.zeros((s, n_rows))
    for i in range(n_rows):
        if active[i]:
            design_row(xyz[i, 0], xyz[i, 1], xyz[i, 2], b)
            for q in range(N_PARAMS):
                cols[q, i] = b[q]
    _bordered_matrix(acc, a_lin, m)
    if not _solve(m, cols):
        return math.nan, iterations, SINGULAR
    for i in range(n_rows):
        if not active[i]:
            continue
        design_row(xyz[i, 0], xyz[i, 1], xyz[i, 2], b)
        bqb = 0.0
        for q in range(N_PARAMS):
            bqb += b[q] * cols[q, i]
        q_vv = 1.0 / p_w[i] - bqb  # cofactor of v_i: 1/p_i - B_i Q_aa B_i^T
        t_out[i] = t_statistic(v_out[i], sigma0, q_vv, n_act - DOF_LOSS)
    # eq. 19 exactly: a damped last step (a fit that did not converge) leaves ||a|| off 1.
    _unit_norm(a)
    if _canonical_sign(a):
        for i in range(n):
            if active[i]:
                v_out[i] = -v_out[i]  # v_i = F(a, x_i) changes sign with a
    return sigma0, iterations, status


@njit(cache=True, inline="always")
def _canonical_sign(a: np.ndarray) -> bool:
    """Scale a by -1 if needed so that its largest-magnitude entry is positive; True if it was."""
    big = 0
    for q in range(1, N_PARAMS):
        if abs(a[q]) > abs(a[big]):
            big = q
    if a[big] < 0.0:
        for q in range(N_PARAMS):
            a[q] = -a[q]
        return True
    return False


@njit(cache=True)
def _centre(xyz: np.ndarray, active: np.ndarray, out: np.ndarray, centroid: np.ndarray) -> None:
    """out = xyz - mean of the active rows (written to centroid (3,))."""
    n_act = 0
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for i in range(xyz.shape[0]):
        if active[i]:
            n_act += 1
            sx += xyz[i, 0]
            sy += xyz[i, 1]
            sz += xyz[i, 2]
    if n_act > 0:
        centroid[0] = sx / n_act
        centroid[1] = sy / n_act
        centroid[2] = sz / n_act
    for i in range(xyz.shape[0]):
        for j in range(3):
            out[i, j] = xyz[i, j] - centroid[j]


# ---------------------------------------------------------------------------------------------
# Many surfaces at once.
# ---------------------------------------------------------------------------------------------


@njit(cache=True, parallel=True)
def _fit_patches(
    points: np.ndarray,
    index: np.ndarray,
    order: np.ndarray,
    var: np.ndarray,
    max_iter: int,
    tol: float,
    t_first_only: bool,
    accelerate: bool,
    params: np.ndarray,
    centroid: np.ndarray,
    v: np.ndarray,
    t: np.ndarray,
    sigma0: np.ndarray,
    iterations: np.ndarray,
    status: np.ndarray,
) -> None:
    """Patch j is points[index[j]], taken in the order ``order``: prange gives each thread one
    contiguous part of it, and an interleaved order (:func:`interleaved_order`) spreads the
    patches that converge slowly, which lie together in space, over all threads."""
    m, k = index.shape
    algebraic = np.full(N_PARAMS, np.nan)
    for s in prange(m):
        j = order[s]
        active = np.ones(k, dtype=np.bool_)
        patch = np.empty((k, 3))
        for i in range(k):
            patch[i] = points[index[j, i]]
        local = np.empty((k, 3))
        _centre(patch, active, local, centroid[j])
        s0, it, st = _fit_one(
            local, active, var, max_iter, tol, t_first_only, accelerate, params[j], v[j], t[j],
            algebraic,
        )
        sigma0[j] = s0
        iterations[j] = it
        status[j] = st


def interleaved_order(m: int, parts: int) -> np.ndarray:
    """range(m) as every parts-th item: 0, p, 2p, ..., then 1, p + 1, ... (a permutation)."""
    parts = max(1, int(parts))
    return np.concatenate([np.arange(r, m, parts) for r in range(parts)]).astype(np.int64)


def _variances(sigma: float | np.ndarray) -> np.ndarray:
    """diag(D_ii) (3,) from a scalar sigma or a per-axis (3,) sigma, in metres."""
    s = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (3,))
    if not np.all(np.isfinite(s)) or np.any(s <= 0.0):
        raise ValueError(f"sigma must be > 0, got {sigma!r}")
    return np.ascontiguousarray(s * s)


def fit_quadrics(
    patches: np.ndarray,
    sigma: float | np.ndarray = 0.005,
    *,
    neighbours: np.ndarray | None = None,
    max_iter: int = 500,
    tol: float = 1e-10,
    t_first_only: bool = False,
    accelerate: bool = True,
) -> QuadricFit:
    """Fit the quadric of eqs. 18-19 to each of m patches of k points (parallel over patches).

    Parameters
    ----------
    patches : (m, k, 3) float, or (n, 3) float with ``neighbours``
        Coordinates; each patch is centred on its own centroid before fitting. k >= 10.
    sigma : float or (3,) float
        Standard deviation of each coordinate (D_ii = diag(sigma^2), eq. 30).
    neighbours : (m, k) int, optional
        Patch j is ``patches[neighbours[j]]`` (gathered inside the parallel loop, so the m x k x 3
        copy is never made).
    max_iter : int
        Adjustments solved at most per patch, over all stages of the iteration (see
        :func:`stage_budget`).
    tol : float
        Convergence when ||da|| < tol.
    t_first_only : bool
        Compute T_i (eq. 31) only for the first point of each patch (the patch detector's tested
        point); the other entries of ``t_stat`` are NaN.
    accelerate : bool
        Begin with the Anderson-accelerated stage (same fixed points, fewer steps); False starts
        with the plain iteration, step for step, followed by the damped restarts.

    Returns
    -------
    QuadricFit
    """
    pts = np.ascontiguousarray(patches, dtype=np.float64)
    if neighbours is None:
        if pts.ndim != 3 or pts.shape[2] != 3:
            raise ValueError(f"patches must have shape (m, k, 3), got {pts.shape}")
        m, k, _ = pts.shape
        pts = pts.reshape(m * k, 3)
        index = np.arange(m * k, dtype=np.int64).reshape(m, k)
    else:
        index = np.ascontiguousarray(neighbours, dtype=np.int64)
        if pts.ndim != 2 or pts.shape[1] != 3 or index.ndim != 2:
            raise ValueError("with neighbours, points must be (n, 3) and neighbours (m, k)")
        if index.size and not (0 <= index.min() and index.max() < pts.shape[0]):
            raise ValueError("neighbours must index rows of the points")
        m, k = index.shape
    if k <= DOF_LOSS:
        raise ValueError(f"a quadric patch needs at least 10 points, got k={k}")
    params = np.zeros((m, N_PARAMS))
    centroid = np.zeros((m, 3))
    v = np.full((m, k), np.nan)
    t = np.full((m, k), np.nan)
    sigma0 = np.full(m, np.nan)
    iterations = np.zeros(m, dtype=np.int64)
    status = np.full(m, TOO_FEW_POINTS, dtype=np.int64)
    if m:
        _fit_patches(
            pts, index, interleaved_order(m, numba.get_num_threads()), _variances(sigma),
            int(max_iter), float(tol), bool(t_first_only), bool(accelerate), params, centroid,
            v, t, sigma0, iterations, status,
        )  # fmt: skip
    return QuadricFit(params, centroid, v, t, sigma0, iterations, status == CONVERGED, status)


@njit(cache=True)
def fit_masked(
    xyz: np.ndarray,
    active: np.ndarray,
    var: np.ndarray,
    max_iter: int,
    tol: float,
    params: np.ndarray,
    centroid: np.ndarray,
    v: np.ndarray,
    t: np.ndarray,
    accelerate: bool = True,
    start: np.ndarray | None = None,
    start_centroid: np.ndarray | None = None,
) -> tuple[float, int, bool]:
    """Fit one quadric to the rows of ``xyz`` (n, 3) where ``active`` (n,) is True.

    The frame is the centroid of the active rows (written to ``centroid`` (3,)); ``var`` (3,) is
    diag(D_ii) of eq. 30. ``params`` (10,), ``v`` and ``t`` (n,) are outputs (eq. 29 residual and
    eq. 31 T for active rows; inactive rows untouched). ``start`` (10,): parameters to start
    from, in the frame of ``start_centroid`` (3,) (an earlier fit's); None: the algebraic start.
    Returns (sigma0, iterations, status), status one of CONVERGED, NOT_CONVERGED, COLLINEAR,
    SINGULAR, TOO_FEW_POINTS.
    Callable from other numba code (the section detector runs it per section in parallel).
    """
    local = np.empty((xyz.shape[0], 3))
    _centre(xyz, active, local, centroid)
    given = np.full(N_PARAMS, np.nan)
    if start is not None and start_centroid is not None:
        moved_frame(start, centroid - start_centroid, given)
    return _fit_one(local, active, var, max_iter, tol, False, accelerate, params, v, t, given)


@njit(cache=True)
def moved_frame(a: np.ndarray, d: np.ndarray, out: np.ndarray) -> None:
    """``out`` (10,): the quadric ``a`` of eq. 18 written for coordinates y = x - d (the same
    surface, its frame's origin moved by ``d`` (3,)), scaled to ||out|| = 1 (eq. 19).

    With F(x) = x^T A x + b^T x + c (A symmetric: a1, a2, a3 on its diagonal, a4/2, a5/2, a6/2
    off it; b = (a7, a8, a9); c = a10), F(y + d) = y^T A y + (2 A d + b)^T y + F(d)."""
    b = np.empty(N_PARAMS)
    design_row(d[0], d[1], d[2], b)
    value = 0.0  # F(d)
    for q in range(N_PARAMS):
        value += a[q] * b[q]
    out[:6] = a[:6]
    out[6], out[7], out[8] = gradient(a, d[0], d[1], d[2])  # 2 A d + b (eqs. 25-27)
    out[9] = value
    _unit_norm(out)


@njit(cache=True, inline="always")
def _unit_norm(a: np.ndarray) -> None:
    """Scale ``a`` to ||a|| = 1 (eq. 19)."""
    norm = 0.0
    for q in range(N_PARAMS):
        norm += a[q] * a[q]
    norm = math.sqrt(norm)
    for q in range(N_PARAMS):
        a[q] /= norm
