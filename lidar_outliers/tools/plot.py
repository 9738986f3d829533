"""Pictures of a result file: top-down view, side profile and score histograms.

A result file is a LAS/LAZ file written by the pipeline: the input's points plus the extra
dimensions ``outlier_flags`` (bitmask) and ``<detector>_score``. The picture shows

* a top-down view and a side profile (along the cloud's main horizontal axis) coloured by flag,
  or, with a truth file (``is_outlier`` per point), by true positive / false alarm / miss;
* per detector, a histogram of its score with the critical value it was compared against, taken
  from the statistics JSON beside the file when there is one, else recomputed from the detector's
  default parameters.

:func:`render_preview` is what the service calls for ``/jobs/{id}/results/preview``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidar_outliers.atomic import atomic_path
from lidar_outliers.errors import LasFormatError, ParameterError
from lidar_outliers.output import FLAGS_DIMENSION as FLAGS
from lidar_outliers.output import FLAGS_DTYPE

SCORE_SUFFIX = "_score"
#: Statistics file names looked for beside a result (the service writes ``statistics.json``).
STATS_NAMES = ("{stem}.stats.json", "{stem}.statistics.json", "{stem}.json", "statistics.json")
FIGSIZE, DPI = (12.0, 10.0), 100
#: Points drawn per category at most (the rarer categories are always drawn in full).
MAX_BACKGROUND = 250_000

COLOURS = {
    "kept": "#b8b8b8",
    "flagged": "#d62728",
    "true negative": "#c4c4c4",
    "true positive": "#2ca02c",
    "false alarm": "#d62728",
    "miss": "#1f77b4",
}


@dataclass
class ResultCloud:
    """What the picture needs from a result file: xyz (n, 3), flags (n,), scores."""

    xyz: np.ndarray
    flags: np.ndarray
    scores: dict[str, np.ndarray]
    name: str


def read_result(path: str | Path) -> ResultCloud:
    """Read xyz, ``outlier_flags`` (zeros if absent) and every ``*_score`` dimension."""
    import laspy

    path = Path(path)
    try:
        las = laspy.read(str(path))
    except FileNotFoundError:
        raise ParameterError(f"no such file: {path}") from None
    except Exception as exc:
        raise LasFormatError(f"{path.name}: not a readable LAS/LAZ file ({exc})") from None
    names = list(las.point_format.extra_dimension_names)
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    flags = np.asarray(las[FLAGS], dtype=FLAGS_DTYPE) if FLAGS in names else np.zeros(
        len(xyz), FLAGS_DTYPE)
    scores = {
        n[: -len(SCORE_SUFFIX)]: np.asarray(las[n], dtype=np.float64)
        for n in names if n.endswith(SCORE_SUFFIX)
    }
    return ResultCloud(xyz, flags, scores, path.name)


def read_truth(path: str | Path, n: int) -> np.ndarray:
    """``is_outlier`` (n,) bool from a truth ``.npz``; refuses one of the wrong length."""
    path = Path(path)
    try:
        with np.load(path) as data:
            truth = np.asarray(data["is_outlier"], dtype=bool)
    except FileNotFoundError:
        raise ParameterError(f"no such truth file: {path}") from None
    except (KeyError, ValueError, OSError) as exc:
        raise ParameterError(f"{path.name}: not a truth file with is_outlier ({exc})") from None
    if truth.shape != (n,):
        raise ParameterError(
            f"{path.name} has {truth.size} truth values but the cloud has {n} points"
        )
    return truth


def find_statistics(result_path: str | Path) -> dict[str, Any] | None:
    """The statistics JSON beside a result file, if one of the usual names exists."""
    result_path = Path(result_path)
    stems = dict.fromkeys([result_path.stem, result_path.name.split(".")[0]])
    for pattern in STATS_NAMES:
        for stem in stems:
            candidate = result_path.with_name(pattern.format(stem=stem))
            if not candidate.is_file():
                continue
            try:
                data = json.loads(candidate.read_text())
            except (OSError, json.JSONDecodeError):
                continue
            if isinstance(data, dict) and "stages" in data:
                return data
    return None


def critical_values(
    detectors: list[str], statistics: dict[str, Any] | None
) -> dict[str, tuple[float | None, str]]:
    """Critical value per detector and where it came from ("statistics" or "default params").

    Without statistics the value is recomputed from the detector's default parameters: the
    normal quantile for ``temporal`` (eq. 17), t(k - 9) for ``patch`` (eq. 31); for ``section``
    and other detectors whose value depends on the data, the large-sample normal quantile.
    """
    out: dict[str, tuple[float | None, str]] = {}
    stages = (statistics or {}).get("stages", [])
    for stage in stages:
        name, crit = stage.get("detector"), stage.get("critical_value")
        if name in detectors and isinstance(crit, int | float):
            out[name] = (float(crit), "statistics")
    for name in detectors:
        if name not in out:
            out[name] = (_default_critical_value(name), "default params")
    return out


def _default_critical_value(name: str) -> float | None:
    from algorithms.stats import normal_critical_value, t_critical_value
    from lidar_outliers.detectors import DETECTORS

    if name not in DETECTORS:
        return None
    defaults = DETECTORS[name].parameters()
    alpha = getattr(defaults, "alpha", None)
    if alpha is None:
        return None
    k = getattr(defaults, "k", None)
    if name == "patch" and k is not None:
        return float(t_critical_value(alpha, k - 9))
    return normal_critical_value(alpha)


def categories(flags: np.ndarray, truth: np.ndarray | None) -> dict[str, np.ndarray]:
    """Point masks by colour category, background first (drawn first, underneath)."""
    flagged = flags != 0
    if truth is None:
        return {"kept": ~flagged, "flagged": flagged}
    return {
        "true negative": ~flagged & ~truth,
        "miss": ~flagged & truth,
        "false alarm": flagged & ~truth,
        "true positive": flagged & truth,
    }


def main_axis(xy: np.ndarray) -> np.ndarray:
    """Unit vector of the cloud's main horizontal direction (first principal axis of xy)."""
    if len(xy) < 2:
        return np.array([1.0, 0.0])
    centred = xy - xy.mean(axis=0)
    _, vecs = np.linalg.eigh(centred.T @ centred)
    axis = vecs[:, -1]
    return axis if axis[np.argmax(np.abs(axis))] > 0 else -axis


