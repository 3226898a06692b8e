"""Inverse FE from a guess with a rough first state (solver.lv.inverse_solve's `rough_first_state`, what
`unload --method hybrid` runs): the first forward solve on the guessed reference stops far from the preset's
tolerance, and the updates still land on the cold inverse's answer, with fewer factorisations."""
from __future__ import annotations

import numpy as np
import pytest

from solver.linear import SparseSolver
from solver.lv import inverse_solve
from solver.meshing import mesh_lv
from solver.parameters import CaseParameters
from solver.shape_model import lv_shape


@pytest.fixture(scope="module")
def lv():
    return mesh_lv(lv_shape(0, 0, 2), 120)


def test_a_rough_first_state_lands_on_the_cold_answer_with_fewer_factorisations(lv):
    """From `fast`'s unloaded geometry (0.2–0.5 mm from `accurate`'s, as a network's guess is)."""
    params = CaseParameters(9.0, 175.0, 65.0, -65.0)
    cold = inverse_solve(lv, params, "accurate")
    guess = inverse_solve(lv, params, "fast").unloaded_nodes
    assert np.abs(guess - cold.unloaded_nodes).max() > 0.1
    with SparseSolver() as converged_solver, SparseSolver() as rough_solver:
        converged = inverse_solve(lv, params, "accurate", initial_unloaded=guess, linsolve=converged_solver)
        rough = inverse_solve(lv, params, "accurate", initial_unloaded=guess, rough_first_state=True,
                              linsolve=rough_solver)
    assert rough.mismatch_mm <= 1e-4
    assert np.abs(rough.unloaded_nodes - cold.unloaded_nodes).max() <= 1e-3
    assert np.abs(rough.unloaded_nodes - converged.unloaded_nodes).max() <= 1e-4
    assert rough_solver.factorizations < converged_solver.factorizations


def test_rough_first_state_without_a_guess_is_the_cold_inverse(lv):
    """Without a guess the first state is load stepping from the ED mesh either way: the same solve."""
    params = CaseParameters(9.0, 175.0, 65.0, -65.0)
    plain = inverse_solve(lv, params, "fast")
    flagged = inverse_solve(lv, params, "fast", rough_first_state=True)
    assert flagged.stats.newton_iterations == plain.stats.newton_iterations
    assert np.abs(flagged.unloaded_nodes - plain.unloaded_nodes).max() <= 1e-9
