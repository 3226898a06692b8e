"""What a user reads in the terminal, whatever the command: one-line errors, warnings as lines,
progress of long solves, sizes and durations in words, strict JSON lines."""
from __future__ import annotations

import json
import os
import re
from contextlib import contextmanager

import typer


def _running_command():
    """The command being run (its click context's command), or None outside one."""
    try:
        from typer._click.globals import get_current_context  # the click typer vendors (≥ 0.16)
    except ImportError:
        from click import get_current_context
    ctx = get_current_context(silent=True)
    return None if ctx is None else ctx.command


def flags_in(text: str) -> str:
    """Text from below the command line with its parameters as a user of it reads them. The lower layers
    name a parameter by its Python name, in backticks (`run_dir`) or with its value (split='lovo:P=10');
    here each becomes its flag (--run-dir, --split 'lovo:P=10'). A name=value whose name is not an
    option of the running command stays as it is (it is a key, such as a --set key)."""
    command = _running_command()
    options = {} if command is None else {p.name: max(p.opts, key=len) for p in command.params
                                          if getattr(p, "opts", None) and p.opts[0].startswith("-")}
    text = re.sub(r"`([a-z][a-z0-9_]*)`", lambda m: options.get(m[1]) or "--" + m[1].replace("_", "-"), text)
    return re.sub(r"(?:^|(?<=[\s(]))([a-z][a-z0-9_]*)=(?=[\w'\"/.-])",
                  lambda m: f"{options[m[1]]} " if m[1] in options else m[0], text)


def say(line: str, err: bool = False) -> None:
    """One line for the user, its parameters as flags (flags_in)."""
    typer.echo(flags_in(line), err=err)


def fail(message: str, code: int = 2) -> None:
    """One line on stderr (its parameters as flags), then exit."""
    typer.echo(f"heartctl: error: {flags_in(message)}", err=True)
    raise typer.Exit(code)


# The one table from an exception to the exit status, by the name of its class or of the nearest base
# class listed (the classes live in packages the command line imports late): bad input 2, a computation
# or a store that failed 1, an interruption 130.
EXIT_CODES = {
    "SolveError": 1, "StoreFullError": 1, "StoreLostError": 1, "DiskFullError": 1,
    "KeyboardInterrupt": 130,
    "MeshError": 2, "ParameterError": 2, "StoreError": 2, "TrainerError": 2, "RayConnectError": 2,
    "RayStartError": 2, "ValueError": 2, "FileNotFoundError": 2, "IsADirectoryError": 2, "NotADirectoryError": 2,
}


def exit_code(exc: BaseException) -> int | None:
    """The exit status EXIT_CODES gives an exception, or None when it lists none of its classes."""
    return next((EXIT_CODES[c.__name__] for c in type(exc).__mro__ if c.__name__ in EXIT_CODES), None)


@contextmanager
def failures(solve: str | None = None, interrupted: str | None = None, other: str | None = None):
    """Within the block, an exception EXIT_CODES lists prints one line and exits with its status. A
    solve that fails says `solve: reason`; an interruption says `interrupted` (without it, it passes
    on: `main` reports it); with `other`, any other exception is a failure too (`other: its first
    line`, exit 1). Anything else passes on unchanged."""
    try:
        yield
    except typer.Exit:
        raise
    except BaseException as exc:
        code = exit_code(exc)
        if code == 130 and interrupted is not None:
            fail(interrupted, code=130)
        if code is None and other is not None and isinstance(exc, Exception):
            text = str(exc).strip()
            fail(f"{other}: {text.splitlines()[0] if text else type(exc).__name__}", code=1)
        if code is None or code == 130:
            raise
        is_solve = any(c.__name__ == "SolveError" for c in type(exc).__mro__)
        fail(f"{solve}: {exc}" if is_solve and solve else str(exc), code=code)


SLOW_SOLVE_S = 30.0  # a solve expected to take longer shows its load steps or inverse updates on stderr


LARGE_MESH_NODES = 20_000  # meshing a larger target says so, with its estimate, before gmsh starts


def available_memory() -> float:
    """Bytes of memory available to a new solve on this machine (psutil)."""
    import psutil

    return float(psutil.virtual_memory().available)


def size_text(nbytes: float) -> str:
    gb = nbytes / 1e9
    return f"{gb:.0f} GB" if gb >= 9.5 else f"{gb:.1f} GB" if gb >= 0.95 else f"{nbytes / 1e6:.0f} MB"


