"""The weight average (ModelConfig.ema_decay): hand-computed updates with the warmed-up decay, a
state round trip, and a training run that validates, keeps and resumes the average."""
from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from torch import nn

from trainer.network.averaging import WeightAverage
from trainer.training.checkpoint import load_run
from trainer.config import TrainConfig, named_config
from trainer.training.loop import fit
from trainer_fixtures import make_tiny_store


def test_average_follows_the_warmed_up_decay():
    model = nn.Linear(2, 1)
    with torch.no_grad():
        model.weight.fill_(1.0)
        model.bias.fill_(0.0)
    avg = WeightAverage(model, 0.5)
    expected = 1.0
    for step, value in enumerate((3.0, -1.0, 5.0)):
        with torch.no_grad():
            model.weight.fill_(value)
        d = min(0.5, (1 + step) / (10 + step))  # 0.1, 2/11, 0.25
        expected = d * expected + (1 - d) * value
        avg.update(model)
        torch.testing.assert_close(avg.model.weight, torch.full((1, 2), expected))
    assert avg.steps == 3 and not any(p.requires_grad for p in avg.model.parameters())
    other = WeightAverage(nn.Linear(2, 1), 0.5)
    other.load_state_dict(avg.state_dict())
    assert other.steps == 3
    torch.testing.assert_close(other.model.weight, avg.model.weight)
    with pytest.raises(ValueError, match="decay"):
        WeightAverage(model, 1.0)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_tiny_store(tmp_path_factory.mktemp("trainer_avg") / "tiny.zarr", shapes=4)


def test_mean_teacher_run_keeps_and_resumes_the_average(store, tmp_path):
    model = replace(named_config("mean-teacher"), hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8)
    cfg = TrainConfig(store=store, config_name="R5-small", model=model, epochs=2, batch_size=4, num_threads=1,
                      sr=0.5)
    run = tmp_path / "run"
    fit(cfg, run)
    state = load_run(run)
    steps = state["weight_average"]["steps"]
    assert steps > 0 and steps % 2 == 0  # the same number of optimiser steps in each epoch
    averaged = state["weight_average"]["weights"]
    assert any(not torch.equal(averaged[k], state["model"][k]) for k in averaged)  # average ≠ the last weights
    assert any(not torch.equal(state["best_model"][k], state["model"][k]) for k in averaged)  # the best is averaged
    if state["best_epoch"] == 2:
        assert all(torch.equal(averaged[k], state["best_model"][k]) for k in averaged)
    fit(replace(cfg, epochs=3), run)
    assert load_run(run)["weight_average"]["steps"] == steps * 3 // 2
