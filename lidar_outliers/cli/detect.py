"""`lidar-outliers detect IN -o OUT`: run a pipeline of detectors on a LAS/LAZ file locally.

Stages are given as groups ``--detector NAME [--option VALUE ...]`` (options generated from the
parameter models of the detectors), in pipeline order, or as a JSON document with ``--params``
(a file, or the object itself); ``--detector`` groups replace the pipeline of the document, the
other flags override its settings. Without a pipeline the sensor profile chooses one
(``--profile``, default auto from a sample of the file's points: spinning -> snow, airborne ->
detached, mobile -> transient then height_field, terrestrial -> height_field). ``--trajectory``
gives the platform's path (lines of ``time x y z``) so that ``transient``
also flags points other beams saw through.
"""

from __future__ import annotations

import argparse
import json
import sys
import typing
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from lidar_outliers.detectors import DETECTORS, get_detector
from lidar_outliers.errors import ParameterError
from lidar_outliers.params import PipelineParams

#: Keys of the pipeline document set by flags of their own.
_PIPELINE_FLAGS = {
    "classify": "--no-classify",
    "noise_class": "--noise-class",
    "reference_classes": "--reference-classes",
    "profile": "--profile",
}


def _option_names(field: str) -> list[str]:
    dashed = "--" + field.replace("_", "-")
    underscored = "--" + field
    return [dashed] if dashed == underscored else [dashed, underscored]


def _stage_parser(name: str) -> argparse.ArgumentParser:
    """A parser for one ``--detector NAME`` group; values stay text, pydantic converts them."""
    spec = get_detector(name)
    parser = argparse.ArgumentParser(prog=f"--detector {name}", add_help=False)
    for field in spec.model.model_fields:
        if field != "detector":
            parser.add_argument(*_option_names(field), dest=field, default=argparse.SUPPRESS)
    return parser


def _all_stage_options() -> dict[str, list[str]]:
    """Option string -> detectors that accept it."""
    owners: dict[str, list[str]] = {}
    for name, spec in DETECTORS.items():
        for field in spec.model.model_fields:
            if field != "detector":
                for option in _option_names(field):
                    owners.setdefault(option, []).append(name)
    return owners


def split_argv(argv: list[str]) -> tuple[list[str], list[tuple[str, dict[str, str]]]]:
    """Take the ``--detector NAME --opt V ...`` groups out of argv.

    Returns the remaining arguments (for argparse) and the stages as (name, {field: text}).
    """
    rest: list[str] = []
    stages: list[tuple[str, dict[str, str]]] = []
    owners = _all_stage_options()
    i = 0
    while i < len(argv):
        token = argv[i]
        if token == "--":
            rest.extend(argv[i:])
            break
        if token != "--detector" and not token.startswith("--detector="):
            rest.append(token)
            i += 1
            continue
        if token.startswith("--detector="):
            name, i = token.split("=", 1)[1], i + 1
        else:
            if i + 1 >= len(argv):
                known = ", ".join(DETECTORS)
                raise ParameterError(f"--detector needs a name (one of: {known})")
            name, i = argv[i + 1], i + 2
        group_end = i
        while group_end < len(argv) and not (
            argv[group_end] == "--detector" or argv[group_end].startswith("--detector=")
        ):
            group_end += 1
        values, leftover = _stage_parser(name).parse_known_args(argv[i:group_end])
        for item in leftover:
            option = item.split("=", 1)[0]
            if option in owners:
                raise ParameterError(
                    f"{option} is not a parameter of detector {name} (it belongs to "
                    f"{', '.join(owners[option])}); put it after --detector {owners[option][0]}"
                )
        rest.extend(leftover)
        stages.append((name, vars(values)))
        i = group_end
    return rest, stages


