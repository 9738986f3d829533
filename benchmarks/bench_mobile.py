"""Recall, false alarms and speed of the mobile-mapping detectors on simulated clouds A, B, C.

    .venv/bin/python benchmarks/bench_mobile.py                      # full size, seeds 0 1 2
    .venv/bin/python benchmarks/bench_mobile.py --scale 0.2 --seeds 0  # quick look

Each cloud is generated in memory by :func:`~lidar_outliers.tools.simulator.simulate`
(the same physics as ``lidar-outliers simulate``). Detectors, all at their defaults:

- ``height_field`` (:mod:`algorithms.height_field`), geometry only;
- ``free_space`` (:mod:`algorithms.free_space`), with each point's scanner position taken
  from the simulated trajectory and the drawn system's lever arms, as a mobile-mapping system
  delivers them;
- ``transient`` (:mod:`algorithms.transient`), coordinates and GPS times only;
- ``mobile`` = a point flagged by any of them (the proposed default for mobile-mapping files);
- ``no_trajectory`` = height_field or transient (what runs when no trajectory comes with a file).

Prints per condition and seed: points, outliers, recall and false alarms (% of the real points)
for each detector, the union's recall per outlier kind, and points per second; then the pooled
figures per condition against the targets (recall >= 90 %, false alarms <= 0.05 %).
``--markdown FILE`` writes the same tables as Markdown. Numba compilation is done (and cached) on
a small cloud before the timed runs.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from algorithms.free_space import detect_free_space, scanner_origins  # noqa: E402
from algorithms.height_field import detect_height_field  # noqa: E402
from algorithms.transient import detect_transient  # noqa: E402
from lidar_outliers.tools.simulator import KIND_NAMES, simulate  # noqa: E402

TARGET_RECALL = 90.0
TARGET_FALSE_ALARM = 0.05


def run_one(condition: str, seed: int, scale: float) -> dict:
    """Simulate one cloud and score the detectors; returns a row of numbers."""
    cloud = simulate(condition, seed, scale)
    out = cloud.is_outlier
    row: dict = {"condition": condition, "seed": seed, "points": len(cloud),
                 "outliers": int(out.sum())}
    start = time.perf_counter()
    hf = detect_height_field(cloud.xyz, gps_time=cloud.gps_time)
    row["height_field_s"] = time.perf_counter() - start
    start = time.perf_counter()
    arms = {a[0]: a[1:] for a in cloud.lever_arms()}  # the system's calibration
    origin = scanner_origins(cloud.gps_time, cloud.point_source_id, cloud.trajectory, arms)
    fs = detect_free_space(cloud.xyz, origin, gps_time=cloud.gps_time)
    row["free_space_s"] = time.perf_counter() - start
    start = time.perf_counter()
    tr = detect_transient(cloud.xyz, cloud.gps_time, cloud.point_source_id)
    row["transient_s"] = time.perf_counter() - start
    flags = {"height_field": hf.flagged, "free_space": fs.flagged, "transient": tr.flagged,
             "mobile": hf.flagged | fs.flagged | tr.flagged,
             "no_trajectory": hf.flagged | tr.flagged}
    for name, f in flags.items():
        row[f"{name}_tp"] = int((f & out).sum())
        row[f"{name}_fp"] = int((f & ~out).sum())
    kinds = {}
    for code in np.unique(cloud.kind[out]):
        m = cloud.kind == code
        kinds[KIND_NAMES[code]] = (int((flags["mobile"] & m).sum()), int(m.sum()))
    row["kinds"] = kinds
    row["sigma_mm"] = 1000.0 * hf.info["sigma"]
    return row


def pct(a: int, b: int) -> float:
    return 100.0 * a / b if b else float("nan")


def table(rows: list[dict]) -> list[str]:
    head = ("| cloud | points | outliers | height_field recall / FA % | free_space recall / FA % "
            "| transient recall / FA % | mobile recall / FA % | no_trajectory recall / FA % "
            "| mobile recall per kind | height_field pts/s | free_space pts/s | transient pts/s |")
    lines = [head, "|" + " --- |" * 12]
    for r in rows:
        real = r["points"] - r["outliers"]
        cells = [f"{r['condition']}_{r['seed']}", f"{r['points']:,}", f"{r['outliers']:,}"]
        for name in ("height_field", "free_space", "transient", "mobile", "no_trajectory"):
            cells.append(f"{pct(r[name + '_tp'], r['outliers']):.1f} / "
                         f"{pct(r[name + '_fp'], real):.4f}")
        cells.append(", ".join(f"{k} {tp}/{n}" for k, (tp, n) in r["kinds"].items()))
        cells.append(f"{r['points'] / r['height_field_s']:,.0f}")
        cells.append(f"{r['points'] / r['free_space_s']:,.0f}")
        cells.append(f"{r['points'] / r['transient_s']:,.0f}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def pooled(rows: list[dict]) -> list[str]:
    lines = ["| condition | detectors | recall % | false alarms % | recall >= 90 % "
             "| false alarms <= 0.05 % |", "|" + " --- |" * 6]
    for name in ("mobile", "no_trajectory"):
        for cond in sorted({r["condition"] for r in rows}):
            rs = [r for r in rows if r["condition"] == cond]
            tp = sum(r[f"{name}_tp"] for r in rs)
            fp = sum(r[f"{name}_fp"] for r in rs)
            n_out = sum(r["outliers"] for r in rs)
            real = sum(r["points"] - r["outliers"] for r in rs)
            rec, fa = pct(tp, n_out), pct(fp, real)
            lines.append(f"| {cond} ({len(rs)} seeds) | {name} | {rec:.1f} | {fa:.4f} | "
                         f"{'met' if rec >= TARGET_RECALL else 'NOT met'} | "
                         f"{'met' if fa <= TARGET_FALSE_ALARM else 'NOT met'} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--conditions", default="ABC", help="conditions to run (default ABC)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--scale", type=float, default=1.0, help="simulator scale (default 1)")
    parser.add_argument("--markdown", type=Path, help="also write the tables to this file")
    args = parser.parse_args(argv)

    run_one("C", 0, 0.05)  # compile (and cache) the numba kernels outside the timings
    rows = []
    for cond in args.conditions:
        for seed in args.seeds:
            row = run_one(cond, seed, args.scale)
            rows.append(row)
            print(f"{cond}_{seed}: {row['points']:,} points, sigma {row['sigma_mm']:.2f} mm, "
                  f"mobile recall {pct(row['mobile_tp'], row['outliers']):.1f} %, "
                  f"false alarms {row['mobile_fp']}", flush=True)
    text = ["", *table(rows), "", *pooled(rows), ""]
    print("\n".join(text))
    if args.markdown:
        command = "    .venv/bin/python benchmarks/bench_mobile.py " + " ".join(
            argv if argv is not None else sys.argv[1:])
        args.markdown.write_text("\n".join([command, *text]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
