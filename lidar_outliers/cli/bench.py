"""`lidar-outliers bench`: accuracy on simulated and real clouds, and speed, as Markdown tables."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from lidar_outliers.errors import ParameterError

NONE = "none"


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="benchmark the detectors on simulated clouds A, B, C and on real data",
        description="Simulate (or reuse, cached under --cache) the paper's clouds A, B and C, run "
        "every outlier pipeline and print the paper's Tables 2-5 beside the published figures; "
        "then the ground filter on ISPRS samples, snow frames, airborne gross outliers and the "
        "speed of each detector. Real-data folders default to ../shared/data/* when present "
        f"(not with --quick); pass '{NONE}' to skip one.",
    )
    parser.add_argument("--quick", action="store_true",
                        help="small clouds, one seed, no default real-data folders (< 1 minute)")
    parser.add_argument("--markdown", type=Path, metavar="FILE",
                        help="also write the tables as Markdown to FILE")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the numbers as JSON")
    parser.add_argument("--seeds", type=int, help="seeds per condition (default 3, quick 1)")
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
    for opt in ("seeds", "scale", "isprs", "wads", "airborne", "markdown", "json"):
        value = getattr(args, opt)
        if value is not None:
            parts += [f"--{opt}", str(value)]
    if args.cache != Path(".bench"):
        parts += ["--cache", str(args.cache)]
    if args.no_speed:
        parts.append("--no-speed")
    return shlex.join(parts)


def run(args: argparse.Namespace) -> int:
    import json

    from lidar_outliers.tools.bench import BenchConfig, run_bench

    if args.seeds is not None and not 1 <= args.seeds <= 100:
        raise ParameterError(f"--seeds must be between 1 and 100, got {args.seeds}")
    if args.scale is not None and not 0.01 <= args.scale <= 1.0:
        raise ParameterError(f"--scale must be between 0.01 and 1, got {args.scale}")
    cfg = BenchConfig(
        quick=args.quick,
        seeds=args.seeds,
        scale=args.scale,
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
