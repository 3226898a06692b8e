"""Physiological parameters of one case: ED pressure, Guccione stiffness C, helix angles.
CLI units (mmHg, Pa, degrees) are kept here; `pressure_pa` converts once."""
from __future__ import annotations

import math
from dataclasses import dataclass

MMHG_TO_PA = 133.322387415
# End-diastolic pressures stay below this even in heart failure; `generate` warns of higher ones (an
# 80 or 120 is likely a systolic value typed by mistake) but lets the solver decide.
HIGHEST_ED_PRESSURE_MMHG = 40.0
# Guccione C of myocardium is ~10²–10⁴ Pa (the paper's grid 50–300 Pa); beyond this the exponential
# law overflows double precision before the solver can report a failure.
HIGHEST_STIFFNESS_PA = 1e6

BASE_CONDITIONS = ("sliding", "clamped", "spring", "heartfem")  # solver.lv.base_supports
FIBRE_RULES = ("laplace", "heartfem")  # solver.fibres.rule_frames
SOLVE_DIRECTIONS = ("forward", "inverse")  # inflate an unloaded mesh, or unload an ED mesh

PAPER_GRID = {
    "pressure_mmhg": (4.0, 6.0, 8.0, 10.0, 12.0, 14.0),
    "stiffness_pa": (50.0, 100.0, 150.0, 200.0, 250.0, 300.0),
    "helix_endo_deg": (60.0, 65.0, 70.0),
    "helix_epi_deg": (-60.0, -65.0, -70.0),
}


class ParameterError(ValueError):
    """A physiological parameter outside what the solver accepts."""


@dataclass(frozen=True)
class CaseParameters:
    pressure_mmhg: float
    stiffness_pa: float
    helix_endo_deg: float
    helix_epi_deg: float

    def __post_init__(self):
        for name in ("pressure_mmhg", "stiffness_pa", "helix_endo_deg", "helix_epi_deg"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ParameterError(f"{name} must be a finite number, got {value!r}")
        if self.pressure_mmhg <= 0:
            raise ParameterError(f"pressure must be > 0 mmHg, got {self.pressure_mmhg}")
        if not 0 < self.stiffness_pa <= HIGHEST_STIFFNESS_PA:
            raise ParameterError(f"stiffness C must be > 0 and ≤ {HIGHEST_STIFFNESS_PA:g} Pa, got {self.stiffness_pa:g}")
        for name in ("helix_endo_deg", "helix_epi_deg"):
            if abs(getattr(self, name)) > 90:
                raise ParameterError(f"{name} must be within ±90°, got {getattr(self, name)}")

    @property
    def pressure_pa(self) -> float:
        return self.pressure_mmhg * MMHG_TO_PA

    def label(self) -> str:
        return (f"P={self.pressure_mmhg:g} mmHg, C={self.stiffness_pa:g} Pa, "
                f"θendo={self.helix_endo_deg:g}°, θepi={self.helix_epi_deg:g}°")
