"""The sweep's summary names the CPUs that solved its pairs (distinct workers per node, at most
each node's CPUs), not the cluster's CPUs at the start."""
from __future__ import annotations

from typer.testing import CliRunner

from cli import app
from orchestrator.pacing import cpus_used


def test_cpus_used_counts_workers_per_node_up_to_its_cpus():
    nodes = {"a": 2.0, "b": 8.0, "c": 4.0}
    # two nodes joined, but every task ran on node a's two workers
    assert cpus_used({("a", 11), ("a", 12)}, nodes) == (2.0, 1)
    # node a's worker replaced once (three pids on two CPUs), one worker on node b
    assert cpus_used({("a", 11), ("a", 12), ("a", 13), ("b", 7)}, nodes) == (3.0, 2)
    # a node Ray no longer lists (gone): its workers count as seen
    assert cpus_used({("gone", 1), ("gone", 2)}, nodes) == (2.0, 1)


def test_one_chain_on_a_two_cpu_ray_reports_one_cpu(tmp_path, local_ray):
    """One pressure chain is one task: one worker solved it, though Ray had two CPUs."""
    r = CliRunner().invoke(app, ["generate", "--store", str(tmp_path / "s.zarr"), "--shapes", "1", "--pressures",
                                 "8,10", "--stiffness", "150", "--endo", "60", "--epi=-60", "--fidelity", "fast",
                                 "--nodes", "200", "--num-cpus", "2"])
    assert r.exit_code == 0, r.output
    assert "pairs" in r.output and "on 1 CPU (the cluster had 2) (" in r.output, r.output
    import ray

    # the command used the Ray this process already ran and left it running (its starter's to stop)
    assert ray.is_initialized() and ray.get_runtime_context().gcs_address == local_ray
