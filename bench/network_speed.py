"""`heartctl bench model`: inference ms per case at several batch sizes and training graphs/s for
a configured model on a real LV mesh, in plain PyTorch (no Ray): eager, or with torch.compile. The
training step is timed on a batch already built, and again with its batch built each step from a
GraphTable as the training loop does, steps back to back (beside PyG's collation of the same batch,
for comparison)."""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from solver.parameters import PAPER_GRID
from storage.schema import PARAM_NAMES

from trainer.training.memory import tune_allocator
from trainer.network.averaging import WeightAverage
from trainer.data.batching import GraphTable, table_device
from trainer.config import named_config
from trainer.errors import TrainerError
from trainer.data.features import MeshFeatures, case_graph, mesh_features
from trainer.data.normalisation import Normalisation
from trainer.network.model import build_model, count_parameters, loss_terms


def _sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn, device, min_s: float = 1.0, min_runs: int = 3, max_runs: int = 200, first: list | None = None) -> float:
    """Seconds per call (after one warm-up call, whose seconds are appended to `first`)."""
    t0 = time.perf_counter()
    fn()
    _sync(device)
    if first is not None:
        first.append(time.perf_counter() - t0)
    runs, t0 = 0, time.perf_counter()
    while runs < min_runs or (time.perf_counter() - t0 < min_s and runs < max_runs):
        fn()
        runs += 1
        _sync(device)
    return (time.perf_counter() - t0) / runs


def _timed_back_to_back(fn, device, min_s: float = 1.0, min_runs: int = 3, max_runs: int = 200) -> float:
    """Seconds per call when calls follow each other without waiting for the GPU in between, as the
    training loop's steps do (the next batch is built while the GPU still works on this step): one
    warm-up call, then rounds of calls (doubling) with one synchronisation after each round."""
    fn()
    _sync(device)
    runs, n, t0 = 0, min_runs, time.perf_counter()
    while True:
        for _ in range(n):
            fn()
        runs += n
        _sync(device)
        elapsed = time.perf_counter() - t0
        if elapsed >= min_s or runs >= max_runs:
            return elapsed / runs
        n = min(runs, max_runs - runs)


def _profile(fn, device, calls: int = 3, rows: int = 25) -> str:
    """torch.profiler table of `calls` calls of fn (after one warm-up): the top `rows` operators by
    self device time on a GPU, by self CPU time on a CPU."""
    from torch.profiler import ProfilerActivity, profile

    fn()
    _sync(device)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        for _ in range(calls):
            fn()
        _sync(device)
    key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    return prof.key_averages().table(sort_by=key, row_limit=rows, max_name_column_width=60)


@dataclass(frozen=True, kw_only=True)
class InferenceTiming:
    """One inference batch size: ms per batch and per case of a batch collated once, and (with the
    attention graph) ms per case of a batch built in each call from a GraphTable (None without)."""

    batch: int
    ms_per_batch: float
    ms_per_case: float
    table_ms_per_case: float | None = None


@dataclass(frozen=True, kw_only=True)
class PreparedTiming:
    """One case on a mesh prepared once (`PreparedCase`): ms per case, whether a CUDA graph replays it,
    and why capturing one failed (None: it did not, or none was tried)."""

    ms_per_case: float
    cuda_graph: bool
    capture_error: str | None


@dataclass(frozen=True, kw_only=True)
class BatchBuilding:
    """Building a training batch: by PyG's collation and copy (ms), from the loop's GraphTable (ms, on
    `table_device`), and a training step with its batch built, steps back to back (ms)."""

    pyg_ms: float
    table_ms: float
    table_device: str
    loop_step_ms: float


@dataclass(frozen=True, kw_only=True)
class ModelBenchResult:
    """`bench model`'s result: where it ran (device, its name, torch threads), the model (configuration,
    parameters, bf16, GAT kernel, cycle, compiled and its compile time, s), the mesh (nodes, directed
    edges), each inference batch, the prepared single case, the linear FE response per mesh (ms; None
    when the configuration takes none), the training step (batch, ms, graphs/s), batch building and the
    loop's graphs/s, and with `profile` torch.profiler's tables."""

    device: str
    device_name: str
    threads: int
    config: str
    nodes: int
    edges: int
    parameters: int
    bf16: bool
    gat_kernel: str
    inference: list[InferenceTiming]
    prepared_single: PreparedTiming
    response_ms_per_mesh: float | None
    train_batch: int
    train_step_ms: float
    train_graphs_per_s: float
    cycle: bool
    batch_building: BatchBuilding
    loop_graphs_per_s: float
    compiled: bool
    compile_s: float
    profile_train: str | None = None
    profile_inference: str | None = None

    def as_dict(self) -> dict:
        """The JSON `--json` prints: every figure, a row's table time and the profiles only where measured."""
        d = asdict(self)
        d["inference"] = [{k: v for k, v in row.items() if v is not None} for row in d["inference"]]
        return {k: v for k, v in d.items() if v is not None or k == "response_ms_per_mesh"}


