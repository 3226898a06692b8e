"""Joining a Ray cluster (--address) is time-boxed: nothing listening, a port that never answers as
Ray does, or a cluster that wants a token → one line naming the address, exit code 2, within seconds."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli import app
from local_ray import stop_local_ray
from orchestrator.ray_session import RayConnectError, join_ray

ROOT = Path(__file__).resolve().parents[1]


def closed_port() -> int:
    """A local port with nothing listening (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def silent_port():
    """A port that accepts connections and never says a word."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    yield server.getsockname()[1]
    server.close()


@pytest.fixture(autouse=True, scope="module")
def no_ray_in_this_process():
    """Each command joins (or fails to join) as a new process would: not a Ray an earlier test left running."""
    stop_local_ray()


GENERATE = ["generate", "--shapes", "1", "--pressures", "8", "--stiffness", "150", "--fidelity", "fast"]


@pytest.mark.parametrize("command", ["generate", "train"])
def test_nothing_listening_is_one_line_within_seconds(tmp_path, command):
    address = f"127.0.0.1:{closed_port()}"
    store = tmp_path / "s.zarr"
    if command == "generate":
        args = GENERATE + ["--store", str(store)]
    else:  # train checks its store before Ray: give it one
        from trainer_fixtures import make_tiny_store

        args = ["train", "--store", make_tiny_store(tmp_path / "tiny.zarr", shapes=2), "--run-dir", str(tmp_path / "r")]
    t = time.monotonic()
    r = CliRunner().invoke(app, args + ["--address", address, "--connect-timeout", "3"])
    assert time.monotonic() - t < 15
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("heartctl: error: no Ray cluster answers at " + address), r.output
    assert "connection refused" in lines[0]
    assert not store.exists()


def test_connect_timeout_needs_an_address_and_a_positive_number(tmp_path):
    store = str(tmp_path / "s.zarr")
    r = CliRunner().invoke(app, GENERATE + ["--store", store, "--connect-timeout", "5"])
    assert r.exit_code == 2 and "--connect-timeout applies to --address" in r.output, r.output
    r = CliRunner().invoke(app, GENERATE + ["--store", store, "--address", "127.0.0.1:1", "--connect-timeout", "0"])
    assert r.exit_code == 2 and "--connect-timeout must be a finite number of seconds > 0" in r.output, r.output
    assert not Path(store).exists()


@pytest.mark.slow
@pytest.mark.parametrize("command", ["generate", "train"])
def test_a_port_that_never_answers_as_ray_times_out(tmp_path, silent_port, command):
    """The port accepts, Ray never connects: the command gives up after --connect-timeout in one line
    and nothing of Ray's own (its own process, since the abandoned connection attempt stays behind in it)."""
    store = tmp_path / "s.zarr"
    if command == "generate":
        args = GENERATE + ["--store", str(store)]
    else:
        from trainer_fixtures import make_tiny_store

        args = ["train", "--store", make_tiny_store(tmp_path / "tiny.zarr", shapes=2), "--run-dir", str(tmp_path / "r")]
    t = time.monotonic()
    p = subprocess.run([sys.executable, "-c", "from cli import main; main()", *args,
                        "--address", f"127.0.0.1:{silent_port}", "--connect-timeout", "1"],
                       cwd=ROOT, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "RAY_ADDRESS": ""})
    assert time.monotonic() - t < 60
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("heartctl: error:"), p.stderr
    assert f"Ray at 127.0.0.1:{silent_port} did not connect within 1 s" in lines[0], p.stderr
    assert not store.exists() and not (tmp_path / "r").exists()


@pytest.mark.slow
def test_an_abandoned_connection_attempt_stays_quiet(silent_port):
    """Ray's C++ client logs its abandoned attempt on fd 2 5 s after it began (`rpc_client.h:153:
    Failed to connect to GCS …`): a process that lives on after the time-out shows none of it, and
    its own later stderr output still shows."""
    script = ("import sys, time\n"
              "from orchestrator.ray_session import RayConnectError, join_ray\n"
              "try:\n"
              f"    join_ray('127.0.0.1:{silent_port}', 1)\n"
              "except RayConnectError as exc:\n"
              "    print('refused:', exc, file=sys.stderr, flush=True)\n"
              "time.sleep(7)\n"
              "print('still here', file=sys.stderr)\n")
    p = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "RAY_ADDRESS": ""})
    assert p.returncode == 0, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith("refused: Ray at") and lines[1] == "still here", p.stderr


def test_a_cluster_that_wants_a_token_says_so(monkeypatch, silent_port):
    import ray

    def refuse(**kwargs):
        raise ConnectionError("Token authentication is enabled but no authentication token was found")

    monkeypatch.setattr(ray, "init", refuse)
    with pytest.raises(RayConnectError, match=rf"cannot join Ray at 127.0.0.1:{silent_port}: Token authentication "
                                              r".*Ray says the authentication token is missing or wrong: set "
                                              r"RAY_AUTH_MODE=token and the head's token"):
        join_ray(f"127.0.0.1:{silent_port}", 5)
