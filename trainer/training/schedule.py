"""Learning-rate schedules that are a pure function of the epoch (nothing to checkpoint)."""
from __future__ import annotations

import math

COSINE_FLOOR = 0.01  # the cosine schedule ends at this fraction of the initial learning rate


def cosine_lr(epoch: int, epochs: int, lr: float, floor: float = COSINE_FLOOR) -> float:
    r"""Learning rate of training epoch `epoch` (0-based) of `epochs`, cosine annealing
    (Loshchilov & Hutter 2017) without restarts:

    .. math:: \eta_e = \eta\,\big(f + (1 - f)\tfrac{1}{2}(1 + \cos(\pi e / E))\big),

    from η at e = 0 down to η·(f + (1 − f)(1 + cos(π(E − 1)/E))/2) ≈ f·η in the last epoch. A run
    resumed with more epochs (a larger E) continues on the longer curve: its rate steps up once."""
    if epochs < 1 or not 0 <= epoch:
        raise ValueError(f"epoch {epoch} of {epochs}")
    e = min(epoch, epochs - 1)
    return lr * (floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * e / epochs)))
