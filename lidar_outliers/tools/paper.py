"""The published figures of Leslar, Wang & Hu (2010), section 4, Tables 1-5, as data.

Keys follow :func:`algorithms.metrics.outlier_confusion` so our results and the paper's sit in
the same rows. Table 5 (algorithm (a) then (b)) also gives the counts per routine.
"""

from __future__ import annotations

CLOUDS = ("A", "B", "C")

#: Table 1: specifications of the three test clouds.
TABLE1: dict[str, dict[str, float]] = {
    "A": {"points": 1098689, "outliers": 11035, "pct_outliers": 1.00},
    "B": {"points": 295147, "outliers": 872, "pct_outliers": 0.30},
    "C": {"points": 237740, "outliers": 31, "pct_outliers": 0.01},
}


def _table(identified, non_outliers, missed, pct_found, pct_cloud, pct_wrong):
    return {
        cloud: {
            "outliers_identified": identified[i],
            "non_outliers_identified": non_outliers[i],
            "outliers_missed": missed[i],
            "pct_outliers_identified": pct_found[i],
            "pct_cloud_identified": pct_cloud[i],
            "pct_cloud_identified_incorrectly": pct_wrong[i],
        }
        for i, cloud in enumerate(CLOUDS)
    }


#: Table 2: algorithm (a), the temporal smoother.
TABLE2 = _table((3414, 291, 4), (55, 27, 3), (7621, 581, 27), (30.94, 33.37, 12.90),
                (0.32, 0.11, 0.00), (0.01, 0.01, 0.00))
#: Table 3: algorithm (b), quadric patches.
TABLE3 = _table((16, 33, 4), (0, 0, 0), (11024, 839, 27), (0.14, 3.78, 12.90),
                (0.00, 0.01, 0.00), (0.00, 0.00, 0.00))
#: Table 4: algorithm (c), quadric sections.
TABLE4 = _table((5221, 712, 15), (15431, 0, 193), (5060, 160, 16), (47.31, 81.65, 48.39),
                (1.88, 0.24, 0.09), (1.40, 0.00, 0.08))
#: Table 5: algorithm (a) preceding algorithm (b); totals plus the per-routine counts.
TABLE5 = _table((3449 + 11, 290 + 24, 4 + 1), (53 + 1, 25 + 0, 4 + 0), (7575, 558, 27),
                (31.35, 36.01, 16.13), (0.32, 0.11, 0.00), (0.00, 0.01, 0.00))
for _cloud, _a, _b, _na, _nb in zip(CLOUDS, (3449, 290, 4), (11, 24, 1), (53, 25, 4), (1, 0, 0),
                                    strict=True):
    TABLE5[_cloud].update({
        "outliers_identified_a": _a, "outliers_identified_b": _b,
        "non_outliers_identified_a": _na, "non_outliers_identified_b": _nb,
    })

#: The paper's table for each pipeline the benchmark runs (our names).
BY_PIPELINE: dict[str, tuple[str, dict[str, dict[str, float]]]] = {
    "temporal": ("Table 2", TABLE2),
    "patch": ("Table 3", TABLE3),
    "section": ("Table 4", TABLE4),
    "temporal->patch": ("Table 5", TABLE5),
}
