"""Shape model version 2 (the anatomical family): reproducible draws, the anatomy it reaches, mesh
quality at a thin apex; version 1 kept for stores that recorded none; shape descriptors (checked
against an atlas LV's published figures) and `heartctl mesh` printing them."""
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from orchestrator.grid import SweepSpec, resolve_spec
from orchestrator.tasks import mesh_shape
from solver.descriptors import outside_range, range_warning, shape_descriptors
from solver.mesh import check_geometry, scaled_jacobian
from solver.meshing import mesh_lv
from solver.shape_model import (MODES, MODES_V2, SHAPE_MODEL_VERSION, lv_shape, shape_coefficients,
                                shape_from_coefficients)

SAVED = Path(__file__).parent / "data"
FIXTURES = Path(__file__).resolve().parents[2] / "shared" / "fixtures" / "l2u"
if not FIXTURES.is_dir():
    FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "l2u"


def _v2(**modes) -> object:
    """A version 2 shape with the named modes at the given SD values, the others at 0."""
    c = np.zeros(len(MODES_V2))
    names = [m.name for m in MODES_V2]
    for name, v in modes.items():
        c[names.index(name)] = v
    return shape_from_coefficients(c, -1, 2)


def test_version_2_draws_are_reproducible_and_extend_version_1():
    assert SHAPE_MODEL_VERSION == 2 and len(MODES_V2) > len(MODES)
    a, b = shape_coefficients(7, 3, 2), shape_coefficients(7, 3, 2)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a[:len(MODES)], shape_coefficients(7, 3, 1))
    coeffs = np.array([shape_coefficients(i, 0, 2) for i in range(300)])
    assert np.all(np.abs(coeffs) <= 2.0)
    m1, m2 = mesh_lv(lv_shape(3, 0, 2), 150), mesh_lv(lv_shape(3, 0, 2), 150)
    np.testing.assert_array_equal(m1.nodes, m2.nodes)
    np.testing.assert_array_equal(m1.tets, m2.tets)
    with pytest.raises(ValueError, match="version"):
        lv_shape(0, 0, 4)


def test_version_3_draws_version_2_uniformly():
    """Version 3: version 2's modes and geometry, each coefficient uniform on [−2, 2], so the tails (|c| > 1.5:
    a quarter of the draws) come about 2.7× as often as in version 2's truncated normal (9 %)."""
    uniform = np.array([shape_coefficients(i, 0, 3) for i in range(400)])
    normal = np.array([shape_coefficients(i, 0, 2) for i in range(400)])
    assert uniform.shape == normal.shape and np.all(np.abs(uniform) <= 2.0)
    np.testing.assert_array_equal(uniform[5], shape_coefficients(5, 0, 3))
    assert 0.21 < np.mean(np.abs(uniform) > 1.5) < 0.29
    assert np.mean(np.abs(normal) > 1.5) < 0.12
    a, b = lv_shape(4, 0, 3), shape_from_coefficients(uniform[4], 4, 2)
    assert a.version == 3 and a.has_map()
    assert (a.endo_semi_axes_mm, a.epi_semi_axes_mm, a.apex_offset_mm) == (b.endo_semi_axes_mm, b.epi_semi_axes_mm,
                                                                           b.apex_offset_mm)


def test_version_1_meshes_unchanged():
    """A store without a recorded version draws version 1: its meshes are the ones saved before."""
    from storage.meshfiles import read_mesh

    saved = read_mesh(SAVED / "lv_shape0_seed0_nodes120.vtu")
    np.testing.assert_allclose(mesh_lv(lv_shape(0), 120).nodes, saved.nodes, atol=1e-9)
    np.testing.assert_allclose(mesh_shape(0, 0, 120, shape_model_version=1)["mesh"].nodes, saved.nodes, atol=1e-9)
    assert not np.allclose(mesh_shape(0, 0, 120, shape_model_version=2)["mesh"].nodes.shape[0], -1)


@pytest.mark.parametrize("nodes, min_quality", [(350, 0.04), (800, 0.12)])
def test_thin_wall_and_apex_mesh_without_inverted_tets(nodes, min_quality):
    """The family's thinnest corner (a 5 mm wall, a 1 mm apex, the septum thinned by its ratio and
    flattening): its coarse mesh has one layer of tets through a ~3 mm septum."""
    shape = _v2(wall_thickness_mm=-2.0, apex_thickness_ratio=-2.0, septal_wall_ratio=2.0, septal_flattening=2.0,
                base_narrowing=2.0, apex_offset_x_mm=2.0, apex_offset_y_mm=-2.0)
    m = mesh_lv(shape, nodes)
    check_geometry(m.nodes, m.tets)
    assert scaled_jacobian(m.nodes, m.tets).min() > min_quality
    assert 0.85 * nodes <= m.n_nodes <= 1.15 * nodes
    np.testing.assert_allclose(m.nodes[m.base_nodes(), 2], 0.0, atol=1e-12)
    d = shape_descriptors(m)
    assert d.mid_wall_thickness_mm < 6.0
    assert d.apical_wall_thickness_mm < 1.5
    assert d.apex_offset_mm > 12.0
    assert d.cavity_volume_ml == pytest.approx(shape.cavity_volume_ml(), rel=0.06)


