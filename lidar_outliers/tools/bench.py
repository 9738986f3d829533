"""`lidar-outliers bench`: accuracy and speed of every detector, as Markdown tables.

Sections, each skipped when its data is absent:

1. Simulated clouds A, B, C (:mod:`lidar_outliers.tools.simulator`, cached under ``.bench/``) on
   reporting seeds kept apart from the seeds detectors are tuned on: every outlier pipeline --
   the paper's ``temporal``, ``patch``, ``section`` and ``temporal->patch``, then every other
   outlier detector of :data:`lidar_outliers.detectors.DETECTORS` alone, then the default
   pipeline when it differs (also with the trajectory, the scanners' lever arms estimated from
   the points) -- in the layout of the paper's Tables 2-5 beside the published figures, plus
   precision, recall and F1;
   a summary against the targets and recall per condition and outlier kind.
2. ISPRS ground-filter samples: type I, type II, total error and kappa per sample and the mean,
   with the defaults (in sample) and leave-one-sample-out over a small parameter grid.
3. WADS snow frames: precision, recall, F1 (pooled and per frame) of each pipeline and of the
   baselines (DROR is a registered detector; Open3D's statistical/radius outlier removal when
   ``open3d`` is importable).
4. Real airborne tiles: per file, the profile chosen from its evidence and what the default
   pipeline then finds: recall on the ``gross`` points, false alarms on the unlabelled points,
   the labelled noise found, against the targets.
5. Speed on cloud A: points/s and peak RSS of one subprocess per detector; the whole temporal
   command against laspy's read and write of the same file, on cloud A of every reporting seed.

Pipelines run through :func:`~lidar_outliers.pipeline.run_pipeline`, the code the CLI and service
run.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lidar_outliers.errors import LidarOutliersError
from lidar_outliers.tools import paper

#: The shared real data: ``shared/data`` beside the checkout (or beside a parent folder of it).
SHARED_DATA = next((p / "shared" / "data" for p in Path(__file__).resolve().parents
                    if (p / "shared" / "data").is_dir()),
                   Path(__file__).resolve().parents[3] / "shared" / "data")
QUICK_SCALE, QUICK_SEEDS = 0.06, 1
FULL_SCALE, FULL_SEEDS = 1.0, 5
#: Seeds detectors may be tuned on (tests, development benchmarks); never reported.
TUNE_SEEDS = (0, 1, 2)
#: Reporting seeds are the first ones from here on that are not tuning seeds.
REPORT_BASE = 100
PAPER_PIPELINES = ("temporal", "patch", "section", "temporal->patch")
#: Targets on the simulated clouds: recall (overall and of every outlier kind) and false alarms
#: (% of the real points).
TARGET_RECALL, TARGET_FALSE_ALARM_PCT = 0.90, 0.05
#: Most points the quadric fits may leave untested, percent of the points a stage gets.
TARGET_UNTESTED_PCT = 0.5
#: Targets on every real airborne tile: recall on ``gross``, false alarms (% of unlabelled).
AIRBORNE_RECALL, AIRBORNE_FALSE_ALARM_PCT = 0.95, 0.1

Print = Callable[[str], None]


@dataclass
class BenchConfig:
    quick: bool = False
    seeds: int | None = None  # reporting seeds per condition
    scale: float | None = None
    tune_seeds: tuple[int, ...] = TUNE_SEEDS
    report_seeds: tuple[int, ...] | None = None  # chosen by the command when None
    fresh: bool = False  # draw the reporting seeds at random
    isprs: Path | None = None
    wads: Path | None = None
    airborne: Path | None = None
    cache: Path = Path(".bench")
    speed: bool = True
    command: str = ""

    @property
    def n_seeds(self) -> int:
        return self.seeds or (QUICK_SEEDS if self.quick else FULL_SEEDS)

    @property
    def sim_scale(self) -> float:
        return self.scale or (QUICK_SCALE if self.quick else FULL_SCALE)


def parse_seeds(spec: str) -> tuple[int, ...]:
    """Seeds from ``"0-2,7,10-12"`` (non-negative); ValueError naming the bad part."""
    seeds: list[int] = []
    for part in (p.strip() for p in spec.split(",")):
        try:
            lo, dash, hi = part.partition("-")
            a, b = int(lo), int(hi) if dash else int(lo)
        except ValueError:
            raise ValueError(f"not a seed or a range of seeds: {part!r}") from None
        if a < 0 or b < a:
            raise ValueError(f"not a seed or a range of seeds: {part!r}")
        seeds.extend(range(a, b + 1))
    return tuple(dict.fromkeys(seeds))


def seed_spec(seeds: tuple[int, ...] | list[int]) -> str:
    """``(0, 1, 2, 7)`` as ``"0-2, 7"``."""
    parts, run = [], []
    for x in sorted(seeds):
        if run and x == run[-1] + 1:
            run.append(x)
            continue
        if run:
            parts.append(f"{run[0]}-{run[-1]}" if len(run) > 2 else ", ".join(map(str, run)))
        run = [x]
    if run:
        parts.append(f"{run[0]}-{run[-1]}" if len(run) > 2 else ", ".join(map(str, run)))
    return ", ".join(parts)


def reporting_seeds(cfg: BenchConfig) -> tuple[int, ...]:
    """The seeds the simulated section reports on: never a tuning seed.

    Given ones are refused when they overlap the tuning seeds; ``fresh`` draws them at random
    (from the operating system's entropy, so each run meets surveys nobody tuned on); otherwise
    the first ``n_seeds`` from REPORT_BASE on that are not tuning seeds.
    """
    tune = set(cfg.tune_seeds)
    if cfg.report_seeds is not None:
        overlap = sorted(tune & set(cfg.report_seeds))
        if overlap:
            raise LidarOutliersError(f"reporting seeds {seed_spec(overlap)} are tuning seeds")
        return tuple(cfg.report_seeds)
    if cfg.fresh:
        rng = np.random.default_rng()
        out: list[int] = []
        while len(out) < cfg.n_seeds:
            x = int(rng.integers(1000, 2**31 - 1))
            if x not in tune and x not in out:
                out.append(x)
        return tuple(sorted(out))
    out = []
    x = REPORT_BASE
    while len(out) < cfg.n_seeds:
        if x not in tune:
            out.append(x)
        x += 1
    return tuple(out)


@dataclass
class Report:
    """The Markdown lines of every section, and the numbers behind them (JSON-able)."""

    lines: list[str] = field(default_factory=list)
    numbers: dict[str, Any] = field(default_factory=dict)

    def markdown(self) -> str:
        return "\n".join(self.lines) + "\n"


# --------------------------------------------------------------------------- pipelines


def outlier_pipelines() -> dict[str, list[str]]:
    """Pipelines to compare, by display name -> detector names in order.

    The paper's four first; then each other outlier detector in the registry alone (so new
    detectors appear without touching this file); then the default pipeline if it is new.
    """
    from lidar_outliers.detectors import DETECTORS
    from lidar_outliers.params import default_stages

    out = {name: name.split("->") for name in PAPER_PIPELINES}
    out = {k: v for k, v in out.items() if all(d in DETECTORS for d in v)}
    for name, spec in DETECTORS.items():
        if spec.kind == "outlier" and name not in out:
            out[name] = [name]
    default = [s.detector for s in default_stages(True)]
    key = "->".join(default)
    if key not in out:
        out[f"default ({key})"] = default
    if "transient" in default:  # the only detector that uses a trajectory (free-space evidence)
        out[f"default ({key}){WITH_TRAJECTORY}"] = default
    return out


#: Suffix of a pipeline name run with the simulator's trajectory file attached to the cloud.
WITH_TRAJECTORY = " + trajectory"


def with_simulated_trajectory(cloud, las_path: Path):
    """The cloud with the trajectory the simulator wrote beside it, or None when there is none."""
    from lidar_outliers.trajectory import read_trajectory

    path = las_path.with_suffix(".trajectory.txt")
    if not path.exists():
        return None
    return cloud.with_trajectory(read_trajectory(path))


def simulated_lever_arms(las_path: Path) -> list[list[float]] | None:
    """The scanners' lever arms from the truth file, as a system's calibration report gives
    them beside its trajectory ([point_source_id, forward, left, up] each)."""
    with np.load(las_path.with_suffix(".truth.npz")) as t:
        if "lever_arms" not in t:
            return None
        arms = np.asarray(t["lever_arms"], dtype=float)
    return [[int(a[0]), *(round(float(v), 6) for v in a[1:])] for a in arms]


@dataclass(frozen=True)
class PipelineRun:
    """A pipeline's outcome on one cloud: flags (n,) bool, flags per stage, seconds, and the
    run's statistics document."""

    flagged: np.ndarray
    per_stage: list[np.ndarray]
    seconds: float
    statistics: dict[str, Any]


