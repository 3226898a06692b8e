"""The training loop: plain PyTorch/PyG, runs without Ray (tests, GPU hosts without Ray); the Ray
Train wrapper passes a `Dist` (rank, device, DDP wrapping, checkpoint report/restore) to distribute it."""
from __future__ import annotations

import math
import os
import random
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from trainer.training.memory import tune_allocator
from trainer.data.augment import rotate_batch, scale_batch
from trainer.network.averaging import WeightAverage
from trainer.data.batching import GraphTable, chunks, table_device
from trainer.training.checkpoint import (check_resume_parts, cpu_state, load_checkpoint, remove_stale_temporaries, run_checkpoint_path,
                         save_checkpoint)
from trainer.config import TrainConfig
from trainer.errors import TrainerError, TrainingDiverged
from trainer.data.store_cases import DataBundle, check_fingerprint, training_data
from trainer.files import write_csv, write_json
from trainer.network.model import build_model, count_parameters, loss_terms
from trainer.data.sampling import MixedBatchSampler, labelled_per_batch
from trainer.training.schedule import cosine_lr
from trainer.training.summary import TrainingSummary

METRIC_COLUMNS = ("epoch", "train_loss", "train_sup", "train_cycle", "val_loss", "val_md_mm", "lr", "epoch_s",
                  "graphs_per_s")


@dataclass
class Dist:
    """How the loop is distributed. The defaults are one process, no Ray."""

    rank: int = 0
    world: int = 1
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    wrap_model: Callable = lambda m: m  # e.g. ray.train.torch.prepare_model (DDP)
    restore: Callable | None = None  # → checkpoint dict or None (e.g. from ray.train.get_checkpoint)
    report: Callable | None = None  # (metrics, state or None) → None; state only on rank 0
    log: Callable = print
    write_local: bool = True  # rank 0 writes checkpoint.pt / metrics.csv into run_dir (its host sees it)

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def seed_epoch(seed: int, epoch: int, rank: int) -> None:
    """Seed torch's generators (dropout draws; the CPU's and every CUDA device's) for one epoch of one
    process from (seed, epoch, rank) alone. A resumed run then draws what an uninterrupted one would
    have drawn, on any device and any rank, with no generator state saved: a CUDA generator's offset
    grows with each tensor's size, so ranks whose batches differ in node count drift apart, and rank
    0's saved state would not be another rank's. Ranks draw independent dropout masks."""
    torch.manual_seed(int(np.random.SeedSequence([seed, epoch, rank, 13]).generate_state(1)[0]))


def _all_reduce(values: list, dist: Dist) -> list:
    if dist.world <= 1:
        return values
    import torch.distributed as tdist

    t = torch.tensor(values, dtype=torch.float64, device=dist.device)
    tdist.all_reduce(t)
    return t.tolist()


def _move(batch, device):
    """Ray's prepare_data_loader does not move a PyG Batch; the loop does it here (a no-op for a
    batch built on the device from a GraphTable there)."""
    return batch.to(device, non_blocking=True)


class TableLoader:
    """The batches of a GraphTable in the order a batch sampler gives them (lists of indices)."""

    def __init__(self, table: GraphTable, batch_sampler):
        self.table, self.batch_sampler = table, batch_sampler

    def __iter__(self):
        return self.table.batches(self.batch_sampler)

    def __len__(self) -> int:
        return len(self.batch_sampler)


