"""The same (shape model version, seed, shape, nodes) gives the same mesh, byte for byte, whatever runs
beside it and whatever the user's gmsh settings: meshes made in three processes at once, each with a
~/.gmsh-options that asks for two surface-meshing threads and another 2D algorithm, equal the mesh
made here. gmsh reads ~/.gmshrc and ~/.gmsh-options at initialize unless told not to, and meshes
surfaces in parallel threads (whose order depends on the load) when Mesh.MaxNumThreads2D > 1."""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("gmsh")

ROOT = Path(__file__).resolve().parents[1]
CASES = ((3, 120), (5, 120))  # shape 3 at 120 nodes came out with 374 tets instead of 373 under load
MESH_DIGESTS = """
import hashlib, sys
sys.path.insert(0, {root!r})
from solver.meshing import mesh_lv
from solver.shape_model import lv_shape
for shape, nodes in {cases!r}:
    m = mesh_lv(lv_shape(shape, 0), nodes)
    print(shape, nodes, len(m.tets), hashlib.sha256(m.nodes.tobytes() + m.tets.tobytes()).hexdigest())
"""
USER_GMSH_OPTIONS = "Mesh.MaxNumThreads2D = 2;\nMesh.MaxNumThreads3D = 2;\nMesh.Algorithm = 5;\n"


def _digests_here() -> list[str]:
    from solver.meshing import mesh_lv
    from solver.shape_model import lv_shape

    lines = []
    for shape, nodes in CASES:
        m = mesh_lv(lv_shape(shape, 0), nodes)
        lines.append(f"{shape} {nodes} {len(m.tets)} {hashlib.sha256(m.nodes.tobytes() + m.tets.tobytes()).hexdigest()}")
    return lines


@pytest.mark.slow
def test_concurrent_meshing_with_user_gmsh_settings_gives_the_same_mesh(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    (home / ".gmsh-options").write_text(USER_GMSH_OPTIONS)
    env = {**os.environ, "HOME": str(home), "OMP_NUM_THREADS": "2"}
    script = MESH_DIGESTS.format(root=str(ROOT), cases=CASES)
    procs = [subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.PIPE, text=True)
             for _ in range(3)]
    outputs = [p.communicate(timeout=120)[0].split("\n")[:-1] for p in procs]
    assert all(p.returncode == 0 for p in procs)
    expected = _digests_here()
    assert outputs == [expected] * 3


@pytest.mark.slow
def test_the_sweep_meshes_each_shape_in_a_fresh_process(monkeypatch):
    """A store's mesh does not depend on the state of the worker that made it: state changed here (a
    stand-in for whatever a long-lived worker accumulates) reaches meshes made in this process, not the
    sweep's."""
    import numpy as np

    import solver.meshing as meshing
    from orchestrator.tasks import mesh_shape
    from solver.shape_model import lv_shape

    clean = meshing.mesh_lv(lv_shape(1, 0, 2), 120)
    monkeypatch.setattr(meshing, "APEX_ELEMENTS_PER_MM", 1.0)
    assert meshing.mesh_lv(lv_shape(1, 0, 2), 120).n_nodes != clean.n_nodes  # the state does reach this process
    swept = mesh_shape(1, 0, 120, shape_model_version=2)["mesh"]
    assert np.array_equal(swept.nodes, clean.nodes) and np.array_equal(swept.tets, clean.tets)
    assert np.array_equal(swept.endo, clean.endo) and swept.info["size_mm"] == clean.info["size_mm"]
