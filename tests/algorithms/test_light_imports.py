"""Detector modules import light: their parameters are read when the command line starts.

The library builds its options from each detector's Parameters class, so importing a detector
module must not import numba or scipy's heavy parts (together about 0.6 s); the kernels and
scipy are imported when a detector runs.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from lidar_outliers.detectors import DETECTORS

#: The module declaring each registered detector's parameters, so a new detector is checked
#: by being declared.
LIGHT_MODULES = sorted(
    {d.parameters.__module__ for d in DETECTORS.values()}
    | {"algorithms.platform_evidence"})  # imported by the profile choice of every command

#: Modules that none of them may import.
HEAVY_MODULES = ["numba", "scipy.spatial", "scipy.sparse", "scipy.stats"]


@pytest.mark.parametrize("module", LIGHT_MODULES)
def test_detector_module_imports_neither_numba_nor_scipy_spatial(module):
    heavy = heavy_imports_of(module)
    assert heavy == [], f"importing {module} imports {heavy}"


@pytest.mark.parametrize("module", ["lidar_outliers.detectors", "lidar_outliers.cli"])
def test_the_registry_and_the_command_line_import_neither(module):
    # Every command reads every detector's parameters when it starts: a command that runs only
    # the temporal detector must not pay for numba and scipy's k-d tree (about 0.35 s).
    heavy = heavy_imports_of(module)
    assert heavy == [], f"importing {module} imports {heavy}"


def heavy_imports_of(module: str) -> list[str]:
    """The HEAVY_MODULES that importing ``module`` in a fresh interpreter imports (the test
    session itself has imported numba and scipy long ago)."""
    code = (
        "import importlib, json, sys\n"
        f"importlib.import_module({module!r})\n"
        f"print(json.dumps([m for m in {HEAVY_MODULES!r} if m in sys.modules]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout)
