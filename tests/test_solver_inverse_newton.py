"""Inverse FE's Newton–Krylov step (solver/inverse_newton.py): its Jacobian–vector product is the
derivative of the forward map x(X), and the Newton inverse lands where the fixed point does, in fewer
updates on a thin, soft wall."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import solver.lv as lv
from solver.fidelity import get_fidelity
from solver.forward import inflate
from solver.inverse_newton import ReferenceJacobian
from solver.linear import SparseSolver
from solver.meshing import mesh_lv
from solver.parameters import CaseParameters
from solver.shape_model import lv_shape

THIN_SOFT = CaseParameters(14.0, 50.0, 70.0, -70.0)  # the box's hardest corner


@pytest.fixture(scope="module")
def thin_lv():
    return mesh_lv(lv_shape(1, 0, 2), 120)  # version 2, shape 1: mid-wall ~7 mm, a thin apex


def _loaded(mesh, X, params, fid):
    """x(X): the forward solve of reference X, fibres on X, at the vertices."""
    problem = lv.lv_problem(mesh.with_nodes(X), params, fid)
    with SparseSolver() as ls:
        z, _ = inflate(problem, params.pressure_pa, linsolve=ls)
    return X + problem.split(z)[0][: mesh.n_nodes]


@pytest.mark.parametrize("preset", ["fast", "accurate"])
def test_the_jacobian_product_is_the_forward_maps_derivative(thin_lv, preset):
    """J v from one residual on a moved reference and one back-substitution equals the central
    difference of two full forward solves (fibres recomputed on each reference) to 1 %."""
    fid = get_fidelity(preset)
    params = CaseParameters(8.0, 150.0, 60.0, -60.0)
    X = thin_lv.nodes
    problem = lv.lv_problem(thin_lv, params, fid)
    rng = np.random.default_rng(0)
    v = rng.normal(size=X.shape) * (X[:, 2:3] < -5.0)  # a smooth-enough move away from the base plane
    v = v / np.abs(v).max()
    with SparseSolver() as ls:
        z, _ = inflate(problem, params.pressure_pa, linsolve=ls)
        jac = ReferenceJacobian(problem, z, params.pressure_pa, ls,
                                frames_of=lambda Y: lv._frames(thin_lv.with_nodes(Y), params, fid, "laplace"))
        jv = jac.product(v)
        jac.restore()
    h = 1e-3
    fd = (_loaded(thin_lv, X + h * v, params, fid) - _loaded(thin_lv, X - h * v, params, fid)) / (2 * h)
    assert np.abs(jv - fd).max() <= 0.01 * np.abs(fd).max()
    assert np.abs(jv - v).max() > 0.1  # the displacement's own change is not negligible here


@pytest.mark.slow
def test_newton_inverse_lands_where_the_fixed_point_does_in_fewer_updates(thin_lv):
    fid = get_fidelity("accurate")
    newton = lv.inverse_solve(thin_lv, THIN_SOFT, replace(fid, inverse_step="newton"))
    fixed = lv.inverse_solve(thin_lv, THIN_SOFT, replace(fid, inverse_step="fixed-point"))
    assert newton.mismatch_mm <= 1e-4 and fixed.mismatch_mm <= 1e-4
    assert np.abs(newton.unloaded_nodes - fixed.unloaded_nodes).max() <= 1e-3
    assert newton.stats.jacobian_products > 0 and newton.updates < fixed.updates
    assert newton.stats.newton_iterations < fixed.stats.newton_iterations, (newton.stats, fixed.stats)
