"""heartctl mesh / solve / unload / verify: round trip through files, units, and every bad input
(one-line error, exit code 2, no output file); a solve that fails exits 1 with its reason."""
import json
import os
from dataclasses import replace
from pathlib import Path

import meshio
import numpy as np
import pytest
from typer.testing import CliRunner

from cli import app
from solver.meshing import mesh_lv
from solver.shape_model import SHAPE_MODEL_VERSION, lv_shape
from storage.meshfiles import OUTPUT_SUFFIXES, read_mesh, write_mesh

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def lv_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("mesh") / "lv.vtu"
    result = run("mesh", "--shape", 4, "--nodes", 250, "-o", path)
    assert result.exit_code == 0, result.output
    return path


def test_mesh_command_writes_tags_and_fibres(lv_file):
    m = meshio.read(lv_file)
    assert {"transmural", "helix_angle_deg"} <= set(m.point_data)
    assert "fibre" in m.cell_data and "surface" in m.cell_data
    lv = read_mesh(lv_file)
    assert len(lv.endo) and len(lv.epi) and len(lv.base)
    assert m.point_data["helix_angle_deg"].max() == pytest.approx(60.0)


def test_mesh_file_fibres_are_the_field_the_preset_solves_with(lv_file, tmp_path):
    """`fibre`/`sheet` hold the chosen preset's field at each tet's centroid (default accurate: P2 φ),
    `fibre_p1`/`fibre_p2` both fields; the two differ by degrees, so the names matter."""
    m = meshio.read(lv_file)
    cells = {k: v[0] for k, v in m.cell_data.items()}
    np.testing.assert_array_equal(cells["fibre"], cells["fibre_p2"])
    np.testing.assert_array_equal(cells["sheet"], cells["sheet_p2"])
    for name in ("fibre_p1", "fibre_p2", "sheet_p1", "sheet_p2"):
        np.testing.assert_allclose(np.linalg.norm(cells[name], axis=1), 1.0, atol=1e-6)
    angle = np.degrees(np.arccos(np.clip(np.abs((cells["fibre_p1"] * cells["fibre_p2"]).sum(axis=1)), 0, 1)))
    assert 1.0 < angle.mean() < 20.0
    fast = tmp_path / "fast.vtu"
    r = run("mesh", "--shape", 4, "--nodes", 250, "--fidelity", "fast", "-o", fast)
    assert r.exit_code == 0, r.output
    np.testing.assert_array_equal(meshio.read(fast).cell_data["fibre"][0], cells["fibre_p1"])


def test_solver_threads_are_set_or_refused_in_one_line(lv_file, tmp_path, monkeypatch):
    """`solve`, `unload` and `verify` take --threads: it sets the sparse solver's and BLAS's thread
    variables; below 1 is one line, exit 2, nothing written."""
    for var in ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        monkeypatch.setenv(var, "7")
    out = tmp_path / "ed.vtu"
    r = run("solve", lv_file, "--pressure", 8, "--stiffness", 150, "--fidelity", "fast", "--threads", 1, "-o", out)
    assert r.exit_code == 0, r.output
    assert os.environ["MKL_NUM_THREADS"] == os.environ["OMP_NUM_THREADS"] == "1"
    for command in (("solve", lv_file, "--pressure", 8, "--stiffness", 150, "-o", tmp_path / "x.vtu"),
                    ("unload", lv_file, "--pressure", 8, "--stiffness", 150, "-o", tmp_path / "x.vtu"),
                    ("verify", "--problem", "land1")):
        r = run(*command, "--threads", 0)
        assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1 and "--threads" in r.output, r.output
    assert not (tmp_path / "x.vtu").exists()


def test_solve_then_unload_round_trip_in_cm(lv_file, tmp_path):
    lv = read_mesh(lv_file)
    cm_file = tmp_path / "lv_cm.vtu"
    write_mesh(cm_file, lv, units="cm")
    ed = tmp_path / "ed.vtu"
    r = run("solve", cm_file, "--pressure", 9, "--stiffness", 120, "--endo", 65, "--epi", -65,
            "--fidelity", "fast", "--units", "cm", "-o", ed)
    assert r.exit_code == 0, r.output
    ed_mesh = meshio.read(ed)
    assert np.abs(ed_mesh.points).max() < 12  # still in cm
    disp = ed_mesh.point_data["displacement"]
    np.testing.assert_allclose(ed_mesh.points - disp, lv.nodes / 10.0, atol=1e-12)
    unloaded = tmp_path / "unloaded.vtu"
    r = run("unload", ed, "--pressure", 9, "--stiffness", 120, "--endo", 65, "--epi", -65,
            "--fidelity", "fast", "--units", "cm", "--method", "fe", "-o", unloaded)
    assert r.exit_code == 0, r.output
    back = meshio.read(unloaded).points * 10.0
    assert np.linalg.norm(back - lv.nodes, axis=1).max() < 1e-3  # mm


