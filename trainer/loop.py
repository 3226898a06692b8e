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

from ._malloc import tune_allocator
from .augment import rotate_batch, scale_batch
from .averaging import WeightAverage
from .batching import GraphTable, chunks, table_device
from .checkpoint import (check_resume_parts, cpu_state, load_checkpoint, remove_stale_temporaries, run_checkpoint_path,
                         save_checkpoint)
from .config import TrainConfig, TrainerError, TrainingDiverged
from .data import DataBundle, check_fingerprint, training_data
from .files import write_csv, write_json
from .model import build_model, count_parameters, loss_terms
from .sampling import MixedBatchSampler, labelled_per_batch
from .schedule import cosine_lr

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
    """Training loader (mixed labelled/unlabelled batches when SR < 1, see trainer.sampling),
    its sampler (set_epoch) and the validation loader; both build their batches from a GraphTable
    (trainer.batching), in the order PyG's DataLoader would with the same sampler."""
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
                           f"resume it with the options it started with, or use a new --run-dir")


def check_resumable(state: dict, cfg: TrainConfig, bundle: DataBundle, run_dir: Path) -> None:
    check_same_run(state, cfg, run_dir)
    if cfg.model.kind != "pca":
        check_resume_parts(state, run_checkpoint_path(run_dir), cfg.model.ema_decay > 0)
    check_fingerprint(state["fingerprint"], bundle.fingerprint, cfg.store)
    if state.get("kind") != ("pca" if cfg.model.kind == "pca" else "gnn"):
        raise TrainerError(f"run directory {run_dir} holds a {state.get('kind')} run; use a new --run-dir")
    split_now = {k: [list(x) for x in v] for k, v in bundle.split.items()}
    if state["split"] != split_now:
        raise TrainerError(f"the store changed since the run in {run_dir} started (its split differs); "
                           f"use a new --run-dir")


def base_state(cfg: TrainConfig, bundle: DataBundle, kind: str) -> dict:
    return {"kind": kind, "train_config": cfg.as_dict(), "normalisation": bundle.norm.as_dict(),
            "fingerprint": bundle.fingerprint, "split": {k: [list(x) for x in v] for k, v in bundle.split.items()},
            "labelled": sorted([list(k) for k in bundle.labelled]), "train_descriptors": bundle.train_descriptors}


