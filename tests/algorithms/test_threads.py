from __future__ import annotations

import pytest

from algorithms.threads import available_cpus, worker_threads


def test_worker_threads_follow_numbas_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("NUMBA_NUM_THREADS", "3")
    assert worker_threads() == 3


@pytest.mark.parametrize("value", [None, "", "0", "two"])
def test_without_a_usable_setting_every_available_cpu_computes(
        monkeypatch: pytest.MonkeyPatch, value: str | None) -> None:
    if value is None:
        monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("NUMBA_NUM_THREADS", value)
    assert worker_threads() == available_cpus() >= 1
