"""The store's two case layouts side by side: a shard per shape (schema version 2, what `generate`
writes) and a chunk per case (version 1), on local disk and on an S3 server on loopback (moto's
server mode, in this process). For each: objects per 1,000 cases, the sweep driver's write time per
case (its own path: HeldResults, write_pairs with read-back, the case table flushed every
FLUSH_INTERVAL_S; results fed chain by chain as the tasks return them), the training loader's read
(trainer.data.store_cases.read_store: every done case into memory) in cases per second, and the store's size.
Geometries are synthetic (a case-dependent shrink of real gmsh meshes: full float32 mantissas).

    .venv/bin/python scripts/bench_store.py --shapes 3 --nodes 800 [--no-s3] [--repeats 3] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from orchestrator import pacing, sweep  # noqa: E402
from orchestrator.grid import SweepSpec, pressure_chains  # noqa: E402
from scripts.bench_checksum import unloaded_like  # noqa: E402
from storage.schema import DONE  # noqa: E402
from storage.writer import PairStore  # noqa: E402
from trainer.data.store_cases import read_store  # noqa: E402

LAYOUTS = {"shard per shape": {}, "chunk per case": {"schema_version": 1}}
BUCKET = "heartctl-bench"
STATS = {"min_jacobian": 0.9, "roundtrip_error_mm": 1e-6, "final_residual": 1e-9, "solve_attempts": 1}


def bench_spec(shapes: int, nodes: int) -> SweepSpec:
    """6 P × 6 C × 3 θendo (108 cases a shape): the paper's pressure chains of six."""
    return SweepSpec(shapes=shapes, pressure_mmhg=(4.0, 6.0, 8.0, 10.0, 12.0, 14.0),
                     stiffness_pa=(50.0, 100.0, 150.0, 200.0, 250.0, 300.0), helix_endo_deg=(60.0, 65.0, 70.0),
                     helix_epi_deg=(-60.0,), fidelity="fast", seed=0, nodes=nodes)


def write_like_the_driver(store: PairStore, meshes: list) -> float:
    """Seconds per case the driver spends storing results, every shape's chains returned in the
    sweep's order: held and written as the sweep does (pacing.HeldResults, sweep._record), the case
    table flushed every FLUSH_INTERVAL_S and at the end."""
    held = pacing.HeldResults(store.sharded, lambda s: int((store.table(s).status == DONE).sum()))
    chains = [(s, c) for s in range(len(meshes)) for c in pressure_chains(store.params, range(store.n_cases))]
    for s, _ in chains:
        held.expect(s)
    n, t = 0, time.perf_counter()
    for s, chain in chains:
        nodes = meshes[s].nodes
        held.add(s, [(k, {"ok": True, "unloaded": unloaded_like(nodes, s * 10_000 + k), "loaded": nodes,
                          "stats": STATS, "host": "bench", "pid": 0}, time.time()) for k in chain])
        for due in held.due():
            n += sum(status == DONE for _, status in sweep._record(store, due, held.take(due), 0))
        store.flush(sweep.FLUSH_INTERVAL_S)
    store.flush()
    assert n == len(meshes) * store.n_cases, n
    return (time.perf_counter() - t) / n


def local_objects(location: str) -> tuple[int, int]:
    files = [p for p in Path(location).rglob("*") if p.is_file() and not p.name.endswith(".lock")]
    return len(files), sum(p.stat().st_size for p in files)


def s3_objects(prefix: str) -> tuple[int, int]:
    import boto3

    pages = boto3.client("s3").get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix)
    objects = [o for page in pages for o in page.get("Contents", [])]
    return len(objects), sum(o["Size"] for o in objects)


def one_store(location: str, spec: SweepSpec, meshes: list, layout: str, count) -> dict:
    """Write a fresh store of the layout like the driver, read it like the trainer; the figures."""
    store = PairStore.create(location, {**spec.store_attrs(), **LAYOUTS[layout]})
    assert store.sharded == (layout == "shard per shape")
    for s, m in enumerate(meshes):
        store.write_shape(s, m.nodes, m.tets, m.endo, m.epi, m.base, m.info["coefficients"], {})
    write_s = write_like_the_driver(store, meshes)
    t = time.perf_counter()
    cases = len(read_store(location).params)
    read_rate = cases / (time.perf_counter() - t)
    objects, size = count()
    return {"objects_per_1000_cases": objects * 1000 / cases, "write_ms_per_case": write_s * 1e3,
            "read_cases_per_s": read_rate, "store_mb": size / 1e6, "objects": objects, "cases": cases}


def start_s3() -> object:
    """moto's S3 server on 127.0.0.1 with a bucket; the AWS variables point at it."""
    import logging

    import boto3
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # no line per request
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    os.environ.update({"AWS_ENDPOINT_URL": f"http://{host}:{port}", "AWS_ACCESS_KEY_ID": "bench",
                       "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1"})
    boto3.client("s3").create_bucket(Bucket=BUCKET)
    return server


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shapes", type=int, default=3, help="shapes, 108 cases each")
    ap.add_argument("--nodes", type=int, default=800, help="target mesh node count")
    ap.add_argument("--repeats", type=int, default=1, help="stores of each kind; medians are printed")
    ap.add_argument("--no-s3", action="store_true", help="local disk only")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    from solver.meshing import mesh_lv
    from solver.shape_model import lv_shape

    spec = bench_spec(args.shapes, args.nodes)
    meshes = [mesh_lv(lv_shape(s), args.nodes) for s in range(args.shapes)]
    server = None if args.no_s3 else start_s3()
    runs: dict = {}
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for r in range(args.repeats):
                for where in (("local",) if server is None else ("local", "s3")):
                    for i, layout in enumerate(LAYOUTS if r % 2 == 0 else reversed(list(LAYOUTS))):
                        name = f"r{r}-{i}.zarr"
                        if where == "local":
                            location = str(Path(tmp) / name)
                            figures = one_store(location, spec, meshes, layout, lambda: local_objects(location))
                        else:
                            figures = one_store(f"s3://{BUCKET}/{name}", spec, meshes, layout, lambda: s3_objects(name))
                        runs.setdefault((where, layout), []).append(figures)
    finally:
        if server is not None:
            server.stop()
    result = {"shapes": args.shapes, "cases_per_shape": spec.cases_per_shape,
              "nodes": int(np.mean([m.n_nodes for m in meshes])), "repeats": args.repeats,
              "figures": {f"{where}, {layout}": {key: statistics.median(run[key] for run in values)
                                                  for key in values[0]}
                          for (where, layout), values in runs.items()}}
    if args.json:
        print(json.dumps(result))
        return result
    print(f"{result['shapes']} shapes × {result['cases_per_shape']} cases, ~{result['nodes']} nodes, "
          f"median of {args.repeats} store(s) each")
    columns = list(result["figures"])
    print(f"{'':26}" + "".join(f"{c:>26}" for c in columns))
    for key, label, fmt in (("objects_per_1000_cases", "objects per 1,000 cases", "{:.0f}"),
                            ("write_ms_per_case", "driver write, ms/case", "{:.2f}"),
                            ("read_cases_per_s", "training read, cases/s", "{:.0f}"),
                            ("store_mb", "store size, MB", "{:.2f}")):
        print(f"{label:26}" + "".join(f"{fmt.format(result['figures'][c][key]):>26}" for c in columns))
    return result


if __name__ == "__main__":
    main()
