"""Progress of long work (a large mesh, a large solve) as short texts for whoever listens: the CLI
listens only when it expects the work to take long, and prints each text as a line on stderr.
Without a listener, report() does nothing (the sweep's workers, the tests, small solves)."""
from __future__ import annotations

from contextlib import contextmanager

_listener = None


@contextmanager
def reporting(listener):
    """Within the block, report(text) calls listener(text)."""
    global _listener
    saved, _listener = _listener, listener
    try:
        yield
    finally:
        _listener = saved


def report(text: str) -> None:
    if _listener is not None:
        _listener(text)
