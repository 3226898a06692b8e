"""Statistical shape model of the human LV at end-diastole, drawn from (seed, shape id); every
mode is N(0,1) truncated to [−2, 2] (in SD units).

Version 1 (`MODES`): a truncated prolate-ellipsoid family with six modes whose means and SDs were
set from healthy ranges (EDV 80–220 mL, wall 6–14 mm). Version 2 (`MODES_V2`, SHAPE_MODEL_VERSION,
the default of new stores and of `heartctl mesh`) widens it to healthy and diseased anatomy: thin
walls (5 mm), apical thinning (to ~1 mm), a septum thicker or thinner than the free wall, a
flattened septum, a base opening narrower than the widest section with the widest section lower
down, and an apex off the long axis. Version 3 (`UNIFORM_VERSION`) is version 2's modes and geometry
with each coefficient uniform on [−2, 2] instead: a space-filling draw that meets the family's tails
(thin walls, a thin apex, a tilted apex, several at once) as often as its centre, for training sets
that must cover the anatomy a user's mesh may have rather than its frequency. Versions 2 and 3 mesh
the same truncated ellipsoidal shell (with the thin apex resolved by gmsh) and move its nodes by a
smooth, invertible map (`LVShape.map_nodes`) that keeps the base plane z = 0 and every node's height. Frame of version 2: the septum faces −x.
The CAP atlas of the seed paper cannot be downloaded here, so the modes are geometric; the sources
of each range are in docs/solver.md. A store records the version it was drawn from
(`shape_model_version`; none recorded = 1) and keeps drawing it."""
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
SHAPE_MODEL_VERSION = 2  # the version new stores and `heartctl mesh` draw from
SHAPE_MODEL_VERSIONS = (1, 2, 3)
UNIFORM_VERSION = 3  # version 2's modes, each coefficient uniform on [−TRUNCATION_SD, TRUNCATION_SD]

# Version 2: each mode's mean ± 2 SD is its range (sources: docs/solver.md, "Shape model").
MODES_V2: tuple[ShapeMode, ...] = (
    ShapeMode("cavity_volume_ml", 135.0, 27.5, "mL", "end-diastolic cavity volume, exact (after the map); 80–190 mL"),
    ShapeMode("elongation", 2.3, 0.25, "-", "endocardial long/short semi-axis ratio c/a of the ellipsoid (sphericity); 1.8–2.8"),
    ShapeMode("wall_thickness_mm", 9.0, 2.0, "mm", "equatorial wall thickness (mean over the circumference); 5–13 mm"),
    ShapeMode("base_height", 0.25, 0.1, "-", "height of the base plane above the ellipsoid's equator, × c; 0.05–0.45"),
    ShapeMode("apex_thickness_ratio", 0.6, 0.2, "-", "apical / equatorial wall thickness (apical thinning); 0.2–1.0"),
    ShapeMode("ellipticity", 0.0, 0.04, "-", "short-axis ellipticity e: a_y/a_x = (1+e)/(1−e); ±0.08"),
    ShapeMode("septal_wall_ratio", 1.0, 0.15, "-", "septal / free-wall thickness over the basal two thirds; 0.7–1.3"),
    ShapeMode("septal_flattening", 0.1, 0.05, "-", "septal side of the short-axis sections pulled in by this fraction of the radius (D shape); 0–0.2"),
    ShapeMode("base_narrowing", 0.07, 0.035, "-", "base opening radius narrowed by this fraction, fading out towards the mid-ventricle; 0–0.14"),
    ShapeMode("apex_offset_x_mm", 0.0, 6.0, "mm", "epicardial apex moved off the long axis along x (septum → free wall); ±12 mm"),
    ShapeMode("apex_offset_y_mm", 0.0, 6.0, "mm", "epicardial apex moved off the long axis along y; ±12 mm"),
)
SEPTUM_ANGLE = np.pi  # azimuth of the septum's centre (−x)


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
    version: int = 1
    septal_wall_ratio: float = 1.0  # version 2's node map (identity at these defaults)
    septal_flattening: float = 0.0
    base_narrowing: float = 0.0
    apex_offset_mm: tuple = (0.0, 0.0)

    def has_map(self) -> bool:
        return self.version >= 2

    @property
    def epi_semi_axes_mm(self) -> tuple[float, float, float]:
        t = self.wall_thickness_mm
        return self.endo_ax_mm + t, self.endo_ay_mm + t, self.endo_c_mm + self.apex_thickness_mm

    @property
    def endo_semi_axes_mm(self) -> tuple[float, float, float]:
        return self.endo_ax_mm, self.endo_ay_mm, self.endo_c_mm

    def cavity_volume_ml(self) -> float:
        if self.has_map():
            return _mapped_cavity_mm3(self) / 1000.0
        return _cap_volume(self.endo_ax_mm, self.endo_ay_mm, self.endo_c_mm, self.base_height_mm) / 1000.0

    def wall_volume_ml(self) -> float:
        """The ellipsoidal shell's (version 2: before its map; the mesh's descriptors measure it after)."""
        ax, ay, c = self.epi_semi_axes_mm
        return (_cap_volume(ax, ay, c, self.base_height_mm)
                - _cap_volume(self.endo_ax_mm, self.endo_ay_mm, self.endo_c_mm, self.base_height_mm)) / 1000.0

    def map_nodes(self, nodes: np.ndarray) -> np.ndarray:
        """Version 2's map of the truncated ellipsoidal shell's nodes [n,3] (mm) onto the shape: in
        each plane z = const, (1) the wall is thickened on one side and thinned on the other
        (septal / free-wall ratio), (2) the septal side pulled in (flattening), (3) the section
        scaled towards the base (base narrowing), (4) shifted sideways (apex offset). Every step
        keeps z and is one-to-one within its plane, so the base stays on z = 0 and no element
        turns inside out (tested)."""
        if not self.has_map():
            return np.array(nodes, dtype=float)
        p = np.array(nodes, dtype=float)
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        zc, c, ta, t = -self.base_height_mm, self.endo_c_mm, self.apex_thickness_mm, self.wall_thickness_mm
        r = np.hypot(x, y)
        th = np.arctan2(y, x)
        # (1) regional thickness, in-plane, over the wall between the two ellipse sections
        k = np.sqrt(np.clip(1.0 - ((z - zc) / c) ** 2, 0.0, None))
        kp = np.sqrt(np.clip(1.0 - ((z - zc) / (c + ta)) ** 2, 0.0, None))
        cs, sn = np.cos(th), np.sin(th)
        with np.errstate(divide="ignore", invalid="ignore"):
            r_e = k / np.sqrt((cs / self.endo_ax_mm) ** 2 + (sn / self.endo_ay_mm) ** 2)
            r_p = kp / np.sqrt((cs / (self.endo_ax_mm + t)) ** 2 + (sn / (self.endo_ay_mm + t)) ** 2)
            xi = np.clip(np.where(r_p > r_e, (r - r_e) / (r_p - r_e), 0.0), 0.0, 1.0)
        kappa = (self.septal_wall_ratio - 1.0) / (self.septal_wall_ratio + 1.0)
        depth = (zc - z) / c  # 0 at the equator, 1 at the endocardial apex
        fade = 1.0 - _smoothstep((depth - 0.3) / 0.5)
        r = r + xi * (r_p - r_e) * kappa * np.cos(th - SEPTUM_ANGLE) * fade
        # (2) septal flattening, faded out near the axis
        r = r * _flattening(r, th, self.septal_flattening, _axis_fade_mm(self))
        # (3) base narrowing
        r = r * _narrowing(z, self.base_narrowing, _narrowing_depth_mm(self))
        # (4) apex offset: a shear growing as the square of the depth below the base
        w = (np.clip(-z, 0.0, None) / (self.base_height_mm + c + ta)) ** 2
        p[:, 0] = r * np.cos(th) + self.apex_offset_mm[0] * w
        p[:, 1] = r * np.sin(th) + self.apex_offset_mm[1] * w
        return p


