"""One writer per store: `heartctl generate` holds a lock file in a local store while it writes.

The sweep driver caches each shape's status and statistics and writes them whole, keeps the audit
trail of runs, and clears temporary files a killed writer left: two drivers on one store would undo
each other's progress and delete each other's files. The lock is a file created with O_EXCL that
names the holder (host, pid, start time). A lock whose holder process is gone (same host, pid no
longer running) is stale and taken over; the holder's own process may take it again. Object stores
(s3://, gs://) have no such file: there, run one driver per store (README, "On a cluster").
"""
from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

from .store import StoreError, _local_path, is_url

LOCK_NAME = ".heartctl-writer.lock"


def holder(location) -> dict | None:
    """The live writer holding the store's lock ({host, pid, since}), or None (no lock, a stale
    one, this process's own, or an object store)."""
    if is_url(location):
        return None
    info = _read(_local_path(location) / LOCK_NAME)
    if info is None or _stale(info) or _own(info):
        return None
    return info


def check_free(location) -> None:
    """StoreError (one line) when another live process writes the store."""
    info = holder(location)
    if info is not None:
        raise StoreError(f"store {location} is being written by pid {info.get('pid')} on {info.get('host')} "
                         f"since {info.get('since')}; wait for that run to end or stop it (if it is gone, "
                         f"delete {_local_path(location) / LOCK_NAME})")


class WriterLock:
    """Held while a driver writes a local store (a context manager; no-op for object stores)."""

    def __init__(self, location):
        self.location = location
        self.path = None if is_url(location) else _local_path(location) / LOCK_NAME
        self.held = False

    def acquire(self) -> "WriterLock":
        if self.path is None:
            return self
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                check_free(self.location)  # raises unless the lock is stale or our own
                try:
                    self.path.unlink()
                except FileNotFoundError:
                    pass
                continue
            with os.fdopen(fd, "w") as f:
                json.dump({"host": socket.gethostname(), "pid": os.getpid(),
                           "since": time.strftime("%Y-%m-%dT%H:%M:%S%z")}, f)
            self.held = True
            return self
        check_free(self.location)
        raise StoreError(f"could not take the writer lock {self.path}")

    def release(self) -> None:
        if self.held:
            info = _read(self.path)
            if info is not None and _own(info):
                self.path.unlink(missing_ok=True)
            self.held = False

    def __enter__(self) -> "WriterLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _read(path: Path) -> dict | None:
    try:
        info = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError):  # a lock its writer died while writing: no holder to name
        return {"host": socket.gethostname(), "pid": -1}
    return info if isinstance(info, dict) else {"host": socket.gethostname(), "pid": -1}


def _own(info: dict) -> bool:
    return info.get("host") == socket.gethostname() and info.get("pid") == os.getpid()


def _stale(info: dict) -> bool:
    """The holder ran on this host and its process is gone (another host's process cannot be seen)."""
    if info.get("host") != socket.gethostname():
        return False
    pid = info.get("pid")
    if not isinstance(pid, int) or pid <= 0:
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, another user's
        return False
    return False
