"""The contract every registered detector keeps (as scikit-learn's ``check_estimator``).

Run over :data:`lidar_outliers.detectors.DETECTORS`, so a new detector is checked by being
declared: score shape, NaN means untested, ``flagged == score > critical``, JSON-able info,
empty and one-point input, a 5e6 m coordinate shift changes nothing, and parameters out of
range refused with the parameter's name (by the stage model and by the parameters themselves).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from pydantic import ValidationError

from algorithms.params import parameter_infos
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors import DETECTORS, GroundResult, build_registry
from lidar_outliers.errors import ParameterError
from lidar_outliers.pipeline import jsonable

SHIFT = np.array([5e6, 5e6, 1e3])


def scene(n: int = 1500, seed: int = 3) -> Cloud:
    """Two scanners sweeping a gently curved road along a straight track, in time order, with
    a few points lifted or sunk by metres: something every detector can test."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 2e-4
    phase = np.arange(n) * 0.09
    x = 8.0 * t + 2.5 * np.cos(phase)
    y = 2.5 * np.sin(phase)
    z = 0.05 * np.sin(0.3 * x) + rng.normal(0.0, 0.004, n)
    spikes = rng.choice(np.arange(30, n - 30), 12, replace=False)
    z[spikes[:8]] += 3.0
    z[spikes[8:]] -= 2.0
    return Cloud(
        xyz=np.c_[x, y, z], origin=np.zeros(3), gps_time=t,
        point_source_id=(np.arange(n) % 2 + 1).astype(np.uint16),
        classification=np.zeros(n, np.uint8),
        intensity=rng.integers(0, 3, n).astype(np.uint16),
    )


def shifted(cloud: Cloud, by: np.ndarray) -> Cloud:
    return dataclasses.replace(cloud, xyz=cloud.xyz + by)


def parameters_for(detector, shift: np.ndarray | None = None):
    """Default parameters; a sensor position moves with the points."""
    params = detector.parameters()
    if shift is not None and hasattr(params, "origin"):
        params = dataclasses.replace(params, origin=tuple(np.add(params.origin, shift).tolist()))
    return params


@pytest.fixture(scope="module")
def cloud() -> Cloud:
    return scene()


@pytest.mark.parametrize("name", list(DETECTORS))
def test_result_shape_flags_and_info(name: str, cloud: Cloud) -> None:
    detector = DETECTORS[name]
    result = detector.run(cloud, parameters_for(detector))
    json.dumps(jsonable(result.info), allow_nan=False)
    if isinstance(result, GroundResult):
        assert detector.kind == "ground"
        assert result.is_ground.shape == (len(cloud),) and result.is_ground.dtype == bool
        return
    assert detector.kind == "outlier"
    score = np.asarray(result.score)
    assert score.shape == (len(cloud),) and np.issubdtype(score.dtype, np.floating)
    flagged = np.asarray(result.flagged)
    assert flagged.shape == (len(cloud),) and flagged.dtype == bool
    critical = np.broadcast_to(np.asarray(result.critical_value, dtype=float), score.shape)
    with np.errstate(invalid="ignore"):
        expected = score > critical
    np.testing.assert_array_equal(flagged, expected & ~np.isnan(score))
    assert not (flagged & np.isnan(score)).any(), "an untested (NaN) point was flagged"
    if "points_tested" in result.info:
        assert result.info["points_tested"] == int(np.count_nonzero(~np.isnan(score)))


@pytest.mark.parametrize("name", list(DETECTORS))
@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_one_point_input(name: str, n: int, cloud: Cloud) -> None:
    detector = DETECTORS[name]
    result = detector.run(cloud.subset(np.arange(n)), parameters_for(detector))
    json.dumps(jsonable(result.info), allow_nan=False)
    if isinstance(result, GroundResult):
        assert result.is_ground.shape == (n,)
    else:
        assert np.asarray(result.score).shape == (n,)
        assert np.asarray(result.flagged).shape == (n,)


@pytest.mark.parametrize("name", list(DETECTORS))
def test_a_far_coordinate_shift_changes_nothing(name: str, cloud: Cloud) -> None:
    """Coordinates near 5,000,000 m (a projected easting/northing) lose no precision."""
    detector = DETECTORS[name]
    near = detector.run(cloud, parameters_for(detector))
    far = detector.run(shifted(cloud, SHIFT), parameters_for(detector, SHIFT))
    if isinstance(near, GroundResult):
        np.testing.assert_array_equal(near.is_ground, far.is_ground)
        return
    np.testing.assert_array_equal(near.flagged, far.flagged)
    np.testing.assert_allclose(far.score, near.score, rtol=1e-5, atol=1e-6, equal_nan=True)


def _out_of_range(info) -> list:
    """Values just outside each declared bound of a parameter."""
    limits = info.limits
    bad = []
    if limits.ge is not None:
        bad.append(limits.ge - 1)
    if limits.gt is not None:
        bad.append(limits.gt)
    if limits.le is not None:
        bad.append(limits.le + 1)
    if limits.lt is not None:
        bad.append(limits.lt)
    return bad


CASES = [(name, info.name, value) for name, detector in DETECTORS.items()
         for info in parameter_infos(detector.parameters) for value in _out_of_range(info)]


@pytest.mark.parametrize(("name", "parameter", "value"), CASES)
def test_out_of_range_parameters_are_refused_by_name(name: str, parameter: str, value) -> None:
    detector = DETECTORS[name]
    default = getattr(detector.parameters(), parameter)
    if isinstance(default, tuple):
        value = tuple(value for _ in default)
    elif isinstance(default, int) and not isinstance(default, bool):
        value = int(np.floor(value)) if value < default else int(np.ceil(value))
    with pytest.raises(ParameterError, match=parameter):
        detector.parameters(**{parameter: value})
    with pytest.raises(ValidationError) as exc:
        detector.stage(**{parameter: value})
    assert parameter in {str(part) for err in exc.value.errors() for part in err["loc"]}


@pytest.mark.parametrize("name", list(DETECTORS))
def test_non_finite_numbers_are_refused(name: str) -> None:
    detector = DETECTORS[name]
    numeric = [info.name for info in parameter_infos(detector.parameters)
               if isinstance(info.default, float)]
    for parameter in numeric:
        with pytest.raises(ParameterError, match=parameter):
            detector.parameters(**{parameter: float("inf")})
        with pytest.raises(ValidationError):
            detector.stage(**{parameter: float("nan")})


def test_registry_refuses_a_shared_bit_or_name() -> None:
    temporal, patch = DETECTORS["temporal"], DETECTORS["patch"]
    twin = dataclasses.replace(patch, name="twin", flag_bit=temporal.flag_bit)
    with pytest.raises(ValueError, match="share bit"):
        build_registry([temporal, twin])
    with pytest.raises(ValueError, match="two detectors"):
        build_registry([temporal, dataclasses.replace(patch, name="temporal")])
    with pytest.raises(ValueError, match="flag_bit"):
        dataclasses.replace(patch, name="odd", flag_bit=3)


def test_every_outlier_detector_has_its_own_bit_of_uint16() -> None:
    bits = [d.flag_bit for d in DETECTORS.values() if d.kind == "outlier"]
    assert len(set(bits)) == len(bits) and all(0 < b < 1 << 16 for b in bits)
