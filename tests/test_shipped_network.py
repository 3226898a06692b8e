"""The network shipped with heartctl: packaging a trained run (half-precision weights, trade table,
manifest of digests), the digest check before use, and `unload` without --run."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import trainer.shipped as shipped
from cli import app
from storage.meshfiles import write_mesh
from trainer.errors import TrainerError
from trainer.data.features import mesh_features
from trainer_fixtures import lv_mesh, make_tiny_store

runner = CliRunner()
PARAMS = ("--pressure", "10", "--stiffness", "150", "--endo", "60", "--epi", "-60")


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def packaged(tmp_path_factory):
    """A tiny trained run, and its package (network folder, manifest) as heartctl ships one."""
    root = tmp_path_factory.mktemp("shipped")
    store = make_tiny_store(root / "tiny.zarr", shapes=3)
    run_dir = root / "run"
    r = run("train", "--store", store, "--run-dir", run_dir, "--no-ray", "--epochs", 1, "--batch-size", 8,
            "--device", "cpu", "--config", "recommended")
    assert r.exit_code == 0, r.output
    folder, manifest = root / "package" / "network", root / "package" / "manifest.json"
    card = shipped.package_run(run_dir, None, {"trained_on": "a tiny store"}, folder, manifest)
    return run_dir, folder, manifest, card


def test_a_packaged_run_predicts_as_the_run_within_half_precision(packaged):
    run_dir, folder, manifest, card = packaged
    assert shipped.shipped_run(folder, manifest) == folder
    assert card["weights"] == "float16" and card["trained_on"] == "a tiny store"
    assert card["bytes"] < (run_dir / "checkpoint.pt").stat().st_size / 4  # no optimiser state, half the bytes a weight
    mesh = lv_mesh(5)
    items = [(mesh_features(mesh), np.array([10.0, 150.0, 60.0, -60.0]), None)]
    error = shipped.half_precision_error_mm(run_dir, folder, items)
    assert 0 < error < 1e-2  # half precision changes the answer, by far less than the network's own error


def test_a_changed_byte_or_a_missing_file_is_refused(packaged, tmp_path):
    _, folder, manifest, _ = packaged
    copy = tmp_path / "network"
    copy.mkdir()
    data = bytearray((folder / "checkpoint.pt").read_bytes())
    data[len(data) // 2] ^= 0x01
    (copy / "checkpoint.pt").write_bytes(bytes(data))
    with pytest.raises(TrainerError, match="does not match its digest"):
        shipped.shipped_run(copy, manifest)
    with pytest.raises(TrainerError, match="has no shipped network"):
        shipped.shipped_run(tmp_path / "nothing", manifest)
    broken = tmp_path / "manifest.json"
    broken.write_text("{")
    with pytest.raises(TrainerError, match="manifest .* is damaged"):
        shipped.shipped_run(folder, broken)


def test_unload_without_run_uses_the_shipped_network(packaged, tmp_path, monkeypatch):
    _, folder, manifest, _ = packaged
    ed = tmp_path / "ed.vtu"
    write_mesh(ed, lv_mesh(5))
    monkeypatch.setattr(shipped, "NETWORK", folder)
    monkeypatch.setattr(shipped, "MANIFEST", manifest)
    r = run("unload", ed, *PARAMS, "--method", "gnn", "-o", tmp_path / "un.vtu")
    assert r.exit_code == 0, r.output
    assert "by the network shipped with heartctl" in r.output
    monkeypatch.setattr(shipped, "MANIFEST", tmp_path / "absent.json")
    r = run("unload", ed, *PARAMS, "--method", "gnn", "-o", tmp_path / "un2.vtu")
    lines = [ln for ln in r.output.splitlines() if ln.startswith("heartctl: error:")]
    assert r.exit_code == 2 and len(lines) == 1 and "no shipped network" in lines[0], r.output
    assert not (tmp_path / "un2.vtu").exists()
    r = run("unload", ed, *PARAMS, "--method", "fe", "--run", folder, "-o", tmp_path / "un3.vtu")
    assert r.exit_code == 2 and "--run applies to --method gnn|hybrid|auto" in r.output


BUNDLED = Path(__file__).parent / "data" / "shipped_reference_pairs.npz"


def test_the_shipped_network_scores_as_its_model_card_says_on_bundled_reference_pairs():
    """Three held-out meshes of its shape family with their `reference` unloaded geometry
    (scripts/bundle_reference_pairs.py): the network's mean node error is what its manifest recorded when
    it was packaged (to 2 µm: another machine's arithmetic), and no pair is twice as far."""
    from solver.mesh import make_mesh
    from solver.parameters import CaseParameters
    from trainer.evaluation.predict import unload_with_network

    run = shipped.shipped_run()  # the digest check
    data = np.load(BUNDLED)
    errors = []
    for i in range(int(data["count"])):
        mesh = make_mesh(data[f"{i}_nodes"], data[f"{i}_tets"].astype(np.int64), data[f"{i}_endo"].astype(np.int64),
                         data[f"{i}_epi"].astype(np.int64), data[f"{i}_base"].astype(np.int64))
        out = unload_with_network(mesh, CaseParameters(*data[f"{i}_params"]), [run])
        errors.append(np.linalg.norm(out.unloaded_nodes - data[f"{i}_reference"], axis=1))
    card = json.loads(shipped.MANIFEST.read_text())["bundled_pairs_mean_mm"]
    assert np.mean([e.mean() for e in errors]) == pytest.approx(card, abs=2e-3)
    assert all(e.mean() <= 2.0 * card for e in errors)
