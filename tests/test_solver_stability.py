"""Stability past the paper's box: the hardest corner of the extended box that converges (softest wall,
highest pressure, the most extreme shape) on a coarse mesh, with both presets, and a case beyond it
that must fail with its reason and no answer."""
from __future__ import annotations

import math
from dataclasses import replace

import pytest

from solver.meshing import mesh_lv
from solver.parameters import CaseParameters
from solver.shape_model import extreme_shapes
from bench.stability import EXTENDED_BOX, PAPER_BOX, Q_OVERFLOW, region_table, stability_case


@pytest.fixture(scope="module")
def extreme_mesh():
    return mesh_lv(extreme_shapes()[0], 200)  # every mode at −2 SD: small, spherical, thin


def test_corners_hardest_first():
    corners = EXTENDED_BOX.corners()
    assert len(corners) == 16 and len(set(corners)) == 16
    assert (corners[0].pressure_mmhg, corners[0].stiffness_pa) == (30.0, 20.0)
    assert (corners[-1].pressure_mmhg, corners[-1].stiffness_pa) == (2.0, 2000.0)
    assert {p.helix_endo_deg for p in PAPER_BOX.corners()} == {60.0, 70.0}


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["fast", "accurate"])
def test_hardest_extended_corner_converges(extreme_mesh, preset):
    row = stability_case(extreme_mesh, CaseParameters(30.0, 20.0, 80.0, -80.0), preset)
    assert row.ok, row
    assert row.finite and row.roundtrip_mm <= 1e-3 and row.min_jacobian > 0
    assert 0 < row.q_max < Q_OVERFLOW and row.q_headroom > 600
    # the first load step is sized to 4 C of pressure (0.02 of 30 mmHg on 20 Pa), where a quarter was cut
    # back; tests/test_solver_fe.py exercises the cutback at the paper box's soft corner
    assert row.step_cuts == 0
    table = region_table([replace(row, box="extended", shape="all −2 SD")])
    assert "| extended | 30 | 20 | " + preset + " | 1/1 |" in table


def test_beyond_the_box_fails_with_its_reason(extreme_mesh):
    row = stability_case(extreme_mesh, CaseParameters(40.0, 5.0, 80.0, -80.0), "fast")
    assert not row.ok and not row.solved and "roundtrip_mm" not in row.as_dict()
    assert "step size collapsed" in row.reason and math.isfinite(row.wall_s)
    assert "0/1" in region_table([replace(row, box="extended", shape="all −2 SD")])


def test_a_stalled_inverse_fails_early_with_its_reason(monkeypatch):
    """An inverse whose mismatch stops falling is a failure after STALL_UPDATES updates, not after the preset's
    60: the update here leaves the reference where it is, so the mismatch never moves."""
    import solver.lv as lv
    from solver.inverse_failure import STALL_UPDATES, InverseError, stalled

    assert not stalled([4.0, 2.9, 3.8, 1.0, 0.5, 0.3, 0.2, 0.1, 0.05, 0.03, 0.02, 0.01])
    assert stalled([4.0, 2.9] + [2.7] * STALL_UPDATES)
    assert not stalled([2.9] * STALL_UPDATES)  # too few updates to judge
    calls = []

    def still(problem, z, X, mismatch, history, accel, stats, ctx):
        calls.append(len(history))
        return X, z

    monkeypatch.setattr(lv, "_update_reference", still)
    mesh = mesh_lv(extreme_shapes()[0], 120)
    with pytest.raises(InverseError, match=r"stalled: .* largest at \d+ % of the height below the base, azimuth"):
        lv.inverse_solve(mesh, CaseParameters(8.0, 150.0, 60.0, -60.0), "fast")
    assert calls == list(range(1, STALL_UPDATES + 1))
