"""s3:// stores against an S3-compatible server on loopback (moto's server mode, in this process):
generate, status and export through the CLI, a killed driver resumed, train and evaluate reading
the store from S3, and the object store's refusals (a missing bucket, wrong credentials, the server
stopped mid-sweep) as one line. Endpoint and credentials come from the AWS environment variables."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("moto.server", reason="s3:// store tests need moto[server] (pip install -e '.[test]')")
pytest.importorskip("s3fs", reason="s3:// store tests need s3fs (pip install -e '.[test]')")

from cli import app  # noqa: E402
from killed_driver import generate_killed_after_first_write  # noqa: E402
from local_ray import start_local_ray, stop_local_ray  # noqa: E402
from storage.reader import PairReader  # noqa: E402
from storage.schema import DONE, PENDING  # noqa: E402
from storage.writer import PairStore  # noqa: E402

pytestmark = pytest.mark.slow  # a local S3 server (and a Ray with its variables) under sweeps, training and outages

BUCKET = "heartctl-test"
# one shape, 3 pressure chains of 2 cases (fast preset, a coarse mesh); one chain in flight at a time
# The ED mesh comes from a file (--meshes, filled by `ed_mesh_folder`), the same for every store here:
# these tests are about the store, and a mesh made again by gmsh in a long-lived Ray worker is not
# always the same to the last node (an open defect of meshing; tests/test_solver_mesh_determinism.py)
ARGS = ["generate", "--meshes", "", "--pressures", "8,12", "--stiffness", "100,200,300", "--endo", "60",
        "--epi=-60", "--fidelity", "fast", "--max-in-flight", "1"]
CASES = 6
AWS_ENV = {"AWS_DEFAULT_REGION": "us-east-1",
           "AWS_MAX_ATTEMPTS": "1"}  # botocore's retries of a refused connection take seconds: one try here
S3_POLICY = json.dumps({"Version": "2012-10-17",
                        "Statement": [{"Effect": "Allow", "Action": "s3:*", "Resource": "*"}]})
runner = CliRunner()


class S3Server:
    """moto's S3 server on 127.0.0.1 (its data lives in this process: a restart on the same port
    serves the same buckets)."""

    def __init__(self):
        from moto.server import ThreadedMotoServer

        self.server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
        self.server.start()
        self.host, self.port = self.server.get_host_and_port()
        self.endpoint = f"http://{self.host}:{self.port}"

    def stop(self) -> None:
        self.server.stop()

    def restart(self) -> None:
        from moto.server import ThreadedMotoServer

        self.server = ThreadedMotoServer(ip_address="127.0.0.1", port=self.port, verbose=False)
        self.server.start()

    def keys(self, prefix: str) -> list[str]:
        import boto3

        s3 = boto3.session.Session().client("s3")  # a new session reads the variables as they are now
        pages = s3.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix)
        return [o["Key"] for page in pages for o in page.get("Contents", [])]


def _fresh_filesystems() -> None:
    """s3fs caches a filesystem (and its credentials) per set of options: close and drop them when
    the environment changes."""
    import s3fs
    from zarr.core.sync import sync

    for fs in list(getattr(s3fs.S3FileSystem, "_cache", {}).values()):
        client = getattr(fs, "_s3creator", None)
        if client is not None and fs.asynchronous:  # zarr's, on zarr's event loop
            sync(client.__aexit__(None, None, None))
    s3fs.S3FileSystem.clear_instance_cache()


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    """The server, a user's access key and the AWS variables pointing at both (restored afterwards),
    and a bucket."""
    import boto3

    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # one line per request otherwise
    server = S3Server()
    mp = pytest.MonkeyPatch()
    empty = tmp_path_factory.mktemp("aws") / "none"  # no ~/.aws profile may creep in
    for name in ("AWS_ENDPOINT_URL_S3", "AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_SECURITY_TOKEN"):
        mp.delenv(name, raising=False)
    for name, value in {**AWS_ENV, "AWS_ENDPOINT_URL": server.endpoint, "AWS_CONFIG_FILE": str(empty),
                        "AWS_SHARED_CREDENTIALS_FILE": str(empty), "AWS_ACCESS_KEY_ID": "setup",
                        "AWS_SECRET_ACCESS_KEY": "setup"}.items():
        mp.setenv(name, value)
    iam = boto3.session.Session().client("iam")  # the key moto checks signatures against when iam_checks is on
    iam.create_user(UserName="heartctl")
    iam.put_user_policy(UserName="heartctl", PolicyName="s3", PolicyDocument=S3_POLICY)
    key = iam.create_access_key(UserName="heartctl")["AccessKey"]
    mp.setenv("AWS_ACCESS_KEY_ID", key["AccessKeyId"])
    mp.setenv("AWS_SECRET_ACCESS_KEY", key["SecretAccessKey"])
    _fresh_filesystems()
    boto3.session.Session().client("s3").create_bucket(Bucket=BUCKET)  # a new session: the key just made
    stop_local_ray()  # the module's Ray: its workers (Ray Train's) inherit the variables above (and keep
    start_local_ray()  # them for the later tests that share it, whose stores are on local disk)
    try:
        yield server
    finally:
        server.stop()
        mp.undo()
        _fresh_filesystems()


@pytest.fixture(scope="module", autouse=True)
def ed_mesh_folder(tmp_path_factory):
    """One ED mesh (shape 0 of the shape model, ~100 nodes) in a folder that ARGS's --meshes names."""
    from solver.meshing import mesh_lv
    from solver.shape_model import SHAPE_MODEL_VERSION, lv_shape
    from storage.meshfiles import write_mesh

    folder = tmp_path_factory.mktemp("ed_meshes")
    write_mesh(folder / "shape0.vtu", mesh_lv(lv_shape(0, 0, version=SHAPE_MODEL_VERSION), 100))
    ARGS[ARGS.index("--meshes") + 1] = str(folder)
    return folder


