"""The smoother of the temporal detector, one block of windows at a time (eqs. 11, 14-17).

Each window holds a tested point k and its neighbours along the scan line; a quadratic in time
(the alpha-beta-gamma state model, eqs. 1-4) is fitted to it by weighted least squares:

- ``smoother_weights``: the coefficients a_i(k) of eq. 11, with lambda of eq. 14;
- ``predict_from_window``: eq. 15, z_p(k) predicted from the neighbours alone;
- ``difference_variance``: eq. 16, the variance of z(k) - z_p(k);
- ``standardised_difference``: eq. 17, tested against the two-sided normal critical value.

Each is vectorised over a :class:`WindowBlock` of windows in plain numpy: no compilation, so a
short command does not pay for numba's start-up.

Numerical care (GPS times near 5e5 s with steps near 1e-5 s, coordinates near 5e6 m):

- times enter only as delta = t_{k+i} - t_k (exact in float64 for neighbouring times), rescaled by
  the window's largest |delta|, and the fit uses polynomials orthogonal over the window instead
  of inverting the moment matrix of eq. 14 (``smoother_weights``);
- coordinates enter only as z_{k+i} - z_k (the a_i of the neighbours sum to 1 - a_0, so eq. 15 is
  an affine combination and the reference z_k cancels exactly in exact arithmetic).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: A segment shorter than this is not tested: three neighbours are the least that determine the
#: quadratic of eq. 15 and the point itself is the fourth.
MIN_SEGMENT_POINTS = 4

#: N_2 / N_0 (the weighted mean square of the second orthogonal polynomial, times scaled to
#: [-1, 1]) below which the window is taken as singular: fewer than three distinct times.
_SINGULAR_RATIO = 1e-12

#: 1 - a_0(k) below this: the point itself carries the whole fit, eq. 15 is undefined.
_MIN_ONE_MINUS_A0 = 1e-10


@dataclass
class WindowBlock:
    """b windows of w rows each as (w, b) arrays: column q holds the q-th window.

    ``t`` (w, b) times, ``z`` (m, w, b) series, ``weight`` (w, b) 1 / sigma^2 of the rows (0 for
    padding, when a window is shorter than w; its rows repeat the window's last row) or None
    for unit sigma everywhere. ``t_k``, ``z_k`` (m, b) and ``variance_k`` (None: 1) belong to the
    tested points. ``t[0]`` and ``t[-1]`` are each window's first and last time.
    """

    t: np.ndarray
    z: np.ndarray
    weight: np.ndarray | None
    t_k: np.ndarray
    z_k: np.ndarray
    variance_k: np.ndarray | None


def _sum_rows(x: np.ndarray, axis: int = 0) -> np.ndarray:
    """Sum over the window rows (``axis``) in row order, the same order in every block (numpy's
    own reductions may sum pairwise for some shapes, which would change the last bits)."""
    rows = np.moveaxis(x, axis, 0)
    total = rows[0].copy()
    for row in rows[1:]:
        total += row
    return total


def smoother_weights(block: WindowBlock) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smoother coefficients a_i(k) of eq. 11 (lambda of eq. 14), by orthogonal polynomials.

    Returns (a, a_0, usable): a (w, b) for every window row (0 for padding), a_0(k) (b,) the
    tested point's own coefficient, and usable (b,) False where the window holds fewer than
    three distinct times or a_0(k) is 1 (the point carries the whole fit).

    Eq. 11 with lambda = M^-1 e_1 (eq. 14) is the least-squares quadratic's hat matrix,
    a_i = w_i p_i^T M^-1 p_k with p = (1, delta, delta^2), and the hat matrix does not depend on
    the polynomial basis. Inverting M itself (condition number up to 1e4 and more with
    uneven weights) loses digits; in the basis of Forsythe's polynomials, orthogonal over the
    window's weighted points (q_0 = 1, q_1 = delta - alpha_1, q_2 = (delta - alpha_2) q_1 -
    beta_1), M is diagonal (N_0, N_1, N_2) and a_i = w_i sum_j q_j(i) q_j(k) / N_j exactly.

    Times enter as delta = (t_{k+i} - t_k) / u with u the window's largest |delta|; the a_i do
    not depend on u nor on a common factor of the weights.
    """
    weight = block.weight

    def weighted_sum(x: np.ndarray) -> np.ndarray:
        return _sum_rows(x if weight is None else weight * x)

    inv_unit = 1.0 / np.maximum(block.t_k - block.t[0], block.t[-1] - block.t_k)
    q1 = np.subtract(block.t, block.t_k, out=np.empty(block.t.shape))  # delta, then q_1
    q1 *= inv_unit
    n0 = np.full(block.t_k.size, float(q1.shape[0])) if weight is None else _sum_rows(weight)
    alpha1 = weighted_sum(q1) / n0
    q1 -= alpha1
    power = q1 * q1
    n1 = weighted_sum(power)
    power *= q1
    gamma, beta1 = weighted_sum(power) / n1, n1 / n0  # alpha_2 - alpha_1 and beta_1
    q2 = np.subtract(q1, gamma, out=power)
    q2 *= q1
    q2 -= beta1
    n2 = weighted_sum(q2 * q2)
    q1_k = -alpha1  # delta_k = 0
    q2_k = (q1_k - gamma) * q1_k - beta1
    c1, c2 = q1_k / n1, q2_k / n2
    a = q1  # w_i (1 / N_0 + c_1 q_1(i) + c_2 q_2(i)), in place of q_1
    a *= c1
    a += 1.0 / n0
    q2 *= c2
    a += q2
    if weight is not None:
        a *= weight
    a_0 = 1.0 / n0 + c1 * q1_k + c2 * q2_k
    if block.variance_k is not None:
        a_0 /= block.variance_k
    usable = n2 > _SINGULAR_RATIO * n0
    usable &= 1.0 - a_0 > _MIN_ONE_MINUS_A0
    return a, a_0, usable


def predict_from_window(block: WindowBlock, a: np.ndarray, a_0: np.ndarray) -> np.ndarray:
    """Eq. 15 relative to the tested point: z_p(k) - z(k), (m, b).

    The neighbours' a_i sum to 1 - a_0(k), so eq. 15 is an affine combination and subtracting
    the local reference z(k) first changes nothing but the rounding (coordinates near 5e6 m).
    The tested point's own row adds a_0 (z(k) - z(k)) = 0, so it needs no exclusion.
    """
    term = np.subtract(block.z, block.z_k[:, None, :], out=np.empty(block.z.shape))
    term *= a
    prediction = _sum_rows(term, axis=1)
    prediction /= 1.0 - a_0
    return prediction


def difference_variance(block: WindowBlock, a_0: np.ndarray) -> np.ndarray:
    """Eq. 16, the variance of z(k) - z_p(k): sigma_k^2 + sum_{i!=k} a_i^2 sigma_i^2 / (1 - a_0)^2.

    With weights 1 / sigma_i^2 the sum collapses: a_i^2 sigma_i^2 = w_i (lambda . p_i)^2 with
    p_i = (1, delta_i, delta_i^2), whose sum over the whole window is lambda^T M lambda =
    lambda_1 (M lambda = e_1, eq. 14), and the point's own term is w_k lambda_1^2 = a_0 lambda_1.
    So eq. 16 = sigma_k^2 + lambda_1 / (1 - a_0) = sigma_k^2 / (1 - a_0): the leave-one-out
    variance of a least-squares smoother (a_0 is its hat-matrix diagonal). The tests check it
    against the literal sum.
    """
    variance_k = 1.0 if block.variance_k is None else block.variance_k
    return variance_k / (1.0 - a_0)


def standardised_difference(dz: np.ndarray, sigma_dz: np.ndarray) -> np.ndarray:
    """Eq. 17: dz / sigma_dz with dz = z(k) - z_p(k) and sigma_dz = sqrt(eq. 16).

    Standard normal under H0: dz = 0.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        return dz / sigma_dz


def block_differences(block: WindowBlock) -> tuple[np.ndarray, np.ndarray]:
    """dz (m, b) = z(k) - z_p(k) (eq. 15) and sigma_dz (b,) = sqrt(eq. 16); NaN if unusable."""
    with np.errstate(divide="ignore", invalid="ignore"):  # unusable windows, masked below
        a, a_0, usable = smoother_weights(block)
        dz = predict_from_window(block, a, a_0)
        np.negative(dz, out=dz)
        sigma_dz = np.sqrt(difference_variance(block, a_0))
    dz[:, ~usable] = np.nan
    sigma_dz[~usable] = np.nan
    return dz, sigma_dz
