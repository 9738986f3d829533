"""The storage interface, one contract for both siblings: files under a folder, and a real S3
server (moto's, a process of its own)."""

from __future__ import annotations

import uuid
from pathlib import Path

import pytest

from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.storage import ObjectMissing, Storage, StorageError, open_storage
from lidar_outliers.jobs.storage.local import LocalStorage
from lidar_outliers.jobs.storage.s3 import S3Storage
from tests.backends import MotoServer

DATA = bytes(range(256)) * 4099  # about 1 MiB, not a multiple of a chunk


@pytest.fixture(params=["local", "s3"])
def storage(request: pytest.FixtureRequest, tmp_path: Path) -> Storage:
    if request.param == "local":
        return LocalStorage(tmp_path / "data")
    moto: MotoServer = request.getfixturevalue("moto")
    return S3Storage(moto.new_bucket(), f"service/{uuid.uuid4().hex[:6]}", moto.url)


def write(path: Path, data: bytes = DATA) -> Path:
    path.write_bytes(data)
    return path


def test_put_get_and_info(storage: Storage, tmp_path: Path) -> None:
    source = write(tmp_path / "in.las")
    assert storage.put_file("jobs/j1/input.las", source) == len(DATA)
    assert source.exists()  # not moved
    info = storage.info("jobs/j1/input.las")
    assert info.size == len(DATA) and info.etag.startswith('"') and info.modified > 0
    assert storage.exists("jobs/j1/input.las") and storage.size("jobs/j1/input.las") == len(DATA)
    assert storage.get_file("jobs/j1/input.las", tmp_path / "out" / "copy.las") == len(DATA)
    assert (tmp_path / "out" / "copy.las").read_bytes() == DATA
    assert storage.read_bytes("jobs/j1/input.las") == DATA
    # moved: the local file is gone, the object replaced whole
    moved = write(tmp_path / "again.las", b"new")
    storage.put_file("jobs/j1/input.las", moved, move=True)
    assert not moved.exists()
    assert storage.read_bytes("jobs/j1/input.las") == b"new"
    assert storage.info("jobs/j1/input.las").etag != info.etag


def test_ranges(storage: Storage, tmp_path: Path) -> None:
    storage.put_file("k/data.bin", write(tmp_path / "d"))
    assert b"".join(storage.iter_range("k/data.bin", 10, 19)) == DATA[10:20]
    assert b"".join(storage.iter_range("k/data.bin", len(DATA) - 5)) == DATA[-5:]
    chunks = list(storage.iter_range("k/data.bin", 1, 300_000, chunk_bytes=65536))
    assert b"".join(chunks) == DATA[1:300_001] and len(chunks) > 1
    assert max(len(c) for c in chunks) <= 65536


def test_missing_objects(storage: Storage, tmp_path: Path) -> None:
    assert storage.info("jobs/none/result.las") is None
    assert not storage.exists("jobs/none/result.las")
    with pytest.raises(ObjectMissing):
        storage.get_file("jobs/none/result.las", tmp_path / "x")
    assert not (tmp_path / "x").exists()
    with pytest.raises(ObjectMissing):
        storage.iter_range("jobs/none/result.las")
    with pytest.raises(ObjectMissing):
        storage.copy("jobs/none/result.las", "jobs/other/input.las")
    storage.delete("jobs/none/result.las")  # nothing to do
    storage.delete_prefix("jobs/none/")
    assert storage.prefix_bytes("jobs/none/") == 0


def test_copy_delete_and_prefixes(storage: Storage, tmp_path: Path) -> None:
    storage.put_file("uploads/1/u.las", write(tmp_path / "u", b"12345"))
    assert storage.copy("uploads/1/u.las", "jobs/j2/input.las") == 5
    storage.put_file("jobs/j2/statistics.json", write(tmp_path / "s", b"{}"))
    storage.put_file("jobs/j20/input.las", write(tmp_path / "o", b"other"))
    assert storage.prefix_bytes("jobs/j2/") == 7
    storage.delete_prefix("jobs/j2/")
    assert not storage.exists("jobs/j2/input.las") and not storage.exists("jobs/j2/statistics.json")
    assert storage.exists("jobs/j20/input.las")  # a sibling whose name starts alike stays
    assert storage.read_bytes("uploads/1/u.las") == b"12345"  # the copy was a copy
    storage.delete("uploads/1/u.las")
    assert not storage.exists("uploads/1/u.las")
    storage.check()


def test_many_objects_under_one_prefix(storage: Storage, tmp_path: Path) -> None:
    if isinstance(storage, S3Storage):
        storage.page_size = 4  # several listing pages and delete requests
    one = write(tmp_path / "one", b"x")
    for i in range(11):
        storage.put_file(f"jobs/many/{i:04d}", one)
    assert storage.prefix_bytes("jobs/many/") == 11
    storage.delete_prefix("jobs/many/")
    assert storage.prefix_bytes("jobs/many/") == 0


def test_keys_must_stay_inside(storage: Storage, tmp_path: Path) -> None:
    for key in ("../escape", "/abs", "jobs//x", "jobs/./x", ""):
        with pytest.raises(ValueError, match="not a storage key"):
            storage.put_file(key, write(tmp_path / "f", b"1"))


def test_local_keys_are_paths_under_data_dir(tmp_path: Path) -> None:
    storage = open_storage(Settings(data_dir=tmp_path))
    assert isinstance(storage, LocalStorage)
    storage.put_file("jobs/j/result.las", write(tmp_path / "r", b"abc"), move=True)
    assert (tmp_path / "jobs" / "j" / "result.las").read_bytes() == b"abc"
    assert not list((tmp_path / "jobs" / "j").glob(".*"))  # no temporary file left


def test_s3_from_settings_and_unreachable_store(moto: MotoServer, tmp_path: Path) -> None:
    bucket = moto.new_bucket()
    settings = Settings(data_dir=tmp_path, storage_url=f"s3://{bucket}/a/b",
                        s3_endpoint_url=moto.url)
    storage = open_storage(settings)
    assert isinstance(storage, S3Storage) and storage.prefix == "a/b"
    storage.put_file("jobs/j/x", write(tmp_path / "x", b"1"))
    assert [o["Key"] for o in moto.client().list_objects_v2(Bucket=bucket)["Contents"]] == [
        "a/b/jobs/j/x"]
    with pytest.raises(ValueError, match="STORAGE_URL"):
        Settings(data_dir=tmp_path, storage_url="https://bucket/x")
    missing = S3Storage(f"no-such-{uuid.uuid4().hex[:6]}", "", moto.url)
    with pytest.raises(StorageError, match="not usable"):
        missing.check()
    with pytest.raises(StorageError, match="cannot store"):
        missing.put_file("jobs/j/x", tmp_path / "x")
