"""An exponential moving average of a model's weights (ModelConfig.ema_decay): the model that
validation sees and the checkpoint keeps as the best, and the mean teacher of cycle_grad="teacher"."""
from __future__ import annotations

import copy

import torch
from torch import nn

from trainer.training.checkpoint import cpu_state


class WeightAverage:
    r"""θ̄ ← d_t·θ̄ + (1 − d_t)·θ after every optimiser step, with the decay warmed up as

    .. math:: d_t = \min\left(d, \frac{1 + t}{10 + t}\right)

    (t = updates so far), so the first steps are not dominated by the random initialisation.
    Buffers are copied, not averaged. The average lives in a frozen copy of the model (`model`),
    on the same device; every rank of a DDP run computes the same average from the same weights."""

    def __init__(self, model: nn.Module, decay: float):
        if not 0 < decay < 1:
            raise ValueError(f"weight-average decay must be in (0, 1), got {decay}")
        self.decay = float(decay)
        self.steps = 0
        self.model = copy.deepcopy(model)
        for p in self.model.parameters():
            p.requires_grad_(False)

    def current_decay(self) -> float:
        return min(self.decay, (1 + self.steps) / (10 + self.steps))

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        weight = 1.0 - self.current_decay()
        for avg, p in zip(self.model.parameters(), model.parameters()):
            avg.lerp_(p.detach(), weight)
        for avg, b in zip(self.model.buffers(), model.buffers()):
            avg.copy_(b)
        self.steps += 1

    def teacher(self) -> dict:
        """The averaged weights by parameter name, for torch.func.functional_call."""
        return dict(self.model.named_parameters())

    def state_dict(self) -> dict:
        return {"weights": cpu_state(self.model), "steps": self.steps}

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["weights"])
        self.steps = int(state["steps"])
