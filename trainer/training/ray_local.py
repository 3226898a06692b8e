"""A local Ray for Ray Train (`heartctl train --local`, or a run on this machine's own Ray): its
ray.init settings and the setup hook of its worker processes. Imports nothing heavy: the hook runs in
every worker process the local Ray starts (Ray Train's controller and synchronisation actors too),
before the worker imports what its task needs."""
from __future__ import annotations

import logging

# A harmless warning of a local Ray (our --local mode), quietened in its worker processes: the
# controller's first resource request to the autoscaling coordinator (there is no autoscaler on one
# machine) times out after 5 s while two busy cores are still starting the workers, which it logs as a
# warning with a full traceback. A filter, not a level: the controller's logging.config.dictConfig
# resets its child loggers' levels.
NO_DASHBOARD_SETUP_HOOK = "trainer.training.ray_local.quieten_local_ray"
LOCAL_RAY_NOISY_LOGGERS = ("ray.train.v2._internal.execution.scaling_policy.autoscaling_coordinator_client",)
# A local Ray is one machine that no cloud drains: Ray Train's preemption watcher (an actor polling the
# nodes' drain state, whose start logs a core-worker error line about its restart policy) has nothing
# to watch there. Its controller checks the workers every 0.25 s rather than every 2 s: a step of its
# start and its end waits one check, seconds in a short local run, and a check is a few local calls.
# And it waits up to 10 min, not 60 s, for the worker group to start: on a busy laptop two workers
# importing torch can take over a minute, and a timeout only kills them and starts the same again
# (Ray retries it without limit), which turns a 10 s run into minutes.
LOCAL_RAY_TRAIN_ENV = {"RAY_TRAIN_ENABLE_PREEMPTION_WATCHER": "0", "RAY_TRAIN_HEALTH_CHECK_INTERVAL_S": "0.25",
                       "RAY_TRAIN_WORKER_GROUP_START_TIMEOUT_S": "600"}


def local_ray_options(num_cpus: int | None = None) -> dict:
    """ray.init keywords of a local Ray for Ray Train (`num_cpus` None: all cores): no dashboard, the
    noisy loggers quietened in its workers, no preemption watcher."""
    return dict(num_cpus=num_cpus, include_dashboard=False,
                runtime_env={"worker_process_setup_hook": NO_DASHBOARD_SETUP_HOOK,
                             "env_vars": dict(LOCAL_RAY_TRAIN_ENV)})  # Ray adds to it


def errors_only(record: logging.LogRecord) -> bool:
    return record.levelno >= logging.ERROR


def quieten_local_ray() -> None:
    """worker_process_setup_hook for a local Ray: only errors from the loggers above."""
    for name in LOCAL_RAY_NOISY_LOGGERS:
        logger = logging.getLogger(name)
        if errors_only not in logger.filters:
            logger.addFilter(errors_only)