def _cap_volume(ax: float, ay: float, c: float, d: float) -> float:
    """Volume (mm^3) of the ellipsoid x²/ax² + y²/ay² + z²/c² ≤ 1 below the plane z = d."""
    return np.pi * ax * ay * ((d + c) - (d**3 + c**3) / (3.0 * c**2))


def _smoothstep(u):
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _axis_fade_mm(shape: LVShape) -> float:
    return 0.4 * min(shape.endo_ax_mm, shape.endo_ay_mm)


def _narrowing_depth_mm(shape: LVShape) -> float:
    """Depth below the base over which base narrowing fades out: to the equator, at least a third of
    the cavity's length."""
    return max(shape.base_height_mm, 0.35 * (shape.base_height_mm + shape.endo_c_mm))


def _flattening(r, th, amount: float, r0: float):
    """Radial factor of the septal flattening: 1 − amount · max(cos(θ − septum), 0)⁴, faded in over r0."""
    bump = np.clip(np.cos(th - SEPTUM_ANGLE), 0.0, None) ** 4
    return 1.0 - amount * bump * _smoothstep(r / r0)


def _narrowing(z, amount: float, depth_mm: float):
    return 1.0 - amount * _smoothstep(1.0 + z / depth_mm)


def modes(version: int = 1) -> tuple[ShapeMode, ...]:
    check_version(version)
    return MODES if version == 1 else MODES_V2


def check_version(version) -> int:
    if version not in SHAPE_MODEL_VERSIONS:
        raise ValueError(f"shape model version must be one of {', '.join(map(str, SHAPE_MODEL_VERSIONS))}, got {version}")
    return int(version)


