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
    copy = tmp_path / "algorithms"
    shutil.copytree(package, copy, ignore=shutil.ignore_patterns("__pycache__"))
    before = source_digest(copy)
    assert before == source_digest(package)
    with open(copy / "quadric.py", "a") as f:
        f.write("\n# an edit in a module whose kernels others inline\n")
    after_quadric = source_digest(copy)
    assert after_quadric != before
    with open(copy / "temporal" / "smoother.py", "a") as f:
        f.write("\n# an edit in a subpackage\n")
    assert source_digest(copy) != after_quadric
