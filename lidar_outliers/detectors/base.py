"""What one detector declaration holds, and the parameter model derived from it.

A detector is declared once, in its own module of this package, as ``DETECTOR = Detector(...)``:
its name, its parameters (the dataclass its algorithm module declares, limits included), the
adapter that runs it on a :class:`~lidar_outliers.cloud.Cloud`, its bit of ``outlier_flags``, a
one-line summary and the dimensions it needs. From that one declaration come the pydantic model
that validates a pipeline stage (and so the command line's options, the API's ``/processes``
description and the statistics' parameter names), the score dimension's name and the flag bit.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, create_model, model_validator

from algorithms.params import Limits, Parameters, parameter_infos
from algorithms.result import DetectorResult
from lidar_outliers.cloud import Cloud
from lidar_outliers.output import FLAG_BITS_AVAILABLE, score_dimension


@dataclass
class GroundResult:
    """Outcome of a ground filter on n points: ``is_ground`` (n,) bool and JSON-able ``info``."""

    is_ground: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


class StageModel(BaseModel):
    """Base of every detector's stage model: ``{"detector": name, **parameters}``.

    Unknown fields and non-finite numbers are refused; after the field checks the declared
    parameters' own rules run (:meth:`algorithms.params.Parameters.check`).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    declared: ClassVar[type[Parameters]]

    def parameters(self) -> Parameters:
        """The stage as its algorithm's parameters dataclass (checked again on the way)."""
        return self.declared(**self.model_dump(exclude={"detector"}))

    @model_validator(mode="after")
    def _declared_rules(self) -> StageModel:
        self.parameters()  # ParameterError is a ValueError: pydantic reports it by name
        return self


