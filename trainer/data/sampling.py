"""Batches for semi-supervised training (SR < 1): every batch mixes labelled and unlabelled cases.

With plain shuffling at SR = 3 % most batches hold no labelled case, so most optimiser steps have
no supervised term, and AdamW's first moment carries each labelled gradient on through the
label-free steps that follow (the effective step on a labelled case is ~1/(1 − β₁) = 10 times
larger and lands late). Here each batch holds `n_labelled` labelled cases, drawn in a fresh random
order and cycled, and batch_size − n_labelled unlabelled ones; an epoch is one pass over the
unlabelled cases. Under DDP the unlabelled cases are sharded by rank and every rank yields the same
number of batches."""
from __future__ import annotations

import math

import numpy as np


def labelled_per_batch(batch_size: int, sr: float, labelled_share: float) -> int:
    """How many of a batch's graphs are labelled: round(batch · max(SR, share)), at least 1 and
    at most batch − 1 (0 when the batch cannot mix: batch size 1 or SR = 1)."""
    if batch_size < 2 or sr >= 1.0:
        return 0
    return int(min(batch_size - 1, max(1, round(batch_size * max(sr, labelled_share)))))


def _permutation_stream(items: list, n: int, rng: np.random.Generator) -> list:
    """n items: consecutive random permutations of `items`, each used up before the next."""
    out = []
    while len(out) < n:
        out.extend(items[i] for i in rng.permutation(len(items)))
    return out[:n]


class MixedBatchSampler:
    """Yields lists of dataset indices: n_labelled labelled + (batch_size − n_labelled) unlabelled."""

    def __init__(self, labelled: list, unlabelled: list, batch_size: int, n_labelled: int, seed: int = 0,
                 rank: int = 0, world: int = 1):
        if not labelled or not unlabelled or not 0 < n_labelled < batch_size:
            raise ValueError("a mixed batch needs labelled and unlabelled cases and 0 < n_labelled < batch_size")
        self.labelled, self.unlabelled = list(labelled), list(unlabelled)
        self.n_labelled, self.n_unlabelled = n_labelled, batch_size - n_labelled
        self.seed, self.rank, self.world = seed, rank, world
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return math.ceil(math.ceil(len(self.unlabelled) / self.world) / self.n_unlabelled)

    def __iter__(self):
        n_batches = len(self)
        order = np.random.default_rng([self.seed, self.epoch, 7]).permutation(len(self.unlabelled))  # same on all ranks
        shard = [self.unlabelled[i] for i in order[self.rank::self.world]] or list(self.unlabelled)
        rng = np.random.default_rng([self.seed, self.epoch, 11, self.rank])
        unl = (shard * math.ceil(n_batches * self.n_unlabelled / len(shard)))[: n_batches * self.n_unlabelled]
        lab = _permutation_stream(self.labelled, n_batches * self.n_labelled, rng)
        for b in range(n_batches):
            yield (lab[b * self.n_labelled:(b + 1) * self.n_labelled]
                   + unl[b * self.n_unlabelled:(b + 1) * self.n_unlabelled])


__all__ = ["MixedBatchSampler", "labelled_per_batch"]