def render(
    result_path: str | Path,
    png_path: str | Path,
    *,
    truth_path: str | Path | None = None,
    stats_path: str | Path | None = None,
    seed: int = 0,
) -> Path:
    """Draw the picture of a result file into a PNG of FIGSIZE x DPI pixels; returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = read_result(result_path)
    truth = read_truth(truth_path, len(res.xyz)) if truth_path is not None else None
    if stats_path is not None:
        try:
            stats = json.loads(Path(stats_path).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ParameterError(f"cannot read statistics {stats_path}: {exc}") from None
    else:
        stats = find_statistics(result_path)
    cats = categories(res.flags, truth)
    rng = np.random.default_rng(seed)
    origin = res.xyz.min(axis=0) if len(res.xyz) else np.zeros(3)
    local = res.xyz - origin
    axis = main_axis(local[:, :2])
    along = local[:, :2] @ axis
    across = local[:, :2] @ np.array([-axis[1], axis[0]])

    fig = plt.figure(figsize=FIGSIZE, dpi=DPI)
    n_hist = max(1, len(res.scores))
    grid = fig.add_gridspec(3, n_hist, height_ratios=[3.0, 2.0, 2.0], hspace=0.45, wspace=0.3)
    top = fig.add_subplot(grid[0, :])
    side = fig.add_subplot(grid[1, :])
    for label, mask in cats.items():
        idx = np.flatnonzero(mask)
        if len(idx) > MAX_BACKGROUND:
            idx = np.sort(rng.choice(idx, MAX_BACKGROUND, replace=False))
        background = label in ("kept", "true negative")
        style = dict(s=0.3 if background else 3.0, c=COLOURS[label], linewidths=0,
                     rasterized=True, label=f"{label} ({int(mask.sum()):,})")
        top.scatter(along[idx], across[idx], **style)
        side.scatter(along[idx], local[idx, 2], **style)
    top.set_aspect("equal", adjustable="datalim")
    top.set_title(f"{res.name}: top-down view ({len(res.xyz):,} points)")
    top.set_xlabel("along the main axis (m)")
    top.set_ylabel("across (m)")
    top.legend(loc="upper right", markerscale=4, fontsize=8)
    side.set_title("side profile along the main axis")
    side.set_xlabel("along (m)")
    side.set_ylabel(f"z - ({origin[2]:.2f}) (m)")

    crits = critical_values(list(res.scores), stats)
    if not res.scores:
        ax = fig.add_subplot(grid[2, 0])
        ax.text(0.5, 0.5, "no detector scores in this file", ha="center", va="center")
        ax.set_axis_off()
    for i, (name, score) in enumerate(res.scores.items()):
        _histogram(fig.add_subplot(grid[2, i]), name, score, crits[name], truth)
    png_path = Path(png_path)
    with atomic_path(png_path) as tmp:
        fig.savefig(tmp, dpi=DPI, format="png")
    plt.close(fig)
    return png_path


def _histogram(ax, name: str, score: np.ndarray, crit: tuple[float | None, str],
               truth: np.ndarray | None) -> None:
    tested = np.isfinite(score)
    value, source = crit
    ax.set_title(f"{name} score ({int(tested.sum()):,} tested)", fontsize=10)
    if not tested.any():
        ax.text(0.5, 0.5, "not tested", ha="center", va="center", transform=ax.transAxes)
        return
    s = score[tested]
    upper = float(np.quantile(s, 0.999))
    if value is not None:  # keep the critical value readable: between 2x and 10x of it
        upper = min(max(upper, 2.0 * value), 10.0 * value)
    bins = np.linspace(0.0 if s.min() >= 0 else float(s.min()), upper, 60)
    clipped = np.clip(s, bins[0], bins[-1])
    if truth is None:
        ax.hist(clipped, bins=bins, color="#7f7f7f")
    else:
        t = truth[tested]
        ax.hist([clipped[~t], clipped[t]], bins=bins, stacked=True,
                color=["#9a9a9a", "#1f77b4"], label=["real", "outlier"])
        ax.legend(fontsize=7)
    ax.set_yscale("log")
    if value is not None:
        ax.axvline(value, color="#d62728", linestyle="--", linewidth=1.2)
        ax.text(value, 0.95, f" critical {value:.2f}\n ({source})", color="#d62728",
                fontsize=7, va="top", transform=ax.get_xaxis_transform())
    ax.set_xlabel("score (last bin holds everything above)", fontsize=8)


def render_preview(result_path: str | Path, png_path: str | Path) -> Path:
    """The service's preview picture of a job result (statistics.json beside it is used)."""
    return render(result_path, png_path)
