"""The detector registry: every module of this package that declares ``DETECTOR``.

Each detector is declared once, in its own module here (:class:`~.base.Detector`: parameters,
adapter, flag bit, summary). The pipeline, the command line, the web service's ``/processes``,
the output's flag bits and the statistics all read :data:`DETECTORS`; adding a detector means
adding its algorithm module, its declaration module here and its tests (``docs/adding-a-
detector.md``). Declaration modules are cheap to import: they import their algorithm's
parameters, and the algorithm's heavy code only when it runs.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Iterable
from typing import Any

from algorithms.params import parameter_infos, type_name
from lidar_outliers.detectors.base import Detector, GroundResult, StageModel
from lidar_outliers.errors import ParameterError

__all__ = [
    "DETECTORS", "FLAG_BITS", "Detector", "GroundResult", "StageModel", "get_detector",
    "parameter_table",
]


def declared_detectors() -> list[Detector]:
    """The ``DETECTOR`` of every module of this package (a broken module raises here)."""
    found = []
    for module_info in pkgutil.iter_modules(__path__):
        module = importlib.import_module(f"{__name__}.{module_info.name}")
        detector = getattr(module, "DETECTOR", None)
        if isinstance(detector, Detector):
            found.append(detector)
    return found


def build_registry(detectors: Iterable[Detector]) -> dict[str, Detector]:
    """Detectors by name: outlier detectors by flag bit, then the others by name.

    Raises ValueError when two detectors share a name or a bit of ``outlier_flags``.
    """
    by_name: dict[str, Detector] = {}
    by_bit: dict[int, str] = {}
    for detector in detectors:
        if detector.name in by_name:
            raise ValueError(f"two detectors are called {detector.name!r}")
        by_name[detector.name] = detector
        if detector.flag_bit is not None:
            if detector.flag_bit in by_bit:
                raise ValueError(f"detectors {by_bit[detector.flag_bit]!r} and "
                                 f"{detector.name!r} share bit {detector.flag_bit} of "
                                 f"outlier_flags")
            by_bit[detector.flag_bit] = detector.name
    order = sorted(by_name.values(), key=lambda d: (d.flag_bit is None, d.flag_bit or 0, d.name))
    return {d.name: d for d in order}


DETECTORS: dict[str, Detector] = build_registry(declared_detectors())

#: Outlier detectors by name -> their bit of the ``outlier_flags`` dimension.
FLAG_BITS: dict[str, int] = {
    name: d.flag_bit for name, d in DETECTORS.items() if d.flag_bit is not None
}


def get_detector(name: str) -> Detector:
    """The registry entry for ``name``; ParameterError naming the known detectors otherwise."""
    try:
        return DETECTORS[name]
    except KeyError:
        known = ", ".join(DETECTORS)
        raise ParameterError(f"unknown detector {name!r} (known: {known})") from None


def parameter_table(detector: Detector) -> list[dict[str, Any]]:
    """Name, type, default, range and description of each parameter of a detector."""
    return [
        {
            "name": info.name,
            "type": type_name(info.annotation),
            "default": info.default,
            "range": info.limits.describe(),
            "description": info.doc,
        }
        for info in parameter_infos(detector.parameters)
    ]
