"""Where a store is, how it is opened, and its errors in words.

A store is a local folder or an object-store URL (s3://, gs://). This module opens its root group,
passes an S3-compatible endpoint on, and turns what zarr, fsspec or botocore raise while a store is
read into one-line StoreErrors: a damaged chunk, a missing bucket, refused credentials, a server
that does not answer.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path


class StoreError(ValueError):
    """A store that cannot be used as asked; the message is one line."""


@contextmanager
def reading_store(location, keep: tuple = ()):
    """Errors from zarr, numcodecs or the filesystem while a store is read (a damaged chunk fails its
    CRC-32C, or raises RuntimeError from its decompressor) as one-line StoreErrors, which the CLI
    reports with exit 2 and Ray Train workers refuse at once instead of retrying. StoreErrors, the
    exception types in `keep` and programming errors (TypeError, AttributeError, NameError) pass
    unchanged, except a checksum mismatch (a ValueError in zarr), which is always damage, and an
    object store's refusal or silence (object_store_problem), which is said in words."""
    try:
        yield
    except Exception as exc:
        if is_checksum_error(exc):
            raise StoreError(f"cannot read store {location}: a stored chunk is damaged (its checksum does not "
                             f"match)") from None
        if isinstance(exc, (StoreError, TypeError, AttributeError, NameError)):
            raise
        reason = object_store_problem(location, exc)
        if reason is None and isinstance(exc, keep):
            raise
        reason = reason or (f"missing {exc.args[0]!r}" if isinstance(exc, KeyError) and exc.args else
                            (str(exc).splitlines()[0] if str(exc) else type(exc).__name__))
        raise StoreError(f"cannot read store {location}: {reason}") from None


def is_checksum_error(exc: Exception) -> bool:
    return type(exc) is ValueError and "checksum do not match" in str(exc)


def first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def read_error_words(exc: Exception) -> str:
    """A chunk read error in words: a checksum mismatch, or the error's first line."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return "its checksum does not match (changed bytes)" if is_checksum_error(exc) else f"it does not read ({text[:100]})"


# --------------------------------------------------------------------------- opening


def is_url(location: str) -> bool:
    return "://" in str(location) and not str(location).startswith("file://")


def local_path(location) -> Path:
    s = str(location)
    return Path(s[len("file://"):] if s.startswith("file://") else s)


def open_group(location, mode: str, storage_options: dict | None = None):
    import zarr

    if is_url(location):
        return zarr.open_group(str(location), mode=mode, zarr_format=3,
                               storage_options=url_options(location, storage_options))
    from zarr.storage import LocalStore

    return zarr.open_group(LocalStore(local_path(location), read_only=(mode == "r")), mode=mode, zarr_format=3)


# --------------------------------------------------------------------------- object stores (s3://)

ENDPOINT_VARS = ("AWS_ENDPOINT_URL_S3", "AWS_ENDPOINT_URL")  # botocore's names, the service's own first


def s3_endpoint(storage_options: dict | None = None) -> str | None:
    """The S3-compatible server an s3:// store is opened at (MinIO, Ceph, moto): the options' own
    endpoint_url, else AWS_ENDPOINT_URL_S3, else AWS_ENDPOINT_URL; None means AWS itself."""
    given = (storage_options or {}).get("endpoint_url")
    return given or next((os.environ[v] for v in ENDPOINT_VARS if os.environ.get(v)), None)


def url_options(location, storage_options: dict | None = None) -> dict | None:
    """fsspec options of a store URL. For s3://, the endpoint of s3_endpoint (older botocore does not
    read the variables itself), and no cached listings, so that a reader sees the shapes a running
    sweep adds; credentials and region come from the usual AWS variables (AWS_ACCESS_KEY_ID,
    AWS_SECRET_ACCESS_KEY, AWS_DEFAULT_REGION) or an instance profile, read by botocore."""
    options = dict(storage_options or {})
    if not str(location).startswith("s3://"):
        return options or None
    endpoint = s3_endpoint(options)
    if endpoint:
        options["endpoint_url"] = endpoint
    options.setdefault("use_listings_cache", False)
    return options


def _exception_chain(exc: BaseException):
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


CREDENTIAL_CODES = frozenset({"InvalidAccessKeyId", "SignatureDoesNotMatch", "AccessDenied", "Forbidden", "403",
                              "ExpiredToken", "InvalidToken", "InvalidClientTokenId"})
UNREACHABLE_ERRORS = frozenset({"EndpointConnectionError", "ConnectTimeoutError", "ReadTimeoutError",
                                "ClientConnectorError", "ServerDisconnectedError", "ConnectionClosedError"})


def object_store_problem(location, exc: BaseException) -> str | None:
    """What an object store (s3://) said, in words, when exc (or an error it was raised from) is its
    refusal or its silence: a missing bucket, credentials refused or missing, an endpoint that does
    not answer. None for a local store and for any other error."""
    if not str(location).startswith("s3://"):
        return None
    server = _server()
    for e in _exception_chain(exc):
        name = type(e).__name__
        code = str(((getattr(e, "response", None) or {}).get("Error") or {}).get("Code", ""))
        if name == "NoSuchBucket" or code == "NoSuchBucket" or "bucket does not exist" in str(e):
            return f"its bucket {_bucket(location)!r} does not exist on {server}; create it or fix the URL"
        if name in ("NoCredentialsError", "PartialCredentialsError"):
            return (f"no AWS credentials found for {server}; set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY "
                    f"(or use an instance profile)")
        if code in CREDENTIAL_CODES or isinstance(e, PermissionError):
            return (f"{server} refused access ({first_line(e)}); check AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY "
                    f"and the bucket's permissions")
        if name in UNREACHABLE_ERRORS or isinstance(e, (ConnectionError, TimeoutError)):
            return (f"{server} does not answer ({name})"
                    + ("" if s3_endpoint() else "; an S3-compatible server is named by AWS_ENDPOINT_URL"))
    return None


def _bucket(location) -> str:
    return str(location)[len("s3://"):].split("/", 1)[0]


def check_bucket(location, storage_options: dict | None = None) -> None:
    """StoreError when the bucket of an s3:// store is missing or refuses these credentials: an s3://
    URL where no store is yet is a new store only in a bucket that exists."""
    import fsspec

    if not str(location).startswith("s3://"):
        return
    fs = fsspec.filesystem("s3", **(url_options(location, storage_options) or {}))
    try:
        fs.info(_bucket(location))
    except Exception as exc:
        problem = (f"its bucket {_bucket(location)!r} does not exist on {_server()}; create it or fix the URL"
                   if isinstance(exc, FileNotFoundError) else object_store_problem(location, exc))  # 404: head_bucket's
        if problem is None:
            raise
        raise StoreError(f"store {location}: {problem}") from None


def _server() -> str:
    where = s3_endpoint()
    return f"the S3 endpoint {where}" if where else "S3"
