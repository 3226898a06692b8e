"""Training-time augmentation that makes exact new FE pairs: rotation about the long axis, and
uniform scaling about the base.

The generated LV problem is equivariant under a rotation R about any line parallel to z: the base
slides on a plane z = const, the in-plane rigid gauge (Σu_x = Σu_y = 0, Σ(X × u)_z = 0) is
invariant, the endocardial pressure follows the surface, and the fibres come from the geometry and
the z axis (e_c = e_z × t). So if (x_ED, X_unloaded) is a solved pair, (R x_ED, R X_unloaded) is one
too, to solver tolerance, and its unloading displacement is R (X − x). Rotating a graph's normalised
coordinates about the z line through the normalisation centre, and its displacement label with the
same R, therefore adds pairs the solver would have produced, at no cost. Node regions (base / mid /
apex × endo / epi) and parameters are invariant and stay as they are.

Uniform scaling by s is exact too. The deformation gradient F, and with it the Guccione stress, is
unchanged when both configurations scale. Each term of the weak form, internal work and pressure work,
gains the same factor s², so scaled pairs stay in equilibrium; the helix angles depend on the relative
wall depth only; the base stays on its plane when the centre of scaling lies in it; the rigid gauge
is kept. So (s x_ED, s X_unloaded) is the solved pair of the scaled shape, with displacement s (X − x).
This is the same discrete problem, not an approximation of it. It makes new combinations of size and the
other shape modes (the shape model's cavity volume spans 86–174 mL at ±2 SD, about ±12 % in length)."""
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
    if getattr(batch, "response", None) is not None:  # the linear response turns with the mesh
        batch.response = rotate_xy(batch.response, per_node)
    return batch


def scale_factors(num_graphs: int, max_pct: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """[num_graphs] factors uniform in [1 − max_pct/100, 1 + max_pct/100] (CPU, float32)."""
    u = torch.rand(num_graphs, generator=generator)
    return 1.0 + (2.0 * u - 1.0) * (max_pct / 100.0)


def scale_batch(batch, max_pct: float, generator: torch.Generator | None = None):
    """The batch with every graph scaled by one random factor s in 1 ± max_pct/100 about the point of
    its base plane on the normalisation axis, (0, 0, max z) in normalised coordinates, so the base stays
    on its plane: x ← p + s (x − p), y ← s y. New tensors, never written in place; NaN labels stay NaN.
    max_pct ≤ 0: the batch unchanged."""
    if max_pct <= 0:
        return batch
    factors = scale_factors(batch.num_graphs, max_pct, generator).to(batch.x.device, batch.x.dtype)
    top = torch.full((batch.num_graphs,), -torch.inf, device=batch.x.device, dtype=batch.x.dtype)
    top = top.scatter_reduce(0, batch.batch, batch.x[:, 2], reduce="amax")
    per_node = factors[batch.batch].unsqueeze(1)
    centre = torch.zeros_like(batch.x)
    centre[:, 2] = top[batch.batch]
    batch.x = centre + per_node * (batch.x - centre)
    batch.y = per_node * batch.y  # the linear response ũ (displacement / size) is unchanged
    return batch
