"""Ray for one command: start a local Ray or join a cluster (time-boxed), and always stop it after.
Used by the sweep (`generate`) and by training (`train`); Ray's notices that say nothing useful are filtered here.

Failures to start or join are one line: RayConnectError (no cluster answers at the address given)
and RayStartError (a local Ray would not start). Both are ConnectionErrors.
"""
from __future__ import annotations

import math
import os
import socket
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass

CONNECT_TIMEOUT_S = 30.0  # joining an existing cluster (--address): then one line, not Ray's retries for minutes
# Ray starts its workers at nice 15; the solves then got a few per cent of a core whenever anything
# else ran (measured: inverse p50 0.42 s idle → 12.8 s beside two busy processes, 0.65 s at nice 0)
WORKER_NICENESS = 0
# the sweep's solver workers run one BLAS/MKL thread each: one task per CPU
THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


class RayConnectError(ConnectionError):
    """No Ray cluster answered at the address given; the message names it, in one line."""


class RayStartError(ConnectionError):
    """Ray could not start here (or joining failed in a way Ray reports itself); one line naming where."""

    def __init__(self, address: str | None, exc: BaseException):
        text = str(exc).strip()
        super().__init__(f"cannot start or join Ray ({address or 'local'}): "
                         f"{text.splitlines()[0] if text else type(exc).__name__}")


@dataclass(frozen=True)
class RayAddress:
    """Where a command's Ray runs: `address` None starts a local Ray; `auto` or HOST:PORT joins a
    cluster, waiting at most `connect_timeout_s` seconds for it (joining only; default 30 s)."""

    address: str | None = None
    connect_timeout_s: float | None = None

    def __post_init__(self):
        if self.connect_timeout_s is None:
            return
        if self.address is None:
            raise ValueError("`connect_timeout` applies to `address` (joining a cluster); a local Ray starts here")
        if not (math.isfinite(self.connect_timeout_s) and self.connect_timeout_s > 0):
            raise ValueError(f"`connect_timeout` must be a finite number of seconds > 0, got {self.connect_timeout_s:g}")

    @property
    def timeout_s(self) -> float:
        return self.connect_timeout_s or CONNECT_TIMEOUT_S


# --------------------------------------------------------------------------- Ray's notices

# Ray (2.60 here) turns token authentication on for every cluster that ray.init() starts and says so
# in a warning each time. That is the setting we want (a local cluster is not open to the network), so the
# notice is dropped; Ray's warning that authentication is *disabled* (RAY_AUTH_MODE=disabled) still shows.
RAY_AUTH_LOGGER = "ray._private.authentication.authentication_token_setup"
RAY_AUTH_ENABLED_NOTICE = "Token authentication is enabled for this Ray cluster"


def not_auth_enabled_notice(record) -> bool:
    return not str(record.msg).startswith(RAY_AUTH_ENABLED_NOTICE)


def not_sigterm_notice(record) -> bool:
    """Ray's worker logger says a helper thread sets no SIGTERM handler: the CLI sets its own."""
    return "SIGTERM handler is not set" not in str(record.msg)


def _add_filter(logger_name: str, keep) -> None:
    import logging

    logger = logging.getLogger(logger_name)
    if keep not in logger.filters:
        logger.addFilter(keep)


def _auth_hint(text: str) -> str:
    """A pointer to Ray's token when Ray's error or log speaks of authentication."""
    words = text.lower()
    if "token" in words or "authenticat" in words:
        return ("; Ray says the authentication token is missing or wrong: set RAY_AUTH_MODE=token and the "
                "head's token (`ray get-auth-token` there) in RAY_AUTH_TOKEN or ~/.ray/auth_token")
    return ""


# --------------------------------------------------------------------------- starting and joining


def start_local_ray(**kwargs):
    """ray.init() of a new local cluster (token authentication on, as Ray defaults), without its notice.
    Always a new one (address "local"): never a cluster that another process started on this machine,
    which Ray would otherwise join (and refuse, when given num_cpus)."""
    import ray

    _add_filter(RAY_AUTH_LOGGER, not_auth_enabled_notice)
    return ray.init(address="local", **kwargs)


