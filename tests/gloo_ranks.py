"""Functions that spawned processes run as the ranks of a gloo process group (a light module: each
spawned process imports it, and not the test module that started it)."""
from __future__ import annotations


def refusal_rank(rank: int, world: int, rendezvous: str, out) -> None:
    """Rank 1 alone cannot read the store: puts (rank, what agreed_refusal gives with that refusal,
    what it gives with none) on `out`."""
    from datetime import timedelta

    import torch
    import torch.distributed as tdist

    from trainer.ray_train import agreed_refusal

    tdist.init_process_group("gloo", init_method=f"file://{rendezvous}", rank=rank, world_size=world,
                             timeout=timedelta(seconds=60))
    try:
        own = "cannot read store s.zarr (rank 1)" if rank == 1 else None
        out.put((rank, agreed_refusal(own, world, torch.device("cpu")), agreed_refusal(None, world, torch.device("cpu"))))
    finally:
        tdist.destroy_process_group()
