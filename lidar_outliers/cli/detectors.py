"""`lidar-outliers detectors`: the detectors with their parameters, defaults, ranges and meaning."""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
from typing import Any

from pydantic import BaseModel

from algorithms.params import type_name
from lidar_outliers.detectors import DETECTORS, parameter_table
from lidar_outliers.params import PipelineParams


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "detectors",
        help="list the detectors and their parameters",
        description="List every detector with its parameters, defaults, ranges and descriptions "
        "(the same models the web service publishes under /processes).",
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    parser.set_defaults(func=run)


def listing() -> dict[str, Any]:
    """Detectors and pipeline-level settings as plain data."""
    detectors = {
        name: {
            "kind": spec.kind,
            "outlier_flags_bit": spec.flag_bit,
            "score_dimension": spec.score_dimension,
            "needs": list(spec.needs),
            "summary": spec.summary,
            "description": spec.description,
            "parameters": parameter_table(spec),
        }
        for name, spec in DETECTORS.items()
    }
    pipeline = model_table(PipelineParams)
    return {"detectors": detectors, "pipeline": pipeline}


def run(args: argparse.Namespace) -> int:
    data = listing()
    if args.json:
        json.dump(data, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    out = []
    for name, det in data["detectors"].items():
        if det["kind"] == "outlier":
            bit, score = det["outlier_flags_bit"], det["score_dimension"]
            role = f"bit {bit} of outlier_flags, score {score}"
        else:
            role = "writes class 2 (ground) / 1 (other) to unflagged points"
        needs = f"; needs {', '.join(det['needs'])}" if det["needs"] else ""
        out.append(f"{name}  ({role}{needs})")
        out.append(textwrap.indent(textwrap.fill(det["description"], 96), "  "))
        out += _rows(det["parameters"], option_prefix="--")
        out.append("")
    out.append("pipeline settings (--params JSON keys; flags of `detect`):")
    out += _rows(data["pipeline"], option_prefix="")
    sys.stdout.write("\n".join(out) + "\n")
    return 0


def model_table(model: type[BaseModel]) -> list[dict[str, Any]]:
    """Name, type, default, range and description of each field of a pydantic model."""
    rows = []
    for name, info in model.model_fields.items():
        bounds = [f"{symbol} {getattr(meta, attr)}" for meta in info.metadata
                  for attr, symbol in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<"))
                  if getattr(meta, attr, None) is not None]
        rows.append({"name": name, "type": type_name(info.annotation), "default": info.default,
                     "range": " and ".join(bounds) or None,
                     "description": info.description or ""})
    return rows


def _rows(params: list[dict[str, Any]], option_prefix: str) -> list[str]:
    lines = []
    for p in params:
        name = option_prefix + (p["name"].replace("_", "-") if option_prefix else p["name"])
        default = json.dumps(p["default"])
        rng = f"  range {p['range']}" if p["range"] else ""
        lines.append(f"    {name:<20} {p['type']:<28} default {default}{rng}")
        lines.append(textwrap.indent(textwrap.fill(p["description"], 88), " " * 8))
    return lines
