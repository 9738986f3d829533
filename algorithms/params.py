"""Detector parameters declared once, as data: name, type, default, limits and meaning.

Each detector's parameters are a frozen dataclass deriving from :class:`Parameters`, every field
made with :func:`param`::

    @dataclass(frozen=True)
    class DrorParameters(Parameters):
        multiplier: float = param(4.0, "Radius = multiplier x range x angular step.", gt=0, le=100)

Building an instance checks every value (type, limits, finite numbers) and then the
parameters' own :meth:`Parameters.check` for rules between fields, raising a
:class:`~algorithms.errors.ParameterError` that names the parameter. The detector function
validates its keyword arguments by building its dataclass, and the library derives from the
same declaration the parameter model of the command line and the web service, so a limit is
written once and means the same everywhere (as scikit-learn's ``_parameter_constraints``).

Types understood: ``bool``, ``int``, ``float``, ``str``, ``Literal[...]``, unions of these,
``tuple[T, ...]``, ``tuple[T1, T2, ...]`` and ``list[T]`` of them. Limits apply to every number
the value holds (each element of a tuple too). ``int`` values are accepted where ``float`` is
declared; ``bool`` never counts as a number.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from dataclasses import dataclass
from functools import cache
from typing import Any, Literal

from algorithms.errors import ParameterError


@dataclass(frozen=True)
class Limits:
    """Bounds on a number: ``ge``/``gt`` below, ``le``/``lt`` above (None: unbounded)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None

    def violated_by(self, value: float) -> str | None:
        """The bound ``value`` breaks, as text (``"must be > 0"``), or None."""
        for bound, symbol, ok in (
            (self.ge, ">=", lambda b: value >= b), (self.gt, ">", lambda b: value > b),
            (self.le, "<=", lambda b: value <= b), (self.lt, "<", lambda b: value < b),
        ):
            if bound is not None and not ok(bound):
                return f"must be {symbol} {bound:g}"
        return None

    def describe(self) -> str | None:
        """``">= 1 and <= 100"``, or None without bounds."""
        parts = [f"{symbol} {bound:g}" for bound, symbol in (
            (self.ge, ">="), (self.gt, ">"), (self.le, "<="), (self.lt, "<")) if bound is not None]
        return " and ".join(parts) or None


def param(default: Any, doc: str, *, ge: float | None = None, gt: float | None = None,
          le: float | None = None, lt: float | None = None) -> Any:
    """A dataclass field of a :class:`Parameters` class: default, meaning and limits."""
    return dataclasses.field(default=default, metadata={
        "doc": doc, "limits": Limits(ge=ge, gt=gt, le=le, lt=lt)})


@dataclass(frozen=True)
class ParameterInfo:
    """One parameter as the declaration gives it."""

    name: str
    annotation: Any
    default: Any
    doc: str
    limits: Limits


@dataclass(frozen=True)
class Parameters:
    """Base of every detector's parameters: checked when built (module docstring)."""

    def __post_init__(self) -> None:
        for info in parameter_infos(type(self)):
            value = getattr(self, info.name)
            problem = _type_problem(value, info.annotation, info.limits)
            if problem is not None:
                raise ParameterError(f"{info.name} {problem}, got {value!r}")
        self.check()

    def check(self) -> None:
        """Rules between parameters; raise ParameterError naming them. None by default."""

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@cache
def parameter_infos(cls: type[Parameters]) -> tuple[ParameterInfo, ...]:
    """The declared parameters of ``cls``, in declaration order, with resolved annotations."""
    hints = typing.get_type_hints(cls)
    return tuple(
        ParameterInfo(name=f.name, annotation=hints[f.name], default=f.default,
                      doc=f.metadata.get("doc", ""), limits=f.metadata.get("limits", Limits()))
        for f in dataclasses.fields(cls)
    )


def _type_problem(value: Any, annotation: Any, limits: Limits) -> str | None:
    """Why ``value`` does not fit ``annotation`` within ``limits`` (text), or None when it does."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        problems = [_type_problem(value, a, limits) for a in args]
        if any(p is None for p in problems):
            return None
        # Prefer the message of the member whose kind matches (a number out of range, say).
        specific = [p for p in problems if not p.startswith("must be of type")]
        return specific[0] if specific else f"must be of type {type_name(annotation)}"
    if origin is Literal:
        return None if value in args and not isinstance(value, bool) else (
            f"must be one of {', '.join(repr(a) for a in args)}")
    if origin in (tuple, list):
        return _sequence_problem(value, origin, args, limits)
    if annotation is bool:
        return None if isinstance(value, bool) else "must be of type bool"
    if annotation in (int, float):
        kind = numbers.Integral if annotation is int else numbers.Real
        if isinstance(value, bool) or not isinstance(value, kind):
            return f"must be of type {annotation.__name__}"
        if not math.isfinite(value):
            return "must be a finite number"
        return limits.violated_by(value)
    if annotation is str:
        return None if isinstance(value, str) else "must be of type str"
    raise TypeError(f"parameter type {annotation!r} is not supported")


def _sequence_problem(value: Any, origin: type, args: tuple, limits: Limits) -> str | None:
    if not isinstance(value, tuple | list):
        return f"must be a {'tuple' if origin is tuple else 'list'}"
    if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
        if len(value) != len(args):
            return f"must hold {len(args)} values"
        members = list(zip(value, args, strict=True))
    else:
        members = [(v, args[0]) for v in value]
    for item, item_type in members:
        problem = _type_problem(item, item_type, limits)
        if problem is not None:
            return f"(each value) {problem}"
    return None


def type_name(annotation: Any) -> str:
    """A short readable name of a parameter type (``float | 'auto'``)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is Literal:
        return " | ".join(repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " | ".join(type_name(a) for a in args)
    if origin in (tuple, list):
        inner = ", ".join("..." if a is Ellipsis else type_name(a) for a in args)
        return f"{origin.__name__}[{inner}]"
    return getattr(annotation, "__name__", str(annotation))

