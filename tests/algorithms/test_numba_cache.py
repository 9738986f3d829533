"""The numba cache folder is keyed by all of the package's sources, so it is never stale."""

from __future__ import annotations

import shutil
from pathlib import Path

import numba

import algorithms
from algorithms import jit, source_digest


def test_kernels_are_cached_in_the_folder_of_the_current_sources():
    assert jit.NUMBA_CACHE_DIR is not None
    assert jit.NUMBA_CACHE_DIR.endswith(f"numba-{source_digest()}")
    assert numba.config.CACHE_DIR == jit.NUMBA_CACHE_DIR
    from algorithms.quadric import _fit_one  # a kernel that inlines others

    assert Path(_fit_one._cache._cache_path).is_relative_to(jit.NUMBA_CACHE_DIR)


def test_an_edit_to_any_module_changes_the_folder(tmp_path):
    package = Path(algorithms.__file__).parent
    for path in package.glob("*.py"):
        shutil.copy(path, tmp_path / path.name)
    before = source_digest(tmp_path)
    assert before == source_digest(package)
    with open(tmp_path / "quadric.py", "a") as f:
        f.write("\n# an edit in a module whose kernels others inline\n")
    assert source_digest(tmp_path) != before
