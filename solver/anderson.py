"""Anderson acceleration of the inverse FE's fixed point (solver.lv.inverse_solve)."""
from __future__ import annotations

import numpy as np


class Anderson:
    """Anderson acceleration (type II) of the fixed point X ← X − G(X), G = x(X) − x_ED.

    With the last m + 1 iterates' g_i = X_i − G_i and f_i = −G_i, the step is
    X⁺ = g_k − ΔG γ, γ = argmin ‖f_k − ΔF γ‖₂, ΔF and ΔG the differences of consecutive f and g."""

    def __init__(self, memory: int = 5):
        self.memory = memory
        self.reset()

    def reset(self) -> None:
        self._g, self._f = [], []

    def step(self, X: np.ndarray, G: np.ndarray) -> np.ndarray:
        g = (X - G).ravel()
        f = -G.ravel()
        self._g.append(g)
        self._f.append(f)
        if len(self._f) > self.memory + 1:
            self._g.pop(0)
            self._f.pop(0)
        if len(self._f) < 2:
            return g.reshape(X.shape)
        dF = np.stack([b - a for a, b in zip(self._f[:-1], self._f[1:])], axis=1)
        dG = np.stack([b - a for a, b in zip(self._g[:-1], self._g[1:])], axis=1)
        gamma, *_ = np.linalg.lstsq(dF, f, rcond=1e-10)
        return (g - dG @ gamma).reshape(X.shape)
