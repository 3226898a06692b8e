"""Guccione law: closed-form homogeneous stress, frame rotation, and tangents vs finite differences."""
import numpy as np
import pytest

from solver.material import FungParameters, green_lagrange, guccione_energy, guccione_stress_tangent


def test_uniaxial_fibre_stretch_matches_closed_form():
    params = FungParameters(150.0)
    lam = 1.15
    F = np.diag([lam, 1.0, 1.0])[None]
    E = green_lagrange(F)
    S, _ = guccione_stress_tangent(E, params, with_tangent=False)
    e11 = 0.5 * (lam**2 - 1.0)
    expected = 150.0 * np.exp(29.9 * e11**2) * 29.9 * e11
    assert S[0, 0, 0] == pytest.approx(expected, rel=1e-12)
    assert np.allclose(S[0][np.triu_indices(3, 1)], 0.0)


def test_simple_shear_in_fibre_sheet_plane():
    params = FungParameters(100.0)
    g = 0.2
    F = np.eye(3)[None].copy()
    F[0, 0, 1] = g  # x = X + g Y
    E = green_lagrange(F)[0]
    Q = 29.9 * E[0, 0] ** 2 + 13.3 * (E[1, 1] ** 2 + E[2, 2] ** 2 + 2 * E[1, 2] ** 2) + 26.6 * 2 * (E[0, 1] ** 2 + E[0, 2] ** 2)
    S, _ = guccione_stress_tangent(E[None], params, with_tangent=False)
    assert S[0, 0, 1] == pytest.approx(100.0 * np.exp(Q) * 26.6 * E[0, 1], rel=1e-12)
    W = guccione_energy(E[None], params)[0]
    assert W == pytest.approx(50.0 * np.expm1(Q), rel=1e-12)


def test_stress_is_energy_derivative():
    rng = np.random.default_rng(0)
    params = FungParameters(200.0)
    E = rng.normal(scale=0.1, size=(3, 3))
    E = 0.5 * (E + E.T)
    S, _ = guccione_stress_tangent(E[None], params, with_tangent=False)
    h = 1e-6
    for a in range(3):
        for b in range(3):
            d = np.zeros((3, 3))
            d[a, b] += 0.5 * h
            d[b, a] += 0.5 * h
            fd = (guccione_energy((E + d)[None], params) - guccione_energy((E - d)[None], params))[0] / (2 * h)
            # dW/dE_ab for a symmetric perturbation equals S_ab
            assert fd == pytest.approx(S[0, a, b], rel=1e-6, abs=1e-8)


def test_material_tangent_matches_finite_differences():
    rng = np.random.default_rng(1)
    params = FungParameters(120.0)
    E = rng.normal(scale=0.1, size=(3, 3))
    E = 0.5 * (E + E.T)
    _, D = guccione_stress_tangent(E[None], params)
    h = 1e-7
    for c in range(3):
        for d in range(3):
            dE = np.zeros((3, 3))
            dE[c, d] += 0.5 * h
            dE[d, c] += 0.5 * h
            Sp, _ = guccione_stress_tangent((E + dE)[None], params, with_tangent=False)
            Sm, _ = guccione_stress_tangent((E - dE)[None], params, with_tangent=False)
            fd = (Sp - Sm)[0] / (2 * h)
            an = 0.5 * (D[0, :, :, c, d] + D[0, :, :, d, c])
            np.testing.assert_allclose(an, fd, rtol=1e-6, atol=1e-6)
