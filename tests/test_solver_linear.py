"""The sparse direct solver releases MKL PARDISO's memory: a generation worker solves thousands
of pairs in one process, and each dropped factorisation used to stay allocated (~6 MB per pair)."""
from __future__ import annotations

import gc
import os

import numpy as np
import pytest
import scipy.sparse as sp

from solver.linear import SparseSolver, available_backends


def _anonymous_rss_mb() -> float:
    with open(f"/proc/{os.getpid()}/status") as f:
        for line in f:
            if line.startswith("RssAnon"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no RssAnon")


def _laplacian_3d(n: int) -> sp.csr_matrix:
    t = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n))
    i = sp.identity(n)
    return (sp.kron(sp.kron(t, i), i) + sp.kron(sp.kron(i, t), i) + sp.kron(sp.kron(i, i), t)).tocsr()


@pytest.mark.skipif("pardiso" not in available_backends() or not os.path.exists("/proc/self/status"),
                    reason="needs pypardiso and Linux /proc")
@pytest.mark.parametrize("release", ["dropped", "context"])
def test_pardiso_memory_is_released(release):
    """Eight solvers, each factorising an 8,000-unknown Laplacian (~14 MB of MKL memory) and then
    dropped (or closed by `with`): the process must not grow by their factorisations (a leak: ~84 MB
    over the last six)."""
    A = _laplacian_3d(20)
    b = np.ones(A.shape[0])
    sizes = []
    for _ in range(8):
        if release == "context":
            with SparseSolver("pardiso") as s:
                x = s.solve(A, b)
        else:
            s = SparseSolver("pardiso")
            x = s.solve(A, b)
            del s
        gc.collect()
        sizes.append(_anonymous_rss_mb())
    assert np.allclose(A @ x, b)
    assert sizes[-1] - sizes[1] < 40, f"anonymous memory grew {sizes[-1] - sizes[1]:.0f} MB over 6 solvers"


def test_sparsity_pattern_sums_duplicates_and_drops_fixed_dofs():
    """SparsityPattern.matrix equals the dense sum of the COO entries (duplicates added) over the
    free dofs, in canonical CSR (sorted column indices, int32), with entries on fixed dofs dropped."""
    from solver.assembly import SparsityPattern

    rng = np.random.default_rng(3)
    n_full = 40
    rows = np.concatenate([rng.integers(0, n_full, 2_000), np.full(300, 2)])  # one entry 300+ times
    cols = np.concatenate([rng.integers(0, n_full, 2_000), np.full(300, 5)])
    values = rng.normal(size=rows.size)
    fixed = np.array([0, 7, 8, 31])
    free = np.setdiff1d(np.arange(n_full), fixed)
    full_to_reduced = -np.ones(n_full, np.int64)
    full_to_reduced[free] = np.arange(free.size)
    pattern = SparsityPattern(rows, cols, full_to_reduced, free.size)
    K = pattern.matrix(values)
    dense = np.zeros((n_full, n_full))
    np.add.at(dense, (rows, cols), values)
    np.testing.assert_allclose(K.toarray(), dense[np.ix_(free, free)], rtol=1e-12, atol=1e-12)
    assert K.has_canonical_format and K.indices.dtype == np.int32 and K.indptr.dtype == np.int32
    assert pattern.nnz == np.unique(full_to_reduced[rows[pattern.keep]] * free.size
                                    + full_to_reduced[cols[pattern.keep]]).size
    assert not pattern.keep[np.isin(rows, fixed) | np.isin(cols, fixed)].any()


@pytest.mark.skipif("pardiso" not in available_backends(), reason="needs pypardiso")
def test_pardiso_is_found_without_searching_site_packages():
    """A fresh process with PYPARDISO_MKL_RT unset points pypardiso at the MKL runtime beside the
    interpreter (pypardiso's own fallback walks every installed package: seconds per process)."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "PYPARDISO_MKL_RT"}
    code = ("import os, glob\n"
            "def no_search(*a, **k):\n"
            "    raise AssertionError('pypardiso searched the installed packages for libmkl_rt')\n"
            "glob.glob = no_search\n"
            "from solver.linear import available_backends, SparseSolver\n"
            "import numpy as np, scipy.sparse as sp\n"
            "assert available_backends()[0] == 'pardiso'\n"
            "x = SparseSolver('pardiso').solve(sp.identity(3, format='csr') * 2.0, np.ones(3))\n"
            "assert np.allclose(x, 0.5) and os.path.exists(os.environ['PYPARDISO_MKL_RT'])\n")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_superlu_names_a_singular_matrix():
    from solver.linear import SingularMatrix

    singular = sp.csr_matrix(np.array([[1.0, 2.0], [2.0, 4.0]]))
    with pytest.raises(SingularMatrix, match="SuperLU"):  # SciPy's own RuntimeError, named
        SparseSolver("superlu").factorize(singular)
    s = SparseSolver("superlu")
    with pytest.raises(SingularMatrix):
        s.factorize(singular)
    assert not s.has_factor  # no stale factorisation is left to solve with


def test_a_tangent_that_will_not_factorise_fails_the_solve_with_its_reason():
    """On SuperLU (aarch64 installs) a singular tangent raised a RuntimeError traceback through
    `heartctl solve`; it is a failed solve (SolveError, exit 1) like PARDISO's non-finite step."""
    from solver.forward import SolveError
    from solver.linear import SingularMatrix
    from solver.lv import forward_solve
    from solver.meshing import mesh_lv
    from solver.parameters import CaseParameters
    from solver.shape_model import lv_shape

    class Refusing(SparseSolver):
        def factorize(self, A):
            raise SingularMatrix("SuperLU: Factor is exactly singular")

    mesh = mesh_lv(lv_shape(0), 120)
    with pytest.raises(SolveError, match="singular tangent"):
        forward_solve(mesh, CaseParameters(8.0, 150.0, 60.0, -60.0), "fast", linsolve=Refusing("superlu"))


