"""Bounded JSON parsing: the fast nesting scan against the depth of the parsed document, and the
places named for non-finite numbers and huge integers."""

from __future__ import annotations

import json
import random
from typing import Any

import pytest

from service.json_body import MAX_DEPTH, nesting_depth, parse_json
from service.problems import Problem


def depth_of(value: Any) -> int:
    """The obvious definition: arrays and objects count one level each."""
    if isinstance(value, dict):
        return 1 + max((depth_of(v) for v in value.values()), default=0)
    if isinstance(value, list):
        return 1 + max((depth_of(v) for v in value), default=0)
    return 0


def random_document(rng: random.Random, depth: int) -> Any:
    if depth == 0 or rng.random() < 0.2:
        return rng.choice([1, 2.5, "s[{", 'q"]}\\', None, True, "}}}]]]"])
    if rng.random() < 0.5:
        return [random_document(rng, depth - 1) for _ in range(rng.randint(0, 3))]
    return {f"k{i}[": random_document(rng, depth - 1) for i in range(rng.randint(0, 3))}


def test_nesting_scan_matches_the_parsed_depth() -> None:
    rng = random.Random(7)
    for _ in range(500):
        document = random_document(rng, rng.randint(0, 12))
        assert nesting_depth(json.dumps(document), limit=100) == depth_of(document)


def test_too_deep_is_400_and_deep_enough_parses() -> None:
    ok = "[" * MAX_DEPTH + "]" * MAX_DEPTH
    assert depth_of(parse_json(ok)) == MAX_DEPTH
    with pytest.raises(Problem) as caught:
        parse_json("[" * 100_000 + "]" * 100_000, "inputs")
    assert caught.value.status == 400 and "nested deeper" in caught.value.detail


@pytest.mark.parametrize("number", ["1e400", "-1e400", "Infinity", "-Infinity", "NaN"])
def test_non_finite_numbers_are_422_at_their_place(number: str) -> None:
    with pytest.raises(Problem) as caught:
        parse_json(f'{{"pipeline": [{{"detector": "temporal", "sigma": {number}}}]}}', "inputs")
    assert caught.value.status == 422
    assert caught.value.extra["errors"][0]["parameter"] == "inputs.pipeline.0.sigma"


@pytest.mark.parametrize("number", ["9223372036854775808", "-9223372036854775808",
                                    "1" + "0" * 5000])
def test_integers_beyond_int64_are_422(number: str) -> None:
    with pytest.raises(Problem) as caught:
        parse_json(f'{{"a": {{"b": [0, {number}]}}}}')
    assert caught.value.extra["errors"][0]["parameter"] == "a.b.1"


def test_ordinary_documents_are_unchanged() -> None:
    text = '{"n1": 9223372036854775807, "x": [1.5, -2e10, "NaN"], "t": true, "z": null}'
    assert parse_json(text) == json.loads(text)
    with pytest.raises(Problem) as caught:
        parse_json("{not json")
    assert caught.value.status == 400


@pytest.mark.parametrize("body", [
    '{"inputs": {"x": "' + '\\"' * 500_000,  # a string that never closes: 1 MB of \"
    '{"a": "' + '\\\\' * 400_000 + '" ' + '"' * 100_000,
    '"' * 1_000_000,
])
def test_unclosed_strings_are_scanned_once_and_refused(body: str) -> None:
    # each later quote must not start the scan of the rest again (quadratic: hours at 1 MB,
    # while the event loop waits)
    assert nesting_depth(body) <= 2
    with pytest.raises(Problem) as err:
        parse_json(body)
    assert err.value.status == 400 and "not valid JSON" in err.value.detail
