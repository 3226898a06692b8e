"""The sparse-matrix GAT layer against torch_geometric's GATConv: same outputs and gradients with
the same weights (concatenated and single heads, with and without existing self loops), and a model
state dict that loads and predicts the same with either kernel."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch
from torch_geometric.nn import GATConv

from trainer.config import TrainConfig, named_config
from trainer.data.features import mesh_features
from trainer.network.model import build_model
from trainer.network.sparse_gat import AttentionGraph, SparseGATConv
from trainer_fixtures import lv_mesh


@pytest.fixture(scope="module")
def lv_edges():
    m = lv_mesh(0)
    return mesh_features(m).edge_index, m.n_nodes


def _lv_batch(shape: int) -> Batch:
    """One unlabelled case on a real LV mesh, as a batch of one graph."""
    from trainer.data.features import case_graph
    from trainer.data.normalisation import Normalisation

    m = lv_mesh(shape)
    norm = Normalisation(tuple(m.nodes.mean(axis=0)), 30.0, 2.0, (4, 50, 60, -70), (14, 300, 70, -60))
    return Batch.from_data_list([case_graph(mesh_features(m), [8.0, 150.0, 65.0, -65.0], norm)])


@pytest.mark.parametrize("heads,out,concat,self_loops", [(4, 16, True, False), (1, 3, True, True), (3, 5, False, False)])
def test_matches_pyg_gatconv(lv_edges, heads, out, concat, self_loops):
    edge_index, n = lv_edges
    if self_loops:  # an input that already holds some self loops: GATConv replaces them by one each
        loops = torch.arange(0, n, 7).repeat(2, 1)
        edge_index = torch.cat([edge_index, loops], dim=1)
    torch.manual_seed(0)
    ref = GATConv(6, out, heads=heads, concat=concat)
    ours = SparseGATConv(6, out, heads=heads, concat=concat)
    ours.load_state_dict(ref.state_dict())
    x = torch.randn(n, 6, dtype=torch.float64)
    ref, ours = ref.double(), ours.double()
    w = torch.randn(n, heads * out if concat else out, dtype=torch.float64)
    xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
    ya, yb = ref(xa, edge_index), ours(xb, AttentionGraph.from_edge_index(edge_index, n))
    torch.testing.assert_close(yb, ya, rtol=1e-10, atol=1e-12)
    (ya * w).sum().backward()
    (yb * w).sum().backward()
    torch.testing.assert_close(xb.grad, xa.grad, rtol=1e-10, atol=1e-12)
    for name, p in ours.named_parameters():
        torch.testing.assert_close(p.grad, dict(ref.named_parameters())[name].grad, rtol=1e-9, atol=1e-12)


def test_plain_edge_index_and_shared_graph_agree(lv_edges):
    edge_index, n = lv_edges
    torch.manual_seed(1)
    conv = SparseGATConv(3, 8, heads=2)
    x = torch.randn(n, 3)
    graph = AttentionGraph.from_edge_index(edge_index, n)
    torch.testing.assert_close(conv(x, edge_index), conv(x, graph))
    assert graph.n_edges == edge_index.shape[1] + n  # one self loop per node


def test_checkpoint_interchanges_between_kernels(lv_edges):
    """A state dict of the pyg-kernel model loads into the sparse one (old checkpoints) and predicts
    the same; the kernel is not part of a run's identity."""
    batch = _lv_batch(0)
    small = replace(named_config("gat-decoder"), hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8)
    torch.manual_seed(2)
    pyg = build_model(replace(small, gat_kernel="pyg"), 0.1).eval()
    sparse = build_model(replace(small, gat_kernel="sparse"), 0.1).eval()
    sparse.load_state_dict(pyg.state_dict())
    with torch.no_grad():
        a, b = pyg(batch), sparse(batch)
    torch.testing.assert_close(b[0], a[0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(b[1], a[1], rtol=1e-4, atol=1e-5)
    ident = [TrainConfig(store="s", model=replace(small, gat_kernel=k)).identity() for k in ("pyg", "sparse")]
    assert ident[0] == ident[1]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("bf16", [False, True])
def test_cuda_kernel_matches_pyg(lv_edges, bf16):
    """On a GPU (cuSPARSE SpMM / SDDMM), fp32 and under bf16 autocast (the sparse product runs in fp32)."""
    edge_index, n = lv_edges
    dev = torch.device("cuda")
    torch.manual_seed(3)
    ref = GATConv(6, 16, heads=4).to(dev)
    ours = SparseGATConv(6, 16, heads=4).to(dev)
    ours.load_state_dict(ref.state_dict())
    x = torch.randn(n, 6, device=dev)
    ei = edge_index.to(dev)
    with torch.autocast("cuda", dtype=torch.bfloat16, enabled=bf16):
        ya, yb = ref(x, ei), ours(x, AttentionGraph.from_edge_index(ei, n))
        (yb.float().square().sum()).backward()
    tol = dict(rtol=3e-2, atol=3e-2) if bf16 else dict(rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(yb.float(), ya.float(), **tol)
    assert all(torch.isfinite(p.grad).all() for p in ours.parameters())


def _prepared_setup(device, gat_kernel="sparse"):
    from trainer.network.prepared import PreparedCase

    batch = _lv_batch(1).to(device)
    torch.manual_seed(4)
    model = build_model(replace(named_config("paper"), hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8,
                                gat_kernel=gat_kernel), 0.1).to(device).eval()
    return model, batch, PreparedCase(model, batch)


def test_prepared_case_matches_the_model():
    """Mesh-only work done once; new coordinates/parameters copied in give the model's answer."""
    model, batch, run = _prepared_setup("cpu")
    x2, p2 = batch.x + 0.01 * torch.randn_like(batch.x), torch.rand(1, 4)
    other = batch.clone()
    other.x, other.params = x2, p2
    with torch.no_grad():
        expect = model(other, cycle=False)[0]
    torch.testing.assert_close(run(x2, p2), expect)
    assert run.cuda_graph is None  # CPU: eager with the prepared graph


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_prepared_case_cuda_graph_replays():
    model, batch, run = _prepared_setup("cuda")
    assert run.cuda_graph is not None, run.capture_error
    x2 = batch.x + 0.01 * torch.randn_like(batch.x)
    other = batch.clone()
    other.x = x2
    with torch.no_grad():
        expect = model(other, cycle=False)[0]
    torch.testing.assert_close(run(x2), expect, rtol=1e-4, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_prepared_case_not_capturable_stays_eager_and_leaves_dropout_working():
    """PyG's GATConv waits for the GPU (boolean masks): no capture is tried, the answer is the
    model's, and training with dropout afterwards works (a failed capture used to break it)."""
    model, batch, run = _prepared_setup("cuda", gat_kernel="pyg")
    assert run.cuda_graph is None and "not capturable" in run.capture_error
    with torch.no_grad():
        expect = model(batch, cycle=False)[0]
    torch.testing.assert_close(run(), expect)
    model.train()
    d_unl, d_ed = model(batch)
    (d_unl.square().mean() + d_ed.square().mean()).backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_shifted_cat_spread_equals_one_add_per_tensor():
    """The GPU's way (shifts spread by repeat_interleave) gives the CPU's (one add per tensor), for
    index vectors and for edge lists [2, E]."""
    from trainer.network.sparse_gat import shifted_cat

    g = torch.Generator().manual_seed(3)
    for shape in [(7,), (2, 5), (1,), (0,)]:
        parts = [torch.randint(0, 50, shape[:-1] + (shape[-1] + k,), generator=g) for k in range(4)]
        shifts = [0, 13, 40, 41]
        expect = torch.empty(shape[:-1] + (sum(p.shape[-1] for p in parts),), dtype=torch.long)
        at = 0
        for p, s in zip(parts, shifts):  # written slice by slice, as GraphTable did before
            expect[..., at:at + p.shape[-1]] = p + s
            at += p.shape[-1]
        assert torch.equal(shifted_cat(parts, shifts, spread=True), expect)
        assert torch.equal(shifted_cat(parts, shifts, spread=False), expect)


def test_direct_sum_equals_the_batched_graph():
    """A batch's AttentionGraph assembled from its meshes' (two meshes, repeated, in mixed order)
    equals the one sorted from the batched edge_index, head-folded patterns included."""
    meshes = [lv_mesh(0), lv_mesh(1)]
    edges = [mesh_features(m).edge_index for m in meshes]
    own = [AttentionGraph.from_edge_index(e, m.n_nodes) for e, m in zip(edges, meshes)]
    order = [1, 0, 0, 1, 1, 0]
    offsets = np.cumsum([0] + [meshes[i].n_nodes for i in order])
    batched = torch.cat([edges[i] + int(o) for i, o in zip(order, offsets[:-1])], dim=1)
    ref = AttentionGraph.from_edge_index(batched, int(offsets[-1]))
    summed = AttentionGraph.direct_sum([own[i] for i in order])
    assert summed.n_nodes == ref.n_nodes and summed.members == tuple(own[i] for i in order)
    for name in ("src", "dst", "crow"):
        assert torch.equal(getattr(summed, name), getattr(ref, name)), name
    for h in (1, 3, 4):
        a, b = summed.heads(h), ref.heads(h)
        assert a.size == b.size
        for name in ("crow", "col", "val_perm", "crow_t", "col_t", "t_perm"):
            assert torch.equal(getattr(a, name), getattr(b, name)), (h, name)


def test_directed_graph_matches_pyg():
    """A random directed graph (transpose pattern differs from the pattern)."""
    g = torch.Generator().manual_seed(5)
    n = 40
    edge_index = torch.unique(torch.randint(0, n, (2, 160), generator=g), dim=1)
    torch.manual_seed(5)
    ref = GATConv(5, 6, heads=3).double()
    ours = SparseGATConv(5, 6, heads=3).double()
    ours.load_state_dict(ref.state_dict())
    xa = torch.randn(n, 5, dtype=torch.float64, requires_grad=True)
    xb = xa.detach().clone().requires_grad_()
    ya, yb = ref(xa, edge_index), ours(xb, edge_index)
    torch.testing.assert_close(yb, ya, rtol=1e-10, atol=1e-12)
    ya.pow(2).sum().backward()
    yb.pow(2).sum().backward()
    torch.testing.assert_close(xb.grad, xa.grad, rtol=1e-10, atol=1e-12)
