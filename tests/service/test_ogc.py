"""The framework-free parts of the OGC API - Processes support: Prefer, the datetime filter,
content negotiation, the JSON Schema to OpenAPI 3.0 downgrade. tests/e2e/test_ogc.py runs
them over HTTP against the real stack."""

from __future__ import annotations

from typing import Literal

import pytest
from pydantic import BaseModel, Field
from starlette.requests import Request

from service.execution import Preference
from service.html import wants_html
from service.joblist import parse_datetime
from service.oas30 import process_input_schema
from service.problems import Problem
from tests.ogc_schemas import check


@pytest.mark.parametrize(("headers", "expected"), [
    ([], (False, False, None)),
    (["respond-async"], (True, False, None)),
    (["wait"], (False, True, None)),
    (["wait=10"], (False, True, 10.0)),
    (["respond-async, wait=5"], (True, True, 5.0)),
    (["handling=lenient", 'wait="30"; foo=bar'], (False, True, 30.0)),
    (["Respond-Async; x=y"], (True, False, None)),
])
def test_prefer_header(headers: list[str], expected: tuple) -> None:
    found = Preference.parse(headers)
    assert (found.respond_async, found.wait, found.wait_seconds) == expected


@pytest.mark.parametrize(("value", "bounds"), [
    (None, (None, None)),
    ("2025-01-02T03:04:05Z", ("2025-01-02T03:04:05.000Z", "2025-01-02T03:04:05.000Z")),
    ("2025-01-02T05:04:05+02:00/..", ("2025-01-02T03:04:05.000Z", None)),
    ("2025-01-02T05:04:05 02:00/", ("2025-01-02T03:04:05.000Z", None)),  # unencoded '+'
    ("../2025-01-02T03:04:05.5Z", (None, "2025-01-02T03:04:05.500Z")),
    ("2025-01-01T00:00:00Z/2025-01-02T00:00:00Z",
     ("2025-01-01T00:00:00.000Z", "2025-01-02T00:00:00.000Z")),
])
def test_datetime_filter_bounds(value: str | None, bounds: tuple) -> None:
    assert parse_datetime(value) == bounds


@pytest.mark.parametrize("value", ["yesterday", "2025-01-02T03:04:05", "../..", "/",
                                   "2025-01-02T00:00:00Z/2025-01-01T00:00:00Z", "a/b/c",
                                   "0001-01-01T00:00:00+14:00", "9999-12-31T23:59:59-14:00",
                                   "../0001-01-01T00:00:00+01:00"])
def test_bad_datetime_filter_is_a_400_naming_it(value: str) -> None:
    with pytest.raises(Problem) as caught:
        parse_datetime(value)
    assert caught.value.status == 400 and caught.value.detail.startswith("datetime:")


def request(query: str = "", accept: str | None = None) -> Request:
    headers = [(b"accept", accept.encode())] if accept is not None else []
    return Request({"type": "http", "method": "GET", "path": "/", "query_string":
                    query.encode(), "headers": headers})


@pytest.mark.parametrize(("query", "accept", "html"), [
    ("", None, False),
    ("", "*/*", False),
    ("", "application/json", False),
    ("", "text/html,application/xhtml+xml,application/xml;q=0.9,*/*;q=0.8", True),
    ("", "application/json, text/html;q=0.5", False),
    ("", "text/html;q=0", False),
    ("f=html", "application/json", True),
    ("f=json", "text/html", False),
])
def test_content_negotiation(query: str, accept: str | None, html: bool) -> None:
    assert wants_html(request(query, accept)) is html


class Stage(BaseModel):
    kind: Literal["a"] = "a"
    ratio: float = Field(0.5, gt=0, lt=1, examples=[0.25])
    origin: tuple[float, float] = (0.0, 0.0)
    classes: list[int] | None = None


class Inputs(BaseModel):
    stages: list[Stage] = Field(default_factory=list)
    mode: Literal["x", "y"] | None = None


def test_pydantic_schemas_become_process_input_schemas() -> None:
    schema = Inputs.model_json_schema()
    defs = schema["$defs"]
    converted = {name: process_input_schema(prop, defs)
                 for name, prop in schema["properties"].items()}
    stage = converted["stages"]["items"]
    assert stage["properties"]["kind"]["enum"] == ["a"]
    assert stage["properties"]["ratio"] == {
        "default": 0.5, "example": 0.25, "exclusiveMaximum": True, "exclusiveMinimum": True,
        "maximum": 1, "minimum": 0, "title": "Ratio", "type": "number"}
    assert stage["properties"]["origin"]["items"] == {"type": "number"}
    assert stage["properties"]["origin"]["minItems"] == 2
    assert stage["properties"]["classes"]["nullable"] is True
    assert converted["mode"] == {"enum": ["x", "y"], "type": "string", "nullable": True,
                                 "default": None, "title": "Mode"}
    for name, prop in converted.items():  # each one a valid input description
        check("inputDescription", {"title": name, "schema": prop})
    with pytest.raises(AssertionError):  # the unconverted schema is not
        check("inputDescription", {"schema": {**schema["properties"]["mode"]}})