def _loaders(bundle: DataBundle, cfg: TrainConfig, dist: Dist):
    """Training loader (mixed labelled/unlabelled batches when SR < 1, see trainer.data.sampling),
    its sampler (set_epoch) and the validation loader; both build their batches from a GraphTable
    (trainer.data.batching), in the order PyG's DataLoader would with the same sampler."""
    from torch.utils.data import BatchSampler, RandomSampler
    from torch.utils.data.distributed import DistributedSampler

    flags = [bool(g.labelled.item()) for g in bundle.train]
    n_lab = labelled_per_batch(cfg.batch_size, cfg.sr, cfg.labelled_share)
    attention = cfg.model.uses_attention_graph
    # compiled, the model builds its attention graph inside the compiled code (a prebuilt one, a
    # Python object of many tensors, would be traced anew for every batch)
    table = GraphTable(bundle.train, table_device(bundle.train, dist.device), attention and not cfg.compile,
                       dist.device)
    if n_lab and any(flags) and not all(flags):
        train_sampler = MixedBatchSampler([i for i, f in enumerate(flags) if f], [i for i, f in enumerate(flags) if not f],
                                          cfg.batch_size, n_lab, cfg.seed, dist.rank, dist.world)
        train = TableLoader(table, train_sampler)
    else:
        if dist.world > 1:
            train_sampler = DistributedSampler(bundle.train, num_replicas=dist.world, rank=dist.rank, shuffle=True,
                                               seed=cfg.seed)
        else:
            gen = torch.Generator()
            train_sampler = RandomSampler(bundle.train, generator=gen)
            train_sampler.set_epoch = lambda epoch: gen.manual_seed(cfg.seed * 100003 + epoch)  # type: ignore[attr-defined]
        train = TableLoader(table, BatchSampler(train_sampler, cfg.batch_size, drop_last=False))
    shard = validation_shard(bundle.val, dist.rank, dist.world)
    val = None
    if shard:
        val = TableLoader(GraphTable(shard, table_device(shard, dist.device), attention, dist.device),
                          chunks(len(shard), cfg.batch_size))
    return train, train_sampler, val


def validation_shard(cases: list, rank: int, world: int) -> list:
    """This rank's validation cases: every world-th from `rank`, without the padding of a
    DistributedSampler (which repeats cases so the ranks get equal shares, and would weight those
    twice in the all-reduced validation loss)."""
    return cases[rank::world]


def _autocast(cfg: TrainConfig, device: torch.device):
    return torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=bool(cfg.bf16 and device.type == "cuda"))


def _validate(model, loader, cfg: TrainConfig, dist: Dist, disp_scale_mm: float) -> tuple[float, float, int]:
    """(val MSE in normalised units, mean node error mm, validation nodes) over the validation cases of
    all ranks; NaN, NaN, 0 without validation cases."""
    acc = torch.zeros(2, dtype=torch.float64, device=dist.device)  # Σ|d|², Σ|d|: summed on the device
    n = 0
    if loader is not None:
        model.eval()
        with torch.no_grad(), _autocast(cfg, dist.device):
            for batch in loader:
                batch = _move(batch, dist.device)
                d_unl, _ = model(batch, cycle=False)
                diff = d_unl.float() - batch.y
                acc += torch.stack([diff.pow(2).sum(), diff.norm(dim=1).sum()]).double()
                n += diff.shape[0]
    sq, ab, n = _all_reduce(acc.tolist() + [n], dist)
    if n == 0:
        return math.nan, math.nan, 0
    return sq / (3 * n), ab / n * disp_scale_mm, int(n)


def best_val_md(history: list, best_epoch) -> float | None:
    """The validation MD (mm) of the kept epoch; None when the run had no validation cases."""
    md = next((r.get("val_md_mm") for r in history if r.get("epoch") == best_epoch), None)
    return float(md) if md is not None and math.isfinite(md) else None


def write_metrics_csv(path: Path, history: list) -> None:
    """A run's per-epoch metrics (history rows) as metrics.csv, METRIC_COLUMNS in order."""
    write_csv(path, history, METRIC_COLUMNS)


def _tensorboard(run_dir: Path):
    for mod in ("torch.utils.tensorboard", "tensorboardX"):
        try:
            writer_cls = __import__(mod, fromlist=["SummaryWriter"]).SummaryWriter
            return writer_cls(str(run_dir / "tb"))
        except Exception:  # not installed (torch's needs the tensorboard package)
            continue
    return None


def discard_fresh_run(run_dir: Path, made_run_dir: bool) -> None:
    """Remove what a fresh run wrote before its first checkpoint (config.json, metrics.csv, the
    TensorBoard events), and the run directory when this run made it and that leaves it empty."""
    for name in ("config.json", "metrics.csv"):
        (run_dir / name).unlink(missing_ok=True)
    shutil.rmtree(run_dir / "tb", ignore_errors=True)
    if not made_run_dir:
        return
    try:
        run_dir.rmdir()
    except OSError:  # not empty: the user's files, or Ray's
        pass


