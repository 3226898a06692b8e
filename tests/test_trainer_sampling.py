"""Mixed labelled/unlabelled batches for SR < 1: every batch has its labelled share, an epoch is
one pass over the unlabelled cases, ranks get disjoint shards and equal batch counts."""
from __future__ import annotations

import pytest

from trainer.config import ModelConfig, TrainConfig, named_config
from trainer.errors import TrainerError
from trainer.data.sampling import MixedBatchSampler, labelled_per_batch


def test_labelled_per_batch():
    assert labelled_per_batch(8, 0.03, 0.25) == 2
    assert labelled_per_batch(8, 0.03, 0.0) == 1  # at least one
    assert labelled_per_batch(8, 0.9, 0.25) == 7  # at most batch − 1
    assert labelled_per_batch(8, 1.0, 0.25) == 0 and labelled_per_batch(1, 0.03, 0.25) == 0
    with pytest.raises(TrainerError):
        TrainConfig(store="s", labelled_share=1.0)


def test_every_batch_mixes_and_an_epoch_covers_the_unlabelled():
    lab, unl = list(range(3)), list(range(3, 40))
    s = MixedBatchSampler(lab, unl, batch_size=8, n_labelled=2, seed=0)
    batches = list(s)
    assert len(batches) == len(s) == 7  # ceil(37 / 6)
    assert all(len(b) == 8 and sum(i in lab for i in b) == 2 for b in batches)
    seen = [i for b in batches for i in b[2:]]
    assert set(seen) == set(unl)  # every unlabelled case once (the last batch is topped up)
    assert len(set(seen[:37])) == 37
    again = list(s)
    assert again == batches  # deterministic per epoch
    s.set_epoch(1)
    assert list(s) != batches


def test_ranks_get_disjoint_shards_and_equal_batch_counts():
    lab, unl = [0, 1], list(range(2, 25))
    per_rank = [list(MixedBatchSampler(lab, unl, 4, 1, seed=3, rank=r, world=2)) for r in (0, 1)]
    assert len(per_rank[0]) == len(per_rank[1])
    shards = [{i for b in batches for i in b[1:]} for batches in per_rank]
    assert not shards[0] & shards[1] and shards[0] | shards[1] == set(unl)


def test_cycle_weight_ramps_up():
    assert named_config("paper").cycle_weight(0) == 0.2
    r2 = named_config("R2")
    assert [round(r2.cycle_weight(e), 3) for e in (0, 4, 9, 30)] == [0.02, 0.1, 0.2, 0.2]
    with pytest.raises(TrainerError):
        ModelConfig(cycle_rampup_epochs=-1)