@pytest.fixture(scope="module")
def local_reference(s3, tmp_path_factory):
    """The same sweep into a store on local disk."""
    loc = str(tmp_path_factory.mktemp("local") / "pairs.zarr")
    r = runner.invoke(app, ARGS + ["--store", loc])
    assert r.exit_code == 0, r.output
    return PairReader(loc)


def _url(name: str) -> str:
    return f"s3://{BUCKET}/{name}"


def _error_lines(result) -> list[str]:
    return [ln for ln in result.stderr.splitlines() if ln.startswith("heartctl: error:")]


def _assert_one_line(result, code: int, *words) -> str:
    """Exactly one error line on stderr naming `words`, exit `code` by heartctl's own exit (not an
    uncaught exception), no traceback; returns the line."""
    assert result.exit_code == code, result.output
    assert isinstance(result.exception, SystemExit), repr(result.exception)
    lines = _error_lines(result)
    assert len(lines) == 1, result.output
    assert "Traceback" not in result.output
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def _assert_same_pairs(reader: PairReader, reference: PairReader) -> None:
    """Every case done, with the arrays of the local-disk store (same command: the same solves)."""
    assert reader.done_cases() == reference.done_cases() == [(0, k) for k in range(CASES)]
    np.testing.assert_array_equal(reader.mesh(0).nodes, reference.mesh(0).nodes)
    for ours, theirs in zip(reader.iter_done(), reference.iter_done()):
        np.testing.assert_allclose(ours.unloaded, theirs.unloaded, rtol=0, atol=1e-4)
        np.testing.assert_allclose(ours.loaded, theirs.loaded, rtol=0, atol=1e-4)


@pytest.fixture(scope="module")
def generated(s3):
    """The sweep into an s3:// store, through the CLI: (its URL, the command's result)."""
    url = _url("cli/pairs.zarr")
    return url, runner.invoke(app, ARGS + ["--store", url])


