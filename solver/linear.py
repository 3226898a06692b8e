"""Sparse direct solves for the Newton systems: MKL PARDISO (pypardiso) when it is installed,
SciPy's SuperLU otherwise. Both accept the nonsymmetric, indefinite saddle-point tangents."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu


def available_backends() -> list[str]:
    names = ["superlu"]
    try:
        import pypardiso  # noqa: F401

        names.insert(0, "pardiso")
    except Exception:  # pragma: no cover - depends on the platform
        pass
    return names


class SparseSolver:
    """Factorise-and-solve. With PARDISO the symbolic analysis (ordering) is done once per sparsity
    pattern and reused by later Newton iterations, which only refactorise."""

    def __init__(self, backend: str = "auto"):
        if backend == "auto":
            backend = available_backends()[0]
        if backend not in ("pardiso", "superlu"):
            raise ValueError(f"unknown linear solver {backend!r}; choose pardiso or superlu")
        self.backend = backend
        self._pardiso = None
        self._pattern_key = None

    def solve(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        if self.backend == "superlu":
            return splu(A.tocsc(), permc_spec="COLAMD").solve(b)
        import pypardiso

        A = A.tocsr()
        A.sort_indices()
        b = np.ascontiguousarray(b, dtype=np.float64)
        key = (A.shape, A.nnz, A.indptr.tobytes().__hash__(), A.indices.tobytes().__hash__())
        if self._pardiso is None:
            ps = pypardiso.PyPardisoSolver(mtype=11)
            ps.set_iparm(1, 1)  # use the iparm values set here, not MKL's defaults
            ps.set_iparm(2, 2)  # METIS nested-dissection ordering
            ps.set_iparm(10, 13)  # pivot perturbation 1e-13 (saddle-point systems)
            ps.set_iparm(11, 1)  # scaling
            ps.set_iparm(13, 1)  # weighted matching
            self._pardiso = ps
        ps = self._pardiso
        if key != self._pattern_key:
            ps.set_phase(11)
            ps._call_pardiso(A, b)
            self._pattern_key = key
        ps.set_phase(23)
        return ps._call_pardiso(A, b).reshape(b.shape)

    def free(self) -> None:
        if self._pardiso is not None:
            self._pardiso.free_memory(everything=True)
            self._pardiso = None
            self._pattern_key = None