def _gcs_host_port(address: str) -> tuple[str, int] | None:
    """(host, port) of a Ray address (HOST:PORT, ray://HOST:PORT, or auto → the running cluster's),
    or None when it cannot be told (auto with no cluster recorded: ray.init says so itself)."""
    if address == "auto":
        try:
            from ray._private.services import canonicalize_bootstrap_address

            address = canonicalize_bootstrap_address("auto") or ""
        except Exception:
            return None
    address = address.split("://", 1)[-1]
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def join_ray(address: str, timeout_s: float = CONNECT_TIMEOUT_S, **kwargs):
    """ray.init(address=…) of an existing cluster, time-boxed: RayConnectError (one line naming the
    address) when nothing listens there, or when Ray has not connected within timeout_s. The port is
    probed first (a refused or unreachable port fails at once); ray.init then runs in a helper thread
    so that a port that accepts but never answers as Ray does not hang the command."""
    import tempfile
    import threading

    import ray

    start = time.monotonic()
    target = _gcs_host_port(address)
    if target is not None:
        try:
            socket.create_connection(target, timeout=timeout_s).close()
        except OSError as exc:
            why = "timed out" if isinstance(exc, socket.timeout) else (exc.strerror or type(exc).__name__).lower()
            where = "" if address == f"{target[0]}:{target[1]}" else f"{target[0]}:{target[1]}: "
            raise RayConnectError(f"no Ray cluster answers at {address} ({where}{why}"
                                  f"{f' after {timeout_s:g} s' if why == 'timed out' else ''}); start it with "
                                  f"`ray start` on the head node or check HOST:PORT") from None
    outcome: dict = {}

    def connect():
        try:
            outcome["context"] = ray.init(address=address, **kwargs)
        except BaseException as exc:  # handed to the caller's thread
            outcome["error"] = exc

    _add_filter("ray._private.worker", not_sigterm_notice)
    # Ray's C++ client logs each failed attempt on stderr (a line a second for ~20 s, the reason among
    # them: an authentication token missing or wrong) before ray.init gives up. While it tries, stderr
    # goes to a file: on success its lines are passed on, on failure read for the reason of one line.
    captured = tempfile.TemporaryFile()
    sys.stderr.flush()
    saved_fd = os.dup(2)
    os.dup2(captured.fileno(), 2)
    thread = threading.Thread(target=connect, name="ray-connect", daemon=True)
    try:
        thread.start()
        thread.join(max(timeout_s - (time.monotonic() - start), 0.1))
    finally:
        sys.stderr.flush()
        if thread.is_alive():
            _mute_abandoned_connect(saved_fd)
        else:
            os.dup2(saved_fd, 2)
            os.close(saved_fd)
    captured.seek(0)
    said = captured.read().decode(errors="replace")
    captured.close()
    if thread.is_alive():
        raise RayConnectError(f"Ray at {address} did not connect within {timeout_s:g} s (is it a Ray head's GCS port, "
                              f"and this machine's Ray the same version?){_auth_hint(said)}; raise `connect_timeout` "
                              f"if it is slow")
    if "error" in outcome:
        exc = outcome["error"]
        text = str(exc).strip()
        first = text.splitlines()[0] if text else type(exc).__name__
        raise RayConnectError(f"cannot join Ray at {address}: {first}{_auth_hint(text + said)}") from None
    if said:
        sys.stderr.write(said)
    return outcome["context"]


def _mute_abandoned_connect(saved_fd: int) -> None:
    """After ray.init is abandoned (still trying in its thread), Ray's C++ client keeps logging its
    attempts on file descriptor 2 (`rpc_client.h:153: Failed to connect to GCS …` 5 s after it began,
    then every ~40 s) for as long as the process lives. The command ends with one line of its own:
    fd 2 goes to /dev/null for good, and Python's sys.stderr (when it is fd 2) writes to the terminal
    through `saved_fd` (a copy of the original fd 2), so that line and any later Python output still
    show. Under a test runner whose sys.stderr is no file, only fd 2 is muted."""
    import io

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    os.close(devnull)
    try:
        uses_fd2 = sys.stderr is not None and sys.stderr.fileno() == 2
    except (AttributeError, OSError, ValueError):
        uses_fd2 = False
    if not uses_fd2:
        os.close(saved_fd)
        return
    old = sys.stderr
    sys.stderr = io.TextIOWrapper(io.FileIO(saved_fd, "w", closefd=True), encoding=old.encoding or "utf-8",
                                  errors="backslashreplace", line_buffering=True)


def start_or_join(where: RayAddress, join_options: dict | None = None, **start_options):
    """Join the cluster at `where.address` (time-boxed; ray.init keywords `join_options`), or start a
    local Ray (keywords `start_options`; its workers at WORKER_NICENESS). A Ray this process already
    runs is used as it is. Raises RayConnectError or RayStartError, one line each."""
    import ray

    try:
        if where.address:
            return join_ray(where.address, where.timeout_s, **(join_options or {}))
        if ray.is_initialized():
            return None
        start_options.setdefault("_system_config", {"worker_niceness": WORKER_NICENESS})
        return start_local_ray(**start_options)
    except RayConnectError:
        raise
    except (ConnectionError, ValueError, RuntimeError) as exc:
        ray.shutdown()
        raise RayStartError(where.address, exc) from None


@contextmanager
def ray_session(where: RayAddress, join_options: dict | None = None, **start_options):
    """Ray for the block: started or joined as start_or_join does, and shut down on leaving it,
    however the block ends (a result, an error, Ctrl-C). A local Ray this process already ran is
    used and left running: it is its starter's to stop (a notebook's, a caller's)."""
    import ray

    ours = bool(where.address) or not ray.is_initialized()
    start_or_join(where, join_options, **start_options)
    try:
        yield
    finally:
        if ours:
            ray.shutdown()


# --------------------------------------------------------------------------- the sweep's Ray


def sweep_ray_options(num_cpus: int | None = None, local: bool = False, quiet: bool = True) -> dict:
    """ray_session's keywords for the sweep's solver workers: one BLAS thread each, Ray's own logging
    quiet; a local Ray's dashboard listens on 127.0.0.1 only, and in --local mode there is none
    (two CPUs unless `num_cpus`)."""
    import logging

    for k, v in THREAD_ENV.items():
        os.environ.setdefault(k, v)
    shared = dict(runtime_env={"env_vars": dict(THREAD_ENV)}, logging_level=logging.WARNING if quiet else logging.INFO,
                  log_to_driver=not quiet, configure_logging=True)
    dashboard = {"include_dashboard": False} if local else {"dashboard_host": "127.0.0.1"}
    return dict(join_options=shared, num_cpus=num_cpus or (2 if local else None), **dashboard, **shared)


def init_ray(address: str | None = None, num_cpus: int | None = None, local: bool = False, quiet: bool = True,
             connect_timeout_s: float | None = None):
    """Start (or join, with `address`) Ray for the sweep, left running: sweep_ray_options on
    start_or_join. The caller shuts it down (ray_session does both)."""
    return start_or_join(RayAddress(address, connect_timeout_s), **sweep_ray_options(num_cpus, local, quiet))
