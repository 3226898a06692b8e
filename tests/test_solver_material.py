"""Guccione law: closed-form homogeneous stress, frame rotation, tangents vs finite differences, and the
Voigt conventions assembly relies on."""
import numpy as np
import pytest

from solver.material import (VOIGT_INDEX, VOIGT_PAIRS, FungParameters, green_lagrange, guccione_energy,
                             guccione_response, voigt_frame_tensors)


def test_uniaxial_fibre_stretch_matches_closed_form():
    params = FungParameters(150.0)
    lam = 1.15
    F = np.diag([lam, 1.0, 1.0])[None]
    E = green_lagrange(F)
    S = guccione_response(E, params).stress
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
    S = guccione_response(E[None], params).stress
    assert S[0, 0, 1] == pytest.approx(100.0 * np.exp(Q) * 26.6 * E[0, 1], rel=1e-12)
    W = guccione_energy(E[None], params)[0]
    assert W == pytest.approx(50.0 * np.expm1(Q), rel=1e-12)


def test_stress_is_energy_derivative():
    rng = np.random.default_rng(0)
    params = FungParameters(200.0)
    E = rng.normal(scale=0.1, size=(3, 3))
    E = 0.5 * (E + E.T)
    S = guccione_response(E[None], params).stress
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
    D = guccione_response(E[None], params).tangent()
    h = 1e-7
    for c in range(3):
        for d in range(3):
            dE = np.zeros((3, 3))
            dE[c, d] += 0.5 * h
            dE[d, c] += 0.5 * h
            Sp = guccione_response((E + dE)[None], params).stress
            Sm = guccione_response((E - dE)[None], params).stress
            fd = (Sp - Sm)[0] / (2 * h)
            an = 0.5 * (D[0, :, :, c, d] + D[0, :, :, d, c])
            np.testing.assert_allclose(an, fd, rtol=1e-6, atol=1e-6)


def test_voigt_tangent_is_the_tensor_tangent_and_the_closed_form():
    """D_v = diag(d) + c σσᵀ read at VOIGT_INDEX is C e^Q [B_ab (δ_ac δ_bd + δ_ad δ_bc)/2 + 2 (B∘E)_ab (B∘E)_cd]."""
    rng = np.random.default_rng(2)
    params = FungParameters(80.0, b_ff=17.0, b_xx=5.0, b_fx=11.0)
    E = rng.normal(scale=0.1, size=(4, 3, 3))
    E = 0.5 * (E + np.swapaxes(E, -1, -2))
    law = guccione_response(E, params)
    B = params.exponent_weights()
    BE = B * E
    scale = 80.0 * np.exp(np.einsum("...ab,...ab->...", BE, E))
    eye = np.eye(3)
    sym = 0.5 * (np.einsum("ac,bd->abcd", eye, eye) + np.einsum("ad,bc->abcd", eye, eye))
    D = scale[:, None, None, None, None] * (B[:, :, None, None] * sym + 2.0 * np.einsum("...ab,...cd->...abcd", BE, BE))
    np.testing.assert_allclose(law.tangent(), D, rtol=1e-13, atol=1e-12 * np.abs(D).max())
    Dv = law.voigt_tangent()
    np.testing.assert_allclose(Dv, np.swapaxes(Dv, -1, -2), rtol=1e-14)
    v = VOIGT_INDEX
    assert all(tuple(VOIGT_PAIRS[v[a, b]]) == (min(a, b), max(a, b)) for a in range(3) for b in range(3))


def test_voigt_frame_tensors_give_strain_stress_and_strain_derivative():
    """ε_v = M_v : E (engineering shears), S = Σ_v σ_v M_v in global components, ∂ε_v/∂F = F M_v."""
    rng = np.random.default_rng(3)
    params = FungParameters(150.0)
    frames = np.linalg.qr(rng.normal(size=(5, 3, 3)))[0]
    F = np.eye(3) + rng.normal(scale=0.1, size=(5, 3, 3))
    M = voigt_frame_tensors(frames)

    def voigt_strain(F):
        E_loc = np.swapaxes(frames, -1, -2) @ green_lagrange(F) @ frames
        engineering = np.where(VOIGT_PAIRS[:, 0] == VOIGT_PAIRS[:, 1], 1.0, 2.0)
        return E_loc[..., VOIGT_PAIRS[:, 0], VOIGT_PAIRS[:, 1]] * engineering

    np.testing.assert_allclose(np.einsum("...vIJ,...IJ->...v", M, green_lagrange(F)), voigt_strain(F), atol=1e-14)
    law = guccione_response(np.swapaxes(frames, -1, -2) @ green_lagrange(F) @ frames, params)
    S = frames @ law.stress @ np.swapaxes(frames, -1, -2)
    np.testing.assert_allclose(np.einsum("...v,...vIJ->...IJ", law.voigt_stress(), M), S, rtol=1e-12, atol=1e-9)
    h = 1e-6
    for i in range(3):
        for J in range(3):
            d = np.zeros((3, 3))
            d[i, J] = h
            fd = (voigt_strain(F + d) - voigt_strain(F - d)) / (2 * h)
            np.testing.assert_allclose((F[:, None] @ M)[..., i, J], fd, atol=1e-9)