def duration_text(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.0f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


class progress_of:
    """Within the block, a solve estimated to take over SLOW_SOLVE_S seconds says so in one line on
    stderr, then prints solver.progress's reports (load steps, inverse updates) as lines with the
    time taken; a shorter one prints nothing."""

    def __init__(self, est, what: str):
        self._est, self._what = est, what

    def __enter__(self):
        import time
        from solver.progress import reporting

        est = self._est
        if est is None or est.seconds <= SLOW_SOLVE_S:
            self._block = None
            return self
        typer.echo(f"heartctl: {self._what}: the {est.preset} {'inverse ' if est.inverse else ''}solve of "
                   f"{est.nodes:,} nodes ({est.unknowns:,} unknowns) takes about {duration_text(est.seconds)} and "
                   f"{size_text(est.peak_bytes)} (a rough estimate); progress follows", err=True)
        start = time.monotonic()
        self._block = reporting(lambda text: typer.echo(f"heartctl: {time.monotonic() - start:.0f} s: {text}",
                                                        err=True))
        self._block.__enter__()
        return self

    def __exit__(self, *exc):
        if self._block is not None:
            self._block.__exit__(*exc)
        return False


def mesh_progress(nodes: int):
    """Meshing a target above LARGE_MESH_NODES: its estimated time and memory in one line on stderr now,
    then gmsh's retries at another element size as lines."""
    import time
    from contextlib import nullcontext

    from solver.budget import estimate_mesh
    from solver.progress import reporting

    if nodes <= LARGE_MESH_NODES:
        return nullcontext()
    peak, seconds = estimate_mesh(nodes)
    typer.echo(f"heartctl: meshing {nodes:,} nodes takes about {duration_text(seconds)} and "
               f"{size_text(peak)} (gmsh, one thread; a rough estimate)", err=True)
    start = time.monotonic()
    return reporting(lambda text: typer.echo(f"heartctl: {time.monotonic() - start:.0f} s: {text}", err=True))


class warnings_as_lines:
    """Within the block, heartctl's warnings for the user (solver.mesh.MeshUnitsWarning) print as
    one line each on stderr, `heartctl: warning: …`; other warnings pass on as usual."""

    def __enter__(self):
        import warnings

        from solver.mesh import MeshUnitsWarning

        self._category = MeshUnitsWarning
        self._catcher = warnings.catch_warnings(record=True)
        self._caught = self._catcher.__enter__()
        warnings.simplefilter("always", MeshUnitsWarning)
        return self

    def __exit__(self, *exc):
        import warnings

        self._catcher.__exit__(*exc)
        for w in self._caught:
            if issubclass(w.category, self._category):
                say(f"heartctl: warning: {w.message}", err=True)
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        return False


def _finite_or_none(value):
    """JSON has no NaN or Infinity: a non-finite number becomes null (nested dicts and lists too;
    NumPy / torch scalars and arrays as Python numbers and lists)."""
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        value = value.tolist()
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    return value


def json_line(value) -> str:
    """One line of strict JSON (non-finite numbers as null; other objects by their str)."""
    return json.dumps(_finite_or_none(value), default=str, allow_nan=False)


def _terminated(signum, frame):
    raise KeyboardInterrupt


def stop_on_sigterm() -> None:
    """SIGTERM (kill, Slurm, systemd) ends a long command as Ctrl-C does: one line, exit 130, done work
    kept; without this, Ray's own handler dumps a C++ stack. Main thread only (signal's rule)."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminated)


def machine_line(threads: int) -> str:
    """Date, machine and solver threads, for a report's header."""
    import datetime
    import platform

    return (f"{datetime.date.today().isoformat()}, {platform.machine()} {os.cpu_count()}-core machine, "
            f"{threads} solver thread(s)")


def seconds_text(x) -> str:
    if x is None:
        return "—"
    if x >= 3600:
        return f"{x / 3600:.1f} h"
    if x >= 60:
        return f"{x / 60:.1f} min"
    return f"{x:.2f} s"


def usage_exception_types() -> tuple:
    """(usage errors, other click errors, aborts) of click and of the click typer vendors (≥ 0.16)."""
    import importlib

    mods = []
    for name in ("typer._click.exceptions", "click.exceptions"):
        try:
            mods.append(importlib.import_module(name))
        except ImportError:
            pass
    aborts = {typer.Abort, *(m.Abort for m in mods if hasattr(m, "Abort"))}
    return tuple(m.UsageError for m in mods), tuple(m.ClickException for m in mods), tuple(aborts)
