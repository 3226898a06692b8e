"""Shape descriptors of an LV mesh (mm): the figures that say whether a mesh is like the shapes a
network was trained on. One pure function, `shape_descriptors(TetMesh) -> ShapeDescriptors`.

Conventions (those of every heartctl mesh): long axis z, base plane at the top (max z), apex at
negative z. "Level" runs from 0 at the base plane to 1 at the endocardial apex (the lowest
endocardial node). Wall thickness at an endocardial node is its distance to the nearest epicardial
node (as `solver.mesh.lv_dimensions` measures it); the apical wall thickness is the height of the
lowest endocardial node above the lowest epicardial one. Short-axis sections are cuts of the
endocardium by planes parallel to the base."""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

MID_LEVELS = (0.35, 0.65)  # the mid-ventricular band (level)
SECTORS = 6  # azimuthal sectors of the mid band for regional thickness
SECTION_LEVELS = np.linspace(0.01, 0.95, 48)  # levels of the short-axis sections


@dataclass(frozen=True)
class ShapeDescriptors:
    """Named shape figures of one LV mesh. Units are in DESCRIPTOR_UNITS (and in each name)."""

    cavity_volume_ml: float  # endocardium closed by the base plane
    wall_volume_ml: float  # sum of the tets' volumes
    wall_to_cavity_volume: float
    cavity_length_mm: float  # base plane to the endocardial apex
    mid_wall_thickness_mm: float  # mean over endocardial nodes of the mid band (levels 0.35–0.65)
    # (apical: the lowest endocardial node's height above the lowest epicardial node)
    apical_wall_thickness_mm: float  # at the endocardial apex
    min_sector_wall_thickness_mm: float  # thinnest of 6 azimuthal sectors of the mid band (sector mean)
    sector_thickness_ratio: float  # thinnest / thickest sector of the mid band (1: uniform wall)
    base_to_max_radius: float  # base opening radius / largest cavity radius (radius = √(area/π) of a section)
    widest_level: float  # level of the widest short-axis section
    apex_offset_mm: float  # distance of the endocardial apex from the base normal through the base opening's centre
    apex_tilt_deg: float  # angle of the base-centre → endocardial-apex line from the base normal
    mid_section_ellipticity: float  # minor / major axis of the mid section's inertia ellipse (1: circular)
    mid_section_non_ellipticity: float  # RMS departure of the mid section's outline from that ellipse, × its radius

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def names(cls) -> tuple:
        return tuple(f.name for f in fields(cls))


DESCRIPTOR_UNITS = {
    "cavity_volume_ml": "mL", "wall_volume_ml": "mL", "wall_to_cavity_volume": "-", "cavity_length_mm": "mm",
    "mid_wall_thickness_mm": "mm", "apical_wall_thickness_mm": "mm", "min_sector_wall_thickness_mm": "mm",
    "sector_thickness_ratio": "-", "base_to_max_radius": "-", "widest_level": "-", "apex_offset_mm": "mm",
    "apex_tilt_deg": "°", "mid_section_ellipticity": "-", "mid_section_non_ellipticity": "-",
}
DESCRIPTOR_LABELS = {
    "cavity_volume_ml": "cavity volume", "wall_volume_ml": "wall volume",
    "wall_to_cavity_volume": "wall / cavity volume", "cavity_length_mm": "cavity length",
    "mid_wall_thickness_mm": "mid-wall thickness", "apical_wall_thickness_mm": "apical wall thickness",
    "min_sector_wall_thickness_mm": "thinnest mid-wall sector", "sector_thickness_ratio": "regional thickness ratio",
    "base_to_max_radius": "base opening / largest cavity radius", "widest_level": "level of the widest section",
    "apex_offset_mm": "apex offset from the long axis", "apex_tilt_deg": "apex tilt",
    "mid_section_ellipticity": "mid-section ellipticity", "mid_section_non_ellipticity": "mid-section non-ellipticity",
}


