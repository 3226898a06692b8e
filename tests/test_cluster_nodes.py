"""Two Ray nodes on this machine (ray.cluster_utils.Cluster: a head and a worker node, one CPU each),
the worker node lost mid-run. The sweep, joined with --address, finishes on the head with every case
done once and equal to the same pressure chains solved uninterrupted. Ray Train (two CPU workers, on different nodes) loses
the node of one of them, restarts from its last checkpoint on the nodes left (FailureConfig) and ends
with the weights of the same two ranks trained uninterrupted in plain DDP."""
from __future__ import annotations

import os
import threading
from contextlib import contextmanager
from pathlib import Path
from dataclasses import replace

import numpy as np
import pytest
import torch

ray = pytest.importorskip("ray")

from orchestrator.grid import SweepSpec, pressure_chains  # noqa: E402
from orchestrator.tasks import run_chain  # noqa: E402
from orchestrator.ray_session import WORKER_NICENESS, init_ray  # noqa: E402
from process_tree import processes_titled  # noqa: E402
from orchestrator.sweep import run_sweep  # noqa: E402
from storage.reader import PairReader  # noqa: E402
from storage.schema import DONE  # noqa: E402
from trainer.training.checkpoint import load_run  # noqa: E402
from trainer.config import PAPER, TrainConfig  # noqa: E402
from trainer.training.ray_local import LOCAL_RAY_TRAIN_ENV  # noqa: E402
from trainer_fixtures import make_tiny_store  # noqa: E402
from gloo_ranks import fit_rank, spawn_ranks  # noqa: E402
from local_ray import stop_local_ray  # noqa: E402

pytestmark = pytest.mark.slow  # a two-node cluster losing a node, for a sweep and for Ray Train: make test-all

SMALL = replace(PAPER, hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8)


@pytest.fixture(scope="module")
def cluster():
    """A head node and a worker node of one CPU each, this process the driver (joined by address)."""
    from ray.cluster_utils import Cluster

    stop_local_ray()  # this process joins the two-node cluster instead
    recorded = Path("/tmp/ray/ray_current_cluster")  # where Ray notes the latest cluster for address "auto"
    before = recorded.read_bytes() if recorded.is_file() else None
    env_before = {k: os.environ.get(k) for k in LOCAL_RAY_TRAIN_ENV}
    os.environ.update(LOCAL_RAY_TRAIN_ENV)  # the nodes' processes inherit the local Ray's Ray Train settings
    # a lost node is found dead after 3 missed health checks 0.5 s apart (Ray's defaults: 5 missed, 3 s apart)
    health = {"health_check_period_ms": 500, "health_check_timeout_ms": 500, "health_check_failure_threshold": 3}
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1,
                                                      "_system_config": {"worker_niceness": WORKER_NICENESS, **health}})
    c.add_node(num_cpus=1)
    c.wait_for_nodes()
    init_ray(address=c.address)
    _a_solver_worker_on_every_node()
    yield c
    ray.shutdown()
    c.shutdown()
    for k, v in env_before.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    if before is None:  # leave no dead cluster for a later `--address auto` to find
        recorded.unlink(missing_ok=True)
    else:
        recorded.write_bytes(before)


def _a_solver_worker_on_every_node() -> None:
    """A worker process of this job on every node, the solver imported and the process left idle in
    its node's pool, so a sweep's first tasks start on both nodes at once: a node that had still to
    start a process (seconds on a busy machine) could see the other run every chain first."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    def import_the_solver() -> None:  # local: Ray ships it by value (this test module is not on the workers' path)
        import orchestrator.tasks  # noqa: F401

    warm = ray.remote(num_cpus=1)(import_the_solver)
    ray.get([warm.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)).remote()
             for n in ray.nodes() if n["Alive"]])


def _worker_node(cluster):
    """The cluster's one non-head node."""
    workers = list(cluster.worker_nodes)
    assert len(workers) == 1, workers
    return workers[0]


def _raylet_pid(node) -> int:
    from ray._private import ray_constants

    return node.all_processes[ray_constants.PROCESS_TYPE_RAYLET][0].process.pid


def _busy_on(node, title: bytes = b"ray::run_chain") -> bool:
    """Whether a worker process of `node` runs `title` (a pressure chain, or a Ray Train worker)."""
    return bool(processes_titled(title, _raylet_pid(node)))


def _epochs_logged(run) -> int:
    """Epochs rank 0 has written to the run's metrics.csv (header excluded)."""
    path = run / "metrics.csv"
    return max(0, len(path.read_text().splitlines()) - 1) if path.is_file() else 0


