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


SKEW_LIMIT = 0.1  # a symmetric-part step whose relative residual ‖A x − b‖/‖b‖ exceeds this: use the LU of A


class _SymmetricPart:
    """½(A + Aᵀ) on the upper triangle (what PARDISO's symmetric types read) for one CSR pattern that
    is structurally symmetric: the positions are worked out once, each tangent's values then cost one
    gather. `symmetric` is False (and `of` unusable) for a pattern that is not."""

    def __init__(self, A: sp.csr_matrix):
        n = A.shape[0]
        rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(A.indptr))
        at = sp.csr_matrix((np.arange(1, A.nnz + 1, dtype=float), (A.indices, rows)), shape=A.shape)
        at.sort_indices()  # at holds, at (j, i), 1 + the position of A's entry (i, j)
        self.symmetric = (at.nnz == A.nnz and np.array_equal(at.indptr, A.indptr)
                          and np.array_equal(at.indices, A.indices))
        if not self.symmetric:
            return
        transposed = at.data.astype(np.int64) - 1  # the position in A of each entry's mirror image
        # the upper triangle with every diagonal entry: PARDISO's symmetric types need the diagonal
        # stored, zeros included (the gauge multipliers' rows have none; without it MKL factorised
        # wrongly, or crashed, once a solver had analysed another pattern)
        upper = A.indices >= rows
        missing = np.setdiff1d(np.arange(n), rows[A.indices == rows])
        r = np.concatenate([rows[upper], missing])
        c = np.concatenate([A.indices[upper], missing])
        order = np.lexsort((c, r))
        source = np.concatenate([np.flatnonzero(upper), np.full(missing.size, -1)])[order]  # −1: a zero
        self.stored = source >= 0  # the upper triangle's entries that A stores (the others: zero diagonals)
        self.source = source[self.stored]  # A's positions of the upper triangle's stored entries
        self.mirror = transposed[self.source]  # and of their mirror images below the diagonal
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=n))]).astype(np.int32)
        self.indices = c[order].astype(np.int32)

    def of(self, A: sp.csr_matrix) -> sp.csr_matrix:
        upper = np.zeros(self.stored.size)
        upper[self.stored] = 0.5 * (A.data[self.source] + A.data[self.mirror])
        return sp.csr_matrix((upper, self.indices, self.indptr), shape=A.shape)


