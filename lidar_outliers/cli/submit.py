"""`lidar-outliers submit IN --server URL --key KEY`: run a job on the service, wait for it and
fetch the flagged cloud and the statistics (through :class:`lidar_outliers.client.Client`).

The pipeline is given as for `detect` (``--params``, ``--detector NAME --opt V`` groups, the
pipeline flags) and checked here before the file is sent. ``--process NAME`` runs one detector's
process instead, with ``--params`` holding that process's inputs. Progress bars show on a
terminal only. A refused request or a failed job ends the command with the server's problem in
one line.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from lidar_outliers.atomic import write_json_atomic
from lidar_outliers.cli import EXIT_INTERRUPTED, fail
from lidar_outliers.cli.detect import (
    add_pipeline_arguments,
    build_params,
    read_params_document,
    split_argv,
)
from lidar_outliers.errors import ParameterError

__all__ = ["register", "split_argv"]

SERVER_ENV, KEY_ENV = "LIDAR_OUTLIERS_SERVER", "LIDAR_OUTLIERS_KEY"


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "submit",
        help="run a job on the service and download its result",
        description="Upload a LAS/LAZ file to the job service, run a pipeline on it, wait, and "
        "download the flagged cloud and the statistics. Prints the statistics JSON unless "
        "--stats is given.",
        epilog="example: lidar-outliers submit scan.laz --server http://127.0.0.1:8000 "
        "--detector temporal --sigma 0.01 --detector patch -o flagged.laz "
        f"(the key from {KEY_ENV})",
    )
    parser.add_argument("input", metavar="IN", help="input LAS or LAZ file")
    parser.add_argument("--server", metavar="URL", default=os.environ.get(SERVER_ENV),
                        help=f"the service, e.g. http://127.0.0.1:8000 (default ${SERVER_ENV})")
    parser.add_argument("--key", metavar="KEY", default=os.environ.get(KEY_ENV),
                        help=f"your API key (default ${KEY_ENV})")
    parser.add_argument("--process", metavar="NAME", default="pipeline",
                        help="the process to run (default pipeline; a detector's name runs it "
                        "alone, --params then holding its inputs)")
    add_pipeline_arguments(parser)
    parser.add_argument("-o", "--output", metavar="OUT",
                        help="where to write the flagged cloud; LAS or LAZ by its suffix "
                        "(default: IN's name with .flagged, in the current folder)")
    parser.add_argument("--keep", choices=["all", "inliers", "outliers"], default="all",
                        help="download all points (default) or only the inliers or outliers")
    parser.add_argument("--stats", metavar="FILE", help="write the statistics JSON here")
    parser.add_argument("--timeout", type=float, metavar="SECONDS",
                        help="give up waiting after this long (the job goes on)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(func=run)


def job_inputs(args: argparse.Namespace) -> dict[str, Any]:
    """The inputs of the execute request, checked with the models the server uses."""
    if args.process == "pipeline":
        return build_params(args).model_dump(mode="json", exclude_unset=True)
    if args.extra:
        raise ParameterError("--detector groups make a pipeline; leave out --process "
                             f"{args.process} or give its inputs with --params")
    if args.profile is not None:
        raise ParameterError("--profile chooses a default pipeline; it needs --process pipeline")
    inputs = read_params_document(args.params) if args.params else {}
    for field, value in (("classify", args.classify), ("noise_class", args.noise_class),
                         ("reference_classes", args.reference_classes)):
        if value is not None:
            inputs[field] = value
    return inputs


def run(args: argparse.Namespace) -> int:
    from lidar_outliers.client import Client

    if not args.server:
        raise ParameterError(f"--server is required (or set {SERVER_ENV})")
    if not args.key:
        raise ParameterError(f"--key is required (or set {KEY_ENV}); `lidar-outliers users add "
                             "NAME` makes one on the server")
    source = Path(args.input)
    if not source.is_file():
        raise ParameterError(f"no such file: {source}")
    if args.trajectory and not Path(args.trajectory).is_file():
        raise ParameterError(f"no such file: --trajectory {args.trajectory}")
    inputs = job_inputs(args)
    out = Path(args.output) if args.output else Path(f"{source.stem}.flagged{source.suffix}")
    shown = not args.quiet and sys.stderr.isatty()
    with Client(args.server, args.key) as api:
        with _bytes_bar(shown, f"upload {source.name}") as progress:
            job = api.submit(source, args.process, inputs, args.trajectory, progress=progress)
        job_id = job["jobID"]
        try:
            with _job_bar(shown, job_id) as callback:
                api.wait(job_id, callback, timeout=args.timeout)
        except KeyboardInterrupt:
            fail(f"interrupted; job {job_id} goes on on the server (DELETE /jobs/{job_id} "
                 "cancels it)", EXIT_INTERRUPTED)
        with _bytes_bar(shown, f"download {out.name}") as progress:
            api.download(job_id, out, keep=args.keep, progress=progress)
        stats = api.statistics(job_id)
    if args.stats:
        write_json_atomic(args.stats, stats)
    else:
        json.dump(stats, sys.stdout, indent=2)
        sys.stdout.write("\n")
    if shown:
        overall = stats.get("overall", {})
        sys.stderr.write(f"{out}: {overall.get('points_flagged', 0):,} of "
                         f"{overall.get('points', 0):,} points flagged (job {job_id})\n")
    return 0


@contextmanager
def _bytes_bar(shown: bool, what: str) -> Iterator[Callable[[int, int], None] | None]:
    """A progress callback drawing a bytes bar on a terminal; None elsewhere."""
    if not shown:
        yield None
        return
    from tqdm import tqdm

    bar = tqdm(desc=what, unit="B", unit_scale=True, unit_divisor=1024, file=sys.stderr,
               leave=False)

    def update(done: int, total: int) -> None:
        if total and bar.total != total:
            bar.total = total
        bar.update(done - bar.n)

    try:
        yield update
    finally:
        bar.close()


@contextmanager
def _job_bar(shown: bool, job_id: str) -> Iterator[Callable[[dict[str, Any]], None] | None]:
    """A callback drawing the job's progress (0-100 %) and status on a terminal."""
    if not shown:
        yield None
        return
    from tqdm import tqdm

    bar = tqdm(total=100, desc=f"job {job_id[:8]}", unit="%", file=sys.stderr, leave=False,
               bar_format="{l_bar}{bar}| {n:.0f}% [{elapsed}]")

    def update(doc: dict[str, Any]) -> None:
        bar.set_description_str(f"job {job_id[:8]} {doc['status']}", refresh=False)
        bar.update(max(0, int(doc.get("progress") or 0) - bar.n))

    try:
        yield update
    finally:
        bar.close()
