"""GraphTable batches equal PyG's collation field by field (two meshes of different sizes, labels
withheld, the linear response), the loop's loaders visit the cases in the order PyG's DataLoader
would, and bad tables are refused."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import BatchSampler, RandomSampler
from torch_geometric.data import Batch
from torch_geometric.loader import DataLoader

from trainer.data.batching import GraphTable, chunks
from trainer.data.features import case_graph, mesh_features
from trainer.data.normalisation import Normalisation
from trainer.training.loop import TableLoader
from trainer_fixtures import lv_mesh, synthetic_unloaded


def _graphs(response: bool) -> list:
    """20 cases on two meshes (~120 and ~160 nodes), alternating; every third unlabelled. With
    `response`, each mesh's graphs share one [n, 3] response tensor, as MeshFeatures.response gives
    (random here: the linear FE solve needs scikit-fem, which a GPU host running these tests lacks)."""
    feats = [mesh_features(lv_mesh(0)), mesh_features(lv_mesh(1, nodes=160))]
    assert feats[0].ed_mm.shape[0] != feats[1].ed_mm.shape[0]
    norm = Normalisation(tuple(feats[0].ed_mm.mean(axis=0)), 30.0, 2.0, (4, 50, 60, -70), (14, 300, 70, -60))
    gen = torch.Generator().manual_seed(5)
    responses = [torch.randn(f.ed_mm.shape[0], 3, generator=gen) for f in feats]
    out = []
    for i in range(20):
        f = feats[i % 2]
        p, c = 4.0 + i % 5 * 2.5, 50.0 + 25.0 * i
        g = case_graph(f, [p, c, 60.0 + i % 3, -65.0], norm, synthetic_unloaded(f.ed_mm, p, c),
                       labelled=i % 3 != 0, key=(i % 2, i))
        if response:
            g.response = responses[i % 2]
        out.append(g)
    return out


def assert_same_batch(a: Batch, b: Batch) -> None:
    assert sorted(a.keys()) == sorted(b.keys())
    for k in b.keys():
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        assert torch.equal(torch.nan_to_num(a[k].cpu(), nan=-7.0), torch.nan_to_num(b[k].cpu(), nan=-7.0)), k
    assert a.num_graphs == b.num_graphs


@pytest.mark.parametrize("response", [False, True])
def test_table_batch_equals_pyg_collation(response):
    graphs = _graphs(response)
    table = GraphTable(graphs)
    assert table.n_topologies == 2 and len(table) == 20
    rng = np.random.default_rng(3)
    orders = [rng.permutation(20)[:7], [5], [3, 3, 8], list(range(20))]  # repeats, one graph, all
    for order in orders:
        assert_same_batch(table.batch(order), Batch.from_data_list([graphs[i] for i in order]))
    b = table.batch([1, 0])
    assert b.ptr.tolist() == [0, graphs[1].num_nodes, graphs[1].num_nodes + graphs[0].num_nodes]
    assert torch.isnan(b.y[b.ptr[1]:]).all() and not torch.isnan(b.y[:b.ptr[1]]).any()  # case 0 unlabelled


def test_table_loader_visits_cases_like_pyg_dataloader():
    graphs = _graphs(False)
    gen_a, gen_b = torch.Generator().manual_seed(11), torch.Generator().manual_seed(11)
    pyg = DataLoader(graphs, batch_size=6, sampler=RandomSampler(graphs, generator=gen_a))
    ours = TableLoader(GraphTable(graphs), BatchSampler(RandomSampler(graphs, generator=gen_b), 6, drop_last=False))
    assert len(ours) == len(pyg) == 4
    for a, b in zip(ours, pyg, strict=True):
        assert_same_batch(a, b)
    val = TableLoader(GraphTable(graphs[:7]), chunks(7, 3))
    assert [b.key[:, 1].tolist() for b in val] == [[0, 1, 2], [3, 4, 5], [6]]


@pytest.mark.parametrize("config", ["paper", "gat-decoder"])  # GAT encoder; GAT encoder and decoder
def test_attention_graph_from_the_table_gives_the_same_model_outputs(config):
    """With `attention`, a batch carries its AttentionGraph assembled from each mesh's; the model
    uses it and gives what it gives when it sorts the graph from the edges itself, in every pass:
    unloading, cycle, and the reverse decoder on the labelled members of a mixed batch."""
    from dataclasses import replace

    from trainer.config import named_config
    from trainer.network.model import build_model

    graphs = _graphs(True)
    cfg = replace(named_config(config), hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8, reverse_weight=0.5)
    assert cfg.uses_attention_graph
    torch.manual_seed(0)
    model = build_model(cfg, 0.1).eval()
    order = [3, 0, 7, 12, 5]  # graphs 0, 3 and 12 unlabelled
    with_graph = GraphTable(graphs, attention=True).batch(order)
    plain = GraphTable(graphs).batch(order)
    assert with_graph.attention_graph.members is not None and "attention_graph" not in plain.keys()
    with torch.no_grad():
        a, b = model(with_graph, reverse=True), model(plain, reverse=True)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)
    assert a[2].shape[0] == sum(graphs[i].num_nodes for i in order if i % 3)


def test_bad_tables_are_refused():
    graphs = _graphs(False)
    with pytest.raises(ValueError, match="at least one graph"):
        GraphTable([])
    with pytest.raises(ValueError, match="same attributes"):
        GraphTable([graphs[0], _graphs(True)[1]])
    odd = graphs[0].clone()
    odd.extra = torch.zeros(3)
    with pytest.raises(ValueError, match="got attributes"):
        GraphTable([odd])
    with pytest.raises(ValueError, match="at least one graph"):
        GraphTable(graphs).batch([])


def test_saved_meshes_stand_in_for_gmsh():
    """The meshes a GPU host without gmsh uses (trainer_fixtures.lv_mesh): readable, tagged, and the
    same sizes as the gmsh meshes they were written from."""
    from storage.meshfiles import read_mesh
    from trainer_fixtures import saved_mesh_path

    for (shape, nodes), n in {(0, 120): 122, (1, 120): 119, (1, 160): 168}.items():
        m = read_mesh(saved_mesh_path(shape, 0, nodes))
        assert m.n_nodes == n and len(m.endo) and len(m.epi) and len(m.base)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_table_on_cuda_equals_host_collation():
    graphs = _graphs(True)
    table = GraphTable(graphs, "cuda", attention=True)
    order = [4, 1, 1, 18, 7]
    b = table.batch(order)
    assert b.x.is_cuda and b.edge_index.is_cuda and b.ptr.is_cuda and b.attention_graph.src.is_cuda
    graph = b.attention_graph
    del b.attention_graph
    assert_same_batch(b, Batch.from_data_list([graphs[i] for i in order]))
    from trainer.network.sparse_gat import AttentionGraph

    ref = AttentionGraph.from_edge_index(b.edge_index, b.num_nodes)
    assert torch.equal(graph.src, ref.src) and torch.equal(graph.heads(4).val_perm, ref.heads(4).val_perm)
    # a table kept in host memory (too large for the GPU): its batches' attention graphs are on the GPU
    # all the same, since Batch.to moves tensors only
    host = GraphTable(graphs, "cpu", attention=True, attention_device="cuda").batch(order)
    assert not host.x.is_cuda and host.attention_graph.src.is_cuda
    from dataclasses import replace

    from trainer.config import named_config
    from trainer.network.model import build_model

    model = build_model(replace(named_config("paper"), hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8),
                        0.1).cuda().eval()
    with torch.no_grad():
        torch.testing.assert_close(model(host.to("cuda"), cycle=False)[0], model(b.to("cuda"), cycle=False)[0])
