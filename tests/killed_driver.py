"""`heartctl generate` in a new process whose driver is killed (SIGKILL) right after it has written and
recorded its first batch of cases: the kill lands mid-sweep by construction, whatever the solver's speed."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
KILLED_AFTER_FIRST_WRITE = """
import os, signal, sys
import orchestrator.sweep as sweep
recorded = sweep._record
def record_then_die(store, *args):
    out = recorded(store, *args)
    store.flush()
    os.kill(os.getpid(), signal.SIGKILL)
sweep._record = record_then_die
from cli import main
sys.argv = ["heartctl", *sys.argv[1:]]
main()
"""


def generate_killed_after_first_write(args: list[str], ray_address: str) -> None:
    """Run `heartctl generate ARGS --address RAY_ADDRESS` (a Ray this test started: the driver's kill
    leaves it running, as a cluster would be); asserts the driver was killed, not ended."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    killed = subprocess.run([sys.executable, "-c", KILLED_AFTER_FIRST_WRITE, *args, "--address", ray_address],
                            cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert killed.returncode == -signal.SIGKILL, killed.stdout[-2000:] + killed.stderr[-2000:]