@contextmanager
def _node_killed_when(cluster, pick):
    """While the block runs, a thread calls pick() every 20 ms; the first time it returns (node, note)
    the node is killed (no graceful shutdown). Yields a list that then holds the note, or the
    thread's error."""
    killed, stop = [], threading.Event()

    def watch():
        try:
            while not stop.is_set():
                hit = pick()
                if hit is not None:
                    cluster.remove_node(hit[0], allow_graceful=False)
                    killed.append(hit[1])
                    return
                stop.wait(0.02)
        except Exception as exc:  # noqa: BLE001 - reported by the test
            killed.append(exc)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        yield killed
    finally:
        stop.set()
        watcher.join(timeout=60)


def _sweep_spec() -> SweepSpec:
    # four chains of three pairs on ~150-node meshes: each node has a chain in flight for most of the run
    return SweepSpec(shapes=1, pressure_mmhg=(6.0, 10.0, 14.0), stiffness_pa=(50.0, 100.0, 200.0, 300.0),
                     helix_endo_deg=(60.0,), helix_epi_deg=(-60.0,), fidelity="fast", seed=0, nodes=150).validate()


def test_a_node_lost_mid_sweep_every_case_done_once_and_intact(cluster, tmp_path):
    spec = _sweep_spec()

    def busy_worker_node():  # the driver records a shape's cases in batches: watch the node, not the events
        node = _worker_node(cluster)
        return (node, node) if _busy_on(node) else None  # in the middle of a pressure chain

    lost = str(tmp_path / "lost.zarr")
    with _node_killed_when(cluster, busy_worker_node) as killed:
        rep = run_sweep(spec, lost, progress=False)
    assert killed and not isinstance(killed[0], Exception), f"the worker node never had a pair in flight {killed}"
    assert rep.done == spec.n_cases and rep.failed == 0 and rep.lost == 0
    assert sorted(k for _, k, _ in rep.records) == list(range(spec.n_cases))  # each case recorded once
    assert (PairReader(lost).status(0) == DONE).all()

    cluster.add_node(num_cpus=1)  # the cluster whole again for the next test
    # the same chains solved here, uninterrupted: nothing half-written or mixed from the lost node's attempt
    reader = PairReader(lost)
    stored = {c.index: c for c in reader.iter_done()}
    assert sorted(stored) == list(range(spec.n_cases))
    case_params = reader.case_params(0)
    for chain in pressure_chains(case_params, range(spec.n_cases)):
        for k, solved in zip(chain, run_chain(reader.mesh(0), [case_params[k] for k in chain], spec.fidelity)):
            np.testing.assert_allclose(stored[k].unloaded, solved["unloaded"], rtol=0, atol=1e-5)
            np.testing.assert_allclose(stored[k].loaded, solved["loaded"], rtol=0, atol=1e-5)
    cluster.wait_for_nodes()


def test_ray_train_loses_a_node_and_resumes_from_its_last_checkpoint(cluster, tmp_path):
    from trainer.training.ray_train import train_with_ray

    store = make_tiny_store(tmp_path / "tiny.zarr", shapes=4)
    cfg = TrainConfig(store=store, config_name="paper-small", model=replace(SMALL, dropout=0.0), epochs=5,
                      batch_size=4, num_threads=1)

    # the uninterrupted run: the same two ranks in plain DDP (no Ray), in processes of their own
    whole = tmp_path / "whole"
    spawn_ranks(fit_rank, 2, str(tmp_path / "rendezvous"), cfg.as_dict(), str(whole))

    cluster.add_node(num_cpus=1)  # a spare: two CPUs are left for the restart when a node is lost
    cluster.wait_for_nodes()
    run = tmp_path / "lost"

    def a_training_node_after_the_first_checkpoint():
        ray_dir = run / "ray"
        if ray_dir.is_dir() and any(p.name.startswith("checkpoint_") for p in ray_dir.iterdir()):
            hosts = [n for n in cluster.worker_nodes if _busy_on(n, b"ray::RayTrainWorker")]
            if hosts:  # a node running one of the two training workers, and the epochs finished then
                return hosts[0], _epochs_logged(run)
        return None

    with _node_killed_when(cluster, a_training_node_after_the_first_checkpoint) as killed:
        summary = train_with_ray(cfg, run, gpus=0, cpu_workers=2, max_failures=2)
    assert killed and not isinstance(killed[0], Exception), killed
    assert killed[0] < cfg.epochs, f"the node died after the run's last epoch ({killed})"
    assert summary.epoch == cfg.epochs and summary.workers == 2 and summary.backend == "gloo"
    assert any(p.name.startswith("checkpoint_") for p in (run / "ray").iterdir())
    lost, whole = load_run(run), load_run(whole)
    assert [h["epoch"] for h in lost["history"]] == list(range(1, cfg.epochs + 1))
    for part in ("model", "best_model"):
        for name, w in whole[part].items():
            torch.testing.assert_close(lost[part][name], w, rtol=0, atol=1e-6, msg=f"{part}.{name}")
