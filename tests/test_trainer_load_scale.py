"""output_scale="load": the displacement-size fit on the loading parameters, the per-graph factor
on the decoders' output, and its round trip through the normalisation a checkpoint keeps."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch

from trainer.config import named_config
from trainer.errors import TrainerError
from trainer.data.store_cases import build_training_data
from trainer.data.features import case_graph, mesh_features
from trainer.data.normalisation import Normalisation, fit_load_scale, load_features
from trainer.network.model import build_model
from trainer_fixtures import lv_mesh, make_tiny_store, synthetic_unloaded


def test_fit_recovers_a_power_law_of_pressure_and_stiffness():
    """RMS displacement ∝ P^1.2 · C^−0.6 over the paper's box: the log-quadratic fit in p̂ reproduces
    it within 2 % at grid points it was fitted on and between them."""
    P = np.repeat([4.0, 6.0, 8.0, 10.0, 12.0, 14.0], 6)
    C = np.tile([50.0, 100.0, 150.0, 200.0, 250.0, 300.0], 6)
    rms = 0.05 * P**1.2 * C**-0.6 * 40
    p_hat = np.stack([(P - 4) / 10, (C - 50) / 250, np.zeros_like(P), np.zeros_like(P)], 1)
    box = (4.0, 50.0, 14.0, 300.0)
    coef = fit_load_scale(p_hat, box, rms, disp_scale_mm=2.0)
    assert len(coef) == load_features(p_hat, box).shape[1]
    fitted = 2.0 * np.exp(load_features(p_hat, box) @ np.array(coef))
    assert np.abs(fitted / rms - 1).max() < 0.02
    between = np.array([[0.55, 0.35, 0.0, 0.0]])  # P = 9.5 mmHg, C = 137.5 Pa
    truth = 0.05 * 9.5**1.2 * 137.5**-0.6 * 40
    assert 2.0 * np.exp(load_features(between, box) @ np.array(coef))[0] == pytest.approx(truth, rel=0.02)


def test_features_clip_to_the_grid_box_alike_in_numpy_and_torch():
    p = np.array([[1.7, -0.4, 0.5, 0.2]])
    box = (4.0, 50.0, 14.0, 300.0)
    a = load_features(p, box)
    b = load_features(torch.tensor(p), box).numpy()
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a[0, :3], [1.0, np.log(14.0), np.log(50.0)])  # P clipped to 14 mmHg, C to 50 Pa


@pytest.fixture(scope="module")
def graphs():
    m = lv_mesh(0)
    f = mesh_features(m)
    norm = Normalisation(tuple(m.nodes.mean(axis=0)), 30.0, 2.0, (4, 50, 60, -70), (14, 300, 70, -60))
    return [case_graph(f, [p, c, 65.0, -65.0], norm, synthetic_unloaded(m.nodes, p, c))
            for p, c in ((4.0, 300.0), (14.0, 50.0))]


def test_output_is_the_global_models_times_each_graphs_factor(graphs):
    cfg = replace(named_config("A1ema-wall-d0-load"), hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8)
    coef = (0.5, 1.0, -0.5, 0.02, -0.01, 0.0, 0.1, 0.0)  # ~ P · C^−½
    torch.manual_seed(0)
    plain = build_model(replace(cfg, output_scale="global"), 0.1).eval()
    scaled = build_model(cfg, 0.1, coef).eval()
    missing, unexpected = scaled.load_state_dict(plain.state_dict(), strict=False)
    assert missing == ["load_coef"] and not unexpected
    batch = Batch.from_data_list(graphs)
    with torch.no_grad():
        a = plain(batch)[0]
        b = scaled(batch)[0]
    factor = torch.exp(load_features(batch.params, (4.0, 50.0, 14.0, 300.0)) @ torch.tensor(coef))
    assert factor[1] > 2 * factor[0]  # 14 mmHg / 50 Pa against 4 mmHg / 300 Pa
    torch.testing.assert_close(b, a * factor[batch.batch].unsqueeze(1), atol=1e-6, rtol=1e-5)
    assert torch.equal(build_model(cfg, 0.1).load_coef, torch.zeros(8))  # neutral until fitted
    with pytest.raises(ValueError, match="8 values"):
        build_model(cfg, 0.1, (1.0, 2.0))
    with pytest.raises(TrainerError, match="output_scale"):
        replace(cfg, output_scale="per-node")


def test_training_data_fits_the_scale_on_labelled_training_cases(tmp_path):
    store = make_tiny_store(tmp_path / "t.zarr", shapes=4, pressures=(6.0, 14.0), stiffness=(50.0, 300.0))
    b = build_training_data(store, "shape", seed=0)
    assert len(b.norm.load_coef) == 8
    keys = b.split["train"] + b.split["test"]
    p_hat = np.stack([b.norm.params(b.cases.params[k]) for k in keys])
    predicted = b.norm.disp_scale_mm * np.exp(load_features(p_hat, b.norm.load_box) @ np.array(b.norm.load_coef))
    actual = np.array([np.sqrt(np.mean(b.cases.displacement(k) ** 2)) for k in keys])
    assert actual.max() > 4 * actual.min()  # the loading spans a wide range of displacement sizes
    assert np.abs(predicted / actual - 1).max() < 0.1  # unseen test shapes too
    again = Normalisation.from_dict(b.norm.as_dict())
    assert again == b.norm
    old = {k: v for k, v in b.norm.as_dict().items() if k != "load_coef"}  # a run saved before this field
    assert Normalisation.from_dict(old).load_coef == ()
