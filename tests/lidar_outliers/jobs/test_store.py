"""The job store on SQLite and PostgreSQL: keys as hashes only, the job state machine,
persistence, pagination, and limits that hold when submissions race."""

from __future__ import annotations

import multiprocessing
import threading
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

import pytest
import sqlalchemy as sa

from lidar_outliers.jobs.store import (
    JobStatus,
    LimitExceeded,
    QuotaExceeded,
    Store,
    StoreError,
    TooManyActiveJobs,
    hash_key,
)


def new_job(store: Store, user_id: int, job_id: str | None = None, **limits):
    return store.create_job(user_id, "temporal", {"pipeline": None}, {"points": 10}, False, 100,
                            job_id=job_id, **limits)


def test_keys_are_stored_as_hashes_only(store: Store) -> None:
    user, key = store.add_user("alice")
    with store.engine.connect() as db:
        rows = db.execute(sa.text("SELECT * FROM users")).all()
    assert [row.key_hash for row in rows] == [hash_key(key)]
    assert not any(key in str(value) for row in rows for value in row)
    if store.path is not None:  # nor anywhere in SQLite's files
        raw = b"".join(p.read_bytes() for p in store.path.parent.glob("service.sqlite3*"))
        assert key.encode() not in raw
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
    assert [u.name.split("#")[0] for u in store.list_users()] == ["alice", "alice"]


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
    done = store.transition(job.id, JobStatus.successful, "done", stored_bytes=5_000_000_000)
    assert done.progress == 100 and done.finished and done.stored_bytes == 5_000_000_000
    assert done.worker_pid is None
    assert store.transition(job.id, JobStatus.running) is None  # final stays final
    assert store.transition(job.id, JobStatus.dismissed).status is JobStatus.dismissed
    assert store.transition(job.id, JobStatus.successful) is None
    assert store.set_progress(job.id, 50, "late worker") is JobStatus.dismissed
    assert store.transition("no-such-id", JobStatus.running) is None
    assert store.set_progress("no-such-id", 1, "") is None
    store.annotate(job.id, "note")
    assert store.get_job(job.id).message == "note"


def test_records_survive_a_new_store_and_list_newest_first(store: Store,
                                                           database_url: str) -> None:
    alice, key = store.add_user("alice")
    bob, _ = store.add_user("bob")
    ids = [new_job(store, alice.id, f"job{i}").id for i in range(5)]
    new_job(store, bob.id, "bobs")
    reopened = Store(database_url)
    try:
        assert reopened.user_for_key(key).id == alice.id
        page, total = reopened.list_jobs(alice.id, limit=2, offset=0)
        assert total == 5 and [j.id for j in page] == ids[::-1][:2]
        page, _ = reopened.list_jobs(alice.id, limit=2, offset=4)
        assert [j.id for j in page] == [ids[0]]
        assert [j.seq for j in reopened.list_jobs(bob.id, 10, 0)[0]] == [1]
        assert reopened.count_active(alice.id) == 5
        reopened.transition("job0", JobStatus.dismissed)
        assert reopened.count_active(alice.id) == 4
        assert reopened.stored_bytes(alice.id) == 500
    finally:
        reopened.close()


def test_uploads_and_retention_queries(store: Store) -> None:
    alice, _ = store.add_user("alice")
    upload = store.add_upload(alice.id, "scan.las", "uploads/1/u.las", 1234, {"points": 5})
    assert store.get_upload(upload.id, alice.id) == upload
    assert store.get_upload(upload.id, alice.id + 1) is None  # another user's
    assert store.stored_bytes(alice.id) == 1234
    assert store.uploads_created_before("9999") == [upload]
    assert store.uploads_created_before("0000") == []
    job = new_job(store, alice.id)
    store.transition(job.id, JobStatus.failed, "broken")
    assert [j.id for j in store.jobs_finished_before("9999")] == [job.id]
    assert store.jobs_finished_before("0000") == []
    store.delete_job(job.id)
    store.delete_upload(upload.id)
    assert store.get_job(job.id) is None and store.get_upload(upload.id, alice.id) is None
    assert store.stored_bytes(alice.id) == 0


