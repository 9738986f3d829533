"""`lidar-outliers plot`: a picture of a result file (top-down, side profile, score histograms)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "plot",
        help="draw a result file: views coloured by flag and score histograms",
        description="Draw a top-down view and a side profile of a result file coloured by flag "
        "(with --truth: true positive / false alarm / miss) and a histogram of each detector's "
        "score against its critical value.",
    )
    parser.add_argument("result", type=Path, help="result LAS/LAZ written by `detect`")
    parser.add_argument("--truth", type=Path, help="truth .npz with is_outlier per point")
    parser.add_argument("--stats", type=Path,
                        help="statistics JSON (default: one beside the result, if any)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="PNG to write")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lidar_outliers.tools.plot import render

    path = render(args.result, args.output, truth_path=args.truth, stats_path=args.stats)
    print(path)
    return 0
