"""`lidar-outliers bench`: accuracy on simulated and real clouds, and speed, as Markdown tables."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from lidar_outliers.errors import ParameterError

NONE = "none"
#: Mirrors :data:`lidar_outliers.tools.bench.REPORT_BASE` (the tools module loads on run).
REPORT_BASE = 100


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="benchmark the detectors on simulated clouds A, B, C and on real data",
        description="Simulate (or reuse, cached under --cache) the paper's clouds A, B and C on "
        "reporting seeds apart from the tuning seeds, run every outlier pipeline and print the "
        "paper's Tables 2-5 beside the published figures, the targets and recall per outlier "
        "kind; then the ground filter on ISPRS samples, snow frames, airborne gross outliers "
        "and the speed of each detector. Real-data folders default to ../shared/data/* when "
        f"present (not with --quick); pass '{NONE}' to skip one.",
    )
    parser.add_argument("--quick", action="store_true",
                        help="small clouds, one seed, no default real-data folders (< 1 minute)")
    parser.add_argument("--markdown", type=Path, metavar="FILE",
                        help="also write the tables as Markdown to FILE")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the numbers as JSON")
    parser.add_argument("--seeds", type=int,
                        help="reporting seeds per condition (default 5, quick 1); the command "
                        f"takes the first ones from {REPORT_BASE} on that are not tuning seeds")
    parser.add_argument("--tune-seeds", metavar="SEEDS", default=None,
                        help="seeds the detectors were tuned on, never reported, e.g. 0-2,7 "
                        "(default 0-2)")
    parser.add_argument("--report-seeds", metavar="SEEDS", default=None,
                        help="report on exactly these seeds (e.g. to repeat a --fresh run); "
                        "refused if one is a tuning seed")
    parser.add_argument("--fresh", action="store_true",
                        help="draw the reporting seeds at random (printed in the report)")
    parser.add_argument("--scale", type=float,
                        help="simulation scale 0.01-1 (default 1, quick 0.06)")
    for name in ("isprs", "wads", "airborne"):
        parser.add_argument(f"--{name}", metavar="DIR",
                            help=f"folder of {name} files (default ../shared/data/{name})")
    parser.add_argument("--cache", type=Path, default=Path(".bench"),
                        help="where simulated clouds are kept (default .bench)")
    parser.add_argument("--no-speed", action="store_true", help="skip the speed section")
    parser.set_defaults(func=run)


def _folder(value: str | None, name: str, quick: bool) -> Path | None:
    from lidar_outliers.tools.bench import default_folder

    if value is None:
        return default_folder(name, quick)
    if value.lower() == NONE:
        return None
    path = Path(value)
    if not path.is_dir():
        raise ParameterError(f"--{name}: no such folder: {value}")
    return path


def command_line(args: argparse.Namespace) -> str:
    """The command as given (rebuilt from the parsed options, so it is exact under any caller)."""
    parts = ["lidar-outliers", "bench"]
    if args.quick:
        parts.append("--quick")
    for opt in ("seeds", "tune_seeds", "report_seeds", "scale", "isprs", "wads", "airborne",
                "markdown", "json"):
        value = getattr(args, opt)
        if value is not None:
            parts += [f"--{opt.replace('_', '-')}", str(value)]
    if args.fresh:
        parts.append("--fresh")
    if args.cache != Path(".bench"):
        parts += ["--cache", str(args.cache)]
    if args.no_speed:
        parts.append("--no-speed")
    return shlex.join(parts)


def run(args: argparse.Namespace) -> int:
    import json

    from lidar_outliers.tools.bench import TUNE_SEEDS, BenchConfig, parse_seeds, run_bench

    if args.seeds is not None and not 1 <= args.seeds <= 100:
        raise ParameterError(f"--seeds must be between 1 and 100, got {args.seeds}")
    if args.scale is not None and not 0.01 <= args.scale <= 1.0:
        raise ParameterError(f"--scale must be between 0.01 and 1, got {args.scale}")
    seeds = {}
    for opt in ("tune_seeds", "report_seeds"):
        value = getattr(args, opt)
        try:
            seeds[opt] = parse_seeds(value) if value is not None else None
        except ValueError as exc:
            raise ParameterError(f"--{opt.replace('_', '-')}: {exc}") from None
    tune = seeds["tune_seeds"] if seeds["tune_seeds"] is not None else TUNE_SEEDS
    report = seeds["report_seeds"]
    if report is not None:
        if args.fresh:
            raise ParameterError("--report-seeds and --fresh exclude each other")
        overlap = sorted(set(report) & set(tune))
        if overlap:
            raise ParameterError(f"--report-seeds: {', '.join(map(str, overlap))} "
                                 "also tuning seed(s); report on surveys nobody tuned on")
    cfg = BenchConfig(
        quick=args.quick,
        seeds=args.seeds,
        scale=args.scale,
        tune_seeds=tune,
        report_seeds=report,
        fresh=args.fresh,
        isprs=_folder(args.isprs, "isprs", args.quick),
        wads=_folder(args.wads, "wads", args.quick),
        airborne=_folder(args.airborne, "airborne", args.quick),
        cache=args.cache,
        speed=not args.no_speed,
        command=command_line(args),
    )

    def say(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    report = run_bench(cfg, say)
    text = report.markdown()
    sys.stdout.write(text)
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(text)
    if args.json:
        args.json.write_text(json.dumps(report.numbers, indent=2, default=str) + "\n")
    return 0