def pick_resume_state(candidates: list) -> dict | None:
    """The most advanced of the available checkpoints (Ray's and the run directory's)."""
    states = [s for s in candidates if s is not None]
    return max(states, key=lambda s: int(s.get("epoch", 0))) if states else None


def check_same_run(state: dict, cfg: TrainConfig, run_dir: Path) -> None:
    """TrainerError unless the checkpoint `state` was written by a run `cfg` may resume."""
    saved = TrainConfig.from_dict(state["train_config"])
    old, new = saved.identity(), cfg.identity()
    if old != new:
        diff = [k for k in sorted(old.keys() | new.keys()) if old.get(k) != new.get(k)]
        shown = {**{k: (old.get(k), new.get(k)) for k in diff}, "split": (saved.split, cfg.split),
                 "model": (saved.config_name, cfg.config_name)}
        said = [f"{k} {shown[k][0]} (this command: {shown[k][1]})" if shown[k][0] != shown[k][1]
                else f"{k} settings other than {shown[k][1]}'s" for k in diff]
        raise TrainerError(f"run directory {run_dir} holds a run started with {', '.join(said)}; "
                           f"resume it with the options it started with, or use a new `run_dir`")


def check_resumable(state: dict, cfg: TrainConfig, bundle: DataBundle, run_dir: Path) -> None:
    check_same_run(state, cfg, run_dir)
    if cfg.model.kind != "pca":
        check_resume_parts(state, run_checkpoint_path(run_dir), cfg.model.ema_decay > 0)
    check_fingerprint(state["fingerprint"], bundle.fingerprint, cfg.store)
    if state.get("kind") != ("pca" if cfg.model.kind == "pca" else "gnn"):
        raise TrainerError(f"run directory {run_dir} holds a {state.get('kind')} run; use a new `run_dir`")
    split_now = {k: [list(x) for x in v] for k, v in bundle.split.items()}
    if state["split"] != split_now:
        raise TrainerError(f"the store changed since the run in {run_dir} started (its split differs); "
                           f"use a new `run_dir`")


def base_state(cfg: TrainConfig, bundle: DataBundle, kind: str) -> dict:
    return {"kind": kind, "train_config": cfg.as_dict(), "normalisation": bundle.norm.as_dict(),
            "fingerprint": bundle.fingerprint, "split": {k: [list(x) for x in v] for k, v in bundle.split.items()},
            "labelled": sorted([list(k) for k in bundle.labelled]), "train_descriptors": bundle.train_descriptors}


def fit(cfg: TrainConfig, run_dir: str | os.PathLike, dist: Dist | None = None,
        bundle: DataBundle | None = None) -> TrainingSummary:
    """Train (or resume) the configured model into run_dir; returns a summary dict.

    run_dir gets checkpoint.pt (model, best model, optimiser, scheduler, epoch, normalisation,
    config, split, history; the weight average when ema_decay > 0, whose weights are then the ones
    validated and kept as the best model), metrics.csv, config.json and TensorBoard events when available."""
    dist = dist or Dist()
    run_dir = Path(run_dir)
    tune_allocator()
    if cfg.num_threads:
        torch.set_num_threads(cfg.num_threads)
    seed_everything(cfg.seed)
    t0 = time.perf_counter()
    bundle = bundle or training_data(cfg)
    local = run_checkpoint_path(run_dir)
    if dist.restore is not None:
        state = dist.restore()
    else:
        state = load_checkpoint(local) if local.is_file() else None
    if state is not None:
        check_resumable(state, cfg, bundle, run_dir)
    writes = dist.is_main and dist.write_local
    made_run_dir = writes and not run_dir.exists()
    if writes:
        _open_run_dir(cfg, run_dir, dist)
    if cfg.model.kind == "pca":
        return _fit_pca(cfg, run_dir, bundle, dist, t0)
    run = _Training.make(cfg, bundle, dist, state, run_dir)
    run.writer = _tensorboard(run_dir) if writes else None
    if writes:
        write_metrics_csv(run_dir / "metrics.csv", run.standing.history)
    if dist.is_main:
        _log_start(cfg, bundle, dist, run.n_params, run.sampler)
    for epoch in range(run.standing.start_epoch, cfg.epochs):
        if run.standing.stopped:
            break
        t_ep = time.perf_counter()
        sums = run.train_epoch(epoch)
        row, n_val = run.judge_epoch(epoch, sums, t_ep, made_run_dir)
        run.record_epoch(epoch, row, n_val, local if writes else None)
        if run.standing.stopped:
            break
    if run.writer is not None:
        run.writer.close()
    s = run.standing
    done = len(s.history)
    return TrainingSummary(config=cfg.config_name, run_dir=str(run_dir), epochs_run=done - s.start_epoch, epoch=done,
                           resumed_from=s.start_epoch, best_epoch=s.best_epoch, best_val_loss=s.best_val,
                           best_val_md_mm=best_val_md(s.history, s.best_epoch), stopped_early=bool(s.stopped),
                           n_parameters=run.n_params, train_cases=len(bundle.train),
                           labelled_cases=len(bundle.labelled), wall_s=time.perf_counter() - t0)