def shape_coefficients(shape_id: int, seed: int = 0, version: int = 1) -> np.ndarray:
    """Mode coefficients in SD units, N(0,1) truncated to [−2, 2] (version 3: uniform on [−2, 2]);
    (version, seed, id) → same values, always (version 2 draws its first six modes as version 1 does,
    then its five new ones)."""
    if shape_id < 0:
        raise ValueError(f"shape id must be ≥ 0, got {shape_id}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(shape_id)]))
    n_modes = len(modes(version))
    if version == UNIFORM_VERSION:
        return rng.uniform(-TRUNCATION_SD, TRUNCATION_SD, n_modes)
    out = np.empty(n_modes)
    for k in range(n_modes):
        v = rng.standard_normal()
        while abs(v) > TRUNCATION_SD:
            v = rng.standard_normal()
        out[k] = v
    return out


def shape_from_coefficients(coefficients, shape_id: int = -1, version: int = 1) -> LVShape:
    """Geometry from mode coefficients (SD units): the endocardial short axis a is solved so the
    cavity below the base has exactly the volume of mode 1 (version 2: after its node map)."""
    coefficients = np.asarray(coefficients, dtype=float)
    n_modes = len(modes(version))
    if coefficients.shape != (n_modes,) or not np.all(np.isfinite(coefficients)):
        raise ValueError(f"expected {n_modes} finite shape coefficients")
    if version >= 2:
        return _shape_v2(coefficients, shape_id, version)
    v = {m.name: m.mean + m.sd * c for m, c in zip(MODES, coefficients)}
    k, f, e = v["elongation"], v["base_height"], v["ellipticity"]
    g = (1.0 + f) - (f**3 + 1.0) / 3.0
    a = (v["cavity_volume_ml"] * 1000.0 / (np.pi * k * g)) ** (1.0 / 3.0)
    ratio = np.sqrt((1.0 + e) / (1.0 - e))
    c = k * a
    t = v["wall_thickness_mm"]
    return LVShape(int(shape_id), tuple(float(x) for x in coefficients), a / ratio, a * ratio, c, t,
                   t * v["apex_thickness_ratio"], f * c)


def _shape_v2(coefficients: np.ndarray, shape_id: int, version: int = 2) -> LVShape:
    v = {m.name: m.mean + m.sd * c for m, c in zip(MODES_V2, coefficients)}
    k, f, e = v["elongation"], v["base_height"], v["ellipticity"]
    ratio = np.sqrt((1.0 + e) / (1.0 - e))
    t = v["wall_thickness_mm"]
    extra = dict(version=version, septal_wall_ratio=float(v["septal_wall_ratio"]),
                 septal_flattening=float(v["septal_flattening"]), base_narrowing=float(v["base_narrowing"]),
                 apex_offset_mm=(float(v["apex_offset_x_mm"]), float(v["apex_offset_y_mm"])))
    # the cavity of a unit-size shape after the map (the map's steps that move the endocardium are
    # scale-free), then a scaled to give mode 1's volume
    unit = LVShape(int(shape_id), (), 1.0 / ratio, ratio, k, 0.0, 0.0, f * k, **extra)
    a = (v["cavity_volume_ml"] * 1000.0 / _mapped_cavity_mm3(unit)) ** (1.0 / 3.0)
    c = k * a
    return LVShape(int(shape_id), tuple(float(x) for x in coefficients), a / ratio, a * ratio, c, t,
                   t * v["apex_thickness_ratio"], f * c, **extra)


def _mapped_cavity_mm3(shape: LVShape, n_z: int = 400, n_theta: int = 720) -> float:
    """Cavity volume below z = 0 of the endocardium after the map (sections: ellipse, flattened,
    narrowed; the shear keeps areas), by the midpoint rule over n_z sections."""
    c, zc = shape.endo_c_mm, -shape.base_height_mm
    depth = shape.base_height_mm + c
    z = -depth * (np.arange(n_z) + 0.5) / n_z
    th = np.linspace(0.0, 2 * np.pi, n_theta, endpoint=False)
    k = np.sqrt(np.clip(1.0 - ((z - zc) / c) ** 2, 0.0, None))[:, None]
    cs, sn = np.cos(th)[None, :], np.sin(th)[None, :]
    r = k / np.sqrt((cs / shape.endo_ax_mm) ** 2 + (sn / shape.endo_ay_mm) ** 2)
    r = r * _flattening(r, th[None, :], shape.septal_flattening, _axis_fade_mm(shape))
    r = r * _narrowing(z, shape.base_narrowing, _narrowing_depth_mm(shape))[:, None]
    area = 0.5 * (r ** 2).sum(axis=1) * (2 * np.pi / n_theta)
    return float(area.sum() * depth / n_z)


def lv_shape(shape_id: int, seed: int = 0, version: int = 1) -> LVShape:
    """Shape `shape_id` of the model's `version` at `seed` (version 1 unless asked: stores without a
    recorded version and the solver's benchmarks draw version 1; new stores record theirs)."""
    return shape_from_coefficients(shape_coefficients(shape_id, seed, version), shape_id, version)


def extreme_shapes() -> list[LVShape]:
    """The three most extreme members used by the stability checks: all modes at −2 SD, all at
    +2 SD, and a mixed corner (small, spherical, thick, high base, thin apex, elliptic)."""
    mixed = np.array([-2.0, -2.0, 2.0, 2.0, -2.0, 2.0])
    return [shape_from_coefficients(np.full(len(MODES), -2.0), -1),
            shape_from_coefficients(np.full(len(MODES), 2.0), -2),
            shape_from_coefficients(mixed, -3)]