@dataclass(frozen=True)
class ModelBench:
    """What `heartctl bench model` times: `config`'s network on `device` (cpu | cuda), at the
    comma-separated inference `batches` and a `train_batch` (None: 32 on a CPU, 128 on a GPU), on a
    gmsh mesh of about `nodes` nodes or the `mesh` file (in `mesh_units`); `threads` torch CPU threads
    (None: torch's), `bf16`, `gat_kernel` (sparse | pyg), `compile_model`, and `profile` tables; each
    figure is timed over at least `min_seconds` (and three calls)."""

    device: str = "cpu"
    nodes: int = 650
    config: str = "paper"
    batches: str = "1,32,128"
    train_batch: int | None = None
    bf16: bool = False
    threads: int | None = None
    gat_kernel: str = "sparse"
    mesh: Path | None = None
    mesh_units: str = "mm"
    compile_model: bool = False
    profile: bool = False
    min_seconds: float = 1.0

    def __post_init__(self):
        from solver.meshing import check_node_target

        sizes = self.batch_sizes
        check_node_target(self.nodes)
        if not sizes or min(sizes) < 1 or self.nodes < 50 or (self.train_batch is not None and self.train_batch < 1):
            raise ValueError("`batches` need sizes ≥ 1, `nodes` ≥ 50, `train_batch` ≥ 1")
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"`device` must be cpu or cuda, got {self.device!r}")
        if self.threads is not None and self.threads < 1:
            raise ValueError("`threads` must be ≥ 1")
        if not 0 <= self.min_seconds <= 600:
            raise ValueError(f"`min_seconds` must be in 0–600, got {self.min_seconds:g}")
        if self.mesh is not None and not Path(self.mesh).is_file():
            raise ValueError(f"mesh={self.mesh}: no such file")
        if self.mesh is None and self.mesh_units != "mm":
            raise ValueError("`units` gives the length unit of the `mesh` file; without `mesh` none is read")

    @property
    def batch_sizes(self) -> list[int]:
        try:
            return [int(b) for b in self.batches.replace(",", " ").split()]
        except ValueError:
            raise ValueError(f"`batches` must be comma-separated integers, got {self.batches!r}") from None

    def run(self) -> ModelBenchResult:
        """bench_model with these settings (torch's CPU threads set first)."""
        if self.threads is not None:
            torch.set_num_threads(self.threads)
        return bench_model(self.device, self.nodes, self.config, self.batch_sizes, self.train_batch, self.bf16,
                           gat_kernel=self.gat_kernel, mesh_path=None if self.mesh is None else str(self.mesh),
                           compile_model=self.compile_model, profile=self.profile, mesh_units=self.mesh_units,
                           min_s=self.min_seconds)