def _section(nodes: np.ndarray, tris: np.ndarray, z0: float) -> tuple[float, np.ndarray, np.ndarray]:
    """Cut of a triangulated surface by the plane z = z0: (enclosed area, centroid [2], outline
    points [k,2]), the area by Green's theorem over the cut's segments."""
    z = nodes[tris, 2] - z0
    above = z > 0
    n_above = above.sum(axis=1)
    crossing = (n_above == 1) | (n_above == 2)
    pts, segs = [], []
    for t, zz, ab in zip(tris[crossing], z[crossing], above[crossing]):
        p = nodes[t]
        ends = []
        for i, j in ((0, 1), (1, 2), (2, 0)):
            if ab[i] != ab[j]:
                s = zz[i] / (zz[i] - zz[j])
                ends.append(p[i] + s * (p[j] - p[i]))
        if len(ends) != 2:
            continue
        a, b = ends[0][:2], ends[1][:2]
        normal = np.cross(p[1] - p[0], p[2] - p[0])
        # orient each segment along e_z × n so that the outline runs one way round
        direction = np.array([-normal[1], normal[0]])
        if np.dot(b - a, direction) < 0:
            a, b = b, a
        segs.append((a, b))
        pts.append(a)
    if not segs:
        return 0.0, np.zeros(2), np.zeros((0, 2))
    A = np.array([s[0] for s in segs])
    B = np.array([s[1] for s in segs])
    cross = A[:, 0] * B[:, 1] - B[:, 0] * A[:, 1]
    area = 0.5 * cross.sum()
    cx = ((A[:, 0] + B[:, 0]) * cross).sum() / (6.0 * area) if abs(area) > 1e-12 else 0.0
    cy = ((A[:, 1] + B[:, 1]) * cross).sum() / (6.0 * area) if abs(area) > 1e-12 else 0.0
    return abs(float(area)), np.array([cx, cy]), np.array(pts)


def _inertia_ellipse(outline: np.ndarray, centre: np.ndarray, area: float) -> tuple[float, float]:
    """(minor / major axis, RMS departure from the ellipse) of a section outline: the ellipse is the
    one with the outline points' second moments, scaled to the section's area."""
    p = outline - centre
    if len(p) < 6 or area <= 0:
        return float("nan"), float("nan")
    cov = np.cov(p.T)
    w, v = np.linalg.eigh(cov)
    if w.min() <= 0:
        return float("nan"), float("nan")
    ratio = float(np.sqrt(w[0] / w[1]))
    q = p @ v / np.sqrt(w)  # in the principal frame, unit-variance units
    r = np.linalg.norm(q, axis=1)
    return ratio, float(np.sqrt(((r / r.mean() - 1.0) ** 2).mean()))


def shape_descriptors(mesh) -> ShapeDescriptors:
    """Descriptors of an LV TetMesh in mm (tagged endo, epi, base). Pure: reads the mesh only."""
    from .mesh import signed_tet_volumes

    nodes = np.asarray(mesh.nodes, dtype=float)
    endo_n = mesh.endo_nodes()
    z_base = float(nodes[mesh.base_nodes(), 2].mean())
    apex = int(endo_n[np.argmin(nodes[endo_n, 2])])
    length = z_base - float(nodes[apex, 2])
    if length <= 0:
        raise ValueError("the endocardium does not reach below the base plane")
    # cavity: endocardium closed by the base plane (endo normals point into the cavity)
    tri = nodes[mesh.endo]
    area_z = 0.5 * np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2]
    cavity = float(-((tri[:, :, 2].mean(axis=1) - z_base) * area_z).sum()) / 1e3
    wall = float(np.abs(signed_tet_volumes(nodes, mesh.tets)).sum()) / 1e3

    from scipy.spatial import cKDTree

    epi_n = mesh.epi_nodes()
    thickness = cKDTree(nodes[epi_n]).query(nodes[endo_n])[0]
    level = (z_base - nodes[endo_n, 2]) / length

    # base opening: the endocardial ring on the base plane
    base_set = set(mesh.base_nodes().tolist())
    ring = np.array([n for n in endo_n if n in base_set])
    ring_centre = nodes[ring, :2].mean(axis=0) if ring.size else np.zeros(2)
    areas, centres, outlines = [], [], []
    for lv in SECTION_LEVELS:
        a, c, o = _section(nodes, mesh.endo, z_base - lv * length)
        areas.append(a)
        centres.append(c)
        outlines.append(o)
    radii = np.sqrt(np.asarray(areas) / np.pi)
    widest = int(np.argmax(radii))
    base_radius = radii[0]

    mid = (level >= MID_LEVELS[0]) & (level <= MID_LEVELS[1])
    if not mid.any():
        mid = np.abs(level - 0.5) == np.abs(level - 0.5).min()
    mid_nodes = endo_n[mid]
    mid_centre = centres[int(np.argmin(np.abs(SECTION_LEVELS - 0.5)))]
    angle = np.arctan2(nodes[mid_nodes, 1] - mid_centre[1], nodes[mid_nodes, 0] - mid_centre[0])
    sector = np.floor((angle + np.pi) / (2 * np.pi) * SECTORS).astype(int) % SECTORS
    sector_means = np.array([thickness[mid][sector == k].mean() for k in range(SECTORS) if (sector == k).any()])

    k_mid = int(np.argmin(np.abs(SECTION_LEVELS - 0.5)))
    ellipticity, non_ellipticity = _inertia_ellipse(outlines[k_mid], centres[k_mid], areas[k_mid])
    offset = float(np.linalg.norm(nodes[apex, :2] - ring_centre))
    return ShapeDescriptors(
        cavity_volume_ml=cavity, wall_volume_ml=wall, wall_to_cavity_volume=wall / cavity if cavity > 0 else float("nan"),
        cavity_length_mm=length, mid_wall_thickness_mm=float(thickness[mid].mean()),
        apical_wall_thickness_mm=float(nodes[apex, 2] - nodes[epi_n, 2].min()),
        min_sector_wall_thickness_mm=float(sector_means.min()),
        sector_thickness_ratio=float(sector_means.min() / sector_means.max()),
        base_to_max_radius=float(base_radius / radii.max()), widest_level=float(SECTION_LEVELS[widest]),
        apex_offset_mm=offset, apex_tilt_deg=float(np.degrees(np.arctan2(offset, length))),
        mid_section_ellipticity=ellipticity, mid_section_non_ellipticity=non_ellipticity)


