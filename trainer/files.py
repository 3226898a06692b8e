"""Result files written whole or not at all: each goes to a temporary name beside its target and is
renamed over it once complete (storage.meshfiles.atomic_write), so a crash never leaves half a CSV."""
from __future__ import annotations

import csv
import json
from pathlib import Path

from storage.meshfiles import atomic_write


def write_csv(path: Path, rows: list, fieldnames: list | None = None) -> None:
    """rows (dicts) as a CSV with a header; fieldnames default to the first row's keys; an empty
    file when there are neither rows nor fieldnames."""
    fieldnames = fieldnames or (list(rows[0]) if rows else None)

    def writer(tmp):
        with open(tmp, "w", newline="") as f:
            if fieldnames:
                w = csv.DictWriter(f, fieldnames=fieldnames, extrasaction="ignore")
                w.writeheader()
                w.writerows(rows)

    atomic_write(Path(path), writer)


def write_json(path: Path, obj) -> None:
    atomic_write(Path(path), lambda tmp: Path(tmp).write_text(json.dumps(obj, indent=2)))