def _epilog() -> str:
    lines = ["detectors and their options (see `lidar-outliers detectors` for details):"]
    for name, spec in DETECTORS.items():
        opts = [
            f"{_option_names(f)[0]} (default {info.default})"
            for f, info in spec.model.model_fields.items()
            if f != "detector"
        ]
        lines.append(f"  --detector {name}: " + ", ".join(opts))
    lines += [
        "",
        "example: lidar-outliers detect in.laz -o out.laz --detector temporal --n1 5 --n2 5 "
        "--sigma 0.01 --detector patch --k 40",
    ]
    return "\n".join(lines)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "detect",
        help="flag outliers in a LAS/LAZ file (runs locally, no server needed)",
        description="Run a pipeline of detectors on a LAS/LAZ file and write the flagged cloud: "
        "the same points with extra dimensions outlier_flags and <detector>_score. Prints the "
        "statistics JSON.",
        epilog=_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("input", metavar="IN", help="input LAS or LAZ file")
    parser.add_argument("-o", "--output", required=True, metavar="OUT", help="output file")
    add_pipeline_arguments(parser)
    parser.add_argument("--stats", metavar="FILE", help="write the statistics JSON here")
    fmt = parser.add_mutually_exclusive_group()
    fmt.add_argument("--laz", dest="laz", action="store_true", default=None, help="write LAZ")
    fmt.add_argument("--las", dest="laz", action="store_false", help="write uncompressed LAS")
    parser.add_argument(
        "--tile-size", type=_tile_size, metavar="METRES",
        help="run tile by tile, square XY tiles of this edge (the same result as the whole cloud, "
        "memory set by the tile); default: files of over 2 M points (about 1.6 GB in memory "
        "whole) in tiles of about 600 k points, smaller ones whole",
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def _tile_size(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a positive number of metres, got {text}")
    return value


def add_pipeline_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that make the pipeline document (:func:`build_params` reads them); shared
    with `submit`."""
    parser.add_argument("--params", metavar="JSON|FILE",
                        help="pipeline parameters: a JSON file, or the JSON object itself")
    parser.add_argument(
        "--detector", metavar="NAME", action="append",
        help="start a pipeline stage (" + ", ".join(DETECTORS) + "); its options follow it; "
        "repeat for more stages",
    )
    parser.add_argument(
        "--trajectory", metavar="FILE",
        help="the platform's trajectory: text lines 'time x y z' (same time base and "
        "coordinates as the cloud; `lidar-outliers simulate` writes one beside the cloud). The "
        "transient detector then also flags points other beams saw through (see its "
        "--lever-arms)",
    )
    parser.add_argument(
        "--no-classify", dest="classify", action="store_false", default=None,
        help="leave the classification untouched",
    )
    parser.add_argument(
        "--noise-class", type=int, metavar="CLASS", help="class for flagged points (default 7)"
    )
    parser.add_argument(
        "--reference-classes", type=int, nargs="+", metavar="CLASS",
        help="input classes taken as truth (e.g. 7 18 for noise, 2 for ground): adds confusion "
        "counts to the statistics",
    )
    parser.add_argument(
        "--profile", choices=profile_choices(),
        help="sensor kind whose default pipeline runs when no --detector is given (default auto: "
        "from the evidence a sample of the file's points carries; spinning -> snow, airborne -> "
        "detached, mobile -> transient then height_field, terrestrial -> height_field)",
    )


def profile_choices() -> list[str]:
    """The values of ``--profile``: those of ``PipelineParams.profile``, so the two agree."""
    return list(typing.get_args(PipelineParams.model_fields["profile"].annotation))


def build_params(args: argparse.Namespace) -> PipelineParams:
    """The pipeline document from --params, the --detector groups and the other flags."""
    data = read_params_document(args.params) if args.params else {}
    stages = args.extra or []
    if stages:
        data["pipeline"] = [{"detector": name, **{k: _option_value(v) for k, v in values.items()}}
                            for name, values in stages]
    if args.classify is False:
        data["classify"] = False
    if args.noise_class is not None:
        data["noise_class"] = args.noise_class
    if args.reference_classes is not None:
        data["reference_classes"] = args.reference_classes
    if args.profile is not None:
        data["profile"] = args.profile
    try:
        return PipelineParams.model_validate(data)
    except ValidationError as exc:
        raise ParameterError(_message(exc, args, stages)) from None


def read_params_document(value: str) -> dict[str, Any]:
    """``--params``: the JSON object itself (text starting with ``{``) or a file holding one."""
    inline = value.lstrip().startswith("{")
    where = "--params" if inline else f"--params {value}"
    try:
        data = json.loads(value if inline else Path(value).read_text())
    except OSError as exc:
        raise ParameterError(f"cannot read --params {value}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise ParameterError(f"{where} is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ParameterError(f"{where} must hold a JSON object")
    return data


def _option_value(text: str) -> Any:
    """A list option (``--lever-arms '[[1, -0.6, 0.45, 0]]'``, ``--origin '[0, 0, 0]'``) as
    JSON; any other value stays text for pydantic to convert."""
    if text.lstrip().startswith("["):
        try:
            return json.loads(text)
        except json.JSONDecodeError:
            pass
    return text


def _message(exc: ValidationError, args: argparse.Namespace, stages: list) -> str:
    """Name the option (``--n1 of --detector temporal``) or the --params key that is wrong."""
    from lidar_outliers.params import validation_message

    err = exc.errors()[0]
    loc = [str(x) for x in err.get("loc", ())]
    text = validation_message(exc).split(": ", 1)[-1].split("; ")[0]
    if loc and loc[0] == "pipeline" and stages and len(loc) >= 2 and loc[1].isdigit():
        name = stages[int(loc[1])][0]
        field = loc[3] if len(loc) >= 4 else None
        if field and field != name:
            return f"{_option_names(field)[0]} of --detector {name}: {text}"
        return f"--detector {name}: {text}"
    if loc and loc[0] in _PIPELINE_FLAGS and getattr(args, loc[0], None) not in (None, True):
        return f"{_PIPELINE_FLAGS[loc[0]]}: {text}"
    where = ""
    if args.params:
        where = " in --params" if args.params.lstrip().startswith("{") else f" in {args.params}"
    return validation_message(exc) + where


def run(args: argparse.Namespace) -> int:
    from lidar_outliers.process import process_file

    params = build_params(args)
    out = Path(args.output)
    laz = args.laz
    if laz is None and out.suffix.lower() in (".laz", ".las"):
        laz = out.suffix.lower() == ".laz"
    with _progress_bar(enabled=not args.quiet and sys.stderr.isatty()) as progress:
        stats = process_file(args.input, out, params, laz=laz, progress=progress,
                             stats_path=args.stats, trajectory=args.trajectory,
                             tile_size=args.tile_size)
    if not args.stats:
        json.dump(stats, sys.stdout, indent=2)
        sys.stdout.write("\n")
    return 0


class _progress_bar:  # noqa: N801 - used as a context manager like a function
    """tqdm bar on a terminal; a no-op callback otherwise."""

    def __init__(self, enabled: bool) -> None:
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=100, unit="%", file=sys.stderr, leave=False,
                            bar_format="{l_bar}{bar}| {n:.0f}% [{elapsed}<{remaining}]")

    def __enter__(self):
        return self.update if self.bar is not None else None

    def update(self, fraction: float, message: str) -> None:
        assert self.bar is not None
        self.bar.set_description_str(message, refresh=False)
        self.bar.update(max(0.0, 100.0 * fraction - self.bar.n))

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.close()