Run = Callable[[Cloud, Any], DetectorResult | GroundResult]
#: XY metres a point's result may depend on around it, from the stage's parameters; None: the
#: result depends on the whole cloud (or on its time series), so the stage is not run in tiles.
Halo = Callable[[Any], "float | None"]
#: ``reach(cloud, params, where, allowed)``: (n,) metres of the neighbourhood each point of
#: ``cloud`` actually used (k-th neighbour, search radius), for the points of the (n,) bool
#: mask ``where`` (others: anything): for detectors whose reach depends on the data, checked
#: against the halo; inf: more points than the cloud at hand holds (the halo grows until they
#: are there). ``allowed`` (n,): the reach each point may have in this region; a point whose
#: neighbourhood is known to lie within it may report that bound instead of the exact reach.
Reach = Callable[[Cloud, Any, np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Estimate:
    """A parameter the detector estimates from the whole cloud (``height_field``'s ``sigma:
    auto``), made of values each point has from its neighbourhood alone.

    ``applies(params)``: whether these parameters ask for the estimate. ``values(cloud,
    params)``: (n,) float, each point's value (NaN: none), or (n, m) for a round that fixes m
    estimates at once. ``pin(params, parts)``: the parameters with the estimate fixed, and the
    statistics' info on it, from the values of all the points in file order (``parts``:
    consecutive pieces). A tiled run computes the values
    tile by tile, pins, then runs the tiles with the pinned parameters: the whole cloud's
    result. Several parameters are estimated in rounds, in an order the detector keeps:
    ``applies`` holds until the last is fixed, ``values`` and ``pin`` serve the first not yet
    fixed, and those fixed with it from the same round's (n, m) values (``detached``: its
    spacings, then its voxel size, which starts at one of them; ``height_field``: sigma and
    its spacing, then its voxel size).
    ``reach`` then answers for the values of that round.
    """

    applies: Callable[[Any], bool]
    values: Callable[[Cloud, Any], np.ndarray]
    pin: Callable[[Any, list[np.ndarray]], tuple[Any, dict[str, Any]]]


@dataclass(frozen=True)
class Prepass:
    """Per-point facts a detector reads from the whole file, gathered before its tiles run
    (``transient``: which points are persistent, the scan-line neighbours, which may lie
    anywhere, and the clusters of the single-epoch points, which may span any number of tiles).

    ``halo(params)``: XY metres around a tile that ``values`` needs to be exact for the tile's
    points. ``values(cloud, params)``: per-point arrays by name, (n,) each, on the stage's
    input of a tile's region. ``combine(params, columns, out)``: fills ``out`` ((n,) records of
    ``dtype`` in file order) from ``columns``: every point's ``values`` in file order, plus
    ``in_stage`` (bool: the point reached the stage), ``gps_time``, ``point_source_id`` and
    ``x``, ``y``, ``z`` (the local frame's coordinates), as (n,) arrays on disk; returns the
    statistics' info on it. The detector's ``run`` then finds, on a tile,
    ``cloud.known[name]``: its points' records of ``out`` and their ``index`` in the file. A
    tiled run gathers the values tile by tile, combines, then runs the tiles with the
    detector's ``halo`` (:mod:`lidar_outliers.tiling`).
    """

    halo: Callable[[Any], float]
    values: Callable[[Cloud, Any], dict[str, np.ndarray]]
    dtype: np.dtype
    combine: Callable[[Any, dict[str, np.ndarray], np.ndarray], dict[str, Any]]


def no_halo(_params: Any) -> None:
    """The default: not declared, so the stage runs on the whole cloud."""
    return None


def knn_reach(xyz: np.ndarray, k: int, where: np.ndarray,
              allowed: np.ndarray | None = None) -> np.ndarray:
    """(n,) distance from each point of the mask ``where`` to its k-th nearest point (itself
    counted first; 0 outside the mask), or a bound of it within ``allowed``
    (:func:`algorithms.tiles.kth_distance_within`); inf where the cloud has fewer than k points
    (every point then needs more points than these: a tile's halo grows until it holds k)."""
    from algorithms.tiles import kth_distance_within

    return kth_distance_within(xyz, k, where, allowed)


@dataclass(frozen=True)
class Detector:
    """One detector, declared once (module docstring).

    ``kind`` ``"outlier"`` sets bit ``flag_bit`` of ``outlier_flags`` and writes
    ``<name>_score``; ``"ground"`` writes classes 2/1 instead (no bit, no score). ``run`` gets
    the cloud and the stage's :class:`~algorithms.params.Parameters` instance.

    ``halo(params)``: how far (XY metres) a point's result may depend on other points, so that
    a tile run with that much of the neighbouring points around it gives the whole cloud's
    result (:mod:`lidar_outliers.tiling`); None when it depends on the whole cloud. ``reach``:
    for neighbourhoods set by the data (k nearest), the reach each point used; a tile whose
    points reached further than the halo is run again with a wider one. ``uses_trajectory``:
    with a trajectory the detector follows beams across the cloud, so it does not run in tiles.
    ``whole_cloud``: why the detector needs the whole cloud (its halo None), for the statistics.
    ``streams``: the result depends on each scanner's time series alone (no XY neighbourhood),
    so a tiled run whose pipeline starts with such stages streams them over the file in time
    order first and tiles the rest (:mod:`lidar_outliers.prepass`).
    ``prepass``: facts from the whole file the tiles read (:class:`Prepass`); the ``halo`` then
    holds with them given.
    """

    name: str
    parameters: type[Parameters]
    run: Run
    summary: str
    kind: Literal["outlier", "ground"] = "outlier"
    flag_bit: int | None = None
    needs: tuple[str, ...] = ()
    halo: Halo = no_halo
    reach: Reach | None = None
    uses_trajectory: bool = False
    whole_cloud: str | None = None
    estimate: Estimate | None = None
    streams: bool = False
    prepass: Prepass | None = None
    model: type[StageModel] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if (self.kind == "outlier") != (self.flag_bit is not None):
            raise ValueError(f"detector {self.name}: an outlier detector needs a flag_bit, "
                             f"a ground filter has none")
        if self.flag_bit is not None and not _is_flag_bit(self.flag_bit):
            raise ValueError(f"detector {self.name}: flag_bit {self.flag_bit} is not one of the "
                             f"{FLAG_BITS_AVAILABLE} bits of outlier_flags (1, 2, 4, ...)")
        object.__setattr__(self, "model", stage_model(self.name, self.parameters))

    @property
    def score_dimension(self) -> str | None:
        """The float32 extra dimension holding this detector's score (outlier detectors)."""
        return score_dimension(self.name) if self.kind == "outlier" else None

    @property
    def description(self) -> str:
        return " ".join((self.parameters.__doc__ or self.summary).split())

    def stage(self, **values: Any) -> StageModel:
        """A validated stage of this detector (pydantic errors name the parameter)."""
        return self.model(detector=self.name, **values)


def _is_flag_bit(bit: int) -> bool:
    return isinstance(bit, int) and bit > 0 and bit & (bit - 1) == 0 and (
        bit < 1 << FLAG_BITS_AVAILABLE)


def stage_model(name: str, parameters: type[Parameters]) -> type[StageModel]:
    """The pydantic model of one stage: ``detector`` plus each declared parameter, with its
    default, description and limits (the JSON Schema of ``/processes`` shows them)."""
    fields: dict[str, Any] = {"detector": (Literal[name], name)}  # type: ignore[valid-type]
    for info in parameter_infos(parameters):
        fields[info.name] = (
            _constrained(info.annotation, info.limits),
            Field(info.default, description=info.doc),
        )
    title = "".join(part.capitalize() for part in name.split("_")) + "Params"
    model = create_model(title, __base__=StageModel, __doc__=parameters.__doc__, **fields)
    model.declared = parameters
    return model


def _constrained(annotation: Any, limits: Limits) -> Any:
    """``annotation`` with ``limits`` on every number it holds (pydantic cannot put bounds on a
    union, so they go on its numeric members and on the elements of tuples and lists)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    bounds = {k: v for k, v in vars(limits).items() if v is not None}
    if annotation in (int, float):
        return Annotated[annotation, Field(**bounds)] if bounds else annotation
    if origin in (typing.Union, types.UnionType):
        return typing.Union[tuple(_constrained(a, limits) for a in args)]  # noqa: UP007
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple[_constrained(args[0], limits), ...]  # type: ignore[misc]
        return tuple[tuple(_constrained(a, limits) for a in args)]  # type: ignore[misc]
    if origin is list:
        return list[_constrained(args[0], limits)]  # type: ignore[misc]
    return annotation
