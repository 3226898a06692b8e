"""Sparse direct solves for the Newton systems: MKL PARDISO (pypardiso) when it is installed,
SciPy's SuperLU otherwise. Both accept the nonsymmetric, indefinite saddle-point tangents.

A factorisation is kept after `factorize` so that later right-hand sides (modified Newton) only
cost a forward/back substitution; PARDISO's symbolic analysis is redone only when the sparsity
pattern changes."""
from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu


def _point_pypardiso_at_mkl() -> None:
    """Set PYPARDISO_MKL_RT to the MKL runtime pip installs beside this interpreter ({prefix}/lib),
    when it is there and the variable is unset. Without it, importing pypardiso (which builds a
    default solver) and each new solver search all of {prefix}/lib*/** recursively for the library:
    1–3 s per process with torch installed, paid by every `heartctl unload`, `solve` and worker."""
    if os.environ.get("PYPARDISO_MKL_RT"):
        return
    import site
    import sys

    for folder in (os.path.join(sys.prefix, "lib"), os.path.join(sys.prefix, "Library", "bin"),
                   os.path.join(site.USER_BASE or "", "lib")):
        try:
            found = sorted((f for f in os.listdir(folder) if "mkl_rt" in f), key=len)
        except OSError:
            continue
        if found:
            os.environ["PYPARDISO_MKL_RT"] = os.path.join(folder, found[0])
            return


def available_backends() -> list[str]:
    names = ["superlu"]
    try:
        _point_pypardiso_at_mkl()
        import pypardiso  # noqa: F401

        names.insert(0, "pardiso")
    except Exception:  # pragma: no cover - depends on the platform
        pass
    return names


class SingularMatrix(ArithmeticError):
    """The linear solver could not factorise the matrix. SuperLU raises it for an exactly singular
    matrix; PARDISO (pivot perturbation on, for the saddle-point systems) perturbs tiny pivots and
    raises it only for its own errors, so callers check the residual where it matters (Newton's
    convergence test, `solver.lv.linear_response`)."""


class SparseSolver:
    def __init__(self, backend: str = "auto"):
        if backend == "auto":
            backend = available_backends()[0]
        if backend not in ("pardiso", "superlu"):
            raise ValueError(f"unknown linear solver {backend!r}; choose pardiso or superlu")
        self.backend = backend
        self._pardiso = None
        self._pattern_key = None
        self._lu = None
        self._A = None
        self.factorizations = 0
        self.solves = 0

    @property
    def has_factor(self) -> bool:
        return self._A is not None

    @property
    def size(self) -> int:
        """Order of the kept factorisation (0 when none is kept)."""
        return 0 if self._A is None else self._A.shape[0]

    def factorize(self, A: sp.csr_matrix) -> None:
        """Factorise A for later solves; SingularMatrix when the backend finds it singular."""
        A = A.tocsr()
        A.sort_indices()
        self.factorizations += 1
        if self.backend == "superlu":
            try:
                self._lu = splu(A.tocsc(), permc_spec="COLAMD")
            except RuntimeError as exc:  # "Factor is exactly singular"
                self.forget()
                raise SingularMatrix(f"SuperLU: {exc}") from None
            self._A = A
            return
        import pypardiso

        if self._pardiso is None:
            ps = pypardiso.PyPardisoSolver(mtype=11)
            # pypardiso globs site-packages for libmkl_rt on every construction (~0.5 s);
            # remember the library it found so later solvers in this process skip the search
            os.environ.setdefault("PYPARDISO_MKL_RT", ps.libmkl._name)
            ps.set_iparm(1, 1)  # use the iparm values set here, not MKL's defaults
            ps.set_iparm(2, 2)  # METIS nested-dissection ordering
            ps.set_iparm(10, 13)  # pivot perturbation 1e-13 (saddle-point systems)
            ps.set_iparm(11, 1)  # scaling
            ps.set_iparm(13, 1)  # weighted matching
            self._pardiso = ps
        ps = self._pardiso
        key = (A.shape, A.nnz, hash(A.indptr.tobytes()), hash(A.indices.tobytes()))
        dummy = np.zeros(A.shape[0])
        if key != self._pattern_key:
            ps.set_phase(11)
            ps._call_pardiso(A, dummy)
            self._pattern_key = key
        ps.set_phase(22)
        try:
            ps._call_pardiso(A, dummy)
        except pypardiso.pardiso_wrapper.PyPardisoError as exc:
            self.forget()
            raise SingularMatrix(f"PARDISO: {exc}") from None
        self._A = A

    def solve_factored(self, b: np.ndarray) -> np.ndarray:
        """Solve with the last factorisation (which may belong to an older tangent)."""
        if self._A is None:
            raise RuntimeError("no factorisation to solve with")
        self.solves += 1
        b = np.ascontiguousarray(b, dtype=np.float64)
        if self.backend == "superlu":
            return self._lu.solve(b)
        self._pardiso.set_phase(33)
        return self._pardiso._call_pardiso(self._A, b).reshape(b.shape)

    def solve(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        self.factorize(A)
        return self.solve_factored(b)

    def forget(self) -> None:
        """Drop the factorisation and PARDISO's analysis: after a failed solve the next factorisation
        starts afresh. The analysis (phase 11) is skipped while the pattern stays the same, but with
        scaling and weighted matching on it depends on the matrix's values too: a load-stepping
        restart from zero strain, factorised with the scaling and matching of a failed full-load
        attempt's tangent, collapsed at 0 % of the load (a network's guess for an l2u mesh)."""
        self._A = None
        self._lu = None
        self._pattern_key = None

    def free(self) -> None:
        """Release MKL's memory for this solver (PARDISO phase −1). MKL keeps a factorisation's
        memory until told to, not until the Python handle is collected: without this a Ray worker
        grew by ~6 MB per training pair (to 16 GB, then killed for memory)."""
        if self._pardiso is not None:
            self._pardiso.free_memory(everything=True)
            self._pardiso = None
        self.forget()

    def __enter__(self) -> "SparseSolver":
        return self

    def __exit__(self, *exc) -> None:
        self.free()

    def __del__(self):  # a solver dropped without free(): release MKL's memory all the same
        try:
            self.free()
        except Exception:  # interpreter shutdown: modules may already be gone
            pass