def test_linear_response_refuses_an_answer_that_does_not_solve_its_system(monkeypatch):
    """PARDISO answers a singular system with huge finite numbers (pivot perturbation): the linear
    response checks its residual instead of trusting them."""
    from solver.forward import SolveError
    from solver.lv import linear_response
    from solver.meshing import mesh_lv
    from solver.parameters import CaseParameters
    from solver.shape_model import lv_shape

    mesh = mesh_lv(lv_shape(0), 120)
    params = CaseParameters(1.0, 150.0, 65.0, -65.0)
    assert np.all(np.isfinite(linear_response(mesh, params)))
    monkeypatch.setattr(SparseSolver, "solve", lambda self, A, b: np.full(b.shape, 2.5e12))
    with pytest.raises(SolveError, match="singular tangent"):
        linear_response(mesh, params)


@pytest.mark.skipif("pardiso" not in available_backends(), reason="needs pypardiso")
def test_a_forgotten_factorisation_is_analysed_again(monkeypatch):
    """PARDISO's analysis (phase 11: ordering, scaling, weighted matching, which depend on the values)
    runs once per pattern while Newton goes well, and again after forget() (a failed solve): a restart
    must not factorise with the analysis of the failed attempt's tangent (a load-stepping restart
    collapsed at 0 % of the load that way; tests/test_l2u.py has the real case)."""
    A = _laplacian_3d(6)
    b = np.ones(A.shape[0])
    s = SparseSolver("pardiso")
    phases = []
    s.factorize(A)
    call = s._pardiso._call_pardiso

    def spy(M, rhs):
        phases.append(s._pardiso.phase)
        return call(M, rhs)

    monkeypatch.setattr(s._pardiso, "_call_pardiso", spy)
    s.factorize(A * 2.0)
    x = s.solve_factored(b)
    s.forget()
    s.factorize(A * 3.0)
    s.factorize(A * 4.0)
    assert phases == [22, 33, 11, 22, 22]
    assert np.allclose((A * 2.0) @ x, b)
    s.free()


def _nearly_symmetric(skew: float, seed: int = 0) -> sp.csr_matrix:
    """A Laplacian-like saddle-free matrix with a skew part of relative size `skew` on its pattern."""
    A = _laplacian_3d(8)
    rng = np.random.default_rng(seed)
    upper = sp.triu(A, k=1).tocoo()
    s = rng.uniform(-1.0, 1.0, upper.nnz) * skew
    S = sp.csr_matrix((np.concatenate([s, -s]), (np.concatenate([upper.row, upper.col]),
                                                np.concatenate([upper.col, upper.row]))), shape=A.shape)
    return (A + S).tocsr()


@pytest.mark.skipif("pardiso" not in available_backends(), reason="needs pypardiso")
def test_the_symmetric_part_steps_approximately_and_solves_exactly_or_falls_back_to_lu():
    """The LDLᵀ of ½(A + Aᵀ) answers a nearly symmetric A approximately in `solve_factored` (its
    relative residual measured), exactly in `solve` (refined against A); for a matrix too far from
    symmetric, or a pattern that is not symmetric, the solver factorises A itself and is exact."""
    b = np.linspace(1.0, 2.0, 512)
    A = _nearly_symmetric(1e-3)
    s = SparseSolver("pardiso")
    s.factorize(A)
    x = s.solve_factored(b)
    assert s.symmetric_part and 1e-8 < s.skew_residual < 1e-2
    assert np.linalg.norm(A @ x - b) == pytest.approx(s.skew_residual * np.linalg.norm(b))
    exact = np.linalg.solve(A.toarray(), b)
    np.testing.assert_allclose(s.solve(A, b), exact, rtol=1e-12, atol=0)
    assert s.symmetric_part
    with pytest.raises(ValueError, match="right-hand side of 511 unknowns"):  # never MKL's memory error
        s.solve_factored(b[:-1])

    far = _nearly_symmetric(0.9, seed=1)
    x = s.solve(far, b)
    assert not s.symmetric_part and s.skew_residual > 0.1  # LU from now on
    np.testing.assert_allclose(x, np.linalg.solve(far.toarray(), b), rtol=1e-12, atol=0)
    np.testing.assert_allclose(s.solve(A, b), exact, rtol=1e-12, atol=0)
    s.free()

    lower = (sp.tril(_laplacian_3d(8)) + 6.0 * sp.identity(512)).tocsr()  # pattern not symmetric
    with SparseSolver("pardiso") as t:
        np.testing.assert_allclose(t.solve(lower, b), np.linalg.solve(lower.toarray(), b), rtol=1e-12, atol=0)
        assert t._pardiso.mtype == 11
