"""Processes by their parent chain, for tests that kill a Ray worker or node in the middle of its work."""
from __future__ import annotations

from pathlib import Path


def descends_from(pid: int, ancestor: int) -> bool:
    """Whether `ancestor` is `pid` or one of its parents (Linux /proc)."""
    while pid > 1:
        if pid == ancestor:
            return True
        try:
            stat = (Path("/proc") / str(pid) / "stat").read_text()
        except OSError:
            return False
        pid = int(stat.rsplit(")", 1)[1].split()[1])  # field 4, after the parenthesised name
    return False


def processes_titled(title: bytes, ancestor: int) -> list[int]:
    """PIDs of the processes below `ancestor` whose command line starts with `title` (Ray names a busy
    worker process after its task or actor: ray::run_chain, ray::RayTrainWorker)."""
    pids = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            cmd = (d / "cmdline").read_bytes()
        except OSError:
            continue
        if cmd.startswith(title) and descends_from(int(d.name), ancestor):
            pids.append(int(d.name))
    return pids