def format_descriptors(d: ShapeDescriptors) -> str:
    """One line: every descriptor with its unit."""
    parts = []
    for name, value in d.as_dict().items():
        unit = DESCRIPTOR_UNITS[name]
        parts.append(f"{DESCRIPTOR_LABELS[name]} {value:.3g}{'' if unit == '-' else ' ' + unit}")
    return "; ".join(parts)


# The descriptors a mesh is compared on with a network's training shapes, and the least margin
# beyond the training range (in the descriptor's unit) that counts as outside it.
RANGE_CHECKED = {
    "cavity_volume_ml": 5.0, "wall_to_cavity_volume": 0.03, "mid_wall_thickness_mm": 0.5,
    "apical_wall_thickness_mm": 0.5, "min_sector_wall_thickness_mm": 0.5, "sector_thickness_ratio": 0.03,
    "base_to_max_radius": 0.02, "widest_level": 0.05, "apex_offset_mm": 2.0, "mid_section_non_ellipticity": 0.01,
}
RANGE_MARGIN = 0.1  # × the training range, added on each side


def descriptor_table(descriptors: list) -> dict:
    """Descriptors of several meshes (ShapeDescriptors or dicts) as {name: [values]} (checkpoints)."""
    rows = [d.as_dict() if isinstance(d, ShapeDescriptors) else dict(d) for d in descriptors]
    return {name: [float(r[name]) for r in rows] for name in ShapeDescriptors.names()}


def outside_range(descriptors: ShapeDescriptors, table: dict) -> list[dict]:
    """The descriptors of a mesh that lie outside the range of `table` ({name: [values]}, the
    training shapes'), each range widened by RANGE_MARGIN of its width and at least RANGE_CHECKED's
    margin: [{name, label, unit, value, lo, hi, excess}], the farthest (in range widths) first."""
    out = []
    values = descriptors.as_dict()
    for name, floor in RANGE_CHECKED.items():
        trained = np.asarray([v for v in table.get(name, []) if np.isfinite(v)], dtype=float)
        value = values.get(name)
        if trained.size == 0 or value is None or not np.isfinite(value):
            continue
        lo, hi = float(trained.min()), float(trained.max())
        margin = max(RANGE_MARGIN * (hi - lo), floor)
        if lo - margin <= value <= hi + margin:
            continue
        excess = (lo - value if value < lo else value - hi) / max(hi - lo, floor)
        out.append({"name": name, "label": DESCRIPTOR_LABELS[name], "unit": DESCRIPTOR_UNITS[name],
                    "value": float(value), "lo": lo, "hi": hi, "excess": float(excess)})
    return sorted(out, key=lambda o: -o["excess"])


def range_warning(outside: list[dict], most: int = 3) -> str | None:
    """One line naming the descriptors outside the training shapes' range (None: none are)."""
    if not outside:
        return None

    def fmt(v, unit):
        return f"{v:.3g}{'' if unit == '-' else ' ' + unit}"

    parts = [f"{o['label']} {fmt(o['value'], o['unit'])} (trained {o['lo']:.3g}–{fmt(o['hi'], o['unit'])})"
             for o in outside[:most]]
    more = f" and {len(outside) - most} more" if len(outside) > most else ""
    return (f"the mesh lies outside the network's training shapes: {'; '.join(parts)}{more}; the network "
            f"extrapolates: check its answer with `check`, or use `method` hybrid")