def _open_run_dir(cfg: TrainConfig, run_dir: Path, dist: Dist) -> None:
    """The run directory made (or kept), temporaries a cut-short save left removed, config.json written."""
    run_dir.mkdir(parents=True, exist_ok=True)
    stale = remove_stale_temporaries(run_dir)
    if stale:
        dist.log(f"removed {len(stale)} temporary checkpoint file(s) a save cut short left in {run_dir}")
    write_json(run_dir / "config.json", cfg.as_dict())


def _log_start(cfg: TrainConfig, bundle: DataBundle, dist: Dist, n_params: int, sampler) -> None:
    """One line on what is trained on what, and the mixed batches' make-up when SR < 1."""
    kept = f" of {cfg.train_fraction:g} of the training shapes" if cfg.train_fraction < 1 else ""
    dist.log(f"{cfg.config_name}: {n_params:,} parameters; {len(bundle.train)} training cases{kept} "
             f"({len(bundle.labelled)} labelled, SR {cfg.sr:g}"
             + (f", label seed {cfg.labels_seed}" if cfg.label_seed is not None else "")
             + f"), {len(bundle.val)} validation, "
             f"{len(bundle.test)} test; {dist.world} process(es) on {dist.device.type}"
             + (f"; training graphs turned about the long axis by up to ±{cfg.rotate_deg:g}°"
                if cfg.rotate_deg else "")
             + (f"; training graphs scaled about their base by up to ±{cfg.scale_pct:g} %"
                if cfg.scale_pct else ""))
    if isinstance(sampler, MixedBatchSampler):
        dist.log(f"batches of {sampler.n_labelled} labelled + {sampler.n_unlabelled} unlabelled cases "
                 f"({len(sampler)} per epoch and process)")


def _load_error(exc: BaseException) -> str:
    return str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__


@dataclass
class _Standing:
    """Where a training run stands between epochs: the epoch it started (or resumed) at, the best
    validation loss so far and its epoch and weights, the epochs since it improved, the history,
    whether it stopped early, and the last epoch a checkpoint holds."""

    start_epoch: int = 0
    best_val: float = math.inf
    best_epoch: int = -1
    bad_epochs: int = 0
    history: list = field(default_factory=list)
    best_model: dict | None = None
    stopped: bool = False
    saved_epoch: int | None = None

    @classmethod
    def resumed(cls, state: dict, patience: int) -> "_Standing":
        bad_epochs = int(state["bad_epochs"])
        return cls(int(state["epoch"]), float(state["best_val"]), int(state["best_epoch"]), bad_epochs,
                   list(state["history"]), state.get("best_model"),
                   stopped=bad_epochs >= patience,  # a rerun with a longer patience trains on
                   saved_epoch=int(state["epoch"]))