def test_verify_json_land1():
    r = run("verify", "--problem", "land1", "--fidelity", "fast", "--json")
    assert r.exit_code == 0, r.output
    obj = json.loads(r.output.strip().splitlines()[-1])
    assert obj["problem"] == "land1" and obj["fidelity"] == "fast" and 3.5 < obj["deflection_z_mm"] < 4.3


def _write_bad(tmp_path, kind, lv_file):
    lv = read_mesh(lv_file)
    path = tmp_path / f"{kind}.vtu"
    if kind == "garbage":
        path.write_bytes(b"\x00not a mesh at all\xff" * 10)
    elif kind == "triangles":
        meshio.write(path, meshio.Mesh(lv.nodes, [("triangle", lv.epi)]))
    elif kind == "inverted":  # fold the mesh: push one interior node through its neighbours
        surface = np.unique(np.vstack([lv.endo, lv.epi, lv.base]))
        v = np.setdiff1d(np.arange(lv.n_nodes), surface)[0]
        ring = np.unique(lv.tets[np.any(lv.tets == v, axis=1)])
        nodes = lv.nodes.copy()
        nodes[v] += 3.0 * (nodes[ring].mean(axis=0) - nodes[v]) + [0.0, 0.0, 15.0]
        meshio.write(path, meshio.Mesh(nodes, [("tetra", lv.tets)]))
    elif kind == "nan":
        nodes = lv.nodes.copy()
        nodes[3, 1] = np.nan
        meshio.write(path, meshio.Mesh(nodes, [("tetra", lv.tets)]))
    elif kind == "solid":
        from skfem import MeshTet

        from solver.mesh import orient_positive

        box = MeshTet.init_tensor(*(np.linspace(0, 10, 3),) * 2, np.linspace(-10, 0, 3))
        meshio.write(path, meshio.Mesh(box.p.T, [("tetra", orient_positive(box.p.T, box.t.T))]))
    elif kind == "missing":
        pass
    elif kind == "turned":  # tags kept, long axis turned onto x: the base no longer faces +z
        write_mesh(path, lv, nodes_mm=lv.nodes[:, [2, 1, 0]] * [1.0, 1.0, -1.0])
    elif kind == "swapped":  # endocardium and epicardium tags exchanged
        write_mesh(path, replace(lv, endo=lv.epi, epi=lv.endo))
    elif kind == "apex_base":  # the base tag on apical epicardium, the epicardium's on the base
        order = np.argsort(lv.nodes[lv.epi].mean(axis=1)[:, 2])
        write_mesh(path, replace(lv, base=lv.epi[order[:20]], epi=np.vstack([lv.epi[order[20:]], lv.base])))
    elif kind == "floating":  # one separate tet beside the wall
        extra = lv.nodes[lv.tets[0]] + [0.0, 0.0, -200.0]
        nodes = np.vstack([lv.nodes, extra])
        tets = np.vstack([lv.tets, np.arange(lv.n_nodes, lv.n_nodes + 4)[None]])
        meshio.write(path, meshio.Mesh(nodes, [("tetra", tets)]))
    elif kind == "repeated":  # a tet with a repeated node: zero volume exactly
        tets = lv.tets.copy()
        tets[5, 3] = tets[5, 0]
        meshio.write(path, meshio.Mesh(lv.nodes, [("tetra", tets)]))
    elif kind in ("index_past", "index_negative"):  # a tet naming a point the file does not have
        tets = lv.tets.copy()
        tets[7, 2] = lv.n_nodes + 4 if kind == "index_past" else -1
        meshio.write(path, meshio.Mesh(lv.nodes, [("tetra", tets)]))
    elif kind == "huge":  # coordinates ×1e200: numpy would overflow on them
        meshio.write(path, meshio.Mesh(lv.nodes * 1e200, [("tetra", lv.tets)]))
    elif kind == "unused_point":  # a point in no tet: dropping it would renumber the output's nodes
        meshio.write(path, meshio.Mesh(np.vstack([lv.nodes, [[0.0, 0.0, 50.0]]]), [("tetra", lv.tets)]))
    elif kind == "wedges":  # tets plus a few wedge cells, which a tet reader would drop silently
        wedges = np.array([[0, 1, 2, 3, 4, 5], [6, 7, 8, 9, 10, 11]])
        meshio.write(path, meshio.Mesh(lv.nodes, [("tetra", lv.tets), ("wedge", wedges)]))
    elif kind in ("untagged_part", "unknown_tag", "tagged_twice", "endo_tagged_epi"):
        endo, epi = lv.endo, lv.epi
        codes = {"endo": 1, "epi": 2, "base": 3}
        tris = np.vstack([lv.endo, lv.epi, lv.base])
        tags = np.concatenate([np.full(len(lv.endo), 1), np.full(len(lv.epi), 2), np.full(len(lv.base), 3)])
        low = np.argsort(lv.nodes[endo].mean(axis=1)[:, 2])[: len(endo) // 2]  # the apical half of the endocardium
        if kind == "untagged_part":  # the apical endocardium carries no tag
            tris = np.vstack([np.delete(endo, low, axis=0), epi, lv.base])
            tags = np.concatenate([np.full(len(endo) - len(low), 1), np.full(len(epi), 2), np.full(len(lv.base), 3)])
        elif kind == "unknown_tag":
            tags = tags.astype(float)
            tags[:3] = 1.5
        elif kind == "tagged_twice":
            tris, tags = np.vstack([tris, endo[:4]]), np.concatenate([tags, np.full(4, codes["epi"])])
        else:  # a consistent split of the boundary, but the apical endocardium labelled epicardium
            tags[low] = codes["epi"]
        meshio.write(path, meshio.Mesh(lv.nodes, [("tetra", lv.tets), ("triangle", tris)],
                                       cell_data={"surface": [np.zeros(len(lv.tets)), tags]}))
    return path


BAD_MESHES = {
    "garbage": "cannot read mesh file",
    "triangles": "no linear tetrahedra",
    "inverted": "inverted",
    "nan": "NaN",
    "solid": "endocardium",
    "missing": "does not exist",
    "turned": "cut facing +z",
    "swapped": "not inside the epicardium",
    "apex_base": "cut facing +z",
    "floating": "separate pieces",
    "repeated": "degenerate",
    "wedges": "not linear tetrahedra (wedge)",
    "index_past": "tetrahedra refer to point",
    "index_negative": "tetrahedra refer to point -1",
    "unused_point": "1 points that belong to no tetrahedron",
    "huge": "e+201 mm, beyond ±10000 mm: no LV",
    "untagged_part": "carry no surface tag",
    "unknown_tag": "other than 1 (endo)",
    "tagged_twice": "more than one surface tag",
    "endo_tagged_epi": "epicardium is 2 separate pieces",
}


@pytest.mark.parametrize("command", ["solve", "unload"])
@pytest.mark.parametrize("kind", list(BAD_MESHES))
def test_bad_mesh_is_rejected(tmp_path, lv_file, command, kind):
    path = _write_bad(tmp_path, kind, lv_file)
    out = tmp_path / "out.vtu"
    r = run(command, path, "--pressure", 8, "--stiffness", 150, "-o", out)
    assert r.exit_code == 2, r.output
    assert BAD_MESHES[kind] in r.output
    assert len(r.output.strip().splitlines()) == 1
    assert not out.exists() and not list(tmp_path.glob(".out*"))


BAD_PARAMS = [
    (["--pressure", 0, "--stiffness", 150], "pressure must be > 0"),
    (["--pressure", -3, "--stiffness", 150], "pressure must be > 0"),
    (["--pressure", 8, "--stiffness", 0], "stiffness C must be > 0"),
    (["--pressure", 8, "--stiffness", 1e308], "≤ 1e+06 Pa"),
    (["--pressure", 8, "--stiffness", 150, "--endo", 95], "within ±90"),
    (["--pressure", 8, "--stiffness", 150, "--epi", -120], "within ±90"),
    (["--pressure", "nan", "--stiffness", 150], "finite"),
    (["--pressure", 8, "--stiffness", 150, "--fibres", "bogus"], "--fibres must be laplace or heartfem"),
]


def test_the_input_mesh_is_never_the_output(tmp_path, lv_file):
    mine = tmp_path / "mine.vtu"
    mine.write_bytes(Path(lv_file).read_bytes())
    before = mine.read_bytes()
    for command in ("solve", "unload"):
        r = run(command, mine, "--pressure", 8, "--stiffness", 150, "-o", mine)
        assert r.exit_code == 2 and "is the input mesh" in r.output, r.output
    assert mine.read_bytes() == before
    r = run("unload", lv_file, "--pressure", 8, "--stiffness", 150, "--tol-mm", "inf", "-o", tmp_path / "u.vtu")
    assert r.exit_code == 2 and "--tol-mm must be a finite number" in r.output
    assert not (tmp_path / "u.vtu").exists()


@pytest.mark.parametrize("args,message", BAD_PARAMS)
def test_bad_parameters_are_rejected(tmp_path, lv_file, args, message):
    out = tmp_path / "out.vtu"
    r = run("solve", lv_file, *args, "-o", out)
    assert r.exit_code == 2, r.output
    assert message in r.output
    assert not out.exists()


def test_unknown_fidelity_and_units_are_usage_errors(tmp_path, lv_file):
    out = tmp_path / "out.vtu"
    assert run("solve", lv_file, "--pressure", 8, "--stiffness", 150, "--fidelity", "ultra", "-o", out).exit_code == 2
    assert run("solve", lv_file, "--pressure", 8, "--stiffness", 150, "--units", "inch", "-o", out).exit_code == 2
    assert not out.exists()


def test_solve_that_does_not_converge_exits_1_without_output(tmp_path, lv_file):
    out = tmp_path / "out.vtu"
    r = run("solve", lv_file, "--pressure", 1e5, "--stiffness", 50, "--fidelity", "fast", "-o", out)
    assert r.exit_code == 1, r.output
    assert "did not converge" in r.output and "% of load" in r.output
    assert not out.exists()


def test_mesh_command_rejects_bad_shape(tmp_path):
    out = tmp_path / "m.vtu"
    r = run("mesh", "--shape", -1, "-o", out)
    assert r.exit_code == 2 and "shape id" in r.output
    r = run("mesh", "--shape", 0, "--seed", -1, "-o", out)
    assert r.exit_code == 2 and "--seed must be ≥ 0" in r.output
    assert not out.exists()


@pytest.mark.parametrize("args,message", [
    (("bench", "solver", "--nodes", 10), "node count"),
    (("bench", "solver", "--shape", -1, "--nodes", 60), "shape id"),
    (("bench", "solver", "--threads", 0), "--threads"),
    (("bench", "corners", "--nodes", 10), "node count"),
    (("bench", "corners", "--fibres", "random"), "--fibres must be laplace or heartfem"),
])
def test_benchmarks_reject_bad_sizes(args, message):
    r = run(*args)
    assert r.exit_code == 2 and message in r.output, r.output
    assert r.output.count("heartctl: error:") == 1 and "Traceback" not in r.output


def test_output_folder_must_exist(tmp_path, lv_file):
    r = run("solve", lv_file, "--pressure", 8, "--stiffness", 150, "-o", tmp_path / "nope" / "out.vtu")
    assert r.exit_code == 2 and "does not exist" in r.output


def test_a_tagged_base_need_not_be_exactly_flat(tmp_path, lv_file):
    """A base tilted by 2° with 0.3 mm of noise in z (a network's output, a segmentation's cut) still
    reads: the checks only refuse a base that faces sideways or down, or sits away from the top."""
    lv = read_mesh(lv_file)
    rng = np.random.default_rng(0)
    nodes = lv.nodes.copy()
    tilt = np.deg2rad(2.0)
    nodes[:, 2] += np.tan(tilt) * nodes[:, 0]
    base = np.unique(lv.base)
    nodes[base, 2] += rng.normal(0.0, 0.3, base.size)
    path = tmp_path / "uneven.vtu"
    write_mesh(path, lv, nodes_mm=nodes)
    back = read_mesh(path)
    assert len(back.base) == len(lv.base)


@pytest.mark.parametrize("name,message", [
    ("out.stl", ".vtu or .vtk"),  # meshio would write the surface triangles only
    ("out.msh", ".vtu or .vtk"),  # meshio's writer would drop the displacement field
    ("out.xyz", ".vtu or .vtk"),  # no format at all: meshio raised a traceback, after the solve
    ("ro/out.vtu", "not writable"),
])
def test_output_must_hold_tets_in_a_writable_folder(tmp_path, lv_file, monkeypatch, name, message):
    import os

    (tmp_path / "ro").mkdir(mode=0o500)
    if os.access(tmp_path / "ro", os.W_OK):  # root: permissions are not enforced, so say what they would
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p).name == "ro" else real(p, mode))
    for command in ("solve", "unload"):
        r = run(command, lv_file, "--pressure", 8, "--stiffness", 150, "-o", tmp_path / name)
        assert r.exit_code == 2 and message in r.output, r.output
        assert r.output.count("heartctl: error:") == 1 and "Traceback" not in r.output
    assert not list(tmp_path.glob("out*")) and not list((tmp_path / "ro").iterdir())


