"""One local Ray for the tests that run sweeps or Ray Train in this process.

Starting and stopping a local Ray costs ~4 s on the 2-core box; the commands under test use a Ray their
process already runs and leave it running (orchestrator.ray_session), so the tests share one: started
by the first test that asks for `local_ray`, with the settings of both a `--local` sweep and a local Ray
Train (two CPUs, no dashboard, one BLAS thread per worker, Ray Train's local settings), and stopped at
the end of the session. A test that needs a Ray of its own (a cluster of two nodes, an S3 server's
variables in the workers' environment) calls `stop_local_ray()` first.
"""
from __future__ import annotations


def start_local_ray() -> str:
    """This process's local Ray, started when none runs (its workers inherit this process's
    environment as it is then); its GCS address."""
    import ray

    from orchestrator.ray_session import RayAddress, start_or_join, sweep_ray_options
    from trainer.training.ray_local import local_ray_options

    if not ray.is_initialized():
        sweep, train = sweep_ray_options(2, local=True), local_ray_options(2)
        sweep.pop("join_options")
        env = {**sweep["runtime_env"]["env_vars"], **train["runtime_env"]["env_vars"]}
        start_or_join(RayAddress(), **{**sweep, **train, "runtime_env": {**train["runtime_env"], "env_vars": env}})
    return ray.get_runtime_context().gcs_address


def stop_local_ray() -> None:
    import ray

    ray.shutdown()