def test_version_2_reaches_a_narrow_base_a_low_waist_and_a_flat_septum():
    low = shape_descriptors(mesh_lv(_v2(base_height=2.0, base_narrowing=2.0), 350))
    assert low.base_to_max_radius < 0.85 and low.widest_level >= 0.25
    flat = shape_descriptors(mesh_lv(_v2(septal_flattening=2.0), 350))
    round_ = shape_descriptors(mesh_lv(_v2(septal_flattening=-2.0), 350))  # 0: no flattening
    assert flat.mid_section_non_ellipticity > round_.mid_section_non_ellipticity + 0.01
    uniform = shape_descriptors(mesh_lv(_v2(), 350))
    septal = shape_descriptors(mesh_lv(_v2(septal_wall_ratio=-2.0), 350))  # septum 0.7 × the free wall
    assert septal.sector_thickness_ratio < uniform.sector_thickness_ratio - 0.1


def test_stores_keep_their_shape_model_version():
    new = SweepSpec(shapes=2)
    assert new.shape_model_version == 2 and new.store_attrs()["shape_model_version"] == 2
    old_attrs = {k: v for k, v in SweepSpec(shapes=2).store_attrs().items() if k != "shape_model_version"}
    assert SweepSpec.from_attrs(old_attrs).shape_model_version == 1
    resumed = resolve_spec({"shapes": 5, "seed": None}, stored_attrs=old_attrs)  # grows: still version 1
    assert resumed.shape_model_version == 1 and resumed.conflicts(old_attrs) == []
    assert resolve_spec({"shapes": 5}, local=True, stored_attrs=old_attrs).shape_model_version == 1
    assert any("shape model version" in c for c in SweepSpec(shapes=2).conflicts(old_attrs))
    uniform = resolve_spec({"shapes": 2, "shape_model_version": 3})
    assert uniform.store_attrs()["shape_model_version"] == 3
    v3_attrs = uniform.store_attrs()
    assert resolve_spec({"shapes": 4, "shape_model_version": None}, stored_attrs=v3_attrs).conflicts(v3_attrs) == []
    asked_other = resolve_spec({"shapes": 4, "shape_model_version": 2}, stored_attrs=v3_attrs)
    assert any("shape model version 2 (store has 3)" in c for c in asked_other.conflicts(v3_attrs))


@pytest.mark.skipif(not FIXTURES.is_dir(), reason="shared/fixtures/l2u not present")
def test_descriptors_of_an_atlas_lv():
    """Shape 59 of the seed paper's test split: the figures measured on it for the shape-family
    comparison (mid-wall ~5.0 mm, apex ~0.9 mm, apex off the axis by 8–10°)."""
    from storage.meshfiles import read_mesh

    d = shape_descriptors(read_mesh(FIXTURES / "ED59_10_150_60_60.vtu", "cm"))
    assert d.mid_wall_thickness_mm == pytest.approx(5.0, abs=0.2)
    assert d.apical_wall_thickness_mm == pytest.approx(0.9, abs=0.1)
    assert 10.5 <= d.apex_offset_mm <= 16.2 and 8.0 <= d.apex_tilt_deg <= 10.0
    assert 0.79 <= d.base_to_max_radius <= 0.99 and 0.25 <= d.widest_level <= 0.35
    assert d.wall_to_cavity_volume == pytest.approx(0.47, abs=0.02)
    assert 109 <= d.cavity_volume_ml <= 152


def test_outside_range_names_the_descriptor():
    base = shape_descriptors(mesh_lv(lv_shape(0), 150))
    table = {k: [v * 0.95, v * 1.05] for k, v in base.as_dict().items()}
    table["apex_offset_mm"] = [0.0, 0.0]
    assert outside_range(base, table) == [] and range_warning([]) is None
    thin = shape_descriptors(mesh_lv(shape_from_coefficients([0, 0, -4.0, 0, 0, 0]), 150))  # a 5 mm wall
    out = outside_range(thin, table)
    assert "mid_wall_thickness_mm" in [o["name"] for o in out]
    line = range_warning(out)
    assert out[0]["label"] in line and "`check`" in line and "`method` hybrid" in line and "\n" not in line


def test_cli_mesh_prints_descriptors(tmp_path):
    from cli import app

    r = CliRunner().invoke(app, ["mesh", "--shape", "1", "--nodes", "150", "-o", str(tmp_path / "m.vtu")])
    assert r.exit_code == 0, r.output
    assert "shape model 2" in r.output
    assert "mid-wall thickness" in r.output and "apex offset from the long axis" in r.output
    r = CliRunner().invoke(app, ["mesh", "--shape", "1", "--nodes", "150", "--shape-model", "4",
                                 "-o", str(tmp_path / "m.vtu")])
    assert r.exit_code == 2 and "version" in r.output


def test_generate_refuses_an_unknown_shape_model(tmp_path):
    from cli import app

    res = CliRunner().invoke(app, ["generate", "--store", str(tmp_path / "s.zarr"), "--shape-model", "4", "--dry-run"])
    assert res.exit_code == 2 and "shape model version must be one of 1, 2, 3" in res.output
    assert not (tmp_path / "s.zarr").exists()
