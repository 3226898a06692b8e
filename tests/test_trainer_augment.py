"""Rotation about the long axis and scaling about the base as augmentation (trainer.data.augment): one angle
(or factor) per graph, applied to coordinates and labels alike, within the asked range, never writing
the dataset's graphs."""
import math

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch, Data

from trainer.data.augment import rotate_batch, rotate_xy, scale_batch
from trainer.config import TrainConfig
from trainer.errors import TrainerError


def _graph(n: int, seed: int, labelled: bool = True) -> Data:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 3, generator=g)
    y = torch.randn(n, 3, generator=g) if labelled else torch.full((n, 3), float("nan"))
    return Data(x=x, y=y, edge_index=torch.zeros(2, 0, dtype=torch.long))


def _nodes(batch, i: int) -> torch.Tensor:
    """Indices of graph i's nodes in a batch."""
    return (batch.batch == i).nonzero().squeeze(1)


def _angle(before: torch.Tensor, after: torch.Tensor) -> np.ndarray:
    """Per row, the angle (rad) that turns before[:, :2] into after[:, :2]."""
    a = torch.atan2(after[:, 1], after[:, 0]) - torch.atan2(before[:, 1], before[:, 0])
    return np.angle(np.exp(1j * a.double().numpy()))


def test_rotate_xy_quarter_turn_keeps_z():
    v = torch.tensor([[1.0, 0.0, 2.0], [0.0, 3.0, -1.0]], dtype=torch.float64)
    out = rotate_xy(v, torch.tensor([math.pi / 2, math.pi / 2], dtype=torch.float64))
    torch.testing.assert_close(out, torch.tensor([[0.0, 1.0, 2.0], [-3.0, 0.0, -1.0]], dtype=torch.float64))


def test_one_angle_per_graph_for_coordinates_and_labels_alike():
    graphs = [_graph(30, 0), _graph(45, 1), _graph(20, 2, labelled=False)]
    batch = Batch.from_data_list(graphs)
    x0, y0 = batch.x.clone(), batch.y.clone()
    out = rotate_batch(batch, 40.0, torch.Generator().manual_seed(3))
    angles = []
    for i in range(3):
        nodes = _nodes(batch, i)
        a = _angle(x0[nodes], out.x[nodes])
        assert np.ptp(a) < 1e-5  # every node of a graph turns by the same angle
        angles.append(a[0])
        torch.testing.assert_close(out.x[nodes, 2], x0[nodes, 2])  # about z: heights unchanged
        torch.testing.assert_close(out.x[nodes, :2].norm(dim=1), x0[nodes, :2].norm(dim=1))
        if i < 2:
            np.testing.assert_allclose(_angle(y0[nodes], out.y[nodes]), a[0], atol=1e-5)  # the label turns with it
        else:
            assert torch.isnan(out.y[nodes]).all()  # a withheld label stays withheld
    assert all(abs(a) <= math.radians(40.0) + 1e-6 for a in angles)
    assert len({round(float(a), 4) for a in angles}) == 3
    torch.testing.assert_close(graphs[0].x, x0[:30])  # the dataset's graphs are not written


def test_zero_degrees_is_the_identity_and_the_range_is_checked():
    batch = Batch.from_data_list([_graph(10, 0)])
    x = batch.x
    assert rotate_batch(batch, 0.0).x is x
    with pytest.raises(TrainerError, match="`rotate_deg`"):
        TrainConfig(store="s.zarr", rotate_deg=181.0)
    with pytest.raises(TrainerError, match="`rotate_deg`"):
        TrainConfig(store="s.zarr", rotate_deg=-1.0)


def test_scaling_one_factor_per_graph_about_its_base_point():
    graphs = [_graph(30, 0), _graph(45, 1), _graph(20, 2, labelled=False)]
    batch = Batch.from_data_list(graphs)
    x0, y0 = batch.x.clone(), batch.y.clone()
    out = scale_batch(batch, 10.0, torch.Generator().manual_seed(3))
    factors = []
    for i in range(3):
        nodes = _nodes(batch, i)
        pivot = torch.tensor([0.0, 0.0, float(x0[nodes, 2].max())])
        ratio = (out.x[nodes] - pivot).norm(dim=1) / (x0[nodes] - pivot).norm(dim=1)
        assert float(ratio.max() - ratio.min()) < 1e-5  # every node of a graph by the same factor
        s = float(ratio[0])
        torch.testing.assert_close(out.x[nodes], pivot + s * (x0[nodes] - pivot))
        assert float(out.x[nodes, 2].max()) == pytest.approx(float(pivot[2]), abs=1e-6)  # the base stays on its plane
        if i < 2:
            torch.testing.assert_close(out.y[nodes], s * y0[nodes])  # the displacement scales with it
        else:
            assert torch.isnan(out.y[nodes]).all()
        factors.append(s)
    assert all(0.9 - 1e-6 <= s <= 1.1 + 1e-6 for s in factors)
    assert len({round(s, 4) for s in factors}) == 3
    torch.testing.assert_close(graphs[1].x, x0[30:75])  # the dataset's graphs are not written


def test_zero_percent_is_the_identity_and_the_range_is_checked():
    batch = Batch.from_data_list([_graph(10, 0)])
    x = batch.x
    assert scale_batch(batch, 0.0).x is x
    with pytest.raises(TrainerError, match="`scale_pct`"):
        TrainConfig(store="s.zarr", scale_pct=31.0)
    with pytest.raises(TrainerError, match="`scale_pct`"):
        TrainConfig(store="s.zarr", scale_pct=-1.0)
