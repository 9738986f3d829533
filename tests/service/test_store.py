"""The SQLite store: keys as hashes only, the job state machine, persistence, pagination."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from lidar_outliers.jobs.store import JobStatus, Store, StoreError, hash_key


@pytest.fixture
def store(tmp_path: Path) -> Store:
    return Store(tmp_path / "service.sqlite3")


def new_job(store: Store, user_id: int, job_id: str | None = None):
    return store.create_job(user_id, "temporal", {"pipeline": None}, {"points": 10}, False, 100,
                            job_id=job_id)


def test_keys_are_stored_as_hashes_only(store: Store, tmp_path: Path) -> None:
    user, key = store.add_user("alice")
    raw = (tmp_path / "service.sqlite3").read_bytes()
    for suffix in ("-wal", "-shm"):
        extra = tmp_path / f"service.sqlite3{suffix}"
        raw += extra.read_bytes() if extra.exists() else b""
    assert key.encode() not in raw
    rows = sqlite3.connect(tmp_path / "service.sqlite3").execute(
        "SELECT key_hash FROM users").fetchall()
    assert rows == [(hash_key(key),)]
    assert store.user_for_key(key).name == "alice"
    assert store.user_for_key(key + "x") is None
    assert len(key) > 40  # 32 random bytes, URL-safe


def test_names_unique_and_revocation(store: Store) -> None:
    _, key = store.add_user("alice")
    with pytest.raises(StoreError, match="exists"):
        store.add_user("alice")
    with pytest.raises(StoreError, match="without spaces"):
        store.add_user("two words")
    store.revoke_user("alice")
    assert store.user_for_key(key) is None
    with pytest.raises(StoreError, match="no active user"):
        store.revoke_user("alice")
    _, again = store.add_user("alice")  # the name is free again, with a new key
    assert store.user_for_key(again).name == "alice"


def test_one_place_moves_jobs_between_states(store: Store) -> None:
    user, _ = store.add_user("alice")
    job = new_job(store, user.id)
    assert job.status is JobStatus.accepted
    assert store.transition(job.id, JobStatus.successful) is None  # not from accepted
    running = store.transition(job.id, JobStatus.running, "reading", worker_pid=123)
    assert running.status is JobStatus.running and running.attempts == 1
    assert running.started and running.worker_pid == 123
    again = store.transition(job.id, JobStatus.running, worker_pid=456)  # a re-delivery
    assert again.attempts == 2
    assert store.set_progress(job.id, 40, "stage 1/2") is JobStatus.running
    assert store.get_job(job.id).progress == 40
    done = store.transition(job.id, JobStatus.successful, "done", stored_bytes=500)
    assert done.progress == 100 and done.finished and done.stored_bytes == 500
    assert done.worker_pid is None
    assert store.transition(job.id, JobStatus.running) is None  # final stays final
    assert store.transition(job.id, JobStatus.dismissed).status is JobStatus.dismissed
    assert store.transition(job.id, JobStatus.successful) is None
    assert store.set_progress(job.id, 50, "late worker") is JobStatus.dismissed
    assert store.transition("no-such-id", JobStatus.running) is None


def test_records_survive_a_new_store_and_list_newest_first(store: Store) -> None:
    alice, key = store.add_user("alice")
    bob, _ = store.add_user("bob")
    ids = [new_job(store, alice.id, f"job{i}").id for i in range(5)]
    new_job(store, bob.id, "bobs")
    reopened = Store(store.path)
    assert reopened.user_for_key(key).id == alice.id
    page, total = reopened.list_jobs(alice.id, limit=2, offset=0)
    assert total == 5 and [j.id for j in page] == ids[::-1][:2]
    page, _ = reopened.list_jobs(alice.id, limit=2, offset=4)
    assert [j.id for j in page] == [ids[0]]
    assert reopened.count_active(alice.id) == 5
    reopened.transition("job0", JobStatus.dismissed)
    assert reopened.count_active(alice.id) == 4
    assert reopened.stored_bytes(alice.id) == 500
