"""S3-compatible object storage of sweep archives (boto3).

:class:`ObjectStore` wraps one bucket and key prefix (``s3://bucket/prefix``).
Every upload is verified after the fact: the object is written with its MD5
(``Content-MD5``, so the server refuses a body damaged on the way) and its SHA-256
as metadata, then read back with ``HEAD``: the size, the ``ETag`` (the MD5 of a
single-part upload) and the stored SHA-256 must all match the local file, else
:class:`UploadMismatch`. Downloads are checked against the stored SHA-256.

Configuration: ``[storage.s3]`` keys (endpoint, region, keys), else the usual AWS
environment variables and files, which boto3 reads itself (``AWS_ENDPOINT_URL``,
``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_DEFAULT_REGION``,
``AWS_PROFILE``). Path-style addressing (``http://host/bucket/key``) so that
self-hosted servers (MinIO, Ceph, moto) work without DNS names per bucket.

Errors: a server that cannot be reached, refuses the credentials or has no such
bucket raises :class:`ObjectStoreUnavailable` (a :class:`station.db.StoreUnavailable`:
the web layer answers 503) naming the bucket and the endpoint.
"""

from __future__ import annotations

import base64
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from calibration.archive import sha256_hex
from station.db import StoreUnavailable

SHA256_META = "sha256"
"""User metadata key holding the object's SHA-256 (hex)."""


class ObjectStoreUnavailable(StoreUnavailable):
    """The object store cannot be reached or refuses the request."""


class UploadMismatch(StoreUnavailable):
    """An uploaded object does not read back as the local file (size, MD5 or SHA-256)."""


def split_s3_url(url: str) -> tuple[str, str]:
    """``s3://bucket/a/b`` -> ``("bucket", "a/b")`` (no leading or trailing slash)."""
    if not url.startswith("s3://"):
        raise ValueError(f"not an s3:// URL: {url!r}")
    rest = url[len("s3://") :]
    bucket, _, key = rest.partition("/")
    if not bucket:
        raise ValueError(f"no bucket in {url!r}")
    return bucket, key.strip("/")


def file_digests(path: Path) -> tuple[bytes, str, str]:
    """The file's bytes, MD5 (hex) and SHA-256 (hex)."""
    data = path.read_bytes()
    return data, hashlib.md5(data).hexdigest(), hashlib.sha256(data).hexdigest()


@dataclass(frozen=True)
class StoredObject:
    """An object as the server describes it (key relative to the bucket)."""

    key: str
    size: int
    etag: str
    sha256: str | None


def _s3_settings(settings: Any) -> dict[str, Any]:
    """``[storage.s3]`` (an :class:`station.config.S3Config`, a dict, or None) as a dict."""
    if settings is None:
        return {}
    if isinstance(settings, dict):
        return dict(settings)
    return dict(settings.model_dump())


