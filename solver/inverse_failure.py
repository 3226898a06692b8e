"""How an inverse FE solve fails: the error it raises, the stall rule, and where the mismatch that would
not fall lies (the reason names it, so a failed case in a store says where its geometry gave out)."""
from __future__ import annotations

import numpy as np

from .forward import SolveError

# an inverse whose last STALL_UPDATES updates all left the mismatch above STALL_GAIN × its best before them
# has failed: converging solves cut it ~5× over as many updates (docs/solver.md, "Stability at the extremes")
STALL_UPDATES = 10
STALL_GAIN = 0.9


class InverseError(SolveError):
    """The inverse's own iteration failed (it stalled, folded a trial reference, or ran out of updates), with
    every forward solve inside it converged: solving the same start again with smaller load steps gives the
    same updates, so a retry needs another start."""


def stalled(history: list) -> bool:
    """The last STALL_UPDATES mismatches (mm) all above STALL_GAIN × the best one before them."""
    if len(history) <= STALL_UPDATES:
        return False
    return min(history[-STALL_UPDATES:]) > STALL_GAIN * min(history[:-STALL_UPDATES])


def where_largest(mismatch: np.ndarray, x_ed: np.ndarray) -> str:
    """Where the largest nodal mismatch [n, 3] mm lies on the ED geometry x_ED [n, 3] mm (base plane at its
    largest z, apex at its smallest): its level as a percentage of the height from base to apex, and its
    azimuth about the long axis (0° = +x; the built-in shapes' septum faces −x, 180°)."""
    i = int(np.argmax(np.linalg.norm(mismatch, axis=1)))
    z = x_ed[:, 2]
    level = (z.max() - z[i]) / max(float(np.ptp(z)), 1e-12)
    centre = x_ed[:, :2].mean(axis=0)
    azimuth = np.degrees(np.arctan2(*(x_ed[i, :2] - centre)[::-1])) % 360.0
    return f"largest at {100 * level:.0f} % of the height below the base, azimuth {azimuth:.0f}°"
