"""`generate --dry-run`: the plan of a sweep (cases, what a resume leaves, estimated core-hours
and store size from a short calibration solve). Runs in-process, without Ray, writes nothing."""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass

from storage.reader import PairReader
from storage.schema import CHUNK_PER_CASE, case_layout, encoded_case_bytes

from .grid import MAX_CHAIN, SweepSpec
from .tasks import mesh_shape, run_case, run_chain

PAPER_FULL_CASES = 19_440
FAST_GOAL_CORE_HOURS = 8.0
WORKER_VCPUS = 32  # cluster.yaml's worker node (c7i.8xlarge)
SHAPE_OBJECTS = 21  # per shape: its group's zarr.json, 11 arrays' zarr.json, 9 single-chunk arrays


def store_objects(shapes: int, cases_per_shape: int, sharded: bool = True) -> int:
    """Objects the store holds when complete (files on disk, keys in S3): per shape its group and array
    metadata and single-chunk arrays, and one shard of `unloaded` and one of `loaded` (a version 1
    store: one chunk per case of each); plus the root."""
    return shapes * (SHAPE_OBJECTS + 2 * (1 if sharded else cases_per_shape)) + 2


def existing_counts(location: str) -> dict:
    """Done and failed cases of the store's shapes, and how many shapes it has meshed."""
    try:
        reader = PairReader(location)
    except Exception:
        return {"done": 0, "failed": 0, "meshed": 0}
    counts = reader.counts()
    return {"done": counts.done, "failed": counts.failed, "meshed": counts.meshed}


def calibrate(spec: SweepSpec, warm_start: bool = True) -> dict:
    """Mesh shape 0 and solve one mid-grid pair at the requested fidelity (single thread); with
    `warm_start` and more than one pressure, then the next pressure up (or down) started from it, and
    price a pair as the mean over a pressure chain: (cold + (n − 1) · warm) / n."""
    t0 = time.perf_counter()
    m = mesh_shape(0, spec.seed, spec.nodes, *spec.mesh_source(0), shape_model_version=spec.shape_model_version)
    mesh_s = time.perf_counter() - t0
    params = spec.mid_params()
    res = run_case(m["mesh"], params, spec.fidelity, spec.base, fibres=spec.fibres)
    out = {"nodes": int(m["mesh"].n_nodes), "tets": int(len(m["mesh"].tets)), "mesh_s": mesh_s,
           "params": params, "pair_s": res["task_wall_s"], "cold_pair_s": res["task_wall_s"], "ok": res["ok"],
           "reason": res["reason"]}
    pressures = sorted(spec.pressure_mmhg)
    if warm_start and res["ok"] and len(pressures) > 1:
        i = pressures.index(params[0])
        nxt = (pressures[i + 1] if i + 1 < len(pressures) else pressures[i - 1],) + tuple(params[1:])
        warm = run_chain(m["mesh"], [params, nxt], spec.fidelity, spec.base, fibres=spec.fibres)[1]
        if warm["ok"]:
            n = min(len(pressures), MAX_CHAIN)
            out["warm_pair_s"] = warm["task_wall_s"]
            out["pair_s"] = (res["task_wall_s"] + (n - 1) * warm["task_wall_s"]) / n
    if res["ok"]:
        out["case_bytes"] = encoded_case_bytes(res["unloaded"], res["loaded"])
        out["inverse_s"] = res["stats"]["inverse_wall_s"]
        out["forward_s"] = res["stats"]["forward_wall_s"]
    else:
        out["case_bytes"] = 2 * out["nodes"] * 3 * 4
    return out


@dataclass
class PlanCost:
    """A plan's price from its calibration solve (`calibrate`): core-hours of what is left to run, wall
    time at `cores`, the cores (and cluster.yaml worker nodes) that finish it in an hour, the store's
    size, the paper's full sweep at this fidelity and mesh size, and for `fast` the goal it meets."""

    calibration: dict
    core_hours: float
    cores: int | None
    wall_hours_at_cores: float | None
    cores_for_one_hour: int
    worker_nodes_for_one_hour: int
    store_bytes_estimate: int
    paper_full_sweep_core_hours: float
    paper_full_sweep_store_bytes: int
    fast_goal: dict | None = None


@dataclass
class SweepPlan:
    """What `generate --dry-run` reports: the grid, what a resume leaves to run, and with a calibration
    its cost (PlanCost)."""

    store: str
    resume: bool
    shapes: int
    grows_from: int | None
    shapes_to_mesh: int
    cases_per_shape: int
    cases: int
    done: int
    failed: int
    to_run: int
    fidelity: str
    seed: int
    mesh_nodes: int
    grid: dict
    store_objects: int
    cost: PlanCost | None = None

    def as_dict(self) -> dict:
        """The plan as one flat JSON object (the cost's keys beside the grid's; none left out but an
        unknown wall time and a missing goal)."""
        d = {k: v for k, v in asdict(self).items() if k != "cost"}
        if self.cost is not None:
            d.update({k: v for k, v in asdict(self.cost).items()
                      if v is not None or k not in ("cores", "wall_hours_at_cores", "fast_goal")})
        return d


def make_plan(spec: SweepSpec, location: str, store_attrs: dict | None, cores: int | None = None,
              calibration: bool = True, warm_start: bool = True, retry_failed: bool = False) -> SweepPlan:
    """The plan of a sweep of `spec` into `location` (store_attrs: its root attributes, None for a new
    store); with `calibration`, priced by a calibration solve of shape 0 on this machine."""
    counts = existing_counts(location) if store_attrs is not None else {"done": 0, "failed": 0, "meshed": 0}
    remaining = spec.n_cases - counts["done"] - (0 if retry_failed else counts["failed"])
    to_mesh = spec.shapes - counts["meshed"]
    plan = SweepPlan(str(location), store_attrs is not None, spec.shapes,
                     spec.grows(store_attrs) if store_attrs is not None else None, to_mesh, spec.cases_per_shape,
                     spec.n_cases, counts["done"], counts["failed"], remaining, spec.fidelity, spec.seed, spec.nodes,
                     spec.grid_attrs(), store_objects(spec.shapes, spec.cases_per_shape,
                                                      store_attrs is None or case_layout(store_attrs) != CHUNK_PER_CASE))
    if calibration:
        plan.cost = _cost(spec, calibrate(spec, warm_start), remaining, to_mesh, cores)
    return plan


def _cost(spec: SweepSpec, cal: dict, remaining: int, to_mesh: int, cores: int | None) -> PlanCost:
    core_s = remaining * cal["pair_s"] + to_mesh * cal["mesh_s"]
    one_hour = max(1, math.ceil(core_s / 3600))
    full = PAPER_FULL_CASES * cal["pair_s"] / 3600
    goal = ({"core_hours_goal": FAST_GOAL_CORE_HOURS, "pair_s_goal": 1.5, "meets": bool(full <= FAST_GOAL_CORE_HOURS)}
            if spec.fidelity == "fast" else None)
    return PlanCost(cal, core_s / 3600, cores or None, core_s / 3600 / cores if cores else None, one_hour,
                    math.ceil(one_hour / WORKER_VCPUS),
                    int(spec.n_cases * cal["case_bytes"] + spec.shapes * cal["nodes"] * 3 * 8 * 1.2), full,
                    int(PAPER_FULL_CASES * cal["case_bytes"]), goal)


def cluster_cores() -> int:
    import os

    return os.cpu_count() or 1

