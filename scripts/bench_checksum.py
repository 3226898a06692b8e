"""Cost of the CRC-32C checksum on every stored chunk: the store's own write path (write_pair: two
chunks written and read back, set_case, flush) in seconds per case, and the training loader's read
path (trainer.data.store_cases.read_store: every done case into memory) in cases per second, with the store's codecs (Blosc zstd + CRC-32C) and
with Blosc alone. The two variants alternate, repeat after repeat, on a fresh store each time; the
medians are printed (a shared machine's noise hits both alike).

    .venv/bin/python scripts/bench_checksum.py --shapes 4 --cases 60 --nodes 800 --repeats 7 [--folder /dev/shm]
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import storage.writer as store_module  # noqa: E402  (the writer compresses with its chunk_codecs)
from storage.schema import DONE  # noqa: E402
from storage.writer import PairStore, stats_row  # noqa: E402
from trainer.data.store_cases import read_store  # noqa: E402

WITH_CRC = store_module.chunk_codecs


def without_crc() -> tuple:
    return WITH_CRC()[:1]  # Blosc only


def unloaded_like(nodes: np.ndarray, k: int) -> np.ndarray:
    """A smooth, case-dependent shrink (the bytes of real unloaded geometries: full float32 mantissas)."""
    rng = np.random.default_rng(k)
    s = 0.02 + 0.04 * rng.random()
    out = nodes * (1.0 - s)
    out[:, 2] += s * nodes[:, 2] * 0.5
    return out


def one_store(folder: Path, meshes: list, cases: int, checksum: bool) -> tuple[float, float, float, float]:
    """(write s per case, read cases per s, write CPU s per case, read CPU s per case) of a fresh store.
    CPU time is the process's, every thread's (zarr encodes and writes in its own threads): less moved
    by other processes on the machine than wall time."""
    from orchestrator.grid import SweepSpec

    store_module.chunk_codecs = WITH_CRC if checksum else without_crc
    try:
        spec = SweepSpec(shapes=len(meshes), pressure_mmhg=tuple(float(p) for p in range(1, cases + 1)),
                         stiffness_pa=(150.0,), helix_endo_deg=(60.0,), helix_epi_deg=(-60.0,), fidelity="fast",
                         seed=0, nodes=800)
        location = str(folder / ("crc.zarr" if checksum else "plain.zarr"))
        store = PairStore.create(location, spec.store_attrs())
        for s, m in enumerate(meshes):
            store.write_shape(s, m.nodes, m.tets, m.endo, m.epi, m.base, np.zeros(3), {})
        data = [[(unloaded_like(m.nodes, k), m.nodes) for k in range(cases)] for m in meshes]
        stats = {"min_jacobian": 0.9, "roundtrip_error_mm": 1e-6, "final_residual": 1e-9}
        t, c = time.perf_counter(), time.process_time()
        for s in range(len(meshes)):
            for k, (unloaded, loaded) in enumerate(data[s]):
                assert store.write_pair(s, k, unloaded, loaded, stats) is None
                store.set_case(s, k, DONE, stats_row(stats))
                store.flush(2.0)  # the sweep driver's interval
        store.flush()
        write_s = (time.perf_counter() - t) / (len(meshes) * cases)
        write_cpu = (time.process_time() - c) / (len(meshes) * cases)
        t, c = time.perf_counter(), time.process_time()
        n = len(read_store(location).params)  # the training loader's read of every done case
        read_rate = n / (time.perf_counter() - t)
        read_cpu = (time.process_time() - c) / n
        shutil.rmtree(location)
        return write_s, read_rate, write_cpu, read_cpu
    finally:
        store_module.chunk_codecs = WITH_CRC


def codec_alone(n_nodes: int, repeats: int, chunks: int = 200) -> dict:
    """µs per [n,3] float32 chunk written and read through zarr in memory (no disk, no validation), the
    store's codecs against Blosc alone; the fastest of `repeats` alternating passes."""
    import zarr
    from zarr.storage import MemoryStore

    rng = np.random.default_rng(0)
    x = (rng.random((n_nodes, 3)) * 80.0).astype(np.float32)
    arrays = {}
    for checksum, codecs in ((True, WITH_CRC()), (False, without_crc())):
        g = zarr.open_group(MemoryStore(), mode="w", zarr_format=3)
        arrays[checksum] = g.create_array("u", shape=(chunks, n_nodes, 3), chunks=(1, n_nodes, 3), dtype=np.float32,
                                          fill_value=np.nan, compressors=codecs)
    times = {(c, op): [] for c in (True, False) for op in ("write", "read")}
    for r in range(max(repeats, 5)):
        for checksum in ((True, False) if r % 2 == 0 else (False, True)):
            a = arrays[checksum]
            t = time.perf_counter()
            for k in range(chunks):
                a[k] = x
            times[checksum, "write"].append((time.perf_counter() - t) / chunks * 1e6)
            t = time.perf_counter()
            for k in range(chunks):
                a[k]
            times[checksum, "read"].append((time.perf_counter() - t) / chunks * 1e6)
    return {f"{op}_{'crc32c' if c else 'plain'}": min(v) for (c, op), v in times.items()}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shapes", type=int, default=4)
    ap.add_argument("--cases", type=int, default=60, help="cases per shape")
    ap.add_argument("--nodes", type=int, default=800, help="target mesh node count")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--folder", default=None, help="where the stores go (default: the system's temporary folder; "
                                                   "/dev/shm takes the disk out and leaves the codec's CPU cost)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    from solver.meshing import mesh_lv
    from solver.shape_model import lv_shape

    meshes = [mesh_lv(lv_shape(s), args.nodes) for s in range(args.shapes)]
    runs = {True: [], False: []}
    with tempfile.TemporaryDirectory(dir=args.folder) as tmp:
        one_store(Path(tmp), meshes[:1], 4, True)  # warm imports and caches
        for r in range(args.repeats):
            for checksum in ((True, False) if r % 2 == 0 else (False, True)):
                runs[checksum].append(one_store(Path(tmp), meshes, args.cases, checksum))

    def med(checksum: bool, i: int) -> float:
        return statistics.median(run[i] for run in runs[checksum])

    def best(checksum: bool, i: int) -> float:  # the repeat least disturbed by other processes
        values = [run[i] for run in runs[checksum]]
        return max(values) if i == 1 else min(values)

    result = {"folder": args.folder or tempfile.gettempdir(), "shapes": args.shapes, "cases_per_shape": args.cases,
              "nodes": int(np.mean([m.n_nodes for m in meshes])), "repeats": args.repeats}
    for i, (key, scale) in enumerate((("write_ms_per_case", 1e3), ("read_cases_per_s", 1.0),
                                      ("write_cpu_ms_per_case", 1e3), ("read_cpu_ms_per_case", 1e3))):
        result[key] = {"crc32c": scale * med(True, i), "plain": scale * med(False, i)}
        result[key + "_best"] = {"crc32c": scale * best(True, i), "plain": scale * best(False, i)}
        result[key + "_each_repeat"] = {"crc32c": [scale * run[i] for run in runs[True]],
                                        "plain": [scale * run[i] for run in runs[False]]}
    result["write_overhead_pct"] = 100 * (med(True, 0) / med(False, 0) - 1)
    result["read_overhead_pct"] = 100 * (med(False, 1) / med(True, 1) - 1)  # time per case
    result["write_cpu_overhead_pct"] = 100 * (med(True, 2) / med(False, 2) - 1)
    result["read_cpu_overhead_pct"] = 100 * (med(True, 3) / med(False, 3) - 1)
    result["write_overhead_pct_best"] = 100 * (best(True, 0) / best(False, 0) - 1)
    result["read_overhead_pct_best"] = 100 * (best(False, 1) / best(True, 1) - 1)
    result["codec_alone_us_per_chunk"] = codec_alone(meshes[0].n_nodes, args.repeats)
    if args.json:
        print(json.dumps(result))
    else:
        w, r = result["write_ms_per_case"], result["read_cases_per_s"]
        wc, rc = result["write_cpu_ms_per_case"], result["read_cpu_ms_per_case"]
        print(f"{result['shapes']} shapes × {result['cases_per_shape']} cases, ~{result['nodes']} nodes, "
              f"median of {result['repeats']} alternating repeats, stores in {result['folder']}")
        print(f"write (write_pair + read-back + case table): {w['crc32c']:.3f} ms/case with CRC-32C, "
              f"{w['plain']:.3f} without ({result['write_overhead_pct']:+.1f} %); CPU {wc['crc32c']:.3f} vs "
              f"{wc['plain']:.3f} ms ({result['write_cpu_overhead_pct']:+.1f} %)")
        print(f"read (trainer.data.store_cases.read_store, the training loader): {r['crc32c']:.0f} cases/s with CRC-32C, "
              f"{r['plain']:.0f} without ({result['read_overhead_pct']:+.1f} % time); CPU {rc['crc32c']:.3f} vs "
              f"{rc['plain']:.3f} ms/case ({result['read_cpu_overhead_pct']:+.1f} %)")
        print(f"best repeat: write {result['write_overhead_pct_best']:+.1f} %, read {result['read_overhead_pct_best']:+.1f} %")
        c = result["codec_alone_us_per_chunk"]
        print(f"codec alone (zarr, memory, one [n,3] chunk): write {c['write_crc32c']:.0f} vs {c['write_plain']:.0f} µs, "
              f"read {c['read_crc32c']:.0f} vs {c['read_plain']:.0f} µs")
    return result


if __name__ == "__main__":
    main()