def bench_model(device: str = "cpu", nodes: int = 650, config: str = "paper", batches=(1, 32, 128),
                train_batch: int | None = None, bf16: bool = False, seed: int = 0, min_s: float = 1.0,
                gat_kernel: str = "sparse", mesh_path: str | None = None, compile_model: bool = False,
                profile: bool = False, mesh_units: str = "mm") -> ModelBenchResult:
    """mesh_path: time on this mesh (any format storage.meshfiles reads, in `mesh_units`) instead of meshing shape 0
    with gmsh for `nodes` nodes (lets a GPU host without gmsh run the benchmark). compile_model: run
    the batched inference and the training step through torch.compile (dynamic shapes; the first,
    untimed call of each pays the compilation, reported as compile_s). profile: also return torch.profiler
    tables (top operators by device time, or CPU time on a CPU) of three training steps and of three
    batched inferences at the largest batch, as `profile_train` / `profile_inference`."""
    from torch_geometric.data import Batch

    b = _Bench.make(device, nodes, config, bf16, seed, gat_kernel, mesh_path, compile_model, mesh_units)
    response_ms = None
    if b.cfg.uses_response:  # computed once per mesh, on the CPU, before any case of it is predicted
        response_ms = _timed(lambda: MeshFeatures.response.func(b.feat), torch.device("cpu"), min_s) * 1e3  # uncached
    cases = [b.graph() for _ in range(max(batches))]
    rows = _time_inference(b, cases, batches, min_s)
    from trainer.network.prepared import PreparedCase

    prepared = PreparedCase(b.model, Batch.from_data_list([b.graph()]).to(b.dev), bf16=bf16)
    s = _timed(prepared, b.dev, min_s)
    prepared_row = PreparedTiming(ms_per_case=s * 1e3, cuda_graph=prepared.cuda_graph is not None,
                                  capture_error=prepared.capture_error)
    tb = train_batch or (128 if b.dev.type == "cuda" else 32)
    step, s, building = _time_training(b, tb, seed, min_s)
    profiles = {}
    if profile:
        profiles["profile_train"] = _profile(step, b.dev)
        b.model.eval()
        big = Batch.from_data_list(cases).to(b.dev)
        profiles["profile_inference"] = _profile(lambda: b.infer(big), b.dev)
    dev = b.dev
    return ModelBenchResult(
        **profiles, device=str(dev), device_name=torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
        threads=torch.get_num_threads(), config=config, nodes=int(b.mesh.n_nodes),
        edges=int(b.feat.edge_index.shape[1]), parameters=count_parameters(b.model),
        bf16=bool(bf16 and dev.type == "cuda"), gat_kernel=gat_kernel, inference=rows, prepared_single=prepared_row,
        response_ms_per_mesh=response_ms, train_batch=tb, train_step_ms=s * 1e3, train_graphs_per_s=tb / s,
        cycle=b.cfg.cycle, batch_building=building, loop_graphs_per_s=tb / building.loop_step_ms * 1e3,
        compiled=bool(compile_model), compile_s=sum(b.compile_s) if compile_model else 0.0)


@dataclass
class _Bench:
    """What every figure of bench_model shares: the mesh and its features, a normalisation over the
    paper's box, the model (and its torch.compile'd runner), bf16 autocast, and the seconds each
    compiled callable's first call took."""

    dev: torch.device
    cfg: object
    mesh: object
    feat: MeshFeatures
    norm: Normalisation
    model: torch.nn.Module
    run: object
    amp: object
    rng: np.random.Generator
    attention: bool  # batches built from a GraphTable with the attention graph assembled from the mesh's
    compile_s: list

    @classmethod
    def make(cls, device: str, nodes: int, config: str, bf16: bool, seed: int, gat_kernel: str,
             mesh_path: str | None, compile_model: bool, mesh_units: str) -> "_Bench":
        tune_allocator()
        dev = torch.device(device)
        if dev.type == "cuda" and not torch.cuda.is_available():
            raise TrainerError("`device` cuda: no CUDA device is available here")
        if gat_kernel not in ("sparse", "pyg"):
            raise TrainerError(f"`gat_kernel` must be sparse or pyg, got {gat_kernel!r}")
        cfg = replace(named_config(config), gat_kernel=gat_kernel)
        if cfg.kind != "gnn":
            raise TrainerError("bench model times the graph network; choose a gnn `config`")
        torch.manual_seed(seed)
        mesh = _bench_mesh(mesh_path, mesh_units, nodes, seed)
        feat = mesh_features(mesh)
        c = feat.ed_mm.mean(axis=0)
        norm = Normalisation(tuple(c), float(np.sqrt(((feat.ed_mm - c) ** 2).sum(axis=1).mean())), 1.0,
                             tuple(min(PAPER_GRID[a]) for a in PARAM_NAMES),
                             tuple(max(PAPER_GRID[a]) for a in PARAM_NAMES))
        model = build_model(cfg, 0.1).to(dev)
        run = torch.compile(model, dynamic=True) if compile_model else model
        if dev.type == "cuda":
            torch.set_float32_matmul_precision("high")  # TF32 for fp32 matmuls, as the training loop
        amp = torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=bool(bf16 and dev.type == "cuda"))
        # not under torch.compile, which would trace the attention graph's assembly on every new batch
        attention = cfg.uses_attention_graph and not compile_model
        return cls(dev, cfg, mesh, feat, norm, model, run, amp, np.random.default_rng(seed), attention, [])

    def graph(self):
        """A case of the mesh at random parameters of the paper's grid, with a random unloaded geometry."""
        p = [self.rng.choice(PAPER_GRID[a]) for a in PARAM_NAMES]
        return case_graph(self.feat, p, self.norm, self.feat.ed_mm + self.rng.normal(0, 1, self.feat.ed_mm.shape),
                          True, response=self.cfg.uses_response)

    def infer(self, batch) -> None:
        with torch.no_grad(), self.amp:
            self.run(batch, cycle=False)