class ObjectStore:
    """One bucket of an S3-compatible server (see the module docstring).

    Args:
        url: ``s3://bucket`` or ``s3://bucket/prefix``.
        settings: ``[storage.s3]`` (endpoint_url, region, access_key_id,
            secret_access_key, connect_timeout_s); missing keys from the environment.
    """

    def __init__(self, url: str, settings: Any = None) -> None:
        import boto3
        from botocore.config import Config

        self.url = url.rstrip("/")
        self.bucket, self.prefix = split_s3_url(self.url)
        s3 = _s3_settings(settings)
        self.settings = s3
        timeout = float(s3.get("connect_timeout_s") or 5.0)
        session = boto3.session.Session()
        self.client = session.client(
            "s3",
            endpoint_url=s3.get("endpoint_url") or None,
            region_name=s3.get("region") or os.environ.get("AWS_DEFAULT_REGION") or "us-east-1",
            aws_access_key_id=s3.get("access_key_id") or None,
            aws_secret_access_key=s3.get("secret_access_key") or None,
            config=Config(
                connect_timeout=timeout,
                read_timeout=max(30.0, timeout),
                retries={"max_attempts": 2, "mode": "standard"},
                s3={"addressing_style": "path"},
            ),
        )
        self.endpoint = str(self.client.meta.endpoint_url)

    # ------------------------------------------------------------------ errors

    def _error(self, exc: BaseException, doing: str) -> ObjectStoreUnavailable:
        from botocore.exceptions import ClientError

        where = f"the object store {self.url} at {self.endpoint}"
        if isinstance(exc, ClientError):
            code = str(exc.response.get("Error", {}).get("Code", ""))
            text = str(exc.response.get("Error", {}).get("Message", "")) or code
            hint = {
                "NoSuchBucket": "create the bucket, or correct [storage] archive_url",
                "404": "create the bucket, or correct [storage] archive_url",
                "AccessDenied": "check the credentials and the bucket's policy",
                "403": "check the credentials and the bucket's policy",
                "InvalidAccessKeyId": "check the access key",
                "SignatureDoesNotMatch": "check the secret key",
            }.get(code, "see the server's log")
            return ObjectStoreUnavailable(
                f"{where} refused to {doing}: {code} {text}; {hint}", path=self.url, cause=text
            )
        text = str(exc) or type(exc).__name__
        return ObjectStoreUnavailable(
            f"{where} is unreachable ({doing}): {text}; check that the server runs and the "
            "endpoint ([storage.s3] endpoint_url or AWS_ENDPOINT_URL)",
            path=self.url,
            cause=text,
        )

    def key(self, relative: str) -> str:
        """The object key of ``relative`` under this store's prefix."""
        relative = relative.strip("/")
        return f"{self.prefix}/{relative}" if self.prefix else relative

    # ------------------------------------------------------------------ operations

    def check(self) -> None:
        """Raise :class:`ObjectStoreUnavailable` unless the bucket can be reached."""
        try:
            self.client.head_bucket(Bucket=self.bucket)
        except Exception as exc:  # noqa: BLE001 - botocore raises many kinds
            raise self._error(exc, "open the bucket") from exc

    def put_file(self, key: str, path: Path) -> StoredObject:
        """Upload a file and verify it read back (:class:`UploadMismatch` otherwise)."""
        data, md5, sha = file_digests(path)
        try:
            self.client.put_object(
                Bucket=self.bucket,
                Key=key,
                Body=data,
                ContentMD5=base64.b64encode(bytes.fromhex(md5)).decode(),
                Metadata={SHA256_META: sha},
            )
            head = self.client.head_object(Bucket=self.bucket, Key=key)
        except Exception as exc:  # noqa: BLE001
            raise self._error(exc, f"store {key}") from exc
        stored = StoredObject(
            key,
            int(head.get("ContentLength", -1)),
            str(head.get("ETag", "")).strip('"'),
            (head.get("Metadata") or {}).get(SHA256_META),
        )
        if stored.size != len(data) or stored.etag != md5 or stored.sha256 != sha:
            raise UploadMismatch(
                f"{self.url}: {key} does not read back as uploaded (size {stored.size} vs "
                f"{len(data)}, ETag {stored.etag} vs MD5 {md5}, SHA-256 {stored.sha256} vs {sha})",
                path=self.url,
            )
        return stored

    def list(self, prefix: str) -> list[StoredObject]:
        """Every object under ``prefix`` (a key prefix; SHA-256 not included)."""
        out: list[StoredObject] = []
        try:
            paginator = self.client.get_paginator("list_objects_v2")
            for page in paginator.paginate(Bucket=self.bucket, Prefix=prefix.rstrip("/") + "/"):
                for item in page.get("Contents", []):
                    out.append(
                        StoredObject(
                            item["Key"], int(item["Size"]), str(item["ETag"]).strip('"'), None
                        )
                    )
        except Exception as exc:  # noqa: BLE001
            raise self._error(exc, f"list {prefix}") from exc
        return out

    def get_file(self, key: str, dest: Path) -> str:
        """Download an object to ``dest`` (atomically), checked against its stored
        SHA-256; returns that SHA-256."""
        try:
            obj = self.client.get_object(Bucket=self.bucket, Key=key)
            data = obj["Body"].read()
        except Exception as exc:  # noqa: BLE001
            raise self._error(exc, f"read {key}") from exc
        sha = sha256_hex(data)
        expected = (obj.get("Metadata") or {}).get(SHA256_META)
        if expected is not None and expected != sha:
            raise UploadMismatch(
                f"{self.url}: {key} is damaged: SHA-256 {sha}, stored {expected}", path=self.url
            )
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(f".{dest.name}.part")
        tmp.write_bytes(data)
        tmp.replace(dest)
        return sha

    def head(self, key: str) -> StoredObject | None:
        """The object's size, ETag and SHA-256, or None when there is none."""
        from botocore.exceptions import ClientError

        try:
            head = self.client.head_object(Bucket=self.bucket, Key=key)
        except ClientError as exc:
            if str(exc.response.get("Error", {}).get("Code")) in ("404", "NoSuchKey", "NotFound"):
                return None
            raise self._error(exc, f"read {key}") from exc
        except Exception as exc:  # noqa: BLE001
            raise self._error(exc, f"read {key}") from exc
        return StoredObject(
            key,
            int(head.get("ContentLength", -1)),
            str(head.get("ETag", "")).strip('"'),
            (head.get("Metadata") or {}).get(SHA256_META),
        )


__all__ = [
    "SHA256_META",
    "ObjectStore",
    "ObjectStoreUnavailable",
    "StoredObject",
    "UploadMismatch",
    "file_digests",
    "split_s3_url",
]