def fit(cfg: TrainConfig, run_dir: str | os.PathLike, dist: Dist | None = None,
        bundle: DataBundle | None = None) -> dict:
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
        run_dir.mkdir(parents=True, exist_ok=True)
        stale = remove_stale_temporaries(run_dir)
        if stale:
            dist.log(f"removed {len(stale)} temporary checkpoint file(s) a save cut short left in {run_dir}")
        write_json(run_dir / "config.json", cfg.as_dict())
    if cfg.model.kind == "pca":
        return _fit_pca(cfg, run_dir, bundle, dist, t0)

    model = build_model(cfg.model, bundle.norm.disp_to_coord, bundle.norm.load_coef, bundle.norm.load_box)
    n_params = count_parameters(model)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, mode="min", factor=cfg.lr_factor, patience=cfg.lr_patience)
    start_epoch, best_val, best_epoch, bad_epochs, history = 0, math.inf, -1, 0, []
    best_model = None
    stopped = False
    if state is not None:
        try:
            model.load_state_dict(state["model"])
            opt.load_state_dict(state["optimizer"])
            sched.load_state_dict(state["scheduler"])
        except (RuntimeError, KeyError, ValueError, TypeError) as exc:
            raise TrainerError(f"checkpoint in {run_dir} is damaged: cannot resume from it "
                               f"({str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__})") from None
        start_epoch = int(state["epoch"])
        best_val, best_epoch = float(state["best_val"]), int(state["best_epoch"])
        bad_epochs, history = int(state["bad_epochs"]), list(state["history"])
        best_model = state.get("best_model")
        stopped = bad_epochs >= cfg.patience  # a rerun with a longer --patience trains on
        if dist.is_main:
            dist.log(f"resuming {run_dir} from epoch {start_epoch} (best validation {best_val:.4g} at epoch {best_epoch})")
        saved_lr = float(state["train_config"].get("lr", cfg.lr))
        if cfg.lr_schedule == "plateau" and saved_lr != cfg.lr:  # cosine sets each epoch's rate itself
            for group in opt.param_groups:
                group["lr"] = cfg.lr
            if dist.is_main:
                dist.log(f"--lr {cfg.lr:g} (the run started at {saved_lr:g}): the rate restarts at {cfg.lr:g}")
    elif bundle.parent is not None:  # fine-tuning: the parent's weights, a fresh optimiser and schedule
        try:
            model.load_state_dict(bundle.parent.weights)
        except (RuntimeError, KeyError, ValueError, TypeError) as exc:
            raise TrainerError(f"--init-from {bundle.parent.path}: its weights do not load into this network "
                               f"({str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__})") from None
        if dist.is_main:
            dist.log(f"starting from {bundle.parent.describe()}: its weights and normalisation, a fresh optimiser "
                     f"and learning-rate schedule")
    model.to(dist.device)
    average = WeightAverage(model, cfg.model.ema_decay) if cfg.model.ema_decay > 0 else None
    if average is not None and state is not None:
        try:
            average.load_state_dict(state["weight_average"])
        except (RuntimeError, KeyError, ValueError, TypeError) as exc:
            raise TrainerError(f"checkpoint in {run_dir} is damaged: its weight average does not load "
                               f"({str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__})") from None
    evaluated = average.model if average is not None else model  # what validation sees and best_model keeps
    uses_teacher = average is not None and cfg.model.cycle and cfg.model.cycle_grad == "teacher"
    if dist.device.type == "cuda":
        torch.set_float32_matmul_precision("high")  # TF32 tensor cores for the fp32 dense layers
    for s in opt.state.values():  # optimiser moments follow the model
        for k, v in s.items():
            if isinstance(v, torch.Tensor) and k != "step":
                s[k] = v.to(dist.device)
    wrapped = dist.wrap_model(model)
    if cfg.compile and cfg.model.kind == "gnn":  # validation and checkpoints use the plain model
        wrapped = torch.compile(wrapped, dynamic=True)
    train_loader, sampler, val_loader = _loaders(bundle, cfg, dist)
    writer = _tensorboard(run_dir) if writes else None
    if writes:
        write_metrics_csv(run_dir / "metrics.csv", history)
    if dist.is_main:
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
    epoch = start_epoch
    saved_epoch = start_epoch if state is not None else None  # the last epoch a checkpoint holds
    for epoch in range(start_epoch, cfg.epochs):
        if stopped:
            break
        t_ep = time.perf_counter()
        if cfg.lr_schedule == "cosine":
            for group in opt.param_groups:
                group["lr"] = cosine_lr(epoch, cfg.epochs, cfg.lr)
        sampler.set_epoch(epoch)
        wrapped.train()
        acc = torch.zeros(3, dtype=torch.float64, device=dist.device)  # loss·graphs, sup·graphs, cycle·graphs
        n_graphs = 0  # summed on the device: no step waits for the GPU to report its loss
        seed_epoch(cfg.seed, epoch, dist.rank)
        aug_gen = torch.Generator().manual_seed((cfg.seed * 100003 + epoch) * 1009 + dist.rank)
        for batch in train_loader:
            batch = rotate_batch(_move(batch, dist.device), cfg.rotate_deg, aug_gen)
            batch = scale_batch(batch, cfg.scale_pct, aug_gen)
            opt.zero_grad(set_to_none=True)
            with _autocast(cfg, dist.device):
                d_unl, d_ed, d_rev = wrapped(batch, reverse=True, teacher=average.teacher() if uses_teacher else None)
            terms = loss_terms(d_unl, d_ed, batch, cfg.model.cycle_weight(epoch), d_rev, cfg.model.reverse_weight)
            terms["loss"].backward()
            opt.step()
            if average is not None:
                average.update(model)
            g = batch.num_graphs
            acc += torch.stack([terms[k].detach().double() for k in ("loss", "sup", "cycle")]) * g
            n_graphs += g
        sums = _all_reduce(acc.tolist() + [n_graphs], dist)
        train_loss = sums[0] / max(sums[3], 1)
        val_loss, val_md, n_val = _validate(evaluated, val_loader, cfg, dist, bundle.norm.disp_scale_mm)
        if not math.isfinite(train_loss) or (n_val and not math.isfinite(val_loss)):
            # all ranks see the same reduced sums, so all stop here; nothing of this epoch is kept
            if saved_epoch is None and writes:  # a fresh run with nothing worth keeping leaves nothing behind
                if writer is not None:
                    writer.close()
                discard_fresh_run(run_dir, made_run_dir)
            kept = (f"{run_dir} keeps its checkpoint from epoch {saved_epoch}" if saved_epoch is not None
                    else "nothing of this run was kept")
            raise TrainingDiverged(f"training diverged in epoch {epoch + 1} (training loss {train_loss:.4g}, "
                                   f"validation loss {val_loss:.4g}); {kept}; lower the learning rate (--lr, now "
                                   f"{opt.param_groups[0]['lr']:g})"
                                   + (" or start a new run directory" if saved_epoch is not None else ""))
        monitor = val_loss if n_val else train_loss  # no validation cases: the training loss decides
        if cfg.lr_schedule == "plateau":
            sched.step(monitor)
        if monitor < best_val:
            best_val, best_epoch, bad_epochs = monitor, epoch + 1, 0
            best_model = cpu_state(evaluated)
        else:
            bad_epochs += 1
        stopped = bad_epochs >= cfg.patience
        ep_s = time.perf_counter() - t_ep
        row = {"epoch": epoch + 1, "train_loss": train_loss, "train_sup": sums[1] / max(sums[3], 1),
               "train_cycle": sums[2] / max(sums[3], 1), "val_loss": val_loss, "val_md_mm": val_md,
               "lr": opt.param_groups[0]["lr"], "epoch_s": ep_s, "graphs_per_s": sums[3] / ep_s}
        history.append(row)
        last = epoch + 1 == cfg.epochs or stopped
        save = last or (epoch + 1) % max(cfg.checkpoint_every, 1) == 0
        ckpt = None
        if writes:
            write_metrics_csv(run_dir / "metrics.csv", history)
        if dist.is_main:
            if writer is not None:
                for k, v in row.items():
                    if k != "epoch" and v is not None and math.isfinite(v):
                        writer.add_scalar(k, v, epoch + 1)
                writer.flush()
            dist.log(f"epoch {epoch + 1}/{cfg.epochs}: loss {train_loss:.4g} (sup {row['train_sup']:.4g}, "
                     f"cycle {row['train_cycle']:.4g}), "
                     + (f"val {val_loss:.4g} / MD {val_md:.3f} mm, " if n_val else "no validation cases, ")
                     + f"lr {row['lr']:.2g}, {ep_s:.1f} s ({row['graphs_per_s']:.0f} graphs/s)"
                     + (", torch.compile compiling" if cfg.compile and epoch == start_epoch else "")
                     + (" — early stop" if stopped else ""))
            if save:
                ckpt = {**base_state(cfg, bundle, "gnn"), "model": cpu_state(model), "best_model": best_model,
                        "optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "epoch": epoch + 1,
                        "best_val": best_val, "best_epoch": best_epoch, "bad_epochs": bad_epochs,
                        "history": history, "stopped_early": stopped, "finished": last,
                        "n_parameters": n_params}
                if average is not None:
                    ckpt["weight_average"] = average.state_dict()
                if writes:
                    save_checkpoint(local, ckpt)
                saved_epoch = epoch + 1
        if dist.report is not None:
            dist.report({k: (v if v is None or math.isfinite(v) else None) for k, v in row.items()},
                        ckpt if dist.is_main else None)
        if stopped:
            break
    if writer is not None:
        writer.close()
    done = len(history)
    return {"config": cfg.config_name, "run_dir": str(run_dir), "epochs_run": done - start_epoch, "epoch": done,
            "resumed_from": start_epoch, "best_epoch": best_epoch, "best_val_loss": best_val,
            "best_val_md_mm": best_val_md(history, best_epoch),
            "stopped_early": stopped, "n_parameters": n_params, "train_cases": len(bundle.train),
            "labelled_cases": len(bundle.labelled), "wall_s": time.perf_counter() - t0}


def _fit_pca(cfg: TrainConfig, run_dir: Path, bundle: DataBundle, dist: Dist, t0: float) -> dict:
    from .pca import PCABaseline

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
    return {"config": cfg.config_name, "run_dir": str(run_dir), "epochs_run": 1, "epoch": 1, "resumed_from": 0,
            "best_epoch": 1, "best_val_loss": None, "best_val_md_mm": val_md, "stopped_early": False,
            "n_parameters": int(sum(v.numel() for v in pca.state_dict().values())),
            "train_cases": len(bundle.train), "labelled_cases": len(bundle.labelled),
            "wall_s": time.perf_counter() - t0}