def _bench_mesh(mesh_path: str | None, mesh_units: str, nodes: int, seed: int):
    """The mesh read from mesh_path, or shape 0 of the shape model meshed at `nodes` nodes."""
    if mesh_path is not None:
        from storage.meshfiles import read_mesh

        return read_mesh(mesh_path, mesh_units)
    from solver.meshing import mesh_lv
    from solver.shape_model import lv_shape

    return mesh_lv(lv_shape(0, seed), nodes)


def _time_inference(b: _Bench, cases: list, batches, min_s: float) -> list[InferenceTiming]:
    """ms per batch and per case at each batch size: of a batch collated once, and (with the attention
    graph) of a batch built in each call from a GraphTable as the training loop builds them."""
    from torch_geometric.data import Batch

    b.model.eval()
    inference_table = GraphTable(cases, table_device(cases, b.dev), b.attention, b.dev) if b.attention else None
    rows = []
    for size in batches:
        data = Batch.from_data_list(cases[:size]).to(b.dev)
        s = _timed(lambda batch=data: b.infer(batch), b.dev, min_s, first=b.compile_s)
        table_ms = None
        if inference_table is not None:  # the batch and its attention graph built in each call
            table_ms = _timed(lambda: b.infer(inference_table.batch(range(size)).to(b.dev, non_blocking=True)),
                              b.dev, min_s) * 1e3 / size
        row = InferenceTiming(batch=size, ms_per_batch=s * 1e3, ms_per_case=s * 1e3 / size, table_ms_per_case=table_ms)
        rows.append(row)
    return rows


def _time_training(b: _Bench, tb: int, seed: int, min_s: float):
    """(the training step, its seconds, the batch-building figures): the training loop's step
    (trainer.training.loop.fit: reverse decoder, mean teacher, weight average) on a batch of `tb`, the cost of
    building a batch by PyG's collation and from a GraphTable, and steps back to back with their
    batches built."""
    from torch_geometric.data import Batch

    pool = [b.graph() for _ in range(2 * tb)]  # the cases batches are drawn from, as in an epoch
    table = GraphTable(pool, table_device(pool, b.dev), b.attention, b.dev)
    pick = np.random.default_rng(seed + 1)

    def draw() -> list:
        return pick.choice(len(pool), tb, replace=False).tolist()

    def pyg_batch():
        return Batch.from_data_list([pool[i] for i in draw()]).to(b.dev, non_blocking=True)

    pyg_ms = _timed(pyg_batch, b.dev, min_s) * 1e3
    table_ms = _timed(lambda: table.batch(draw()).to(b.dev, non_blocking=True), b.dev, min_s) * 1e3
    data = table.batch(draw()).to(b.dev, non_blocking=True)
    model, cfg = b.model, b.cfg
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-4)
    average = WeightAverage(model, cfg.ema_decay) if cfg.ema_decay > 0 else None
    uses_teacher = average is not None and cfg.cycle and cfg.cycle_grad == "teacher"

    def step():
        opt.zero_grad(set_to_none=True)
        with b.amp:
            d_unl, d_ed, d_rev = b.run(data, reverse=True, teacher=average.teacher() if uses_teacher else None)
        loss_terms(d_unl, d_ed, data, cfg.lambda_cycle, d_rev, cfg.reverse_weight)["loss"].backward()
        opt.step()
        if average is not None:
            average.update(model)

    s = _timed(step, b.dev, min_s, min_runs=2, first=b.compile_s)

    def loop_step():  # the training loop's step with its batch built from the table
        nonlocal data
        data = table.batch(draw()).to(b.dev, non_blocking=True)
        step()

    loop_ms = _timed_back_to_back(loop_step, b.dev, min_s, min_runs=2) * 1e3
    return step, s, BatchBuilding(pyg_ms=pyg_ms, table_ms=table_ms, table_device=str(table.device), loop_step_ms=loop_ms)
