"""Confusion counts and ground-filter scores against hand-computed tables."""

from __future__ import annotations

import json

import numpy as np
import pytest

from algorithms.metrics import ground_scores, outlier_confusion


def _mask(bits: str) -> np.ndarray:
    return np.array([c == "1" for c in bits], dtype=bool)


def test_outlier_confusion_small_hand_case():
    # 10 points, outliers at 0..3; flagged 0, 1 (hits) and 5, 6, 7 (false alarms).
    truth = _mask("1111000000")
    flagged = _mask("1100011100")
    c = outlier_confusion(truth, flagged)
    assert c["points"] == 10
    assert c["outliers"] == 4
    assert c["outliers_identified"] == 2
    assert c["non_outliers_identified"] == 3
    assert c["outliers_missed"] == 2
    assert c["pct_outliers_identified"] == pytest.approx(50.0)
    assert c["pct_cloud_identified"] == pytest.approx(50.0)
    assert c["pct_cloud_identified_incorrectly"] == pytest.approx(30.0)
    assert c["precision"] == pytest.approx(2 / 5)
    assert c["recall"] == pytest.approx(2 / 4)
    assert c["f1"] == pytest.approx(2 * 0.4 * 0.5 / 0.9)


def test_outlier_confusion_reproduces_paper_table_2_cloud_a():
    # Table 2, cloud A: 1098689 points, 11035 outliers, 3414 identified, 55 false alarms.
    n, outliers, tp, fp = 1_098_689, 11_035, 3_414, 55
    truth = np.zeros(n, bool)
    truth[:outliers] = True
    flagged = np.zeros(n, bool)
    flagged[:tp] = True
    flagged[outliers : outliers + fp] = True
    c = outlier_confusion(truth, flagged)
    assert c["outliers_missed"] == 7_621
    assert round(c["pct_outliers_identified"], 2) == 30.94
    assert round(c["pct_cloud_identified"], 2) == 0.32
    assert round(c["pct_cloud_identified_incorrectly"], 2) == 0.01


def test_outlier_confusion_undefined_ratios_are_none_and_json_ready():
    c = outlier_confusion(np.zeros(5, bool), np.zeros(5, bool))
    assert c["pct_outliers_identified"] is None
    assert c["precision"] is None
    assert c["recall"] is None
    assert c["f1"] is None
    assert c["pct_cloud_identified"] == 0.0
    text = json.dumps(c, allow_nan=False)
    assert all(type(v) in (int, float, type(None)) for v in json.loads(text).values())


def test_ground_scores_small_hand_case():
    # 10 points: 6 ground (2 labelled object), 4 object (1 labelled ground).
    truth = _mask("1111110000")
    pred = _mask("1111001000")
    s = ground_scores(truth, pred)
    assert (s["ground"], s["object"]) == (6, 4)
    assert (s["ground_as_ground"], s["ground_as_object"]) == (4, 2)
    assert (s["object_as_ground"], s["object_as_object"]) == (1, 3)
    assert s["type_i_pct"] == pytest.approx(100 * 2 / 6)
    assert s["type_ii_pct"] == pytest.approx(100 * 1 / 4)
    assert s["total_error_pct"] == pytest.approx(30.0)
    # p_o = 0.7, p_e = (6*5 + 4*5) / 100 = 0.5, kappa = 0.2 / 0.5 = 0.4
    assert s["kappa"] == pytest.approx(0.4)
    assert s["kappa_pct"] == pytest.approx(40.0)


def test_ground_scores_perfect_and_inverted():
    truth = _mask("110100")
    assert ground_scores(truth, truth)["kappa"] == pytest.approx(1.0)
    assert ground_scores(truth, truth)["total_error_pct"] == 0.0
    inverted = ground_scores(truth, ~truth)
    assert inverted["kappa"] == pytest.approx(-1.0)
    assert inverted["type_i_pct"] == 100.0
    assert inverted["type_ii_pct"] == 100.0


def test_ground_scores_single_class_has_undefined_terms():
    s = ground_scores(np.ones(4, bool), np.ones(4, bool))
    assert s["type_ii_pct"] is None
    assert s["kappa"] is None
    assert s["total_error_pct"] == 0.0
    json.dumps(s, allow_nan=False)


def test_ground_scores_kappa_matches_explicit_formula_on_random_labels():
    rng = np.random.default_rng(7)
    truth = rng.random(1000) < 0.6
    pred = np.where(rng.random(1000) < 0.8, truth, ~truth)
    s = ground_scores(truth, pred)
    table = np.array([[np.sum(truth & pred), np.sum(truth & ~pred)],
                      [np.sum(~truth & pred), np.sum(~truth & ~pred)]], dtype=float)
    n = table.sum()
    p_o = np.trace(table) / n
    p_e = float(table.sum(axis=1) @ table.sum(axis=0)) / n**2
    assert s["kappa"] == pytest.approx((p_o - p_e) / (1 - p_e), rel=1e-12)


@pytest.mark.parametrize("func", [outlier_confusion, ground_scores])
def test_bad_input_is_refused_with_a_named_message(func):
    with pytest.raises(ValueError, match="differ in length"):
        func(np.zeros(3, bool), np.zeros(4, bool))
    with pytest.raises(ValueError, match="boolean"):
        func(np.zeros(3, int), np.zeros(3, bool))
