"""The JSON schemas of OGC API - Processes - Part 1: Core 1.0 (tests/data/ogc-schemas, see its
README), as validators: their relative ``$ref``s resolve inside that folder, never over the
network. They are OpenAPI 3.0 schema objects, read as JSON Schema draft 4 (boolean
``exclusiveMinimum``; ``nullable`` and ``example`` are annotations)."""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

import jsonschema
import yaml
from referencing import Registry, Resource
from referencing.jsonschema import DRAFT4

FOLDER = Path(__file__).resolve().parent / "data" / "ogc-schemas"
BASE = "https://schemas.opengis.net/ogcapi/processes/part1/1.0/openapi/schemas/"


@cache
def registry() -> Registry:
    resources = [(BASE + path.name, Resource.from_contents(
        yaml.safe_load(path.read_text(encoding="utf-8")), default_specification=DRAFT4))
        for path in sorted(FOLDER.glob("*.yaml"))]

    def refuse(uri: str) -> Resource:  # only the copied files: no network
        raise LookupError(f"{uri} is not in {FOLDER}")

    return Registry(retrieve=refuse).with_resources(resources)


def validator(name: str) -> jsonschema.Draft4Validator:
    """A validator of the schema in ``<name>.yaml`` (e.g. ``statusInfo``)."""
    return jsonschema.Draft4Validator({"$ref": BASE + name + ".yaml"}, registry=registry(),
                                      format_checker=jsonschema.Draft4Validator.FORMAT_CHECKER)


def check(name: str, document: Any) -> None:
    """Raise AssertionError listing every way ``document`` breaks ``<name>.yaml``."""
    errors = sorted(validator(name).iter_errors(document), key=lambda e: list(e.absolute_path))
    assert not errors, f"not a valid {name}:\n" + "\n".join(
        f"  at {'/'.join(map(str, e.absolute_path)) or '(root)'}: {e.message}"
        for e in errors[:20])
