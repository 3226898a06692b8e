"""A checkpoint records its training shapes' descriptors; unloading by the network warns (one line,
naming the descriptor) for a mesh outside them, and says nothing for one of its own shapes or with
a checkpoint that records none."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from solver.meshing import mesh_lv
from solver.parameters import CaseParameters
from solver.shape_model import shape_from_coefficients
from trainer.training.checkpoint import load_run, run_checkpoint_path, save_checkpoint
from trainer.config import PAPER, TrainConfig
from trainer.training.loop import fit
from trainer.evaluation.predict import unload_with_network
from trainer_fixtures import lv_mesh, make_tiny_store

SMALL = replace(PAPER, hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8)
PARAMS = CaseParameters(10.0, 150.0, 60.0, -60.0)
OUTSIDE = "outside the network's training shapes"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("shape_range")
    store = make_tiny_store(root / "tiny.zarr", shapes=6)
    cfg = TrainConfig(store=store, config_name="paper-small", model=SMALL, epochs=1, batch_size=4, num_threads=1)
    fit(cfg, root / "run")
    return root / "run"


def _shape_lines(mesh, run_dir) -> list:
    return [w for w in unload_with_network(mesh, PARAMS, run_dir, "gnn").warnings if OUTSIDE in w]


def test_checkpoint_records_training_shapes_descriptors(run):
    state = load_run(run)
    table = state["train_descriptors"]
    assert table["shapes"] == sorted({int(s) for s, _ in state["split"]["train"]})
    assert len(table["mid_wall_thickness_mm"]) == len(table["shapes"]) >= 3
    assert all(8.0 < v < 13.0 for v in table["mid_wall_thickness_mm"])


def test_own_shape_draws_no_warning(run):
    s = load_run(run)["train_descriptors"]["shapes"][0]
    assert _shape_lines(lv_mesh(s), run) == []


def test_thin_wall_draws_a_warning_naming_it(run):
    thin = mesh_lv(shape_from_coefficients([0.0, 0.0, -4.0, 0.0, -1.0, 0.0]), 120)  # a ~5 mm wall
    lines = _shape_lines(thin, run)
    assert len(lines) == 1 and "wall" in lines[0] and "`check`" in lines[0] and "`method` hybrid" in lines[0]


def test_off_axis_apex_draws_a_warning_naming_it(run):
    s = load_run(run)["train_descriptors"]["shapes"][0]
    own = lv_mesh(s)
    nodes = own.nodes.copy()
    depth = -nodes[:, 2] / -nodes[:, 2].min()
    nodes[:, 0] += 13.0 * depth ** 2  # the apex 13 mm off the long axis, the base where it was
    lines = _shape_lines(own.with_nodes(nodes), run)
    assert len(lines) == 1 and "apex offset from the long axis" in lines[0]


def test_checkpoint_without_descriptors_still_loads_and_warns_nothing(run, tmp_path):
    old = tmp_path / "old"
    old.mkdir()
    state = {k: v for k, v in load_run(run).items() if k != "train_descriptors"}
    state.pop("tensors_sha256", None)
    save_checkpoint(run_checkpoint_path(old), state)
    thin = mesh_lv(shape_from_coefficients([0.0, 0.0, -4.0, 0.0, -1.0, 0.0]), 120)
    out = unload_with_network(thin, PARAMS, old, "gnn")
    assert np.all(np.isfinite(out.unloaded_nodes))
    assert not any(OUTSIDE in w for w in out.warnings)
