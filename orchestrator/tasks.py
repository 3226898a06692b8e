"""The work of one task, as plain functions (no Ray here): the sweep wraps them in `ray.remote`,
tests and benchmarks call them directly."""
from __future__ import annotations

import os
import socket
import sys
import time
from dataclasses import replace

import numpy as np

ROBUST_INITIAL_LOAD_STEP = 0.05
ROBUST_MIN_STEP_FACTOR = 0.1


def ray_node_id() -> str | None:
    """The Ray node this process runs on, when it is a Ray worker (Ray already imported and
    connected here); None otherwise, without importing Ray."""
    ray = sys.modules.get("ray")
    try:
        return ray.get_runtime_context().get_node_id() if ray is not None and ray.is_initialized() else None
    except Exception:
        return None


def _single_thread() -> None:
    # one solve per core: keep BLAS / MKL (pypardiso) from oversubscribing the worker's CPU
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def mesh_shape(shape_id: int, seed: int, nodes: int, mesh_file: str | None = None, units: str = "mm",
               shape_model_version: int = 1) -> dict:
    """Mesh one member of the shape model's `shape_model_version`, or read a user's ED mesh file
    (then `seed` and `nodes` do not apply and the coefficients are NaN). Returns the TetMesh and its
    shape coefficients."""
    _single_thread()
    from solver.meshing import mesh_lv_fresh_process
    from solver.shape_model import MODES, lv_shape

    t0 = time.perf_counter()
    if mesh_file is not None:
        from storage.meshfiles import read_mesh

        mesh = read_mesh(mesh_file, units, check_units=False)  # the driver checked (and warned) before submitting
        coefficients = np.full(len(MODES), np.nan)
        cavity_ml = float("nan")
    else:
        shape = lv_shape(int(shape_id), int(seed), int(shape_model_version))
        mesh = mesh_lv_fresh_process(int(shape_id), int(seed), int(shape_model_version), int(nodes))
        coefficients = np.asarray(shape.coefficients, dtype=float)
        cavity_ml = float(shape.cavity_volume_ml())
    info = {k: (float(v) if isinstance(v, (np.floating, float)) else v) for k, v in mesh.info.items()
            if isinstance(v, (int, float, str, np.floating, np.integer))}
    info["cavity_volume_ml"] = cavity_ml
    info["mesh_wall_s"] = time.perf_counter() - t0
    info["host"] = socket.gethostname()
    return {"shape_id": int(shape_id), "mesh": mesh, "coefficients": coefficients, "info": info}


def robust_fidelity(fidelity):
    """The retry setting after a solver failure: smaller first and minimum load steps."""
    return replace(fidelity, initial_load_step=min(fidelity.initial_load_step, ROBUST_INITIAL_LOAD_STEP),
                   min_load_step=fidelity.min_load_step * ROBUST_MIN_STEP_FACTOR)


def run_case(mesh, params, fidelity: str, base: str = "sliding", retry: bool = True,
             fibres: str = "laplace", initial_unloaded: np.ndarray | None = None, workspace=None) -> dict:
    """One training pair: inverse then forward FE. A solver failure (SolveError, or an inverted
    trial geometry) is retried once with `robust_fidelity`, from the ED mesh (never from
    `initial_unloaded`); if that fails too the result says so (ok False, reason) — this function does
    not raise for a case that will not solve. An inverse that failed by its own iteration
    (`InverseError`: stalled, folded, out of updates) from the ED mesh is not retried: smaller load
    steps repeat the same updates.

    mesh: solver TetMesh (the ED geometry); params: (P mmHg, C Pa, θendo °, θepi °) or CaseParameters;
    initial_unloaded: a starting unloaded geometry [n, 3] mm for the first attempt (warm start);
    workspace: a `solver.lv.PairWorkspace` on this mesh for the first attempt (the retry builds its own).
    Returns ok, unloaded/loaded [n,3] (mm, float64) or None, stats (the pair's), reason, attempts,
    host, pid, node (the Ray node id, None outside Ray), started_at / finished_at (unix s), task_wall_s.
    """
    _single_thread()
    from solver.fidelity import get_fidelity
    from solver.forward import SolveError
    from solver.inverse_failure import InverseError
    from solver.lv import make_pair
    from solver.mesh import MeshError
    from solver.parameters import CaseParameters

    started_at = time.time()
    t0 = time.perf_counter()
    if not isinstance(params, CaseParameters):
        params = CaseParameters(*(float(v) for v in params))
    fid = get_fidelity(fidelity) if isinstance(fidelity, str) else fidelity
    settings = [(fid, initial_unloaded, workspace), (robust_fidelity(fid), None, None)]
    settings = settings if retry else settings[:1]
    pair, reasons, attempts, inverse_failed = None, [], 0, False
    for setting, guess, shared in settings:
        attempts += 1
        try:
            pair = make_pair(mesh, params, setting, base, initial_unloaded=guess, fibres=fibres, workspace=shared)
            break
        except (SolveError, MeshError) as exc:
            reasons.append(str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__)
            inverse_failed = isinstance(exc, InverseError)
            if inverse_failed and guess is None:
                break
        except MemoryError:
            raise  # the worker's trouble, not the case's: the driver leaves the chain pending
        except Exception as exc:  # e.g. a linear solver's "factor is exactly singular": this case fails, the chain goes on
            line = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            reasons.append(f"{type(exc).__name__}: {line}".strip(" :"))
    out = _result(pair is not None, attempts, started_at, time.perf_counter() - t0)
    if pair is None:
        out["reason"] = reasons[-1]
        out["first_reason"] = reasons[0]
        out["inverse_failed"] = inverse_failed
    else:
        out["unloaded"] = np.asarray(pair.unloaded_nodes, dtype=float)
        out["loaded"] = np.asarray(pair.loaded_nodes, dtype=float)
        out["stats"] = {k: float(v) for k, v in pair.stats.items()}
    return out