@dataclass
class _Training:
    """One network's training: the model, its optimiser and plateau schedule, the weight average (whose
    weights validation sees when there is one), the distributed model that steps, the loaders, and
    where the run stands."""

    cfg: TrainConfig
    bundle: DataBundle
    dist: Dist
    run_dir: Path
    model: torch.nn.Module
    opt: torch.optim.Optimizer
    sched: object
    standing: _Standing
    average: WeightAverage | None = None
    wrapped: object = None
    train_loader: object = None
    sampler: object = None
    val_loader: object = None
    writer: object = None

    @property
    def n_params(self) -> int:
        return count_parameters(self.model)

    @property
    def evaluated(self) -> torch.nn.Module:
        """What validation sees and best_model keeps: the weight average when there is one."""
        return self.average.model if self.average is not None else self.model

    @classmethod
    def make(cls, cfg: TrainConfig, bundle: DataBundle, dist: Dist, state: dict | None, run_dir: Path) -> "_Training":
        model = build_model(cfg.model, bundle.norm.disp_to_coord, bundle.norm.load_coef, bundle.norm.load_box)
        opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, mode="min", factor=cfg.lr_factor,
                                                           patience=cfg.lr_patience)
        run = cls(cfg, bundle, dist, run_dir, model, opt, sched, _Standing())
        if state is not None:
            run.resume(state)
        elif bundle.parent is not None:  # fine-tuning: the parent's weights, a fresh optimiser and schedule
            try:
                model.load_state_dict(bundle.parent.weights)
            except (RuntimeError, KeyError, ValueError, TypeError) as exc:
                raise TrainerError(f"init_from={bundle.parent.path}: its weights do not load into this network "
                                   f"({_load_error(exc)})") from None
            if dist.is_main:
                dist.log(f"starting from {bundle.parent.describe()}: its weights and normalisation, a fresh optimiser "
                         f"and learning-rate schedule")
        model.to(dist.device)
        run.average = WeightAverage(model, cfg.model.ema_decay) if cfg.model.ema_decay > 0 else None
        if run.average is not None and state is not None:
            try:
                run.average.load_state_dict(state["weight_average"])
            except (RuntimeError, KeyError, ValueError, TypeError) as exc:
                raise TrainerError(f"checkpoint in {run_dir} is damaged: its weight average does not load "
                                   f"({_load_error(exc)})") from None
        if dist.device.type == "cuda":
            torch.set_float32_matmul_precision("high")  # TF32 tensor cores for the fp32 dense layers
        for s in opt.state.values():  # optimiser moments follow the model
            for k, v in s.items():
                if isinstance(v, torch.Tensor) and k != "step":
                    s[k] = v.to(dist.device)
        run.wrapped = dist.wrap_model(model)
        if cfg.compile and cfg.model.kind == "gnn":  # validation and checkpoints use the plain model
            run.wrapped = torch.compile(run.wrapped, dynamic=True)
        run.train_loader, run.sampler, run.val_loader = _loaders(bundle, cfg, dist)
        return run

    def resume(self, state: dict) -> None:
        """Weights, optimiser, schedule and standing from a checkpoint; a changed plateau learning rate
        restarts the rate there."""
        cfg, dist = self.cfg, self.dist
        try:
            self.model.load_state_dict(state["model"])
            self.opt.load_state_dict(state["optimizer"])
            self.sched.load_state_dict(state["scheduler"])
        except (RuntimeError, KeyError, ValueError, TypeError) as exc:
            raise TrainerError(f"checkpoint in {self.run_dir} is damaged: cannot resume from it "
                               f"({_load_error(exc)})") from None
        self.standing = s = _Standing.resumed(state, cfg.patience)
        if dist.is_main:
            dist.log(f"resuming {self.run_dir} from epoch {s.start_epoch} (best validation {s.best_val:.4g} at "
                     f"epoch {s.best_epoch})")
        saved_lr = float(state["train_config"].get("lr", cfg.lr))
        if cfg.lr_schedule == "plateau" and saved_lr != cfg.lr:  # cosine sets each epoch's rate itself
            for group in self.opt.param_groups:
                group["lr"] = cfg.lr
            if dist.is_main:
                dist.log(f"learning rate {cfg.lr:g} (the run started at {saved_lr:g}): the rate restarts at {cfg.lr:g}")

    def train_epoch(self, epoch: int) -> list:
        """One epoch of steps; returns the loss, supervised and cycle terms summed over the epoch's graphs
        and the graph count, reduced over the processes."""
        cfg, dist, average = self.cfg, self.dist, self.average
        uses_teacher = average is not None and cfg.model.cycle and cfg.model.cycle_grad == "teacher"
        if cfg.lr_schedule == "cosine":
            for group in self.opt.param_groups:
                group["lr"] = cosine_lr(epoch, cfg.epochs, cfg.lr)
        self.sampler.set_epoch(epoch)
        self.wrapped.train()
        acc = torch.zeros(3, dtype=torch.float64, device=dist.device)  # loss·graphs, sup·graphs, cycle·graphs
        n_graphs = 0  # summed on the device: no step waits for the GPU to report its loss
        seed_epoch(cfg.seed, epoch, dist.rank)
        aug_gen = torch.Generator().manual_seed((cfg.seed * 100003 + epoch) * 1009 + dist.rank)
        for batch in self.train_loader:
            batch = rotate_batch(_move(batch, dist.device), cfg.rotate_deg, aug_gen)
            batch = scale_batch(batch, cfg.scale_pct, aug_gen)
            self.opt.zero_grad(set_to_none=True)
            with _autocast(cfg, dist.device):
                d_unl, d_ed, d_rev = self.wrapped(batch, reverse=True,
                                                  teacher=average.teacher() if uses_teacher else None)
            terms = loss_terms(d_unl, d_ed, batch, cfg.model.cycle_weight(epoch), d_rev, cfg.model.reverse_weight)
            terms["loss"].backward()
            self.opt.step()
            if average is not None:
                average.update(self.model)
            g = batch.num_graphs
            acc += torch.stack([terms[k].detach().double() for k in ("loss", "sup", "cycle")]) * g
            n_graphs += g
        return _all_reduce(acc.tolist() + [n_graphs], dist)

    def judge_epoch(self, epoch: int, sums: list, t_ep: float, made_run_dir: bool) -> tuple[dict, int]:
        """Validate, stop on a non-finite loss (TrainingDiverged), step the plateau schedule, keep the
        best weights, decide early stopping; returns the epoch's metrics row and its validation cases."""
        cfg, s = self.cfg, self.standing
        train_loss = sums[0] / max(sums[3], 1)
        val_loss, val_md, n_val = _validate(self.evaluated, self.val_loader, cfg, self.dist,
                                            self.bundle.norm.disp_scale_mm)
        if not math.isfinite(train_loss) or (n_val and not math.isfinite(val_loss)):
            self._diverged(epoch, train_loss, val_loss, made_run_dir)
        monitor = val_loss if n_val else train_loss  # no validation cases: the training loss decides
        if cfg.lr_schedule == "plateau":
            self.sched.step(monitor)
        if monitor < s.best_val:
            s.best_val, s.best_epoch, s.bad_epochs = monitor, epoch + 1, 0
            s.best_model = cpu_state(self.evaluated)
        else:
            s.bad_epochs += 1
        s.stopped = s.bad_epochs >= cfg.patience
        ep_s = time.perf_counter() - t_ep
        return {"epoch": epoch + 1, "train_loss": train_loss, "train_sup": sums[1] / max(sums[3], 1),
                "train_cycle": sums[2] / max(sums[3], 1), "val_loss": val_loss,
                "val_md_mm": val_md, "lr": self.opt.param_groups[0]["lr"], "epoch_s": ep_s,
                "graphs_per_s": sums[3] / ep_s}, n_val

    def _diverged(self, epoch: int, train_loss: float, val_loss: float, made_run_dir: bool) -> None:
        """All ranks see the same reduced sums, so all stop here; nothing of this epoch is kept."""
        saved_epoch, run_dir = self.standing.saved_epoch, self.run_dir
        if saved_epoch is None and self.dist.is_main and self.dist.write_local:  # a fresh run leaves nothing
            if self.writer is not None:
                self.writer.close()
            discard_fresh_run(run_dir, made_run_dir)
        kept = (f"{run_dir} keeps its checkpoint from epoch {saved_epoch}" if saved_epoch is not None
                else "nothing of this run was kept")
        raise TrainingDiverged(f"training diverged in epoch {epoch + 1} (training loss {train_loss:.4g}, "
                               f"validation loss {val_loss:.4g}); {kept}; lower the learning rate (`lr`, now "
                               f"{self.opt.param_groups[0]['lr']:g})"
                               + (" or start a new run directory" if saved_epoch is not None else ""))

    def record_epoch(self, epoch: int, row: dict, n_val: int, local: Path | None) -> None:
        """The epoch's row in the history, metrics.csv and TensorBoard, its log line, a checkpoint when
        one is due (written to `local` when this process writes), and the report to Ray Train."""
        cfg, dist, s = self.cfg, self.dist, self.standing
        s.history.append(row)
        last = epoch + 1 == cfg.epochs or s.stopped
        save = last or (epoch + 1) % max(cfg.checkpoint_every, 1) == 0
        ckpt = None
        if local is not None:
            write_metrics_csv(self.run_dir / "metrics.csv", s.history)
        if dist.is_main:
            if self.writer is not None:
                for k, v in row.items():
                    if k != "epoch" and v is not None and math.isfinite(v):
                        self.writer.add_scalar(k, v, epoch + 1)
                self.writer.flush()
            dist.log(f"epoch {epoch + 1}/{cfg.epochs}: loss {row['train_loss']:.4g} (sup {row['train_sup']:.4g}, "
                     f"cycle {row['train_cycle']:.4g}), "
                     + (f"val {row['val_loss']:.4g} / MD {row['val_md_mm']:.3f} mm, " if n_val
                        else "no validation cases, ")
                     + f"lr {row['lr']:.2g}, {row['epoch_s']:.1f} s ({row['graphs_per_s']:.0f} graphs/s)"
                     + (", torch.compile compiling" if cfg.compile and epoch == s.start_epoch else "")
                     + (" — early stop" if s.stopped else ""))
            if save:
                ckpt = self._checkpoint(epoch, last)
                if local is not None:
                    save_checkpoint(local, ckpt)
                s.saved_epoch = epoch + 1
        if dist.report is not None:
            dist.report({k: (v if v is None or math.isfinite(v) else None) for k, v in row.items()},
                        ckpt if dist.is_main else None)

    def _checkpoint(self, epoch: int, last: bool) -> dict:
        s = self.standing
        ckpt = {**base_state(self.cfg, self.bundle, "gnn"), "model": cpu_state(self.model),
                "best_model": s.best_model, "optimizer": self.opt.state_dict(), "scheduler": self.sched.state_dict(),
                "epoch": epoch + 1, "best_val": s.best_val, "best_epoch": s.best_epoch, "bad_epochs": s.bad_epochs,
                "history": s.history, "stopped_early": s.stopped, "finished": last, "n_parameters": self.n_params}
        if self.average is not None:
            ckpt["weight_average"] = self.average.state_dict()
        return ckpt


