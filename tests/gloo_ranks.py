"""Functions that spawned processes run as the ranks of a gloo process group, and spawn_ranks, which
starts them (a light module: each spawned process imports it, and not the test module that started
it)."""
from __future__ import annotations


def refusal_rank(rank: int, world: int, rendezvous: str, out) -> None:
    """Rank 1 alone cannot read the store: puts (rank, what agreed_refusal gives with that refusal,
    what it gives with none) on `out`."""
    from datetime import timedelta

    import torch
    import torch.distributed as tdist

    from trainer.training.ray_train import agreed_refusal

    tdist.init_process_group("gloo", init_method=f"file://{rendezvous}", rank=rank, world_size=world,
                             timeout=timedelta(seconds=60))
    try:
        own = "cannot read store s.zarr (rank 1)" if rank == 1 else None
        out.put((rank, agreed_refusal(own, world, torch.device("cpu")), agreed_refusal(None, world, torch.device("cpu"))))
    finally:
        tdist.destroy_process_group()


def fit_rank(rank: int, world: int, rendezvous: str, train_config: dict, run_dir: str, out) -> None:
    """One rank of a plain DDP run (no Ray) of trainer.training.loop.fit: puts (rank, its summary) on `out`."""
    from datetime import timedelta

    import torch.distributed as tdist
    from torch.nn.parallel import DistributedDataParallel

    from trainer.config import TrainConfig
    from trainer.training.loop import Dist, fit

    tdist.init_process_group("gloo", init_method=f"file://{rendezvous}", rank=rank, world_size=world,
                             timeout=timedelta(seconds=120))
    try:
        out.put((rank, fit(TrainConfig.from_dict(train_config), run_dir,
                           Dist(rank=rank, world=world, wrap_model=DistributedDataParallel))))
    finally:
        tdist.destroy_process_group()


def spawn_ranks(target, world: int, rendezvous: str, *args) -> list:
    """Runs target(rank, world, rendezvous, *args, queue) in `world` spawned processes; what each put
    on the queue, sorted (by rank first)."""
    import torch.multiprocessing as mp

    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    procs = [ctx.Process(target=target, args=(r, world, rendezvous, *args, out), daemon=True) for r in range(world)]
    try:
        for p in procs:
            p.start()
        return sorted((out.get(timeout=300) for _ in procs), key=lambda got: got[0])
    finally:
        for p in procs:
            p.join(30)
            if p.is_alive():
                p.terminate()
