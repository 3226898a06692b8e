"""A digest of the solver's source: stores and cached benchmark results record it, so results of
other solver code are recognised."""
from __future__ import annotations

import hashlib
from pathlib import Path


def solver_digest() -> str:
    """First 12 hex digits of the SHA-256 over the solver package's .py files (names and bytes)."""
    h = hashlib.sha256()
    for p in sorted(Path(__file__).parent.glob("*.py")):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:12]