def run_outlier_pipeline(cloud, stages: list[str], settings: dict[str, dict] | None = None
                         ) -> PipelineRun:
    """The pipeline of ``stages`` (all defaults) on ``cloud``.

    ``settings``: parameters for the stages of a detector (by name), e.g. the lever arms.
    """
    from lidar_outliers.detectors import DETECTORS
    from lidar_outliers.params import parse_pipeline_params
    from lidar_outliers.pipeline import run_pipeline

    settings = settings or {}
    params = parse_pipeline_params({
        "pipeline": [{"detector": d, **settings.get(d, {})} for d in stages],
        "classify": False})
    start = time.perf_counter()
    result = run_pipeline(cloud, params)
    seconds = time.perf_counter() - start
    per_stage = [(result.flags & DETECTORS[d].flag_bit) != 0 for d in stages]
    return PipelineRun(result.flags != 0, per_stage, seconds, result.statistics)


def untested_points(statistics: dict[str, Any]) -> dict[str, dict[str, int]]:
    """Per stage that reports untested points (the quadric fits of ``patch`` and ``section``):
    the points it got and the untested ones by reason, from a run's statistics."""
    out = {}
    for entry in statistics.get("stages", []):
        info = entry.get("info") or {}
        if isinstance(info.get("points_untested"), dict):
            out[entry["detector"]] = {"points_in": int(entry["points_in"]),
                                      **{k: int(v) for k, v in info["points_untested"].items()}}
    return out


# --------------------------------------------------------------------------- simulated clouds


@functools.cache
def simulator_version() -> str:
    """Short hash of the simulator's source: a changed simulator never reuses a stale cache
    (taken once per run, as the modules were loaded)."""
    from lidar_outliers.tools import simulator

    digest = hashlib.sha1()
    for path in sorted(Path(simulator.__file__).parent.glob("*.py")):
        digest.update(path.name.encode() + path.read_bytes())
    return digest.hexdigest()[:10]


def simulated_cloud(cache: Path, condition: str, seed: int, scale: float) -> Path:
    """Path of the cached simulated LAS (written on first use)."""
    from lidar_outliers.tools.simulator import simulate, stem, write_simulation

    folder = cache / "sim" / simulator_version() / f"scale{scale:g}"
    las = folder / f"{stem(condition, seed)}.las"
    if not (las.exists() and las.with_suffix(".truth.npz").exists()):
        write_simulation(simulate(condition, seed, scale), folder)
    return las


def _pooled_confusion(truth: list[np.ndarray], flagged: list[np.ndarray]) -> dict[str, Any]:
    from algorithms.metrics import outlier_confusion

    return outlier_confusion(np.concatenate(truth), np.concatenate(flagged))