def test_generate_status_export_through_the_cli(s3, generated, local_reference, tmp_path):
    url, r = generated
    assert r.exit_code == 0, r.output
    assert f"{url}: {CASES} done, 0 failed of {CASES}" in r.stdout
    assert "cli/pairs.zarr/zarr.json" in s3.keys("cli/")  # on the server, not on this disk
    assert not Path("s3:").exists()

    r = runner.invoke(app, ["status", "--store", url, "--verify"])
    assert r.exit_code == 0, r.output
    assert f"done {CASES} (100.0 %)" in r.stdout and f"verified: all {CASES} done cases read back intact" in r.stdout
    r = runner.invoke(app, ["status", "--store", url, "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout.strip().splitlines()[-1])["done"] == CASES

    out = tmp_path / "case.vtu"
    r = runner.invoke(app, ["export", "--store", url, "--shape", "0", "--case", "3", "-o", str(out)])
    assert r.exit_code == 0, r.output
    import meshio

    mesh = meshio.read(out)
    case = PairReader(url).case(0, 3)
    np.testing.assert_allclose(mesh.points, case.unloaded, atol=1e-6)
    np.testing.assert_allclose(mesh.point_data["displacement"], case.loaded - case.unloaded, atol=1e-6)
    _assert_same_pairs(PairReader(url), local_reference)


def test_killed_driver_then_rerun_does_every_case_once(s3, local_reference):
    import ray

    url = _url("killed/pairs.zarr")
    generate_killed_after_first_write(ARGS + ["--store", url], ray.get_runtime_context().gcs_address)

    reader = PairReader(url)
    before = {k: reader.stats(0)[k].copy() for _, k in reader.done_cases()}
    assert len(before) == 2  # the first chain
    r = runner.invoke(app, ARGS + ["--store", url, "--json"])
    assert r.exit_code == 0, r.output
    report = json.loads(r.stdout.strip().splitlines()[-1])
    assert report["done_before"] == len(before) and report["submitted"] == CASES - len(before)  # none solved twice
    reader = PairReader(url)
    for k, row in before.items():
        np.testing.assert_array_equal(reader.stats(0)[k], row)  # the first run's cases untouched
    runs = reader.stats(0)[:, list(reader.stat_names).index("run")]
    assert sorted(runs.tolist()) == sorted([0.0] * len(before) + [1.0] * (CASES - len(before)))
    _assert_same_pairs(reader, local_reference)


TRAIN = ["--epochs", "2", "--batch-size", "8", "--split", "lovo:P=12", "--json"]  # trained on P 8, tested on P 12


def _train_and_evaluate(url: str, run_dir: Path, *how, evaluate: bool = True) -> dict:
    """train (2 epochs) and evaluate through the CLI; the training summary."""
    r = runner.invoke(app, ["train", "--store", url, "--run-dir", str(run_dir), *how, *TRAIN])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["epoch"] == 2 and (run_dir / "checkpoint.pt").is_file()
    if not evaluate:
        return summary
    r = runner.invoke(app, ["evaluate", "--run", str(run_dir), "--store", url, "--json", "--no-plots"])
    assert r.exit_code == 0, r.output
    metrics = json.loads(r.stdout.strip().splitlines()[-1])
    assert metrics["cases"] == 3 and np.isfinite(metrics["md_mm"])  # the three P = 12 cases
    return summary


def test_train_and_evaluate_read_the_store_from_s3(generated, tmp_path):
    url, made = generated
    assert made.exit_code == 0, made.output
    assert _train_and_evaluate(url, tmp_path / "run", "--no-ray", "--device", "cpu")["mode"] == "in-process"


def test_ray_train_reads_the_store_from_s3(generated, tmp_path):
    """A Ray Train worker (its own process, the AWS variables inherited) reads the pairs from S3
    (evaluate reads them in this process, as after the in-process run above)."""
    url, made = generated
    assert made.exit_code == 0, made.output
    summary = _train_and_evaluate(url, tmp_path / "run", "--gpus", "0", "--workers", "1", evaluate=False)
    assert summary["mode"].startswith("Ray Train, 1 CPU worker")


# --------------------------------------------------------------------------- refusals and failures


def test_a_missing_bucket_is_one_line(s3, tmp_path):
    url = "s3://no-such-bucket/pairs.zarr"
    words = ("no-such-bucket", "does not exist", s3.endpoint)
    for args in (ARGS + ["--store", url], ["status", "--store", url],
                 ["export", "--store", url, "--shape", "0", "--case", "0", "-o", str(tmp_path / "c.vtu")],
                 ["train", "--store", url, "--run-dir", str(tmp_path / "run"), "--no-ray"]):
        r = runner.invoke(app, args)
        _assert_one_line(r, 2, *words)
        assert r.stderr.strip().splitlines() == _error_lines(r)  # nothing else: refused before Ray or torch ran
    assert not (tmp_path / "run").exists() and not (tmp_path / "c.vtu").exists()


def test_an_endpoint_that_does_not_answer_is_one_line(s3, monkeypatch):
    import socket

    with socket.socket() as probe:  # a loopback port where nothing listens
        probe.bind(("127.0.0.1", 0))
        closed = f"http://127.0.0.1:{probe.getsockname()[1]}"
    monkeypatch.setenv("AWS_ENDPOINT_URL", closed)
    _fresh_filesystems()
    try:
        for args in (ARGS + ["--store", _url("silent/pairs.zarr")], ["status", "--store", _url("cli/pairs.zarr")]):
            r = runner.invoke(app, args)
            line = _assert_one_line(r, 2, f"the S3 endpoint {closed} does not answer (EndpointConnectionError)")
            assert r.stderr.strip().splitlines() == [line]
    finally:
        monkeypatch.undo()
        _fresh_filesystems()


@pytest.fixture
def iam_checks():
    """moto checks every request's signature and permissions (by default it takes any key)."""
    from moto import settings
    from moto.core.authorization import ActionAuthenticatorMixin

    saved = settings.INITIAL_NO_AUTH_ACTION_COUNT, ActionAuthenticatorMixin.request_count
    settings.INITIAL_NO_AUTH_ACTION_COUNT, ActionAuthenticatorMixin.request_count = 0, 0
    try:
        yield
    finally:
        settings.INITIAL_NO_AUTH_ACTION_COUNT, ActionAuthenticatorMixin.request_count = saved


def test_wrong_credentials_are_one_line(s3, iam_checks, monkeypatch, tmp_path):
    url = _url("refused/pairs.zarr")
    r = runner.invoke(app, ["status", "--store", url])  # the right key: checked and let in
    _assert_one_line(r, 2, f"no heartctl store at {url}")
    for name, wrong in (("AWS_SECRET_ACCESS_KEY", "not-the-secret"), ("AWS_ACCESS_KEY_ID", "AKIANOTAKEY000000000")):
        with monkeypatch.context() as mp:
            mp.setenv(name, wrong)
            _fresh_filesystems()  # s3fs keeps a filesystem's credentials
            for args in (ARGS + ["--store", url], ["status", "--store", _url("cli/pairs.zarr")]):
                r = runner.invoke(app, args)
                line = _assert_one_line(r, 2, "refused access", "AWS_ACCESS_KEY_ID", s3.endpoint)
                assert r.stderr.strip().splitlines() == [line]
    with monkeypatch.context() as mp:
        for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
            mp.delenv(name)
        mp.setenv("AWS_EC2_METADATA_DISABLED", "true")  # no instance profile to look for
        _fresh_filesystems()
        r = runner.invoke(app, ["status", "--store", _url("cli/pairs.zarr")])
        _assert_one_line(r, 2, "no AWS credentials found", "AWS_ACCESS_KEY_ID")
    _fresh_filesystems()
    assert not s3.keys("refused/")


def test_server_stopped_mid_sweep_then_rerun_resumes(s3, local_reference, monkeypatch):
    """The server goes away between the two shards of the second chain (after one written chain of
    two cases): one line, exit 1; the cases marked done read back intact, the half-written ones are not
    done; once the server is back the same command finishes the store."""
    import orchestrator.sweep as sweep
    from storage.writer import _write_rows

    url = _url("stopped/pairs.zarr")
    monkeypatch.setattr(sweep, "FLUSH_INTERVAL_S", 0.0)  # the case table written after every chain
    real_write, calls = PairStore.write_pairs, []

    def server_goes_away(self, s, pairs):
        calls.append(sorted(pairs))
        if len(calls) == 2:
            block = np.stack([np.asarray(pairs[k][0], dtype=np.float32) for k in calls[-1]])
            _write_rows(self._handle(s)["unloaded"], calls[-1], block)  # the unloaded shard lands
            s3.stop()
        return real_write(self, s, pairs)

    monkeypatch.setattr(PairStore, "write_pairs", server_goes_away)
    try:
        r = runner.invoke(app, ARGS + ["--store", url])
    finally:
        if len(calls) >= 2:
            s3.restart()
    _assert_one_line(r, 1, f"lost the object store while writing {url}", s3.endpoint, "does not answer",
                     "rerun the same command")
    half = calls[1]
    monkeypatch.setattr(PairStore, "write_pairs", real_write)
    _fresh_filesystems()

    r = runner.invoke(app, ["status", "--store", url, "--verify", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout.strip().splitlines()[-1])["done"] == 2
    reader = PairReader(url)
    assert (reader.status(0)[half] == PENDING).all() and sorted(k for _, k in reader.done_cases()) == calls[0]
    assert np.isfinite(reader._shape(0)["unloaded"].oindex[half]).all()  # in the unloaded shard: still not done

    r = runner.invoke(app, ARGS + ["--store", url])
    assert r.exit_code == 0, r.output
    assert f"{CASES} done, 0 failed of {CASES} ({CASES - 2} done and 0 failed in this run" in r.stdout
    _assert_same_pairs(PairReader(url), local_reference)
    assert (PairReader(url).status(0) == DONE).all()


def test_a_missing_object_on_s3_is_damage_that_retry_resets(s3):
    """A done case's object deleted on the server (its shape's loaded shard): `status --verify` names
    every case it held (exit 1), and --retry-damaged's reset marks them pending."""
    import boto3

    from trainer_fixtures import make_tiny_store

    url = make_tiny_store(_url("damage/pairs.zarr"), shapes=1)
    assert PairReader(url).damaged() == []
    boto3.session.Session().client("s3").delete_object(Bucket=BUCKET, Key="damage/pairs.zarr/shapes/0/loaded/c/0/0/0")
    r = runner.invoke(app, ["status", "--store", url, "--verify"])
    assert r.exit_code == 1 and "damaged: shape 0 case 0: its loaded data are missing" in r.stdout, r.output
    assert [k for _, k, _ in PairStore.open(url).reset_damaged([0])] == [0, 1, 2, 3]
    assert (PairReader(url).status(0) == PENDING).all()