def _fit_pca(cfg: TrainConfig, run_dir: Path, bundle: DataBundle, dist: Dist, t0: float) -> TrainingSummary:
    from trainer.network.pca import PCABaseline

    c = bundle.cases
    keys = sorted(bundle.labelled)
    validation = {k: c.displacement(k) for k in bundle.split["val"]}  # done cases, all labelled
    pca = PCABaseline.fit(c.features, keys, c.params, {k: c.displacement(k) for k in keys}, bundle.norm,
                          cfg.model.pca_components, cfg.model.pca_ridge, validation=validation)
    if dist.is_main and dist.write_local:
        state = {**base_state(cfg, bundle, "pca"), "model": pca.state_dict(), "best_model": pca.state_dict(),
                 "epoch": 1, "history": [], "finished": True, "n_parameters": int(sum(v.numel() for v in pca.state_dict().values()))}
        save_checkpoint(run_checkpoint_path(run_dir), state)
        write_metrics_csv(run_dir / "metrics.csv", [])
        dist.log(f"pca: fitted on {len(keys)} labelled training cases "
                 f"({pca.s['disp_comps'].shape[0]} displacement components, ridge "
                 f"{float(np.ravel(pca.s['ridge'])[0]):g}{' chosen on the validation cases' if validation else ''})")
    val_md = pca.mean_distance_mm(c.features, c.params, validation, bundle.norm) if validation else None
    return TrainingSummary(config=cfg.config_name, run_dir=str(run_dir), epochs_run=1, epoch=1, resumed_from=0,
                           best_epoch=1, best_val_loss=None, best_val_md_mm=val_md, stopped_early=False,
                           n_parameters=int(sum(v.numel() for v in pca.state_dict().values())),
                           train_cases=len(bundle.train), labelled_cases=len(bundle.labelled),
                           wall_s=time.perf_counter() - t0)