def bench_simulated(cfg: BenchConfig, report: Report, say: Print) -> dict[str, Path]:
    """Section 1, on the reporting seeds. Returns the path of cloud A per seed (the speed
    section uses the first)."""
    from lidar_outliers.lasio import read_cloud

    pipelines = outlier_pipelines()
    seeds = list(reporting_seeds(cfg))
    truth: dict[str, list[np.ndarray]] = {c: [] for c in paper.CLOUDS}
    kinds: dict[str, list[np.ndarray]] = {c: [] for c in paper.CLOUDS}
    flags: dict[tuple[str, str], list[np.ndarray]] = {}
    stage_flags: dict[tuple[str, str], list[list[np.ndarray]]] = {}
    seconds: dict[tuple[str, str], float] = {}
    points: dict[str, int] = dict.fromkeys(paper.CLOUDS, 0)
    systems: dict[int, dict[str, dict]] = {}
    a_paths: dict[str, Path] = {}
    kind_names: list[str] = []
    failed: dict[str, str] = {}
    untested: dict[tuple[str, str, str], dict[str, int]] = {}
    for cond in paper.CLOUDS:
        for seed in seeds:
            path = simulated_cloud(cfg.cache, cond, seed, cfg.sim_scale)
            if cond == "A":
                a_paths[str(seed)] = path
            cloud = read_cloud(path)
            with np.load(path.with_suffix(".truth.npz")) as t:
                truth[cond].append(np.asarray(t["is_outlier"], dtype=bool))
                kinds[cond].append(np.asarray(t["kind"], dtype=np.uint8))
                kind_names = [str(k) for k in t["kind_names"]]
                if "facts" in t:
                    systems.setdefault(seed, {})[cond] = json.loads(str(t["facts"]))
            points[cond] += len(cloud)
            tracked = with_simulated_trajectory(cloud, path)  # lever arms: from the points
            for name, stages in pipelines.items():
                with_traj = name.endswith(WITH_TRAJECTORY)
                run_on = tracked if with_traj else cloud
                if name in failed or run_on is None:
                    continue
                say(f"  {cond} seed {seed}: {name}")
                try:
                    run = run_outlier_pipeline(run_on, stages)
                except LidarOutliersError as exc:  # e.g. a detector needing another dimension
                    failed[name] = f"{type(exc).__name__}: {exc}"
                    continue
                flags.setdefault((name, cond), []).append(run.flagged)
                stage_flags.setdefault((name, cond), []).append(run.per_stage)
                seconds[(name, cond)] = seconds.get((name, cond), 0.0) + run.seconds
                for stage, counts in untested_points(run.statistics).items():
                    total = untested.setdefault((name, stage, cond), {})
                    for key, value in counts.items():
                        total[key] = total.get(key, 0) + value
    n = len(seeds)
    report.lines += [
        "## Simulated clouds A, B, C",
        "",
        f"Surveys drawn from the simulator's family (`lidar-outliers simulate`, scale "
        f"{cfg.sim_scale:g}): tuned on seeds {seed_spec(cfg.tune_seeds)}, reported on seeds "
        f"{seed_spec(seeds)}. Every seed draws its own scanners, mounting, rates, street, drive "
        "and outlier mix (the systems below); the conditions keep the paper's outlier shares. "
        "Detector defaults may be tuned on the tuning seeds only, so these are surveys they "
        "have not seen. Counts are per cloud, averaged over the seeds; percentages and "
        "precision/recall/F1 are pooled over the seeds. *paper* = Leslar, Wang & Hu (2010).",
        "",
        "| Table 1 | A ours | A paper | B ours | B paper | C ours | C paper |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    row_pts, row_out, row_pct = ["Total No. of Points"], ["Total No. of Outliers"], [
        "Total % of Points Which are Outliers"]
    for c in paper.CLOUDS:
        t = np.concatenate(truth[c])
        row_pts += [f"{points[c] / n:,.0f}", f"{paper.TABLE1[c]['points']:,}"]
        row_out += [f"{t.sum() / n:,.0f}", f"{paper.TABLE1[c]['outliers']:,}"]
        row_pct += [f"{100 * t.mean():.2f}", f"{paper.TABLE1[c]['pct_outliers']:.2f}"]
    report.lines += [_row(r) for r in (row_pts, row_out, row_pct)] + [""]
    report.lines += _systems_table(systems)
    summary = []
    numbers: dict[str, Any] = {}
    kind_numbers: dict[str, Any] = {}
    for name in failed:
        report.lines += [f"### {name}", "", f"Not run on the simulated clouds: {failed[name]}", ""]
    pipelines = {k: v for k, v in pipelines.items() if k not in failed and (k, "A") in flags}
    for name, stages in pipelines.items():
        table_name, published = paper.BY_PIPELINE.get(name, ("", None))
        title = f"### {name}" + (f" (paper's {table_name})" if table_name else " (not in paper)")
        report.lines += [title, "", "| | A ours | A paper | B ours | B paper | C ours | C paper |",
                         "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
        conf = {c: _pooled_confusion(truth[c], flags[(name, c)]) for c in paper.CLOUDS}
        numbers[name] = conf
        rows = _confusion_rows(conf, published, n)
        if len(stages) == 2:
            rows = _stage_rows(stages, truth, stage_flags, name, published, n) + rows
        report.lines += [_row(r) for r in rows] + [""]
        for c in paper.CLOUDS:
            real = conf[c]["points"] - conf[c]["outliers"]
            fa_pct = 100.0 * conf[c]["non_outliers_identified"] / max(real, 1)
            by_kind = _recall_by_kind(flags[(name, c)], kinds[c], kind_names)
            kind_numbers.setdefault(name, {})[c] = by_kind
            summary.append((name, c, conf[c], fa_pct, by_kind, seconds[(name, c)] / n))
    report.lines += [
        "### Summary against the targets",
        "",
        f"Reporting seeds {seed_spec(seeds)}. Target on every cloud: recall >= "
        f"{100 * TARGET_RECALL:.0f} %, recall of every outlier kind >= "
        f"{100 * TARGET_RECALL:.0f} % and false alarms <= {TARGET_FALSE_ALARM_PCT} % of the real "
        "(non-outlier) points.",
        "",
        "| pipeline | cloud | recall % | false alarms % of real | precision % | F1 | "
        "lowest kind recall % | seconds | target |",
        "| --- | --- | ---: | ---: | ---: | ---: | --- | ---: | --- |",
    ]
    targets: dict[str, Any] = {}
    for name, c, conf, fa_pct, by_kind, sec in summary:
        recall = conf["recall"]
        worst = min(by_kind.items(), key=lambda kv: kv[1]["recall"]) if by_kind else None
        met = (recall is not None and recall >= TARGET_RECALL
               and fa_pct <= TARGET_FALSE_ALARM_PCT
               and all(v["recall"] >= TARGET_RECALL for v in by_kind.values()))
        targets.setdefault(name, {})[c] = {"recall": recall, "false_alarm_pct": fa_pct,
                                           "met": bool(met)}
        lowest = f"{_pct(worst[1]['recall'])} ({worst[0]})" if worst else "—"
        report.lines.append(_row([
            name, c, _pct(recall), f"{fa_pct:.3f}", _pct(conf["precision"]), _f(conf["f1"]),
            lowest, f"{sec:.1f}", "met" if met else "not met",
        ]))
    report.lines.append("")
    report.lines += _kind_tables(pipelines, kind_numbers)
    report.lines += _untested_table(untested)
    report.numbers["simulated"] = {
        "scale": cfg.sim_scale, "tune_seeds": list(cfg.tune_seeds), "report_seeds": seeds,
        "pipelines": numbers, "kinds": kind_numbers, "targets": targets,
    }
    return a_paths


def _untested_table(untested: dict[tuple[str, str, str], dict[str, int]]) -> list[str]:
    """Points the quadric fits left untested, per pipeline stage and cloud, by reason, pooled
    over the seeds (target: fewer than ``TARGET_UNTESTED_PCT`` %)."""
    if not untested:
        return []
    reasons = sorted({k for counts in untested.values() for k in counts if k != "points_in"})
    lines = [
        "### Points the quadric fits left untested",
        "",
        f"Pooled over the reporting seeds; % of the points the stage got. Target: fewer than "
        f"{TARGET_UNTESTED_PCT} % untested on every cloud.",
        "",
        "| pipeline | stage | cloud | points | untested % | "
        + " | ".join(f"{r} %" for r in reasons) + " | target |",
        "| --- | --- | --- | ---: | ---: | " + " | ".join("---:" for _ in reasons) + " | --- |",
    ]
    for (name, stage, cond), counts in untested.items():
        points = max(counts["points_in"], 1)
        share = {r: 100.0 * counts.get(r, 0) / points for r in reasons}
        total = sum(share.values())
        lines.append(_row([name, stage, cond, f"{counts['points_in']:,}", f"{total:.3f}",
                           *(f"{share[r]:.3f}" for r in reasons),
                           "met" if total < TARGET_UNTESTED_PCT else "not met"]))
    return [*lines, ""]


def _recall_by_kind(flags: list[np.ndarray], kinds: list[np.ndarray], kind_names: list[str]
                    ) -> dict[str, dict[str, float]]:
    """Recall and count of every outlier kind present (pooled over the seeds)."""
    f, k = np.concatenate(flags), np.concatenate(kinds)
    out = {}
    for code in range(1, len(kind_names)):
        m = k == code
        if m.any():
            out[kind_names[code]] = {"recall": float(np.mean(f[m])), "count": int(m.sum())}
    return out


def _systems_table(systems: dict[int, dict[str, dict]]) -> list[str]:
    """One row per reporting seed: the drawn system, and per condition its rate setting,
    drive and strip (the conditions share system and street, not rates and drive)."""
    if not systems:
        return []
    lines = [
        "### Systems of the reporting seeds",
        "",
        "Per condition: pulse rate per scanner (kHz), cruise speeds (m/s), stops, strip (m).",
        "",
        "| seed | layout | scanners | mirror Hz | range noise mm | A | B | C |",
        "| --- | --- | ---: | --- | ---: | --- | --- | --- |",
    ]
    for seed, by_cond in sorted(systems.items()):
        first = next(iter(by_cond.values()))["system"]
        cells = [str(seed), first["layout"], str(len(first["scanners"])),
                 "/".join(f"{s['scan_hz']:.0f}" for s in first["scanners"]),
                 f"{1000 * first['range_sigma']:.1f}"]
        for c in paper.CLOUDS:
            f = by_cond.get(c)
            if f is None:
                cells.append("—")
                continue
            khz = "/".join(f"{s['pulse_hz'] / 1000:.0f}" for s in f["system"]["scanners"])
            speeds = "/".join(f"{v:.1f}" for v in f["drive"]["cruise_speeds"])
            cells.append(f"{khz} kHz, {speeds} m/s, {len(f['drive']['stops'])} stop(s), "
                         f"{f['street']['strip_length']:.1f} m")
        lines.append(_row(cells))
    return lines + [""]


def _kind_tables(pipelines, kind_numbers) -> list[str]:
    """Recall per outlier kind, one table per condition (reporting seeds pooled)."""
    lines = ["### Recall by outlier kind, per condition", ""]
    for c in paper.CLOUDS:
        first = kind_numbers[next(iter(pipelines))][c] if pipelines else {}
        if not first:  # every pipeline sees the same truth: the same kinds
            continue
        lines += [
            f"Cloud {c} (points of each kind in brackets):",
            "",
            "| pipeline | " + " | ".join(f"{k} ({v['count']:,})" for k, v in first.items())
            + " |",
            "| --- |" + " ---: |" * len(first),
        ]
        for p in pipelines:
            lines.append(_row([p] + [_pct(kind_numbers[p][c][k]["recall"]) for k in first]))
        lines.append("")
    return lines


_ROWS = (
    ("No. of Outliers Identified", "outliers_identified", "count"),
    ("No. of Non-Outliers Identified", "non_outliers_identified", "count"),
    ("No. of Outliers Missed", "outliers_missed", "count"),
    ("% of Outliers Identified", "pct_outliers_identified", "pct"),
    ("% of Point Cloud Identified", "pct_cloud_identified", "pct"),
    ("% of Point Cloud Identified Incorrectly", "pct_cloud_identified_incorrectly", "pct"),
    ("Precision %", "precision", "frac"),
    ("Recall %", "recall", "frac"),
    ("F1", "f1", "f1"),
)


def _confusion_rows(conf, published, n_seeds) -> list[list[str]]:
    rows = []
    for label, key, kind in _ROWS:
        row = [label]
        for c in paper.CLOUDS:
            ours = conf[c][key]
            theirs = (published or {}).get(c, {}).get(key)
            if kind == "count":
                row += [f"{ours / n_seeds:,.0f}", "—" if theirs is None else f"{theirs:,}"]
            elif kind == "pct":
                row += [_num(ours, 2), "—" if theirs is None else f"{theirs:.2f}"]
            else:  # precision/recall/F1 from the paper's counts where it gives them
                row += [_pct(ours) if kind == "frac" else _f(ours),
                        _paper_ratio(key, (published or {}).get(c), kind, c)]
        rows.append(row)
    return rows


def _stage_rows(stages, truth, stage_flags, name, published, n) -> list[list[str]]:
    """Table 5's per-routine rows: outliers and non-outliers identified by each stage."""
    rows = []
    for key_kind, label_kind in (("outliers_identified", "No. of Outliers Identified"),
                                 ("non_outliers_identified", "No. of Non-Outliers Identified")):
        for i, (det, letter) in enumerate(zip(stages, "ab", strict=False)):
            row = [f"{label_kind} - {det}"]
            for c in paper.CLOUDS:
                t = np.concatenate(truth[c])
                f = np.concatenate([s[i] for s in stage_flags[(name, c)]])
                count = int(np.count_nonzero(f & (t if key_kind.startswith("outliers") else ~t)))
                theirs = (published or {}).get(c, {}).get(f"{key_kind}_{letter}")
                row += [f"{count / n:,.0f}", "—" if theirs is None else f"{theirs:,}"]
            rows.append(row)
    return rows


def _paper_ratio(key: str, pub: dict | None, kind: str, cloud: str) -> str:
    """Precision, recall or F1 from the paper's counts (recall against Table 1's outliers, as
    the paper's own percentages are; its missed counts do not always add up to Table 1)."""
    if not pub:
        return "—"
    tp, fp = pub["outliers_identified"], pub["non_outliers_identified"]
    precision = tp / (tp + fp) if tp + fp else None
    recall = tp / paper.TABLE1[cloud]["outliers"]
    f1 = 2 * precision * recall / (precision + recall) if precision and recall else None
    value = {"precision": precision, "recall": recall, "f1": f1}[key]
    return _pct(value) if kind == "frac" else _f(value)


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _num(v, digits: int) -> str:
    return "—" if v is None else f"{v:.{digits}f}"


def _pct(v) -> str:
    return "—" if v is None else f"{100 * v:.1f}"


def _f(v) -> str:
    return "—" if v is None else f"{v:.3f}"


# --------------------------------------------------------------------------- ISPRS


def las_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in (".las", ".laz"))


