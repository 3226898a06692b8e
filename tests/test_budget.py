"""Large meshes: a solve's memory and time are estimated from the mesh size and preset before it starts
(solver.budget); one that cannot fit in the memory available is refused in one line, exit 2, nothing
written; long work (a large mesh target, a long solve) shows progress on stderr, small work nothing."""
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli import app
from solver.budget import estimate_for_nodes, estimate_solve, mesh_counts, unknowns
from storage.meshfiles import read_mesh

DATA = Path(__file__).parent / "data"
MESH = DATA / "lv_shape1_seed0_nodes160.vtu"
runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_the_estimate_grows_with_size_and_preset():
    for nodes in (1_000, 20_000, 134_000):
        fast, accurate, reference = (estimate_for_nodes(p, nodes) for p in ("fast", "accurate", "reference"))
        assert fast.unknowns == 4 * nodes
        assert fast.unknowns < accurate.unknowns < reference.unknowns
        assert fast.peak_bytes < accurate.peak_bytes < reference.peak_bytes
        assert fast.seconds < accurate.seconds < reference.seconds
        inverse = estimate_for_nodes("accurate", nodes, inverse=True)
        assert inverse.peak_bytes > accurate.peak_bytes and inverse.seconds > accurate.seconds
    for preset in ("fast", "accurate", "reference"):
        sizes = [estimate_for_nodes(preset, n) for n in (1_000, 10_000, 100_000)]
        assert sizes[0].peak_bytes < sizes[1].peak_bytes < sizes[2].peak_bytes
        assert sizes[0].seconds < sizes[1].seconds < sizes[2].seconds
    # the measured points it was fitted on (solver/budget.py): 7,702 nodes, accurate, 3.9 GB
    assert 3.5e9 < estimate_solve("accurate", 7702, 43541, 30841, 62458).peak_bytes < 4.5e9
    # the 134k-node fast unload that grew past 10.6 GB before it was stopped
    assert estimate_for_nodes("fast", 134_000, inverse=True).peak_bytes > 10.6e9
    with pytest.raises(ValueError, match="unknown fidelity"):
        estimate_for_nodes("exact", 1000)


def test_counts_of_a_mesh_and_its_refinement():
    from solver.refine import refine_uniform

    lv = read_mesh(MESH)
    edges, faces = mesh_counts(lv.tets, len(lv.endo) + len(lv.epi) + len(lv.base))
    fine = refine_uniform(lv)
    fine_edges, _ = mesh_counts(fine.tets, len(fine.endo) + len(fine.epi) + len(fine.base))
    assert fine.n_nodes == lv.n_nodes + edges and len(fine.tets) == 8 * len(lv.tets)
    assert fine_edges == 2 * edges + 3 * faces + len(lv.tets)
    ref = estimate_solve("reference", lv.n_nodes, edges, len(lv.tets), faces)
    assert ref.unknowns == unknowns(2, fine.n_nodes, fine_edges)


@pytest.mark.parametrize("command", ["solve", "unload"])
def test_a_solve_that_cannot_fit_is_refused_in_one_line(tmp_path, monkeypatch, command):
    monkeypatch.setattr("app.terminal.console.available_memory", lambda: 50e6)
    out = tmp_path / "out.vtu"
    r = run(command, MESH, "--pressure", 8, "--stiffness", 150, "--fidelity", "accurate", "-o", out)
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1, r.output
    inverse = "inverse " if command == "unload" else ""
    assert lines[0].startswith(f"heartctl: error: {MESH}: the accurate {inverse}solve of 168 nodes ("), lines[0]
    assert "MB are available: use --fidelity fast or a coarser mesh" in lines[0]
    assert not out.exists()


def test_a_network_answer_needs_no_solve_budget(tmp_path, monkeypatch):
    """unload --method gnn solves nothing: the memory check does not apply (the shipped network answers)."""
    monkeypatch.setattr("app.terminal.console.available_memory", lambda: 50e6)
    r = run("unload", MESH, "--pressure", 8, "--stiffness", 150, "--method", "gnn", "-o", tmp_path / "x.vtu")
    assert r.exit_code == 0 and "needs about" not in r.output, r.output


def test_a_sweep_whose_workers_cannot_fit_is_refused_in_one_line(tmp_path, monkeypatch):
    """generate estimates one pair's memory at its preset and --nodes, times its local workers, before Ray
    starts: too much is one line naming how many workers fit, and no store is made."""
    monkeypatch.setattr("app.terminal.console.available_memory", lambda: 40e9)
    store = tmp_path / "s.zarr"
    per_worker = estimate_for_nodes("reference", 5_000, inverse=True).peak_bytes
    assert 20e9 < per_worker < 40e9  # one worker fits, two do not
    r = run("generate", "--shapes", 1, "--nodes", 5_000, "--fidelity", "reference", "--num-cpus", 2, "--store", store)
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and "2 workers solving reference pairs of ~5,000-node meshes" in lines[0], r.output
    assert lines[0].endswith("use --num-cpus 1") and not store.exists()


def test_a_long_solve_shows_its_steps_and_a_short_one_nothing(tmp_path, monkeypatch):
    r = run("solve", MESH, "--pressure", 8, "--stiffness", 150, "--fidelity", "fast", "-o", tmp_path / "a.vtu")
    assert r.exit_code == 0 and r.stderr == "", r.output
    quiet = r.stdout
    monkeypatch.setattr("app.terminal.console.SLOW_SOLVE_S", 0.0)
    r = run("solve", MESH, "--pressure", 8, "--stiffness", 150, "--fidelity", "fast", "-o", tmp_path / "b.vtu")
    assert r.exit_code == 0, r.output
    lines = r.stderr.splitlines()
    assert lines[0].startswith(f"heartctl: {MESH}: the fast solve of 168 nodes (672 unknowns) takes about "), lines
    assert lines[0].endswith("(a rough estimate); progress follows")
    steps = [ln for ln in lines[1:] if "load step" in ln]
    assert steps and all(ln.startswith("heartctl: ") for ln in steps) and "100 % of the pressure" in steps[-1], lines
    assert r.stdout.split(":")[0] == quiet.split(":")[0]  # stdout: the same one line
    r = run("unload", MESH, "--pressure", 8, "--stiffness", 150, "--fidelity", "fast", "-o", tmp_path / "c.vtu")
    assert r.exit_code == 0, r.output
    assert "the fast inverse solve of 168 nodes" in r.stderr and "inverse update 0: mismatch" in r.stderr


def test_a_large_mesh_target_says_so_before_gmsh_starts(tmp_path, monkeypatch):
    out = tmp_path / "m.vtu"
    r = run("mesh", "--shape", 1, "--nodes", 160, "-o", out)
    assert r.exit_code == 0 and r.stderr == "", r.output
    monkeypatch.setattr("app.terminal.console.LARGE_MESH_NODES", 100)
    r = run("mesh", "--shape", 1, "--nodes", 160, "-o", out)
    assert r.exit_code == 0, r.output
    first = r.stderr.splitlines()[0]
    assert first.startswith("heartctl: meshing 160 nodes takes about ") and "(gmsh, one thread; a rough estimate)" in first
