"""Accuracy scores: outlier confusion counts (the paper's Tables 2-5) and ground-filter errors.

Everything returned is a plain ``int``, ``float`` or ``None`` so that the dictionaries can go
straight into the statistics JSON. A ratio whose denominator is zero (e.g. the percentage of
outliers found in a cloud without outliers) is ``None``, never NaN, because NaN is not valid JSON.
"""

from __future__ import annotations

import numpy as np


def _as_mask(values: np.ndarray, name: str) -> np.ndarray:
    mask = np.asarray(values)
    if mask.ndim != 1:
        raise ValueError(f"{name} must be a 1-D boolean array, got shape {mask.shape}")
    if mask.dtype != bool:
        raise ValueError(f"{name} must be boolean, got dtype {mask.dtype}")
    return mask


def _pair(a: np.ndarray, b: np.ndarray, name_a: str, name_b: str) -> tuple[np.ndarray, np.ndarray]:
    a = _as_mask(a, name_a)
    b = _as_mask(b, name_b)
    if a.shape != b.shape:
        raise ValueError(f"{name_a} and {name_b} differ in length: {a.shape[0]} vs {b.shape[0]}")
    return a, b


def _ratio(num: int, den: int, scale: float = 1.0) -> float | None:
    return None if den == 0 else scale * num / den


def outlier_confusion(truth: np.ndarray, flagged: np.ndarray) -> dict[str, int | float | None]:
    """Confusion counts of an outlier detector in the layout of the paper's Tables 2-5.

    Parameters
    ----------
    truth : (n,) bool
        True for the reference outliers.
    flagged : (n,) bool
        True for the points the detector flagged.

    Returns
    -------
    dict
        ``points`` n; ``outliers`` reference outliers; ``outliers_identified`` (true positives);
        ``non_outliers_identified`` (false alarms); ``outliers_missed``;
        ``pct_outliers_identified`` = 100 * identified / outliers;
        ``pct_cloud_identified`` = 100 * flagged / points;
        ``pct_cloud_identified_incorrectly`` = 100 * false alarms / points (the paper's percentages,
        e.g. Table 2, cloud A: 3414 of 11035 outliers = 30.94 %, 3469 of 1098689 points = 0.32 %);
        ``precision``, ``recall`` and ``f1`` as fractions in [0, 1]. Undefined ratios are ``None``.
    """
    truth, flagged = _pair(truth, flagged, "truth", "flagged")
    return confusion_from_counts(
        points=int(truth.size), outliers=int(np.count_nonzero(truth)),
        identified=int(np.count_nonzero(truth & flagged)),
        false_alarms=int(np.count_nonzero(~truth & flagged)),
    )


def confusion_from_counts(
    *, points: int, outliers: int, identified: int, false_alarms: int
) -> dict[str, int | float | None]:
    """:func:`outlier_confusion` from its four counts (for results counted chunk by chunk)."""
    n, tp, fp = points, identified, false_alarms
    fn = outliers - tp
    precision = _ratio(tp, tp + fp)
    recall = _ratio(tp, outliers)
    f1 = _ratio(2 * tp, 2 * tp + fp + fn)
    return {
        "points": n,
        "outliers": outliers,
        "outliers_identified": tp,
        "non_outliers_identified": fp,
        "outliers_missed": fn,
        "pct_outliers_identified": _ratio(tp, outliers, 100.0),
        "pct_cloud_identified": _ratio(tp + fp, n, 100.0),
        "pct_cloud_identified_incorrectly": _ratio(fp, n, 100.0),
        "precision": precision,
        "recall": recall,
        "f1": f1,
    }


def ground_scores(
    truth_ground: np.ndarray, predicted_ground: np.ndarray
) -> dict[str, int | float | None]:
    """Type I, type II and total error and Cohen's kappa of a ground filter (Sithole & Vosselman).

    Parameters
    ----------
    truth_ground : (n,) bool
        True for the reference ground points, False for object points.
    predicted_ground : (n,) bool
        True for the points the filter labelled ground.

    Returns
    -------
    dict
        Counts ``points``, ``ground``, ``object``, ``ground_as_ground``, ``ground_as_object``,
        ``object_as_ground``, ``object_as_object``; percentages ``type_i_pct`` = 100 * ground
        labelled object / ground, ``type_ii_pct`` = 100 * object labelled ground / object,
        ``total_error_pct`` = 100 * misclassified / points; ``kappa`` Cohen's kappa as a fraction
        in [-1, 1] (``kappa_pct`` = 100 * kappa, as the ISPRS report prints it). Undefined values
        (an empty class, or chance agreement of 1) are ``None``.
    """
    truth, pred = _pair(truth_ground, predicted_ground, "truth_ground", "predicted_ground")
    n = int(truth.size)
    gg = int(np.count_nonzero(truth & pred))
    go = int(np.count_nonzero(truth & ~pred))
    og = int(np.count_nonzero(~truth & pred))
    oo = n - gg - go - og
    ground, obj = gg + go, og + oo
    kappa = _cohen_kappa(gg, go, og, oo)
    return {
        "points": n,
        "ground": ground,
        "object": obj,
        "ground_as_ground": gg,
        "ground_as_object": go,
        "object_as_ground": og,
        "object_as_object": oo,
        "type_i_pct": _ratio(go, ground, 100.0),
        "type_ii_pct": _ratio(og, obj, 100.0),
        "total_error_pct": _ratio(go + og, n, 100.0),
        "kappa": kappa,
        "kappa_pct": None if kappa is None else 100.0 * kappa,
    }


def _cohen_kappa(gg: int, go: int, og: int, oo: int) -> float | None:
    """Cohen's kappa of a 2x2 table (rows truth, columns prediction): (p_o - p_e) / (1 - p_e)."""
    n = gg + go + og + oo
    if n == 0:
        return None
    p_o = (gg + oo) / n
    p_e = ((gg + go) * (gg + og) + (og + oo) * (go + oo)) / (n * n)
    if p_e >= 1.0:
        return None
    return (p_o - p_e) / (1.0 - p_e)
