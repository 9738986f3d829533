"""Tests of the shared statistics helpers against their defining probabilities."""

import numpy as np
import pytest
from scipy import stats

from algorithms.stats import mad_sigma, normal_critical_value, t_critical_value


def test_normal_critical_value_is_two_sided():
    c = normal_critical_value(0.001)
    assert c == pytest.approx(3.2905267314919, rel=1e-12)
    assert 2.0 * stats.norm.sf(c) == pytest.approx(0.001, rel=1e-12)
    assert normal_critical_value(0.05) == pytest.approx(1.959963984540054, rel=1e-12)


def test_t_critical_value_scalar_and_vector():
    assert isinstance(t_critical_value(0.05, 10), float)
    assert t_critical_value(0.05, 10) == pytest.approx(2.228138851986273, rel=1e-12)
    dof = np.array([1, 5, 31, 1000])
    crit = t_critical_value(0.001, dof)
    assert crit.shape == dof.shape
    np.testing.assert_allclose(2.0 * stats.t.sf(crit, dof), 0.001, rtol=1e-10)
    # Large dof tends to the normal value.
    assert crit[-1] == pytest.approx(normal_critical_value(0.001), rel=1e-2)


def test_t_critical_value_nonpositive_dof_is_nan():
    crit = t_critical_value(0.01, np.array([0, -3, 4]))
    assert np.isnan(crit[0]) and np.isnan(crit[1]) and np.isfinite(crit[2])


@pytest.mark.parametrize("alpha", [0.0, 1.0, -0.1, 2.0])
def test_bad_alpha_refused(alpha):
    with pytest.raises(ValueError, match="alpha"):
        normal_critical_value(alpha)
    with pytest.raises(ValueError, match="alpha"):
        t_critical_value(alpha, 5)


def test_mad_sigma_matches_slow_definition_and_ignores_nan():
    rng = np.random.default_rng(0)
    x = rng.normal(3.0, 0.02, size=2001)
    slow = 1.4826 * np.median(np.abs(x - np.median(x)))
    assert mad_sigma(x) == pytest.approx(slow, rel=1e-4)
    with_nan = np.concatenate([x, [np.nan, np.inf]])
    assert mad_sigma(with_nan) == pytest.approx(mad_sigma(x), rel=1e-15)


def test_mad_sigma_recovers_normal_sigma_despite_outliers():
    rng = np.random.default_rng(1)
    x = rng.normal(0.0, 0.5, size=100_000)
    x[:1000] = 1e6  # 1 % gross outliers barely move the MAD
    assert mad_sigma(x) == pytest.approx(0.5, rel=0.03)


def test_mad_sigma_empty_is_nan():
    assert np.isnan(mad_sigma(np.array([np.nan])))
    assert np.isnan(mad_sigma(np.array([])))
