"""Objects in an S3-compatible store (AWS S3, MinIO, ...) through boto3.

``STORAGE_URL=s3://bucket/prefix`` puts every key under ``prefix/``; ``S3_ENDPOINT_URL`` names a
store other than AWS (path-style addressing then, which MinIO and most others need). Credentials
and the region come from the usual AWS environment variables or files (``AWS_ACCESS_KEY_ID``,
``AWS_SECRET_ACCESS_KEY``, ``AWS_DEFAULT_REGION``, ``AWS_PROFILE`` ...), as boto3 reads them.

Large files go up and down in parts (boto3's managed transfers); copies stay inside the store.
A PUT is atomic in S3, so no reader sees a partial object.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import boto3
import botocore.exceptions
from boto3.s3.transfer import TransferConfig
from botocore.config import Config

from lidar_outliers.atomic import atomic_path
from lidar_outliers.jobs.storage import (
    CHUNK_BYTES,
    ObjectInfo,
    ObjectMissing,
    Storage,
    StorageError,
    check_key,
)

#: Parts of 64 MiB: a 2 GiB upload in 32 requests, four at a time.
TRANSFER = TransferConfig(multipart_threshold=64 * 1024**2, multipart_chunksize=64 * 1024**2,
                          max_concurrency=4)
NOT_FOUND = {"404", "NoSuchKey", "NotFound"}


def _missing(exc: botocore.exceptions.ClientError) -> bool:
    return str(exc.response.get("Error", {}).get("Code")) in NOT_FOUND


class S3Storage(Storage):
    #: Keys per listing page and per delete request (1000: the most S3 allows for either).
    page_size = 1000

    def __init__(self, bucket: str, prefix: str = "", endpoint_url: str | None = None) -> None:
        self.bucket = bucket
        self.prefix = prefix.strip("/")
        self.endpoint_url = endpoint_url
        config = Config(
            retries={"max_attempts": 5, "mode": "standard"},
            s3={"addressing_style": "path"} if endpoint_url else {},
            connect_timeout=10, read_timeout=60,
        )
        # a session of its own: boto3's default session is not safe to share between threads
        self.client = boto3.session.Session().client("s3", endpoint_url=endpoint_url,
                                                     config=config)

    @classmethod
    def from_url(cls, url: str, endpoint_url: str | None = None) -> S3Storage:
        """From ``s3://bucket/prefix``."""
        scheme, _, rest = url.partition("://")
        bucket, _, prefix = rest.partition("/")
        if scheme != "s3" or not bucket:
            raise ValueError(f"not an s3://bucket/prefix URL: {url!r}")
        return cls(bucket, prefix, endpoint_url)

    def object_key(self, key: str) -> str:
        check_key(key)
        return f"{self.prefix}/{key}" if self.prefix else key

    def _error(self, action: str, key: str, exc: Exception) -> StorageError:
        return StorageError(f"object storage {self.describe()}: cannot {action} {key!r}: {exc}")

    def put_file(self, key: str, path: Path, *, move: bool = False) -> int:
        size = path.stat().st_size
        try:
            self.client.upload_file(str(path), self.bucket, self.object_key(key),
                                    Config=TRANSFER)
        except (botocore.exceptions.BotoCoreError,
                botocore.exceptions.ClientError, boto3.exceptions.S3UploadFailedError) as exc:
            raise self._error("store", key, exc) from None
        if move:
            path.unlink(missing_ok=True)
        return size

    def copy(self, source: str, target: str) -> int:
        try:
            self.client.copy({"Bucket": self.bucket, "Key": self.object_key(source)},
                             self.bucket, self.object_key(target), Config=TRANSFER)
        except botocore.exceptions.ClientError as exc:
            if _missing(exc):
                raise ObjectMissing(source) from None
            raise self._error("copy", source, exc) from None
        except botocore.exceptions.BotoCoreError as exc:
            raise self._error("copy", source, exc) from None
        found = self.info(target)
        if found is None:
            raise ObjectMissing(target)
        return found.size

    def get_file(self, key: str, path: Path) -> int:
        with atomic_path(path) as tmp:
            try:
                self.client.download_file(self.bucket, self.object_key(key), str(tmp),
                                          Config=TRANSFER)
            except botocore.exceptions.ClientError as exc:
                if _missing(exc):
                    raise ObjectMissing(key) from None
                raise self._error("read", key, exc) from None
            except botocore.exceptions.BotoCoreError as exc:
                raise self._error("read", key, exc) from None
        return path.stat().st_size

    def iter_range(self, key: str, start: int = 0, end: int | None = None,
                   chunk_bytes: int = CHUNK_BYTES) -> Iterator[bytes]:
        span = f"bytes={start}-" + ("" if end is None else str(end))
        try:
            answer = self.client.get_object(Bucket=self.bucket, Key=self.object_key(key),
                                            Range=span)
        except botocore.exceptions.ClientError as exc:
            if _missing(exc):
                raise ObjectMissing(key) from None
            if exc.response.get("Error", {}).get("Code") == "InvalidRange":
                return iter(())  # an empty object: nothing to read
            raise self._error("read", key, exc) from None
        except botocore.exceptions.BotoCoreError as exc:
            raise self._error("read", key, exc) from None
        return _stream(answer["Body"], chunk_bytes)

    def info(self, key: str) -> ObjectInfo | None:
        try:
            head = self.client.head_object(Bucket=self.bucket, Key=self.object_key(key))
        except botocore.exceptions.ClientError as exc:
            if _missing(exc):
                return None
            raise self._error("look up", key, exc) from None
        except botocore.exceptions.BotoCoreError as exc:
            raise self._error("look up", key, exc) from None
        return ObjectInfo(size=int(head["ContentLength"]), etag=head["ETag"],
                          modified=head["LastModified"].timestamp())

    def delete(self, key: str) -> None:
        try:
            self.client.delete_object(Bucket=self.bucket, Key=self.object_key(key))
        except (botocore.exceptions.BotoCoreError, botocore.exceptions.ClientError) as exc:
            raise self._error("delete", key, exc) from None

    def _list(self, prefix: str) -> Iterator[dict[str, Any]]:
        full = self.object_key(prefix.rstrip("/")) + ("/" if prefix.endswith("/") else "")
        pages = self.client.get_paginator("list_objects_v2").paginate(
            Bucket=self.bucket, Prefix=full, PaginationConfig={"PageSize": self.page_size})
        try:
            for page in pages:
                yield from page.get("Contents", [])
        except (botocore.exceptions.BotoCoreError, botocore.exceptions.ClientError) as exc:
            raise self._error("list", prefix, exc) from None

    def delete_prefix(self, prefix: str) -> None:
        batch: list[dict[str, str]] = []
        for item in self._list(prefix):
            batch.append({"Key": item["Key"]})
            if len(batch) == self.page_size:
                self._delete_batch(batch)
                batch = []
        if batch:
            self._delete_batch(batch)

    def _delete_batch(self, batch: list[dict[str, str]]) -> None:
        try:
            self.client.delete_objects(Bucket=self.bucket,
                                       Delete={"Objects": batch, "Quiet": True})
        except (botocore.exceptions.BotoCoreError, botocore.exceptions.ClientError) as exc:
            raise self._error("delete", batch[0]["Key"], exc) from None

    def prefix_bytes(self, prefix: str) -> int:
        return sum(int(item["Size"]) for item in self._list(prefix))

    def check(self) -> None:
        try:
            self.client.head_bucket(Bucket=self.bucket)
        except (botocore.exceptions.BotoCoreError, botocore.exceptions.ClientError) as exc:
            raise StorageError(f"object storage {self.describe()} is not usable: {exc}") from None

    def describe(self) -> str:
        where = f" at {self.endpoint_url}" if self.endpoint_url else ""
        return f"s3://{self.bucket}/{self.prefix}{where}"


def _stream(body: Any, chunk_bytes: int) -> Iterator[bytes]:
    try:
        yield from body.iter_chunks(chunk_bytes)
    finally:
        body.close()
