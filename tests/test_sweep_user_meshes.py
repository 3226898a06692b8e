"""generate --meshes: a user's ED meshes (any meshio format, any unit) as the shape set."""
import numpy as np
import pytest
from typer.testing import CliRunner

from cli import app
from solver.meshing import mesh_lv
from solver.shape_model import lv_shape
from storage.meshfiles import write_mesh
from storage.reader import PairReader


@pytest.mark.slow
def test_generate_from_user_meshes_in_cm_and_resume(tmp_path, local_ray):
    folder = tmp_path / "meshes"
    folder.mkdir()
    originals = [mesh_lv(lv_shape(i), 150) for i in range(2)]
    for i, m in enumerate(originals):
        write_mesh(folder / f"patient{i}.vtu", m.with_nodes(m.nodes), units="cm")
    store = tmp_path / "user.zarr"
    args = ["generate", "--meshes", str(folder), "--units", "cm", "--store", str(store), "--pressures", "8",
            "--stiffness", "150", "--endo", "60", "--epi=-60", "--fidelity", "fast", "--num-cpus", "1"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    assert "warning" not in r.output  # the unit given fits the meshes' sizes
    reader = PairReader(str(store))
    assert reader.attrs["shape_source"] == "files" and len(reader.attrs["meshes"]) == 2
    for i, m in enumerate(originals):
        np.testing.assert_allclose(reader.mesh(i).nodes, m.nodes, atol=1e-9)  # cm → mm
        assert np.all(np.isnan(reader.shape_arrays(i)["coefficients"]))
    assert len(reader.done_cases()) == 2
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0 and "nothing to run" in again.output
    import json

    as_json = CliRunner().invoke(app, args + ["--json"])  # one JSON object, as a run gives, not the text line
    assert as_json.exit_code == 0, as_json.output
    report = json.loads(as_json.output.strip().splitlines()[-1])
    assert (report["total"], report["done_before"], report["failed_before"], report["submitted"]) == (2, 2, 0, 0)
    # the same store with other files is refused
    (folder / "patient1.vtu").unlink()
    other = CliRunner().invoke(app, args)
    assert other.exit_code == 2 and "--meshes" in other.output


def test_generate_warns_of_meshes_in_another_unit(tmp_path):
    """cm files without --units: one warning line per file, naming cm; the sweep is not refused."""
    folder = tmp_path / "meshes"
    folder.mkdir()
    for i in range(2):
        write_mesh(folder / f"patient{i}.vtu", mesh_lv(lv_shape(i), 150), units="cm")
    r = CliRunner().invoke(app, ["generate", "--meshes", str(folder), "--store", str(tmp_path / "s.zarr"),
                                 "--pressures", "8", "--stiffness", "150", "--fidelity", "fast", "--dry-run"])
    assert r.exit_code == 0, r.output
    warned = [line for line in r.output.splitlines() if line.startswith("heartctl: warning:")]
    assert [w.split(":")[2].strip() for w in warned] == ["patient0.vtu", "patient1.vtu"], r.output
    assert all(w.endswith("this looks like cm; pass --units cm") for w in warned)


def test_generate_warns_of_a_pressure_beyond_end_diastole(tmp_path):
    # a small calibration (mid pressure 10 mmHg, no warm-started second pair): the warning is the point
    small = ["--shapes", "1", "--stiffness", "150", "--fidelity", "fast", "--nodes", "100", "--no-warm-start",
             "--dry-run", "--store", str(tmp_path / "s.zarr")]
    r = CliRunner().invoke(app, ["generate", "--pressures", "8,10,120", *small])
    assert r.exit_code == 0, r.output
    assert "warning: --pressures 120 mmHg: end-diastolic pressures are 0–40 mmHg" in r.output
    r = CliRunner().invoke(app, ["generate", "--pressures", "8,10,14", *small])
    assert r.exit_code == 0 and "warning" not in r.output, r.output


def test_units_without_meshes_is_refused(tmp_path):
    """--units gives the unit of --meshes files; on a shape-model sweep it would be silently ignored."""
    r = CliRunner().invoke(app, ["generate", "--local", "--store", str(tmp_path / "s.zarr"), "--units", "cm"])
    assert r.exit_code == 2 and "--units gives the length unit of --meshes files" in r.output, r.output
    assert not (tmp_path / "s.zarr").exists()