def test_a_refused_write_is_one_line_and_leaves_nothing(tmp_path, lv_file, monkeypatch):
    def disk_full(tmp, *args, **kwargs):
        Path(tmp).write_bytes(b"partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(meshio, "write", disk_full)  # write_mesh's writer, inside the atomic write
    out = tmp_path / "out.vtu"
    r = run("mesh", "--shape", 0, "--nodes", 120, "-o", out)
    assert r.exit_code == 2 and "No space left on device" in r.output, r.output
    assert r.output.count("heartctl: error:") == 1 and "Traceback" not in r.output
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", OUTPUT_SUFFIXES)
def test_every_output_format_keeps_surfaces_and_fields(tmp_path, suffix):
    """What `mesh` and `unload` write (fibre cell data, displacement point data, tags, cm) reads back."""
    out = tmp_path / f"a{suffix}"
    r = run("mesh", "--shape", 2, "--nodes", 120, "--units", "cm", "-o", out)
    assert r.exit_code == 0, r.output
    lv = mesh_lv(lv_shape(2, version=SHAPE_MODEL_VERSION), 120)  # `mesh` draws the current version
    back = read_mesh(out, units="cm")
    np.testing.assert_array_equal(back.tets, lv.tets)
    np.testing.assert_allclose(back.nodes, lv.nodes, rtol=1e-6, atol=1e-6)
    for surface in ("endo", "epi", "base"):
        assert len(getattr(back, surface)) == len(getattr(lv, surface)) > 0
    m = meshio.read(out)
    assert {"transmural", "helix_angle_deg"} <= set(m.point_data) and {"fibre", "sheet"} <= set(m.cell_data)


def test_shape_model_mesh_written_and_read_back_identically(tmp_path):
    lv = mesh_lv(lv_shape(5), 200)
    path = tmp_path / "a.vtu"
    write_mesh(path, lv)
    back = read_mesh(path)
    np.testing.assert_array_equal(back.tets, lv.tets)
    np.testing.assert_allclose(back.nodes, lv.nodes)
    assert len(back.endo) == len(lv.endo) and len(back.base) == len(lv.base)


def test_a_mesh_with_a_small_void_reads_back(tmp_path):
    """Surfaces found from the geometry leave a small closed void in the wall untagged; the file written
    from that mesh must read back (the tags-cover-the-boundary check spares pieces no tag touches)."""
    from solver.mesh import boundary_facets, make_mesh

    lv = mesh_lv(lv_shape(0), 800)
    skin = np.vstack([lv.endo, lv.epi, lv.base])
    skin_edges = {tuple(sorted(e)) for f in skin for e in ((f[0], f[1]), (f[1], f[2]), (f[0], f[2]))}
    inner = next(i for i, tet in enumerate(lv.tets)  # a tet with no edge on the surface: its removal leaves a void
                 if not any(tuple(sorted((tet[a], tet[b]))) in skin_edges for a in range(4) for b in range(a + 1, 4)))
    holed = make_mesh(lv.nodes, np.delete(lv.tets, inner, axis=0))
    assert len(holed.endo) == len(lv.endo) and len(holed.epi) == len(lv.epi)
    assert len(boundary_facets(holed.tets)) == len(skin) + 4  # the void's four triangles carry no tag
    path = tmp_path / "void.vtu"
    write_mesh(path, holed)
    back = read_mesh(path)
    assert back.n_nodes == holed.n_nodes and len(back.tets) == len(lv.tets) - 1


def test_node_order_is_a_convention_not_an_inversion(tmp_path, lv_file):
    """Writers such as dolfin mix tet node orders; such meshes are valid and get reoriented."""
    lv = read_mesh(lv_file)
    tets = lv.tets.copy()
    tets[::2] = tets[::2][:, [1, 0, 2, 3]]
    path = tmp_path / "mixed.vtu"
    meshio.write(path, meshio.Mesh(lv.nodes, [("tetra", tets)]))
    back = read_mesh(path)
    assert len(back.endo) == len(lv.endo)


@pytest.mark.parametrize("argv,words", [
    (["solve", "x.vtu", "--pressure", "abc", "--stiffness", "150", "-o", "y.vtu"], ["--pressure", "valid number"]),
    (["solve", "x.vtu", "--pressure", "8", "--stiffness", "150", "--fidelity", "ultra", "-o", "y.vtu"],
     ["--fidelity", "ultra"]),
    (["unload", "x.vtu", "--pressure", "8", "--stiffness", "150", "--units", "inch", "-o", "y.vtu"], ["--units"]),
    (["train"], ["--store", "heartctl train --help"]),
    (["bogus"], ["No such command"]),
])
def test_usage_errors_through_the_entry_point_are_one_line_and_exit_2(monkeypatch, capsys, argv, words):
    """`heartctl` (cli:main): click's framed usage box becomes one line, like every other bad input."""
    import sys

    from cli import main

    monkeypatch.setattr(sys, "argv", ["heartctl", *argv])
    with pytest.raises(SystemExit) as exit_:
        main()
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("heartctl: error:") and err.count("\n") == 1, err
    assert all(w in err for w in words), err
    monkeypatch.setattr(sys, "argv", ["heartctl", "--help"])
    with pytest.raises(SystemExit) as exit_:
        main()
    assert exit_.value.code == 0 and "Usage" in capsys.readouterr().out


def test_a_mesh_in_another_unit_draws_one_warning_naming_it(tmp_path, lv_file):
    """A cm mesh read as mm (an LV 8 mm long) solves, with one warning line naming cm; the same file
    with --units cm draws none."""
    lv = read_mesh(lv_file)
    cm_file = tmp_path / "lv_cm.vtu"
    write_mesh(cm_file, lv, units="cm")
    r = run("solve", cm_file, "--pressure", 8, "--stiffness", 150, "--fidelity", "fast", "-o", tmp_path / "a.vtu")
    assert r.exit_code == 0, r.output
    warnings = [line for line in r.output.splitlines() if "warning" in line]
    assert len(warnings) == 1, r.output
    assert warnings[0].startswith("heartctl: warning: lv_cm.vtu: LV long axis 8.")
    assert warnings[0].endswith("this looks like cm; pass --units cm")
    r = run("solve", cm_file, "--units", "cm", "--pressure", 8, "--stiffness", 150, "--fidelity", "fast",
            "-o", tmp_path / "b.vtu")
    assert r.exit_code == 0 and "warning" not in r.output, r.output


def test_units_check_names_the_unit_that_fits(tmp_path, lv_file):
    from solver.mesh import MeshUnitsWarning
    from storage.meshfiles import units_warning

    lv = read_mesh(lv_file)
    assert units_warning(lv, "mm", "lv.vtu") is None and "units_warning" not in lv.info
    with pytest.warns(MeshUnitsWarning, match=r"this looks like mm; pass units=mm$"):
        mesh = read_mesh(lv_file, "cm")  # a mm mesh read as cm: 850 mm long
    assert "looks like mm" in mesh.info["units_warning"]
    metres = tmp_path / "lv_m.vtu"
    write_mesh(metres, lv, units="m")
    with pytest.warns(MeshUnitsWarning, match=r"this looks like m; pass units=m$"):
        read_mesh(metres)
    giant = lv.with_nodes(lv.nodes * 3.0)  # 250 mm long, 30 mm wall, ~3.5 L: no unit makes it a human LV
    assert "outside a human LV's sizes" in units_warning(giant, "mm", "giant.vtu")
    assert units_warning(giant, "mm", "giant.vtu", hint=False).count("--units") == 0


@pytest.mark.parametrize("kind,units", [("huge", "mm"), ("huge", "m"), ("nan", "mm")])
def test_absurd_coordinates_are_one_line_without_numpy_warnings(tmp_path, lv_file, kind, units):
    """Warnings as errors: any overflow warning numpy printed on the way would fail the command."""
    import warnings

    path = _write_bad(tmp_path, kind, lv_file)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = run("solve", path, "--pressure", 8, "--stiffness", 150, "--units", units, "-o", tmp_path / "o.vtu")
    assert r.exit_code == 2, (r.output, r.exception)
    assert len(r.output.strip().splitlines()) == 1 and ("beyond ±10000 mm" in r.output or "NaN" in r.output)


def test_mesh_node_count_has_an_upper_limit(tmp_path):
    for nodes in (100_000_000, 10):
        r = run("mesh", "--shape", 0, "--nodes", nodes, "-o", tmp_path / "m.vtu")
        assert r.exit_code == 2 and f"--nodes must be 50–200,000 (a target node count), got {nodes}" in r.output
    r = runner.invoke(app, ["generate", "--store", str(tmp_path / "s.zarr"), "--nodes", "300000", "--dry-run"])
    assert r.exit_code == 2 and "--nodes must be 50–200,000" in r.output, r.output
    assert not (tmp_path / "m.vtu").exists() and not (tmp_path / "s.zarr").exists()


def test_bench_alone_is_one_line_naming_the_benchmarks():
    r = run("bench")
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
    assert r.output.startswith("heartctl: error: heartctl bench needs a benchmark: solver, corners") and "sweep" in r.output


@pytest.mark.parametrize("command", ["solve", "unload"])
def test_a_pressure_above_end_diastolic_is_warned_by_solve_and_unload(lv_file, tmp_path, monkeypatch, command):
    """One warning line before the solve (the solve itself replaced by a failure here: the warning is
    what is tested)."""
    import solver.lv
    from solver.forward import SolveError

    def no_solve(*args, **kwargs):
        raise SolveError("not solved in this test")

    monkeypatch.setattr(solver.lv, "forward_solve", no_solve)
    monkeypatch.setattr("app.terminal.unloading.unload_or_fail", lambda *a: no_solve())
    r = run(command, lv_file, "--pressure", 200, "--stiffness", 150, "-o", tmp_path / "x.vtu")
    assert r.output.splitlines()[0] == ("warning: --pressure 200 mmHg: end-diastolic pressures are 0–40 mmHg; such "
                                        "cases may take long and fail"), r.output
    quiet = run(command, lv_file, "--pressure", 8, "--stiffness", 150, "-o", tmp_path / "x.vtu")
    assert "warning" not in quiet.output


@pytest.mark.slow
def test_unload_adaptive_writes_its_error_estimate(lv_file, tmp_path):
    """--fidelity adaptive --tolerance-mm X: accurate, then refined where the indicator is largest; the
    output carries the estimated nodal error; without a tolerance, or with a network method, one line
    and exit 2, nothing written."""
    out = tmp_path / "adaptive.vtu"
    base = ("unload", lv_file, "--pressure", 8, "--stiffness", 150, "-o", out)
    r = run(*base, "--fidelity", "adaptive", "--tolerance-mm", 5.0)
    assert r.exit_code == 0, r.output
    assert "adaptive" in r.output and "tolerance 5 mm met" in r.output
    m = meshio.read(out)
    assert m.points.shape[0] == read_mesh(lv_file).n_nodes
    estimate = m.point_data["estimated_error"]
    assert np.all(np.isfinite(estimate)) and np.percentile(estimate, 95) <= 5.0
    out.unlink()
    for extra in (("--fidelity", "adaptive"), ("--fidelity", "adaptive", "--tolerance-mm", 0.1, "--method", "gnn"),
                  ("--fidelity", "adaptive", "--tolerance-mm", -1)):
        r = run(*base, *extra)
        assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
        assert not out.exists()


def test_bench_solver_times_each_preset_at_both_cases_and_its_pairs_round_trip():
    """`bench solver --json`: one line per preset and case, its time split adding up, its pair's round trip
    within the preset's tolerance."""
    r = run("bench", "solver", "--fidelity", "fast", "--nodes", 150, "--json")
    assert r.exit_code == 0, r.output
    rows = [json.loads(line) for line in r.output.strip().splitlines() if line.startswith("{")]
    assert [(row["fidelity"], row["case"].split()[0]) for row in rows] == [("fast", "mid"), ("fast", "extreme")]
    for row in rows:
        assert row["forward_assembly_s"] + row["forward_linear_s"] + row["forward_other_s"] == pytest.approx(row["forward_s"])
        assert row["roundtrip_mm"] < 1e-3 and row["inverse_updates"] >= 1 and row["dofs"] > 3 * row["nodes"] // 2