#: PDAL 2.10's SMRF with its default options on the seven shared samples: mean total error %.
SMRF_MEAN_TOTAL_ERROR = 4.65
#: The grid of leave-one-sample-out: the ground filter's main parameters, a few values each.
LOO_GRID: dict[str, tuple[float, ...]] = {
    "slope_threshold": (25.0, 30.0, 35.0, 40.0),
    "terrain_slope": (0.15, 0.2, 0.3),
    "ground_tolerance": (0.3, 0.5, 0.8),
}


def loo_choices(errors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-sample-out from a (configurations, samples) matrix of total errors.

    For each sample the configuration with the least mean error over the other samples (the
    first on ties). Returns the chosen configuration index and its error on the held-out sample,
    both (samples,).
    """
    n_cfg, n_smp = errors.shape
    chosen = np.empty(n_smp, np.int64)
    for s in range(n_smp):
        others = np.delete(errors, s, axis=1)
        chosen[s] = int(np.argmin(others.mean(axis=1)))
    return chosen, errors[chosen, np.arange(n_smp)]


def bench_isprs(folder: Path, report: Report, say: Print) -> None:
    """Section 2: the ground filter on every LAS/LAZ file of ``folder`` (class 2 = truth).

    In sample: the defaults on each sample through the pipeline. Leave-one-sample-out: every
    configuration of :data:`LOO_GRID` on every sample, then for each sample the configuration
    best on the others, scored on it.
    """
    import itertools

    from algorithms.ground import GroundParameters, classify_ground
    from algorithms.metrics import ground_scores
    from lidar_outliers.lasio import read_cloud
    from lidar_outliers.params import parse_pipeline_params
    from lidar_outliers.pipeline import run_pipeline

    files = las_files(folder)
    if not files:
        return
    report.lines += [
        "## ISPRS ground-filter samples",
        "",
        f"`ground` on {len(files)} sample(s) of `{folder}` (incoming classification reset; "
        "reference ground = class 2). *In sample*: the defaults, chosen on these samples. "
        "*LOO* (leave one sample out): for each sample the configuration of the grid below with "
        "the least mean total error on the other samples, scored on the held-out one. "
        f"PDAL 2.10's SMRF with its defaults: mean total error {SMRF_MEAN_TOTAL_ERROR} % on the "
        "seven samples (no per-sample figures).",
        "",
        "| sample | points | type I % | type II % | total error % | kappa % | LOO type I % | "
        "LOO type II % | LOO total % | LOO kappa % | LOO choice | seconds |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: |",
    ]
    params = parse_pipeline_params({"pipeline": [{"detector": "ground"}], "classify": True})
    defaults = GroundParameters().as_dict()
    keys_grid = list(LOO_GRID)
    configs = [dict(zip(keys_grid, v, strict=True))
               for v in itertools.product(*LOO_GRID.values())]
    rows, grid_scores = [], []
    loo_on = len(files) >= 2  # leave-one-out needs another sample to choose on
    for path in files:
        say(f"  ISPRS {path.name}")
        cloud = read_cloud(path)
        truth = cloud.classification == 2
        cloud.classification[:] = 0
        start = time.perf_counter()
        result = run_pipeline(cloud, params)
        sec = time.perf_counter() - start
        rows.append((path.stem, ground_scores(truth, result.classification == 2), sec))
        if not loo_on:
            continue
        say(f"  ISPRS {path.name}: LOO grid of {len(configs)} configurations")
        grid_scores.append([
            ground_scores(truth, classify_ground(cloud.xyz, **{**defaults, **c}).is_ground)
            for c in configs])
    keys = ("type_i_pct", "type_ii_pct", "total_error_pct", "kappa_pct")
    if loo_on:
        errors = np.array([[g[c]["total_error_pct"] for g in grid_scores]
                           for c in range(len(configs))])
        chosen, _ = loo_choices(errors)
        loo = [grid_scores[s][chosen[s]] for s in range(len(files))]
    else:
        errors, chosen = np.zeros((len(configs), 1)), np.zeros(len(files), np.int64)
        loo = [dict.fromkeys(keys) for _ in files]
    for (name, scores, sec), held, c in zip(rows, loo, chosen, strict=True):
        choice = ", ".join(f"{k} {configs[c][k]:g}" for k in keys_grid) if loo_on else "—"
        report.lines.append(_row([
            name, f"{scores['points']:,}", *(_num(scores[k], 2) for k in keys),
            *(_num(held[k], 2) for k in keys), choice, f"{sec:.1f}",
        ]))
    means = {k: _mean([r[1][k] for r in rows]) for k in keys}
    loo_means = {k: _mean([h[k] for h in loo]) for k in keys}
    report.lines += [_row(["**mean**", f"{sum(r[1]['points'] for r in rows):,}"]
                          + [_num(means[k], 2) for k in keys]
                          + [_num(loo_means[k], 2) for k in keys]
                          + ["", f"{sum(r[2] for r in rows):.1f}"]), ""]
    best_all = int(np.argmin(errors.mean(axis=1)))
    default_idx = next((i for i, c in enumerate(configs)
                        if all(c[k] == defaults[k] for k in keys_grid)), None)
    same = int(np.count_nonzero(chosen == default_idx)) if default_idx is not None else 0
    report.lines += [] if not loo_on else [
        "LOO grid: " + "; ".join(f"`{k}` in {{{', '.join(f'{v:g}' for v in vals)}}}"
                                 for k, vals in LOO_GRID.items())
        + f" ({len(configs)} configurations; the other parameters at their defaults). "
        f"Best on all {len(files)} samples: "
        + ", ".join(f"{k} {configs[best_all][k]:g}" for k in keys_grid)
        + f" (mean total error {errors[best_all].mean():.2f} %). The held-out samples chose the "
        f"defaults {same} of {len(files)} times; the gap between the in-sample and the LOO mean "
        f"({means['total_error_pct']:.2f} % vs {loo_means['total_error_pct']:.2f} %) is what "
        "choosing the defaults on these samples gains over a choice made without each sample.",
        "",
    ]
    report.numbers["isprs"] = {
        "samples": {r[0]: r[1] for r in rows}, "mean": means,
        "loo": {"grid": {k: list(v) for k, v in LOO_GRID.items()},
                "samples": {r[0]: {**h, "choice": configs[c]}
                            for r, h, c in zip(rows, loo, chosen, strict=True)},
                "mean": loo_means},
        "smrf_mean_total_error_pct": SMRF_MEAN_TOTAL_ERROR,
    }


def _mean(values: list) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


# --------------------------------------------------------------------------- real outliers


def baselines() -> dict[str, Callable[[Any], np.ndarray]]:
    """Outlier filters from outside the project: Open3D's SOR/ROR when ``open3d`` is installed
    (an optional package; DROR is a registered detector and runs as a pipeline).

    Each takes a Cloud and returns flagged (n,) bool.
    """
    out: dict[str, Callable[[Any], np.ndarray]] = {}
    try:
        import open3d as o3d  # noqa: F401
    except ImportError:
        return out
    out["Open3D statistical (20, 2.0)"] = _open3d_statistical
    out["Open3D radius (3 in 0.5 m)"] = _open3d_radius
    return out


def _open3d_cloud(cloud):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(cloud.xyz)
    return pcd


def _open3d_statistical(cloud) -> np.ndarray:
    _, keep = _open3d_cloud(cloud).remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
    flagged = np.ones(len(cloud), dtype=bool)
    flagged[np.asarray(keep, dtype=int)] = False
    return flagged


def _open3d_radius(cloud) -> np.ndarray:
    _, keep = _open3d_cloud(cloud).remove_radius_outlier(nb_points=3, radius=0.5)
    flagged = np.ones(len(cloud), dtype=bool)
    flagged[np.asarray(keep, dtype=int)] = False
    return flagged


def _labelled_files(folder: Path) -> list[tuple[Path, Path]]:
    pairs = []
    for path in las_files(folder):
        truth = path.with_name(path.name.split(".")[0] + ".truth.npz")
        if truth.exists():
            pairs.append((path, truth))
    return pairs


def run_default_pipeline(cloud, facts) -> tuple[str, np.ndarray, float]:
    """What a job naming no pipeline runs on this file: (row name, flags (n,) bool, seconds)."""
    from lidar_outliers.params import parse_pipeline_params
    from lidar_outliers.pipeline import run_pipeline

    params = parse_pipeline_params({"classify": False})
    start = time.perf_counter()
    result = run_pipeline(cloud, params, facts=facts)
    seconds = time.perf_counter() - start
    stats = result.statistics
    stages = "->".join(stage["detector"] for stage in stats["stages"])
    return f"default: {stats.get('profile', '?')} profile ({stages})", result.flags != 0, seconds


def _all_methods(cloud, say: Print, label: str, facts=None):
    """(name, flagged, seconds) for every outlier pipeline and baseline on one cloud.

    The default pipeline is the one the file's profile chooses (``facts``: its header facts),
    not the mobile default that the simulated section shows.
    """
    say(f"  {label}: default pipeline")
    yield run_default_pipeline(cloud, facts)
    for name, stages in outlier_pipelines().items():
        if name.startswith("default ("):
            continue
        say(f"  {label}: {name}")
        try:
            run = run_outlier_pipeline(cloud, stages)
        except Exception as exc:  # e.g. temporal on a file without gps_time
            yield name, None, f"{type(exc).__name__}: {exc}"
            continue
        yield name, run.flagged, run.seconds
    for name, fn in baselines().items():
        say(f"  {label}: {name}")
        start = time.perf_counter()
        try:
            flagged = fn(cloud)
        except Exception as exc:  # a baseline with another signature must not end the run
            yield name, None, f"{type(exc).__name__}: {exc}"
            continue
        yield name, flagged, time.perf_counter() - start


#: How the snow detector's defaults were chosen on the WADS frames (printed with the table).
WADS_TUNING = ("`snow`'s defaults (intensity 0, k_min 4, multiplier 4, 0.2 degrees) were chosen "
               "on all three frames together: no frame is held out, so every F1 here is in "
               "sample.")


def bench_wads(folder: Path, report: Report, say: Print) -> None:
    """Section 3: falling snow; precision, recall and F1 pooled over the frames and F1 per
    frame."""
    from algorithms.metrics import outlier_confusion
    from lidar_outliers.lasio import inspect_las, read_cloud

    pairs = _labelled_files(folder)
    if not pairs:
        return
    pooled: dict[str, list] = {}
    frames: list[str] = []
    for path, truth_path in pairs:
        cloud = read_cloud(path)
        cloud.classification[:] = 0
        with np.load(truth_path) as t:
            truth = np.asarray(t["is_outlier"], dtype=bool)
        facts = inspect_las(path)
        frames.append(path.stem)
        for name, flagged, sec in _all_methods(cloud, say, path.stem, facts):
            entry = pooled.setdefault(name, [[], [], 0.0, None, {}])
            if flagged is None:
                entry[3] = sec
                continue
            entry[0].append(truth)
            entry[1].append(flagged)
            entry[2] += sec
            entry[4][path.stem] = outlier_confusion(truth, flagged)
    report.lines += [
        "## WADS: falling snow",
        "",
        f"{len(pairs)} frame(s) of `{folder}`; snow (label 110) is the outlier class; precision, "
        "recall and F1 pooled over the frames, then F1 per frame. Target: F1 >= 0.95 without a "
        f"learned model. {WADS_TUNING}",
        "",
        "| method | precision % | recall % | F1 | " + " | ".join(f"F1 {f}" for f in frames)
        + " | seconds |",
        "| --- | ---: | ---: | ---: | " + " | ".join("---:" for _ in frames) + " | ---: |",
    ]
    numbers = {}
    for name, (ts, fs, sec, error, per_frame) in pooled.items():
        if not ts:
            report.lines.append(_row([name, "—", "—", "—", *("—" for _ in frames),
                                      f"failed: {error}"]))
            continue
        conf = outlier_confusion(np.concatenate(ts), np.concatenate(fs))
        numbers[name] = {**conf, "frames": per_frame}
        report.lines.append(_row([
            name, _pct(conf["precision"]), _pct(conf["recall"]), _f(conf["f1"]),
            *(_f(per_frame[f]["f1"]) if f in per_frame else "—" for f in frames), f"{sec:.1f}",
        ]))
    report.lines.append("")
    report.numbers["wads"] = numbers


def gaps_to_unlabelled(xyz: np.ndarray, labelled: np.ndarray, missed: np.ndarray
                       ) -> np.ndarray:
    """Distance (metres, ascending) from each ``missed`` point to the nearest point that is
    not ``labelled``: how far a missed outlier stands from the real returns around it."""
    from scipy.spatial import cKDTree

    real = xyz[~labelled]
    if not missed.any() or len(real) == 0:
        return np.zeros(0)
    dist, _ = cKDTree(real).query(xyz[missed])
    return np.sort(dist)


def bench_airborne(folder: Path, report: Report, say: Print) -> None:
    """Section 4: one row per labelled airborne file: the profile chosen from the file's
    evidence, then what the default pipeline finds (recall on ``gross``, false alarms on the
    unlabelled points, labelled noise found) and the seconds both took; a line on the targets."""
    from lidar_outliers.lasio import inspect_las, read_cloud
    from lidar_outliers.params import parse_pipeline_params
    from lidar_outliers.pipeline import run_pipeline
    from lidar_outliers.profiles import choose_profile, file_evidence

    pairs = _labelled_files(folder)
    if not pairs:
        return
    report.lines += [
        "## Real airborne tiles",
        "",
        f"Every labelled file of `{folder}`: the profile chosen automatically from the evidence "
        "of a sample of its points, then the default pipeline of that profile (classification "
        "reset first). Gross = labelled points more than 1 m below or 20 m above the local "
        "ground; false alarms = flagged points the producer did not label; labelled = all the "
        f"producer's noise. Targets: recall on gross >= {100 * AIRBORNE_RECALL:.0f} %, false "
        f"alarms <= {AIRBORNE_FALSE_ALARM_PCT} % of the unlabelled points, on every file. "
        "*Missed gross, m to an unlabelled return*: for each gross point not found, the "
        "distance to the nearest point the producer did not label (a missed point a few "
        "decimetres from the producer's own ground or vegetation returns is not detached from "
        "them).",
        "",
        "| file | points | points/m2 | profile (evidence; confidence) | gross found | recall % | "
        "false alarms | % of unlabelled | labelled found | missed gross, m to an unlabelled "
        "return | seconds | targets |",
        "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | --- | ---: | --- |",
    ]
    params = parse_pipeline_params({"classify": False})
    numbers: dict[str, Any] = {}
    verdicts = []
    for path, truth_path in pairs:
        say(f"  airborne {path.name}")
        start = time.perf_counter()
        facts = inspect_las(path)
        evidence = file_evidence(path, facts.to_dict())
        choice = choose_profile(evidence)
        cloud = read_cloud(path)
        cloud.classification[:] = 0
        result = run_pipeline(cloud, params, facts=facts, evidence=evidence)
        seconds = time.perf_counter() - start
        flagged = result.flags != 0
        with np.load(truth_path) as t:
            gross = np.asarray(t["gross"], dtype=bool)
            labelled = np.asarray(t["is_outlier"], dtype=bool)
        found = int(np.count_nonzero(flagged & gross))
        gaps = gaps_to_unlabelled(cloud.xyz, labelled, gross & ~flagged)
        recall = found / gross.sum() if gross.any() else None
        fa = int(np.count_nonzero(flagged & ~labelled))
        fa_pct = 100.0 * fa / max(int((~labelled).sum()), 1)
        met = (recall is None or recall >= AIRBORNE_RECALL) and fa_pct <= AIRBORNE_FALSE_ALARM_PCT
        verdicts.append((path.stem, met, recall, fa_pct))
        density = evidence.get("points_per_m2")
        numbers[path.stem] = {
            "points": len(cloud), "points_per_m2": density, "profile": choice.profile,
            "profile_basis": choice.basis, "profile_confidence": choice.confidence,
            "gross": int(gross.sum()), "gross_found": found, "recall": recall,
            "false_alarms": fa, "false_alarm_pct": fa_pct,
            "labelled": int(labelled.sum()),
            "labelled_found": int(np.count_nonzero(flagged & labelled)), "seconds": seconds,
            "missed_gross_gaps_m": [round(float(g), 3) for g in gaps],
        }
        report.lines.append(_row([
            path.name, f"{len(cloud):,}", "—" if density is None else f"{density:.2f}",
            f"{choice.profile} ({choice.basis}; {choice.confidence})",
            f"{found} / {int(gross.sum())}", _pct(recall), f"{fa:,}", f"{fa_pct:.3f}",
            f"{numbers[path.stem]['labelled_found']} / {int(labelled.sum())}",
            ", ".join(f"{g:.2f}" for g in gaps) or "—", f"{seconds:.1f}",
            "met" if met else "not met",
        ]))
    met_count = sum(v[1] for v in verdicts)
    missed = [f"{name} (recall {_pct(recall)} %, false alarms {fa_pct:.3f} %)"
              for name, ok, recall, fa_pct in verdicts if not ok]
    report.lines += [
        "",
        f"Targets met on {met_count} of {len(verdicts)} files"
        + (f"; not met on {', '.join(missed)}." if missed else "."),
        "",
    ]
    report.numbers["airborne"] = numbers


# --------------------------------------------------------------------------- speed


def measure_speed(detector: str, path: Path) -> dict[str, Any]:
    """Run one detector on one file in this process: points, seconds and memory.

    A warm-up run on the first 2,000 points comes first so numba compilation is not timed.
    Memory: ``rss_before_mb`` is the resident set once the cloud is read, ``run_peak_rss_mb``
    the largest resident set sampled (every 5 ms) during the timed run, ``peak_rss_mb`` the
    process's high-water mark (VmHWM; reading the file may set it).
    """
    import threading

    import psutil

    from lidar_outliers.detectors import DETECTORS
    from lidar_outliers.lasio import read_cloud

    spec = DETECTORS[detector]
    cloud = read_cloud(path)
    params = spec.parameters()
    spec.run(cloud.subset(np.arange(min(2000, len(cloud)))), params)
    proc = psutil.Process()
    rss_before = proc.memory_info().rss / 2**20
    peak = [rss_before]
    done = threading.Event()

    def sample() -> None:
        while not done.wait(0.005):
            peak[0] = max(peak[0], proc.memory_info().rss / 2**20)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    start = time.perf_counter()
    cpu = time.process_time()
    try:
        spec.run(cloud, params)
    finally:
        seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
        done.set()
        sampler.join()
    return {
        "detector": detector,
        "points": len(cloud),
        "seconds": seconds,
        "cpu_seconds": cpu,
        "rss_before_mb": rss_before,
        "run_peak_rss_mb": max(peak[0], proc.memory_info().rss / 2**20),
        "peak_rss_mb": _high_water_mb(),
    }


def _high_water_mb() -> float:
    """This process's peak resident set since it started its program: VmHWM on Linux. Not
    getrusage's ru_maxrss, which a child keeps from its parent across exec (the speed table
    showed the bench's own peak in every row)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kilobytes
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


def bench_speed(path: Path, report: Report, say: Print) -> None:
    """Section 5: one fresh subprocess per detector on cloud A (so RSS peaks do not mix)."""
    from lidar_outliers.detectors import DETECTORS

    rows = []
    for name in DETECTORS:
        say(f"  speed: {name}")
        proc = subprocess.run(
            [sys.executable, "-m", "lidar_outliers.tools.bench", "speed-worker", name, str(path)],
            capture_output=True, text=True, env={**os.environ, "PYTHONPATH": _project_root()},
        )
        if proc.returncode != 0:
            tail = (proc.stderr.strip().splitlines() or ["failed"])[-1]
            rows.append(_row([name, "—", "—", "—", "—", "—", "—", f"failed: {tail}"]))
            continue
        m = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(_row([
            name, f"{m['points']:,}", f"{m['seconds']:.2f}",
            f"{m['points'] / max(m['seconds'], 1e-9):,.0f}", f"{m['rss_before_mb']:.0f}",
            f"{m['run_peak_rss_mb']:.0f}",
            f"{m['run_peak_rss_mb'] - m['rss_before_mb']:.0f}", f"{m['peak_rss_mb']:.0f}",
        ]))
        report.numbers.setdefault("speed", {})[name] = m
    report.lines += [
        "## Speed on cloud A",
        "",
        f"`{path.name}` ({_cpu_note()}); each detector in its own subprocess after a warm-up "
        "on 2,000 points (numba compiled). RSS read = resident set with the cloud loaded; run "
        "peak = largest resident set sampled every 5 ms while the detector ran; added = the "
        "difference (the detector's own working memory); high-water = the subprocess's "
        "peak resident set since it started (VmHWM; reading the file may set it).",
        "",
        "| detector | points | seconds | points/s | RSS read MB | run peak MB | added MB | "
        "high-water MB |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        *rows,
        "",
    ]
    patch = report.numbers.get("speed", {}).get("patch")
    if patch:
        rate = patch["points"] / max(patch["seconds"], 1e-9)
        report.lines += [f"`patch`: {rate:,.0f} points/s; target >= {PATCH_TARGET:,} points/s: "
                         f"{'met' if rate >= PATCH_TARGET else 'not met'}.", ""]


#: Targets of the speed section: points per second of ``patch``; the whole temporal command's
#: wall time at most this many times that of reading and writing the file with laspy.
PATCH_TARGET = 50_000
COMMAND_TARGET = 3.0
#: Alternate runs of each command per cloud (the minimum is reported).
COMMAND_RUNS = 3


def bench_command(paths: list[Path], report: Report, say: Print) -> None:
    """The whole ``lidar-outliers detect --detector temporal`` command against the smallest
    laspy command that reads and writes the same file, each a fresh process (interpreter,
    imports, I/O), run alternately ``COMMAND_RUNS`` times per cloud after one warm-up each."""
    rows, ratios = [], []
    with tempfile.TemporaryDirectory(prefix="bench_command_") as tmp:
        for path in paths:
            say(f"  command: {path.name}")
            ours = [sys.executable, "-m", "lidar_outliers", "detect", str(path), "-o",
                    str(Path(tmp) / "ours.las"), "-q", "--detector", "temporal"]
            plain = [sys.executable, "-c", "import sys, laspy; "
                     "laspy.read(sys.argv[1]).write(sys.argv[2])", str(path),
                     str(Path(tmp) / "laspy.las")]
            walls: dict[str, list[float]] = {"ours": [], "laspy": []}
            for i in range(COMMAND_RUNS + 1):  # the first round warms the page cache
                for key, command in (("ours", ours), ("laspy", plain)):
                    wall = _command_seconds(command)
                    if i:
                        walls[key].append(wall)
            ratio = min(walls["ours"]) / min(walls["laspy"])
            ratios.append(ratio)
            rows.append(_row([path.name, f"{_points_in(path):,}", f"{min(walls['ours']):.2f}",
                              f"{min(walls['laspy']):.2f}", f"{ratio:.2f}x"]))
    worst = max(ratios)
    report.numbers["command"] = {"ratios": ratios}
    report.lines += [
        "## The temporal command against laspy I/O",
        "",
        f"Cloud A of each reporting seed ({_cpu_note()}): `lidar-outliers detect IN -o OUT "
        "--detector temporal` against `python -c \"laspy.read(IN).write(OUT)\"`, each a fresh "
        f"process, run alternately {COMMAND_RUNS} times after a warm-up; the least wall time of "
        f"each. Target: at most {COMMAND_TARGET:g}x on every cloud.",
        "",
        "| cloud | points | command s | laspy s | ratio |",
        "| --- | ---: | ---: | ---: | ---: |",
        *rows,
        "",
        f"Largest ratio {worst:.2f}x: {'met' if worst <= COMMAND_TARGET else 'not met'}.",
        "",
    ]


def _command_seconds(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True,
                   env={**os.environ, "PYTHONPATH": _project_root()})
    return time.perf_counter() - start


def _points_in(path: Path) -> int:
    import laspy

    with laspy.open(str(path)) as reader:
        return int(reader.header.point_count)


def _project_root() -> str:
    root = str(Path(__file__).resolve().parents[2])
    old = os.environ.get("PYTHONPATH")
    return root if not old else f"{root}{os.pathsep}{old}"


def _cpu_note() -> str:
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float("nan")
    return f"{os.cpu_count()} CPU(s), load average {load:.1f} at the start"


# --------------------------------------------------------------------------- the whole run


def default_folder(name: str, quick: bool) -> Path | None:
    """The shared data folder ``name`` when present (not in quick mode, which stays short)."""
    folder = SHARED_DATA / name
    return folder if folder.is_dir() and not quick else None


def run_bench(cfg: BenchConfig, say: Print = print) -> Report:
    report = Report()
    report.lines += [
        "# lidar-outliers benchmark",
        "",
        f"Command: `{cfg.command or 'lidar-outliers bench'}`",
        "",
        "Every table below comes from one run of this command. Simulated clouds are generated by "
        "`lidar-outliers simulate`; real data are read from `../shared/data/` when present.",
        "",
    ]
    start = time.perf_counter()
    say("simulated clouds")
    a_paths = bench_simulated(cfg, report, say)
    for label, folder, fn in (("ISPRS", cfg.isprs, bench_isprs), ("WADS", cfg.wads, bench_wads),
                              ("airborne", cfg.airborne, bench_airborne)):
        if folder is not None:
            say(label)
            fn(folder, report, say)
    if cfg.speed and a_paths:
        say("speed")
        bench_speed(next(iter(a_paths.values())), report, say)
        bench_command(list(a_paths.values()), report, say)
    report.lines.append(f"Total benchmark time: {time.perf_counter() - start:.0f} s.")
    return report


def _speed_worker(argv: list[str]) -> int:
    print(json.dumps(measure_speed(argv[0], Path(argv[1]))))
    return 0


if __name__ == "__main__":
    if len(sys.argv) >= 4 and sys.argv[1] == "speed-worker":
        sys.exit(_speed_worker(sys.argv[2:]))
    sys.exit("usage: python -m lidar_outliers.tools.bench speed-worker DETECTOR FILE")