def test_limits_refuse_and_record_nothing(store: Store) -> None:
    alice, _ = store.add_user("alice")
    for _ in range(2):
        new_job(store, alice.id, max_active=2)
    with pytest.raises(TooManyActiveJobs) as refused:
        new_job(store, alice.id, max_active=2)
    assert refused.value.active == 2 and refused.value.limit == 2
    assert store.list_jobs(alice.id, 10, 0)[1] == 2
    first = store.list_jobs(alice.id, 10, 0)[0][-1]
    store.transition(first.id, JobStatus.dismissed, stored_bytes=0)  # frees a slot and bytes
    assert new_job(store, alice.id, max_active=2).active_before == 1
    # quota: 2 x 100 bytes stored; 250 + 100 > 300
    store.add_upload(alice.id, "a", "uploads/1/a.las", 50, max_stored_bytes=300)
    with pytest.raises(QuotaExceeded) as over:
        new_job(store, alice.id, max_stored_bytes=300)
    assert (over.value.stored, over.value.left) == (250, 50)
    with pytest.raises(QuotaExceeded):
        store.add_upload(alice.id, "b", "uploads/1/b.las", 51, max_stored_bytes=300)
    assert store.stored_bytes(alice.id) == 250
    with pytest.raises(StoreError, match="no user"):
        new_job(store, 999)


USERS, ATTEMPTS, LIMIT = 3, 10, 4


def _race(url: str, user_ids: list[int], barrier, attempts: int,
          limits: dict[str, int]) -> list[tuple[int, str]]:
    """``attempts`` threads per user, all released at once; each tries to create one job.
    Returns (user, "ok" or the refusal's class name) for each."""
    store = Store(url, migrate=False)
    try:
        def one(user_id: int) -> tuple[int, str]:
            barrier.wait()
            try:
                new_job(store, user_id, **limits)
                return user_id, "ok"
            except LimitExceeded as exc:
                return user_id, type(exc).__name__

        calls = [u for u in user_ids for _ in range(attempts)]
        with ThreadPoolExecutor(len(calls)) as pool:
            return list(pool.map(one, calls))
    finally:
        store.close()


def test_concurrent_submissions_never_exceed_the_active_limit(store: Store,
                                                             database_url: str) -> None:
    """30 submissions at once, 10 from each of 3 users, limit 4: each user gets exactly 4."""
    users = [store.add_user(f"user{i}")[0].id for i in range(USERS)]
    barrier = threading.Barrier(USERS * ATTEMPTS)
    outcomes = _race(database_url, users, barrier, ATTEMPTS, {"max_active": LIMIT})
    accepted = Counter(u for u, result in outcomes if result == "ok")
    assert accepted == dict.fromkeys(users, LIMIT), accepted
    assert {r for _, r in outcomes} == {"ok", "TooManyActiveJobs"}
    assert [store.count_active(u) for u in users] == [LIMIT] * USERS


def _process_race(url: str, user_ids: list[int], barrier, attempts: int, limits: dict,
                  results) -> None:
    results.put(_race(url, user_ids, barrier, attempts, limits))


def test_concurrent_processes_never_exceed_the_limits(store: Store, database_url: str) -> None:
    """Six processes of five threads each (as API processes on several hosts would): the
    active-job limit and the storage quota hold together."""
    users = [store.add_user(f"user{i}")[0].id for i in range(USERS)]
    # spawned: the children open their own connections (Store below), nothing of the parent's;
    # a fork would also copy locks that other threads of the test run hold (a hang)
    spawn = multiprocessing.get_context("spawn")
    processes, threads = 6, 5
    barrier, results = spawn.Barrier(processes * threads, timeout=120), spawn.Queue()
    # each user's jobs are in 2 processes x 5 threads; quota 350 bytes = 3 jobs of 100
    limits = {"max_active": LIMIT, "max_stored_bytes": 350}
    workers = [spawn.Process(target=_process_race,
                             args=(database_url, [users[i // 2]], barrier, threads, limits,
                                   results)) for i in range(processes)]
    for p in workers:
        p.start()
    try:
        outcomes = [o for _ in workers for o in results.get(timeout=180)]
    finally:
        for p in workers:
            p.join(timeout=60)
            if p.exitcode is None:
                p.kill()
    assert [p.exitcode for p in workers] == [0] * processes
    accepted = Counter(u for u, result in outcomes if result == "ok")
    assert accepted == dict.fromkeys(users, 3), accepted
    assert {r for _, r in outcomes} == {"ok", "QuotaExceeded"}
    assert [store.stored_bytes(u) for u in users] == [300] * USERS


def test_concurrent_uploads_never_exceed_the_quota(store: Store, database_url: str) -> None:
    alice = store.add_user("alice")[0].id
    barrier = threading.Barrier(12)

    def one(i: int) -> bool:
        barrier.wait()
        try:
            store.add_upload(alice, f"u{i}", f"uploads/{alice}/u{i}.las", 100,
                             max_stored_bytes=450)
            return True
        except QuotaExceeded:
            return False

    with ThreadPoolExecutor(12) as pool:
        assert sum(pool.map(one, range(12))) == 4
    assert store.stored_bytes(alice) == 400
