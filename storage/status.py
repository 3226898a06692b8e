"""A store's progress as `heartctl status` reports it: counts by status, failure reasons, throughput
and ETA (store.summarize), and on request every damaged case: a shape whose arrays are not what the
schema implies, a status code out of range, a done case whose data are missing, short, unreadable or
not finite."""
from __future__ import annotations

from .store import PairReader, StoreError, inspect_store, reading_store, summarize


def store_status(location: str, verify: bool = False) -> dict:
    """summarize(location), with "damaged" ({"shape", "case", "reason"} per damaged case, case None
    for every case of a shape; PairReader.damaged) when `verify`, which reads every done case.
    StoreError (one line) when there is no heartctl store at `location` or it cannot be read."""
    with reading_store(location):
        if inspect_store(location) is None:
            raise StoreError(f"no heartctl store at {location}")
        status = summarize(location)
        if verify:
            status["damaged"] = [{"shape": s, "case": k, "reason": r} for s, k, r in PairReader(location).damaged()]
    return status
