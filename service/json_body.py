"""JSON request documents parsed with bounds: nesting depth, finite numbers, integer size.

Python's parser accepts ``NaN``, ``Infinity`` and ``1e400`` (as infinity), integers of any
length up to 4300 digits (then raises ValueError), and nesting until the interpreter's recursion
limit (then raises RecursionError). A request body is none of those things legitimately, so each
one is answered with a 400/422 problem that names where it is, before anything is created.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

from service.problems import Problem

#: Deepest nesting of arrays and objects accepted; the deepest real inputs are about 4.
MAX_DEPTH = 32
#: Integers outside +-2**63 fit no parameter (nor a database column).
MAX_INT = 2**63 - 1
#: Longest integer literal parsed as a number (a longer one is refused without converting it).
_MAX_INT_DIGITS = 20

#: One token of what matters for nesting: a whole string (possessive, so one attempt is
#: linear), a bracket, or a quote that opens no complete string (invalid JSON: stop there,
#: json.loads reports it; trying again from every later quote would be quadratic).
_TOKEN = re.compile(r'"(?:[^"\\]|\\.)*+"|[\[\]{}]|"', re.DOTALL)


class _TooBig:
    """Stands for an integer literal too long to convert; reported with its place."""

    def __init__(self, text: str) -> None:
        self.text = text


def nesting_depth(text: str, limit: int = MAX_DEPTH) -> int:
    """Deepest array/object nesting of a JSON text, counting no further than ``limit + 1``
    (strings are skipped, so brackets inside them do not count)."""
    depth = deepest = 0
    for match in _TOKEN.finditer(text):
        token = match.group()
        if token[0] == '"':
            if len(token) == 1:
                break
            continue
        depth += 1 if token in "[{" else -1
        if depth > deepest:
            deepest = depth
            if deepest > limit:
                break
    return deepest


def _parse_int(text: str) -> int | _TooBig:
    return _TooBig(text) if len(text.lstrip("-")) > _MAX_INT_DIGITS else int(text)


def _place(path: list[str | int], root: str) -> str:
    return ".".join([root, *(str(p) for p in path)]) if root else ".".join(
        str(p) for p in path) or "body"


def _check_numbers(value: Any, path: list[str | int], root: str) -> None:
    """422 at the first non-finite number or out-of-range integer, naming its place."""
    stack: list[tuple[Any, list[str | int]]] = [(value, path)]
    while stack:
        item, where = stack.pop()
        problem = None
        if isinstance(item, float) and not math.isfinite(item):
            problem = f"{item} is not a finite number"
        elif isinstance(item, _TooBig) or (isinstance(item, int) and not isinstance(item, bool)
                                           and abs(item) > MAX_INT):
            problem = f"integer out of range (at most {_MAX_INT_DIGITS - 1} digits, |n| < 2^63)"
        if problem:
            name = _place(where, root)
            raise Problem(422, "invalid-parameter", f"{name}: {problem}",
                          errors=[{"parameter": name, "message": problem}])
        if isinstance(item, dict):
            stack.extend((v, [*where, k]) for k, v in item.items())
        elif isinstance(item, list):
            stack.extend((v, [*where, i]) for i, v in enumerate(item))


def parse_json(text: str, root: str = "") -> Any:
    """The JSON document ``text``; 400 when it is not JSON or nested deeper than
    :data:`MAX_DEPTH`, 422 naming the place of a non-finite number or a huge integer.
    ``root`` prefixes the places named (e.g. ``inputs`` for the multipart field)."""
    where = root or "body"
    depth = nesting_depth(text)
    if depth > MAX_DEPTH:
        raise Problem(400, "invalid-parameter", f"{where}: JSON nested deeper than {MAX_DEPTH} "
                      "levels", errors=[{"parameter": where, "message": "nested too deeply"}])
    try:
        value = json.loads(text, parse_int=_parse_int, parse_constant=float)
    except (json.JSONDecodeError, RecursionError, ValueError) as exc:
        raise Problem(400, "invalid-parameter", f"{where}: not valid JSON ({exc})",
                      errors=[{"parameter": where, "message": "not valid JSON"}]) from None
    _check_numbers(value, [], root)
    return value