class SparseSolver:
    """A sparse direct solver that keeps its last factorisation.

    `symmetric_part` (PARDISO only): factorise S = ½(A + Aᵀ) with the symmetric indefinite LDLᵀ
    instead of A with LU. The tangents here are symmetric but for the follower pressure load on the
    open endocardium (about 4e-4 of the largest entry on an `accurate` LV tangent), and the LDLᵀ
    costs half the LU (13,287 unknowns, P2/P1, one thread: 64 ms against 124 ms). `solve_factored`
    then returns S⁻¹b, an inexact Newton step whose relative residual ‖A x − b‖/‖b‖, measured on the
    first solve after each factorisation (`skew_residual`), is about 1e-3 there. Above SKEW_LIMIT, or for
    a pattern that is not symmetric, the solver factorises A itself from then on. `solve` refines
    S⁻¹b against A to a direct solver's accuracy."""

    def __init__(self, backend: str = "auto", symmetric_part: bool = True):
        if backend == "auto":
            backend = available_backends()[0]
        if backend not in ("pardiso", "superlu"):
            raise ValueError(f"unknown linear solver {backend!r}; choose pardiso or superlu")
        self.backend = backend
        self.symmetric_part = symmetric_part and backend == "pardiso"
        self._pardiso = None
        self._pattern_key = None
        self._half = None  # (pattern key of A, _SymmetricPart)
        self._lu = None
        self._A = None
        self._M = None  # the matrix PARDISO factorised: A, or the upper triangle of ½(A + Aᵀ)
        self._check = False  # measure the next solve's residual against A
        self.skew_residual = float("nan")
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
        """Factorise A (or its symmetric part) for later solves; SingularMatrix when the backend finds
        it singular."""
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

        key = (A.shape, A.nnz, hash(A.indptr.tobytes()), hash(A.indices.tobytes()))
        half = None
        if self.symmetric_part:
            if self._half is None or self._half[0] != key:
                self._half = (key, _SymmetricPart(A))
            half = self._half[1] if self._half[1].symmetric else None
        M, mtype = (A, 11) if half is None else (half.of(A), -2)
        if self._pardiso is not None and self._pardiso.mtype != mtype:
            self.free()
        if self._pardiso is None:
            ps = pypardiso.PyPardisoSolver(mtype=mtype)
            # pypardiso globs site-packages for libmkl_rt on every construction (~0.5 s);
            # remember the library it found so later solvers in this process skip the search
            os.environ.setdefault("PYPARDISO_MKL_RT", ps.libmkl._name)
            ps.set_iparm(1, 1)  # use the iparm values set here, not MKL's defaults
            ps.set_iparm(2, 2)  # METIS nested-dissection ordering
            ps.set_iparm(10, 13 if mtype == 11 else 8)  # pivot perturbation (saddle-point systems)
            ps.set_iparm(11, 1)  # scaling
            # weighted matching for the LU of A; the symmetric part's LDLᵀ does without it: on a P2/P1 LV
            # tangent (12,775 unknowns, one thread) the analysis takes 71 ms without it against 152 ms with
            # it, the factorisation 52 against 59 ms, with no pivot perturbed either way and the same
            # residual (converged and zero-strain states at 9 and 14 mmHg, `fast` and `accurate`,
            # docs/solver.md)
            ps.set_iparm(13, 1 if mtype == 11 else 0)
            self._pardiso = ps
        ps = self._pardiso
        dummy = np.zeros(A.shape[0])
        if key != self._pattern_key:
            ps.set_phase(11)
            ps._call_pardiso(M, dummy)
            self._pattern_key = key
        ps.set_phase(22)
        try:
            ps._call_pardiso(M, dummy)
        except pypardiso.pardiso_wrapper.PyPardisoError as exc:
            self.forget()
            raise SingularMatrix(f"PARDISO: {exc}") from None
        self._A, self._M, self._check = A, M, half is not None

    def solve_factored(self, b: np.ndarray) -> np.ndarray:
        """Solve with the last factorisation (which may belong to an older tangent; with the symmetric
        part, an approximate solve of A x = b even for the current one)."""
        if self._A is None:
            raise RuntimeError("no factorisation to solve with")
        if len(b) != self._A.shape[0]:
            raise ValueError(f"right-hand side of {len(b)} unknowns for a factorisation of {self._A.shape[0]}")
        self.solves += 1
        b = np.ascontiguousarray(b, dtype=np.float64)
        if self.backend == "superlu":
            return self._lu.solve(b)
        x = self._substitute(b)
        if self._check:
            self._check = False
            scale = float(np.linalg.norm(b))
            self.skew_residual = float(np.linalg.norm(b - self._A @ x)) / scale if scale > 0 else 0.0
            if not self.skew_residual <= SKEW_LIMIT:  # too far from symmetric here
                x = self._lu_from_now_on(self._A, b)
        return x

    def _lu_from_now_on(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        """Factorise A itself (the same tangent, so not counted again) and keep to the LU for later
        factorisations; A⁻¹b. SingularMatrix reaches the caller as from `factorize`."""
        self.symmetric_part = False
        self.free()
        self.factorizations -= 1
        self.factorize(A)
        return self._substitute(np.ascontiguousarray(b, dtype=np.float64))

    def _substitute(self, b: np.ndarray) -> np.ndarray:
        self._pardiso.set_phase(33)
        return self._pardiso._call_pardiso(self._M, b).reshape(b.shape)

    def solve(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        """x with A x = b to a direct solver's accuracy (the symmetric part's answer refined against A)."""
        self.factorize(A)
        x = self.solve_factored(b)
        if self._M is None or self._M is self._A:  # SuperLU, or the LU of A
            return x
        r = b - self._A @ x
        scale = float(np.linalg.norm(b))
        r_norm = float(np.linalg.norm(r))
        for _ in range(30):
            if r_norm <= 1e-13 * scale:
                break
            x_next = x + self._substitute(r)
            r_next = b - self._A @ x_next
            next_norm = float(np.linalg.norm(r_next))
            if next_norm >= r_norm:
                break
            x, r, halved, r_norm = x_next, r_next, next_norm <= 0.5 * r_norm, next_norm
            if not halved:  # stalled: at round-off, or too far from symmetric to refine
                break
        if r_norm > 1e-8 * scale:  # not a direct solver's answer: the LU of A instead
            x = self._lu_from_now_on(A, b)
        return x

    def forget(self) -> None:
        """Drop the factorisation and PARDISO's analysis: after a failed solve the next factorisation
        starts afresh. The analysis (phase 11) is skipped while the pattern stays the same, but with
        scaling and weighted matching on it depends on the matrix's values too: a load-stepping
        restart from zero strain, factorised with the scaling and matching of a failed full-load
        attempt's tangent, collapsed at 0 % of the load (a network's guess for an l2u mesh)."""
        self._A = None
        self._M = None
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
