"""What a solve will cost, from the mesh's size and the preset, before it starts: its unknowns, the
peak memory of the process and a rough wall time; and a rough time of meshing a target node count.
Pure functions of counts (no machine state): the CLI compares the peak with the memory available and
refuses a solve that cannot fit, and shows progress for a long one.

Unknowns: fast (P1/P1) 4 per vertex; accurate (P2/P1) 3 per vertex and per edge + 1 per vertex (the
pressure); reference: accurate on the mesh refined once (vertices V + E, 8 T tets, 2 E + 3 F + T
edges, F the faces), after accurate's inverse on the mesh as given (a smaller peak, before it).

The sparse factor's fill dominates the memory. Peak resident memory = BASE_BYTES + a · unknowns^b,
and wall time = t1 · (unknowns / 1e5)^c, fitted per element order on LV meshes of shape 0
(`heartctl mesh --shape 0 --nodes 1000|3000|8000|20000`) solved by `/usr/bin/time -v heartctl solve
MESH --pressure 8 --stiffness 150 --fidelity fast|accurate --threads 1` on a shared 2-core machine
(MKL PARDISO); the exponent and factor from the two largest meshes of each order:

=========  ======  ========  ==========  ========
preset     nodes   unknowns  peak RSS    solve
=========  ======  ========  ==========  ========
fast          872     3,488     194 MB     1.6 s
fast        2,848    11,392     339 MB    11.0 s
fast        7,702    30,808     742 MB    13.3 s
fast       19,472    77,888   1,849 MB    56.5 s
accurate      872    16,484     458 MB     6.1 s
accurate    2,848    56,881   1,360 MB    43.9 s
accurate    7,702   161,431   4,039 MB   211.2 s
=========  ======  ========  ==========  ========

(peak RSS: time's maximum resident set, MB = 1e6 bytes; solve: the wall time the command prints.)
The fits: fast 4.10e3 · unknowns^1.148 bytes and 83 s · (unknowns / 1e5)^1.56, accurate 5.37e3 ·
unknowns^1.125 bytes and 103 s · (unknowns / 1e5)^1.51; the smaller meshes lie within 7 % of the
memory law (BASE_BYTES dominates there), their times below it (assembly, not the factor, dominates).
`heartctl unload --method fe --fidelity fast` of the 7,702- and 19,472-node meshes peaked at 828 and
2,067 MB (1.12× their forward solves) in 39.6 and 135.6 s (9 updates, 2.4–3.0× the forward time):
INVERSE_MEMORY and INVERSE_TIME.
Nested dissection's fill grows as unknowns^(4/3) in 3-D; the fitted exponents (1.1–1.2) are lower at
these sizes, so estimates far above them are more likely low, not high: the refusal errs towards solving.
Times vary 2× with the machine's load and threads; they only decide whether to show progress.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BASE_BYTES = 160e6  # the CLI process with its solver libraries loaded (MKL, SciPy, meshio)
# element order → (a, b) of the factor's memory in bytes, (t1, c) of the forward solve's seconds
MEMORY_LAW = {1: (4.10e3, 1.148), 2: (5.37e3, 1.125)}
TIME_LAW = {1: (83.4, 1.56), 2: (103.0, 1.51)}
INVERSE_MEMORY = 1.12  # an inverse FE (unload) against a forward solve of the same mesh
INVERSE_TIME = 2.5
# typical LV tet meshes of this project (gmsh, 3k–20k nodes): edges and tets per vertex, for a
# target node count with no mesh yet
EDGES_PER_NODE, TETS_PER_NODE = 6.0, 4.4
# `heartctl mesh`: seconds per target node (gmsh in one thread, ~2–4 tries at the element size),
# resident bytes per node (measured 19,472 nodes: 39 s, 909 MB)
MESH_SECONDS_PER_NODE = 2.0e-3
MESH_BYTES_PER_NODE = 38e3

PRESET_ORDER = {"fast": 1, "accurate": 2, "reference": 2}


@dataclass(frozen=True)
class SolveEstimate:
    """The estimate of one solve: `preset` on a mesh of `nodes` vertices, `unknowns` (on the refined
    mesh for reference), peak resident bytes and seconds (rough)."""

    preset: str
    inverse: bool
    nodes: int
    unknowns: int
    peak_bytes: float
    seconds: float


def mesh_counts(tets: np.ndarray, n_boundary_triangles: int) -> tuple[int, int]:
    """(edges, faces) of a tet mesh: its unique vertex pairs, and (4 T + boundary triangles) / 2."""
    tets = np.asarray(tets, dtype=np.int64)
    n = int(tets.max()) + 1 if tets.size else 0
    pairs = np.concatenate([tets[:, [i, j]] for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))])
    pairs.sort(axis=1)
    edges = np.unique(pairs[:, 0] * n + pairs[:, 1]).size
    return int(edges), int((4 * len(tets) + n_boundary_triangles) // 2)


def unknowns(order: int, vertices: int, edges: int) -> int:
    """Unknowns of a mixed solve: P1/P1 4 per vertex; P2/P1 3 per vertex and edge + 1 per vertex."""
    return 4 * vertices if order == 1 else 3 * (vertices + edges) + vertices


def _cost(order: int, dofs: int, inverse: bool) -> tuple[float, float]:
    a, b = MEMORY_LAW[order]
    t1, c = TIME_LAW[order]
    peak = BASE_BYTES + a * dofs ** b * (INVERSE_MEMORY if inverse else 1.0)
    seconds = t1 * (dofs / 1e5) ** c * (INVERSE_TIME if inverse else 1.0)
    return peak, seconds


def estimate_solve(preset: str, vertices: int, edges: int, tets: int, faces: int,
                   inverse: bool = False) -> SolveEstimate:
    """Peak memory and rough time of `preset`'s forward solve (or inverse FE with `inverse`) of a mesh
    with these counts. reference: the accurate solve on the once-refined mesh, plus (inverse) the
    accurate inverse on the mesh as given that starts it (time added, memory the larger peak)."""
    if preset not in PRESET_ORDER:
        raise ValueError(f"unknown fidelity {preset!r}; choose one of {', '.join(PRESET_ORDER)}")
    order = PRESET_ORDER[preset]
    if preset != "reference":
        dofs = unknowns(order, vertices, edges)
        peak, seconds = _cost(order, dofs, inverse)
        return SolveEstimate(preset, inverse, vertices, dofs, peak, seconds)
    dofs = unknowns(2, vertices + edges, 2 * edges + 3 * faces + tets)
    peak, seconds = _cost(2, dofs, inverse)
    if inverse:
        coarse_peak, coarse_s = _cost(2, unknowns(2, vertices, edges), True)
        peak, seconds = max(peak, coarse_peak), seconds + coarse_s
    return SolveEstimate(preset, inverse, vertices, dofs, peak, seconds)


def estimate_for_nodes(preset: str, nodes: int, inverse: bool = False) -> SolveEstimate:
    """estimate_solve for a mesh of about `nodes` vertices not yet made (typical edge and tet counts)."""
    edges, tets = round(EDGES_PER_NODE * nodes), round(TETS_PER_NODE * nodes)
    return estimate_solve(preset, nodes, edges, tets, 2 * tets + round(nodes ** (2 / 3)), inverse)


def estimate_mesh(nodes: int) -> tuple[float, float]:
    """(peak resident bytes, rough seconds) of meshing a target of `nodes` nodes."""
    return BASE_BYTES + MESH_BYTES_PER_NODE * nodes, MESH_SECONDS_PER_NODE * nodes