def run_chain(mesh, params_list, fidelity: str, base: str = "sliding", fibres: str = "laplace",
              warm_start: bool = True) -> list[dict]:
    """Cases of one shape that differ only in pressure, solved in the order given (the sweep gives
    increasing pressure): with `warm_start`, each inverse starts from the unloaded geometry
    extrapolated in pressure from the chain's cases solved so far (`solver.lv.unloaded_guess`), which
    converges to the same tolerance in fewer iterations. A guess that folds an element is dropped (the
    case then starts from its ED mesh). The cases share one `PairWorkspace` (FE problem and sparse
    solver). Once a case's inverse fails by its own iteration (`run_case`'s `inverse_failed`: the
    reference folds or the mismatch stalls), the chain's higher pressures, which deform the wall
    further, are recorded as failed with that reason and not solved (`generate --retry-failed` solves
    them). Returns one result per case, in order."""
    _single_thread()
    from solver.lv import PairWorkspace, unloaded_guess
    from solver.mesh import MeshError, check_geometry

    solved, results, gave_out = [], [], None
    with PairWorkspace(mesh) as workspace:
        for params in params_list:
            pressure = float(params[0] if not hasattr(params, "pressure_mmhg") else params.pressure_mmhg)
            if gave_out is not None:
                results.append(_not_attempted(f"not solved: the inverse failed at {gave_out[0]:g} mmHg in this "
                                              f"chain, a lower pressure ({gave_out[1]})"))
                continue
            guess = unloaded_guess(solved, pressure) if warm_start else None
            if guess is not None:
                try:
                    check_geometry(guess, mesh.tets)
                except MeshError:
                    guess = None
            res = run_case(mesh, params, fidelity, base, fibres=fibres, initial_unloaded=guess, workspace=workspace)
            res["warm_start"] = guess is not None
            if res["ok"]:
                solved.append((pressure, res["unloaded"]))
            elif res.get("inverse_failed"):
                gave_out = (pressure, res["reason"])
            results.append(res)
    return results


def _result(ok: bool, attempts: int, started_at: float, wall_s: float) -> dict:
    """The fields of run_case's result that every case has: where and when it ran, no answer yet."""
    return {"ok": ok, "attempts": attempts, "host": socket.gethostname(), "pid": os.getpid(), "node": ray_node_id(),
            "started_at": started_at, "finished_at": time.time(), "task_wall_s": wall_s,
            "unloaded": None, "loaded": None, "stats": {}, "reason": None}


def _not_attempted(reason: str) -> dict:
    """run_case's result for a case left unsolved on purpose, with its reason."""
    return {**_result(False, 0, time.time(), 0.0), "reason": reason, "first_reason": reason, "warm_start": False}


def warm_up(seconds: float = 0.2) -> int:
    """Import the solver in a worker (benchmarks warm the pool with this)."""
    _single_thread()
    import solver.lv  # noqa: F401

    time.sleep(seconds)
    return os.getpid()
