"""One writer per store: `heartctl generate` holds a lock on a file in a local store while it writes.

The sweep driver caches each shape's status and statistics and writes them whole, keeps the audit
trail of runs, and clears temporary files a killed writer left: two drivers on one store would undo
each other's progress and delete each other's files. The lock is an exclusive `flock` on
`.heartctl-writer.lock` in the store, whose content names the holder (host, pid, start time). The
kernel releases it when the holder's process ends, however it ends, so a killed driver leaves no
stale lock and no two processes can hold it at once. Object stores (s3://, gs://) have no such
file: there, run one driver per store (README and docs/data.md, "On a cluster"). On network file systems flock is
as reliable as their locking.
"""
from __future__ import annotations

import fcntl
import json
import os
import socket
import time

from .location import StoreError, is_url, local_path

LOCK_NAME = ".heartctl-writer.lock"  # the writer lock's file in a local store

# holder() probes the lock by taking it for a moment; a writer that finds it busy tries again for this
# long before it believes another writer holds it (a real writer holds it for the whole sweep).
PROBE_WAIT_S = 1.0


def holder(location) -> dict | None:
    """Who holds the store's writer lock ({host, pid, since}; empty while the holder is still
    writing its name), or None: nobody, this process, or an object store."""
    if is_url(location):
        return None
    path = local_path(location) / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            info = _read(fd)
            own = info.get("pid") == os.getpid() and info.get("host") == socket.gethostname()
            return None if own else info
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def check_free(location) -> None:
    """StoreError (one line) when another process writes the store."""
    info = holder(location)
    if info is not None:
        raise StoreError(_held_message(location, info))


class WriterLock:
    """Held while a driver writes a local store (a context manager; no-op for object stores)."""

    def __init__(self, location):
        self.location = location
        self.path = None if is_url(location) else local_path(location) / LOCK_NAME
        self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> "WriterLock":
        if self.path is None or self._fd is not None:
            return self
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        deadline = time.monotonic() + PROBE_WAIT_S
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() < deadline:  # perhaps only holder()'s probe (status, check_free)
                    time.sleep(0.02)
                    continue
                info = _read(fd)
                os.close(fd)
                raise StoreError(_held_message(self.location, info)) from None
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps({"host": socket.gethostname(), "pid": os.getpid(),
                                 "since": time.strftime("%Y-%m-%dT%H:%M:%S%z")}).encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.ftruncate(self._fd, 0)  # nobody's name in it once free
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "WriterLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _read(fd: int) -> dict:
    try:
        info = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def _held_message(location, info: dict) -> str:
    who = (f"pid {info.get('pid')} on {info.get('host')} since {info.get('since')}" if info.get("pid")
           else "another process")
    return f"store {location} is being written by {who}; wait for that run to end or stop it"
