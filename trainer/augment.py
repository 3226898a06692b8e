"""Training-time augmentation that makes exact new FE pairs: rotation about the long axis.

The generated LV problem is equivariant under a rotation R about any line parallel to z: the base
slides on a plane z = const, the in-plane rigid gauge (Σu_x = Σu_y = 0, Σ(X × u)_z = 0) is
invariant, the endocardial pressure follows the surface, and the fibres come from the geometry and
the z axis (e_c = e_z × t). So if (x_ED, X_unloaded) is a solved pair, (R x_ED, R X_unloaded) is one
too, to solver tolerance, and its unloading displacement is R (X − x). Rotating a graph's normalised
coordinates about the z line through the normalisation centre, and its displacement label with the
same R, therefore adds pairs the solver would have produced, at no cost. Node regions (base / mid /
apex × endo / epi) and parameters are invariant and stay as they are."""
from __future__ import annotations

import math

import torch


def rotation_angles(num_graphs: int, max_deg: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """[num_graphs] angles, rad, uniform in [−max_deg, max_deg] degrees (CPU, float32)."""
    u = torch.rand(num_graphs, generator=generator)
    return (2.0 * u - 1.0) * math.radians(max_deg)


def rotate_xy(vectors: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """Rotate each row of `vectors` [n, 3] about z by its row's angle [n] (rad); z is unchanged.
    A new tensor; NaN rows (withheld labels) stay NaN."""
    c, s = torch.cos(angles).to(vectors.dtype), torch.sin(angles).to(vectors.dtype)
    x, y, z = vectors.unbind(dim=1)
    return torch.stack((c * x - s * y, s * x + c * y, z), dim=1)


def rotate_batch(batch, max_deg: float, generator: torch.Generator | None = None):
    """The batch with every graph's x (normalised ED coordinates) and y (normalised unloading
    displacement) rotated about z by one random angle per graph in ±max_deg degrees. x and y are
    replaced by new tensors, never written in place (a collated batch may share storage with the
    dataset's graphs). max_deg ≤ 0: the batch unchanged."""
    if max_deg <= 0:
        return batch
    angles = rotation_angles(batch.num_graphs, max_deg, generator).to(batch.x.device)
    per_node = angles[batch.batch]
    batch.x = rotate_xy(batch.x, per_node)
    batch.y = rotate_xy(batch.y, per_node)
    return batch
