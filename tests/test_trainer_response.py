"""node_features="wall-response": the mesh's linear FE response as node input — the small-load limit
of the forward solve, unchanged by scaling and turning with the mesh like the unloading displacement
(so the augmentations stay exact), and reaching the encoder only when configured."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch

from solver.lv import forward_solve, linear_response
from solver.parameters import CaseParameters
from trainer.data.augment import rotate_batch
from trainer.config import named_config
from trainer.data.features import case_graph, linear_response_feature, mesh_features
from trainer.data.normalisation import Normalisation
from trainer.network.model import build_model
from trainer_fixtures import lv_mesh, synthetic_unloaded

PARAMS = CaseParameters(1.0, 150.0, 65.0, -65.0)


def test_linear_response_is_the_small_load_limit_of_the_forward_solve():
    m = lv_mesh(0)
    per_pa = linear_response(m, PARAMS, "fast")
    small = CaseParameters(0.002, 150.0, 65.0, -65.0)
    forward = forward_solve(m, small, "fast").displacement / small.pressure_pa
    assert np.abs(per_pa).max() > 1e-4  # mm per Pa: it moves
    assert np.abs(per_pa - forward).max() < 0.01 * np.abs(forward).max()


def test_feature_is_unchanged_by_scaling_and_turns_with_the_mesh():
    m = lv_mesh(1)
    u = linear_response_feature(m)
    assert 0.05 < np.sqrt((u**2).mean()) < 5  # of order one
    base_point = np.array([m.nodes[:, 0].mean(), m.nodes[:, 1].mean(), m.nodes[:, 2].max()])
    scaled = m.with_nodes(base_point + 1.08 * (m.nodes - base_point))
    np.testing.assert_allclose(linear_response_feature(scaled), u, rtol=0, atol=1e-6 * np.abs(u).max())
    a = np.radians(40.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    axis = np.array([3.0, -2.0, 0.0])  # an off-centre z line
    turned = m.with_nodes((m.nodes - axis) @ rot.T + axis)
    np.testing.assert_allclose(linear_response_feature(turned), u @ rot.T, rtol=0, atol=1e-6 * np.abs(u).max())


@pytest.fixture(scope="module")
def graph():
    m = lv_mesh(0)
    norm = Normalisation(tuple(m.nodes.mean(axis=0)), 30.0, 2.0, (4, 50, 60, -70), (14, 300, 70, -60))
    return case_graph(mesh_features(m), [8.0, 150.0, 65.0, -65.0], norm, synthetic_unloaded(m.nodes, 8.0, 150.0),
                      response=True)


def test_rotation_augmentation_turns_the_response_too(graph):
    batch = rotate_batch(Batch.from_data_list([graph]), 180.0, torch.Generator().manual_seed(0))
    turned_x = batch.x[:, :2].norm(dim=1)
    np.testing.assert_allclose(turned_x.numpy(), graph.x[:, :2].norm(dim=1).numpy(), rtol=1e-5)
    assert not torch.allclose(batch.response, graph.response)
    cos_x = torch.nn.functional.cosine_similarity(batch.x[:, :2], graph.x[:, :2], dim=1)[0]
    cos_r = torch.nn.functional.cosine_similarity(batch.response[:, :2], graph.response[:, :2], dim=1)
    torch.testing.assert_close(cos_r, torch.full_like(cos_r, float(cos_x)), atol=1e-4, rtol=0)  # one angle
    torch.testing.assert_close(batch.response[:, 2], graph.response[:, 2])


def test_response_reaches_the_encoder_only_when_configured(graph):
    moved = graph.clone()
    moved.response = -graph.response
    for name, changes in (("A1ema-resp-d0", True), ("A1ema-wall-d0", False)):
        torch.manual_seed(0)
        model = build_model(named_config(name), 0.1).eval()
        with torch.no_grad():
            a = model(Batch.from_data_list([graph]))[0]
            b = model(Batch.from_data_list([moved]))[0]
        assert (not torch.allclose(a, b, atol=1e-6)) == changes, name
    bare = graph.clone()
    del bare.response
    with pytest.raises(ValueError, match="response=True"):
        build_model(named_config("A1ema-resp-d0"), 0.1)(Batch.from_data_list([bare]))
