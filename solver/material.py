"""Guccione (Fung-type) transversely isotropic passive law: second Piola-Kirchhoff stress and
its consistent tangent as pure functions of the Green-Lagrange strain, over quadrature points."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FungParameters:
    """W = C/2 (e^Q - 1), Q = b_ff E_ff^2 + b_xx (E_ss^2 + E_nn^2 + 2 E_sn^2) + b_fx (2 E_fs^2 + 2 E_fn^2).

    `stiffness_pa` is C in Pa; the exponents are dimensionless. Defaults are the paper's.
    """

    stiffness_pa: float
    b_ff: float = 29.9
    b_xx: float = 13.3
    b_fx: float = 26.6

    def exponent_weights(self) -> np.ndarray:
        """B with Q = sum_ij B_ij E_ij^2 in the fibre frame (f, s, n)."""
        b_ff, b_xx, b_fx = self.b_ff, self.b_xx, self.b_fx
        return np.array([[b_ff, b_fx, b_fx], [b_fx, b_xx, b_xx], [b_fx, b_xx, b_xx]])


def green_lagrange(F: np.ndarray) -> np.ndarray:
    """E = (F^T F - I) / 2 for F of shape [..., 3, 3]."""
    return 0.5 * (np.einsum("...kI,...kJ->...IJ", F, F) - np.eye(3))



def guccione_energy(E_local: np.ndarray, params: FungParameters) -> np.ndarray:
    """Strain energy density W in Pa at each point, E given in the fibre frame."""
    Q = np.einsum("ab,...ab->...", params.exponent_weights(), E_local * E_local)
    return 0.5 * params.stiffness_pa * np.expm1(Q)


def guccione_stress_tangent(E_local: np.ndarray, params: FungParameters, with_tangent: bool = True):
    """Second Piola-Kirchhoff stress S (Pa) and material tangent dS/dE (Pa), both in the fibre frame.

    S_ab = C e^Q B_ab E_ab;  dS_ab/dE_cd = C e^Q [B_ab I_abcd + 2 (B∘E)_ab (B∘E)_cd],
    with I_abcd = (δ_ac δ_bd + δ_ad δ_bc)/2 the symmetric identity (minor symmetries kept).
    """
    B = params.exponent_weights()
    BE = B * E_local
    Q = np.einsum("...ab,...ab->...", BE, E_local)
    scale = params.stiffness_pa * np.exp(Q)
    S = scale[..., None, None] * BE
    if not with_tangent:
        return S, None
    eye = np.eye(3)
    sym_identity = 0.5 * (np.einsum("ac,bd->abcd", eye, eye) + np.einsum("ad,bc->abcd", eye, eye))
    D = B[:, :, None, None] * sym_identity + 2.0 * np.einsum("...ab,...cd->...abcd", BE, BE)
    D = scale[..., None, None, None, None] * D
    return S, D
