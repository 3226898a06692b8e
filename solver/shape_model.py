"""Statistical shape model of the human LV at end-diastole: a truncated prolate-ellipsoid family
with six modes, each drawn N(0,1) truncated to [−2, 2] from (seed, shape id).

The CAP atlas of the paper cannot be downloaded here, so the modes are geometric and their means
and SDs are set from published healthy ranges (EDV 80–220 mL, wall 6–14 mm): at ±2 SD every mode
stays inside them, by construction for EDV (mode 1 *is* the cavity volume)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ShapeMode:
    name: str
    mean: float
    sd: float
    unit: str
    meaning: str


MODES: tuple[ShapeMode, ...] = (
    ShapeMode("cavity_volume_ml", 130.0, 22.0, "mL", "end-diastolic cavity volume (size); ±2 SD = 86–174 mL"),
    ShapeMode("elongation", 2.4, 0.2, "-", "endocardial long/short semi-axis ratio c/a (sphericity); 2.0–2.8"),
    ShapeMode("wall_thickness_mm", 10.0, 1.3, "mm", "equatorial wall thickness; 7.4–12.6 mm"),
    ShapeMode("base_height", 0.15, 0.05, "-", "height of the base plane above the equator, × c; 0.05–0.25"),
    ShapeMode("apex_thickness_ratio", 0.8, 0.08, "-", "apical / equatorial wall thickness (apical thinning); 0.64–0.96"),
    ShapeMode("ellipticity", 0.0, 0.04, "-", "short-axis ellipticity e: a_y/a_x = (1+e)/(1−e); ±0.08"),
)
TRUNCATION_SD = 2.0


@dataclass(frozen=True)
class LVShape:
    """One LV at end-diastole. Ellipsoid centre at z = −base_height_mm (base plane z = 0).

    Endocardium: semi-axes (endo_ax_mm, endo_ay_mm, endo_c_mm); epicardium: the same centre,
    (endo_ax + t, endo_ay + t, endo_c + t_apex). Both cut by the base plane z = 0."""

    shape_id: int
    coefficients: tuple[float, ...]
    endo_ax_mm: float
    endo_ay_mm: float
    endo_c_mm: float
    wall_thickness_mm: float
    apex_thickness_mm: float
    base_height_mm: float

    @property
    def epi_semi_axes_mm(self) -> tuple[float, float, float]:
        t = self.wall_thickness_mm
        return self.endo_ax_mm + t, self.endo_ay_mm + t, self.endo_c_mm + self.apex_thickness_mm

    @property
    def endo_semi_axes_mm(self) -> tuple[float, float, float]:
        return self.endo_ax_mm, self.endo_ay_mm, self.endo_c_mm

    def cavity_volume_ml(self) -> float:
        return _cap_volume(self.endo_ax_mm, self.endo_ay_mm, self.endo_c_mm, self.base_height_mm) / 1000.0

    def wall_volume_ml(self) -> float:
        ax, ay, c = self.epi_semi_axes_mm
        return _cap_volume(ax, ay, c, self.base_height_mm) / 1000.0 - self.cavity_volume_ml()


def _cap_volume(ax: float, ay: float, c: float, d: float) -> float:
    """Volume (mm^3) of the ellipsoid x²/ax² + y²/ay² + z²/c² ≤ 1 below the plane z = d."""
    return np.pi * ax * ay * ((d + c) - (d**3 + c**3) / (3.0 * c**2))


def shape_coefficients(shape_id: int, seed: int = 0) -> np.ndarray:
    """Mode coefficients in SD units, N(0,1) truncated to [−2, 2]; (seed, id) → same values, always."""
    if shape_id < 0:
        raise ValueError(f"shape id must be ≥ 0, got {shape_id}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(shape_id)]))
    out = np.empty(len(MODES))
    for k in range(len(MODES)):
        v = rng.standard_normal()
        while abs(v) > TRUNCATION_SD:
            v = rng.standard_normal()
        out[k] = v
    return out


def shape_from_coefficients(coefficients, shape_id: int = -1) -> LVShape:
    """Geometry from mode coefficients (SD units): the endocardial short axis a is solved so the
    cavity below the base has exactly the volume of mode 1."""
    coefficients = np.asarray(coefficients, dtype=float)
    if coefficients.shape != (len(MODES),) or not np.all(np.isfinite(coefficients)):
        raise ValueError(f"expected {len(MODES)} finite shape coefficients")
    v = {m.name: m.mean + m.sd * c for m, c in zip(MODES, coefficients)}
    k, f, e = v["elongation"], v["base_height"], v["ellipticity"]
    g = (1.0 + f) - (f**3 + 1.0) / 3.0
    a = (v["cavity_volume_ml"] * 1000.0 / (np.pi * k * g)) ** (1.0 / 3.0)
    ratio = np.sqrt((1.0 + e) / (1.0 - e))
    c = k * a
    t = v["wall_thickness_mm"]
    return LVShape(int(shape_id), tuple(float(x) for x in coefficients), a / ratio, a * ratio, c, t,
                   t * v["apex_thickness_ratio"], f * c)


def lv_shape(shape_id: int, seed: int = 0) -> LVShape:
    return shape_from_coefficients(shape_coefficients(shape_id, seed), shape_id)


def extreme_shapes() -> list[LVShape]:
    """The three most extreme members used by the stability checks: all modes at −2 SD, all at
    +2 SD, and a mixed corner (small, spherical, thick, high base, thin apex, elliptic)."""
    mixed = np.array([-2.0, -2.0, 2.0, 2.0, -2.0, 2.0])
    return [shape_from_coefficients(np.full(len(MODES), -2.0), -1),
            shape_from_coefficients(np.full(len(MODES), 2.0), -2),
            shape_from_coefficients(mixed, -3)]
