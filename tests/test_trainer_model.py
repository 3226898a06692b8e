"""HeartUnloadNet: output shapes for every configuration, permutation equivariance, mesh-size
agnostic batching, the single-token attention identity, and the cycle term on unlabelled cases."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch

from trainer.config import NAMED_CONFIGS, ModelConfig, named_config
from trainer.errors import TrainerError
from trainer.data.features import case_graph, mesh_edges, mesh_features
from trainer.data.normalisation import Normalisation
from trainer.network.model import CrossAttention, build_model, count_parameters, loss_terms
from trainer_fixtures import lv_mesh, synthetic_unloaded

GNN_CONFIGS = [name for name, c in NAMED_CONFIGS.items() if c.kind == "gnn"]


def small(cfg: ModelConfig) -> ModelConfig:
    return replace(cfg, hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8)


@pytest.fixture(scope="module")
def graphs():
    """Two real meshes with different node counts, as labelled graphs."""
    out = []
    for s in (0, 1):
        m = lv_mesh(s)
        f = mesh_features(m)
        norm = Normalisation(tuple(m.nodes.mean(axis=0)), 30.0, 2.0, (4, 50, 60, -70), (14, 300, 70, -60))
        out.append(case_graph(f, [8.0, 150.0, 65.0, -65.0], norm, synthetic_unloaded(m.nodes, 8.0, 150.0),
                              response=True))
    assert out[0].num_nodes != out[1].num_nodes
    return out


def test_mesh_edges_both_directions_no_duplicates():
    ei = mesh_edges(np.array([[0, 1, 2, 3], [1, 2, 3, 4]]))
    pairs = set(map(tuple, ei.T.tolist()))
    assert len(pairs) == ei.shape[1] == 2 * 9  # 6 + 6 − 3 shared edges, both ways
    assert all((b, a) in pairs for a, b in pairs)


@pytest.mark.parametrize("name", GNN_CONFIGS)
def test_output_shapes_every_config(name, graphs):
    torch.manual_seed(0)
    cfg = small(named_config(name))
    model = build_model(cfg, 0.1)
    batch = Batch.from_data_list(graphs)
    d_unl, d_ed, d_rev = model(batch, reverse=True)  # as the training loop calls it
    assert d_unl.shape == (batch.num_nodes, 3)
    assert (d_ed is None) == (not cfg.cycle)
    if d_ed is not None:
        assert d_ed.shape == (batch.num_nodes, 3)
    terms = loss_terms(d_unl, d_ed, batch, cfg.lambda_cycle, d_rev, cfg.reverse_weight)
    terms["loss"].backward()
    assert all(p.grad is not None for p in model.parameters()), "every parameter takes part (DDP needs it)"


def test_paper_size_model():
    n = count_parameters(build_model(named_config("paper")))
    assert 1.5e6 < n < 3.5e6  # GAT 3 × (128 × 4 heads) = 512 features, ~2 M parameters
    with pytest.raises(TrainerError):
        named_config("A9")


def _permuted(g, perm):
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(len(perm))
    h = g.clone()
    h.x, h.y, h.region, h.wall, h.response = g.x[perm], g.y[perm], g.region[perm], g.wall[perm], g.response[perm]
    h.edge_index = inv[g.edge_index]
    return h


@pytest.mark.parametrize("name", ["paper", "multitoken", "gcn", "sage", "gat-decoder", "broadcast-fusion", "A1ema-wall", "A1ema-resp-d0",
                                  "A1ema-resp-d0-gcn", "R5-resp-d0"])
def test_permutation_equivariance(name, graphs):
    torch.manual_seed(1)
    model = build_model(small(named_config(name)), 0.1).eval()
    g = graphs[0]
    perm = torch.randperm(g.num_nodes)
    with torch.no_grad():
        a, ca = model(Batch.from_data_list([g]))
        b, cb = model(Batch.from_data_list([_permuted(g, perm)]))
    torch.testing.assert_close(b, a[perm], atol=1e-5, rtol=1e-4)
    if ca is not None:
        torch.testing.assert_close(cb, ca[perm], atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("name", ["paper", "multitoken", "max-pooling"])
def test_mesh_size_agnostic_batching(name, graphs):
    """Two meshes of different node counts in one batch give what each gives alone."""
    torch.manual_seed(2)
    model = build_model(small(named_config(name)), 0.1).eval()
    with torch.no_grad():
        together, _ = model(Batch.from_data_list(graphs))
        alone = [model(Batch.from_data_list([g]))[0] for g in graphs]
    torch.testing.assert_close(together, torch.cat(alone), atol=1e-5, rtol=1e-4)


def test_wall_coordinates_reach_the_encoder_only_when_configured(graphs):
    """node_features="wall": (ζ, τ) are node input (changing τ changes the answer); the paper's
    xyz input ignores them. ζ runs 0 (base) … 1 (apex), τ 0 (endocardium) … 1 (epicardium)."""
    g = graphs[0]
    assert g.wall.shape == (g.num_nodes, 2)
    assert float(g.wall.min()) == 0.0 and float(g.wall.max()) == 1.0
    moved = g.clone()
    moved.wall = g.wall.clone()
    moved.wall[:, 1] = 1.0 - moved.wall[:, 1]
    for name, changes in (("A1ema-wall", True), ("A1ema", False)):
        torch.manual_seed(3)
        model = build_model(small(named_config(name)), 0.1).eval()
        with torch.no_grad():
            a = model(Batch.from_data_list([g]))[0]
            b = model(Batch.from_data_list([moved]))[0]
        assert (not torch.allclose(a, b, atol=1e-6)) == changes, name
    assert build_model(named_config("A1ema-wall")).encoder.skips[0].in_features == 5


def test_single_token_attention_is_value_projection():
    """With one key/value token the softmax weight is 1: the general module with a second, masked
    token equals the single-token form h ← LN(h + W_o W_v c)."""
    torch.manual_seed(3)
    W, B = 16, 3
    general = CrossAttention(W, W, heads=4, n_tokens=2)
    single = CrossAttention(W, W, heads=4, n_tokens=1)
    single.v, single.o, single.norm = general.v, general.o, general.norm
    batch = torch.repeat_interleave(torch.arange(B), torch.tensor([5, 7, 4]))
    h = torch.randn(len(batch), W)
    tokens = torch.randn(B, 2, W)
    mask = torch.tensor([[False, True]] * B)
    torch.testing.assert_close(general(h, batch, tokens, mask), single(h, batch, tokens[:, :1]), atol=1e-5, rtol=1e-5)
    assert not hasattr(single, "q") and not hasattr(single, "k")


def test_cycle_term_trains_on_unlabelled_cases(graphs):
    """Unlabelled cases contribute only λ·cycle: non-zero gradients, and steps on them alone reduce it.
    Without the cycle (no-cycle) they contribute nothing."""
    unlabelled = []
    for g in graphs:
        h = g.clone()
        h.y = torch.full_like(g.y, float("nan"))
        h.labelled = torch.tensor([False])
        unlabelled.append(h)
    batch = Batch.from_data_list(unlabelled)

    torch.manual_seed(4)
    model = build_model(small(named_config("paper")), 0.1)
    model.eval()  # no dropout: a clean before/after comparison
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = None
    for step in range(30):
        d_unl, d_ed = model(batch)
        terms = loss_terms(d_unl, d_ed, batch, 0.2)
        assert float(terms["sup"].detach()) == 0.0 and terms["labelled_nodes"] == 0
        torch.testing.assert_close(terms["loss"], 0.2 * terms["cycle"])
        if first is None:
            first = float(terms["loss"].detach())
            opt.zero_grad()
            terms["loss"].backward()
            assert sum(float(p.grad.abs().sum()) for p in model.parameters() if p.grad is not None) > 0
            opt.step()
            continue
        opt.zero_grad()
        terms["loss"].backward()
        opt.step()
    assert float(terms["loss"].detach()) < 0.5 * first

    a1 = build_model(small(named_config("no-cycle")), 0.1)
    d_unl, d_ed = a1(batch)
    terms = loss_terms(d_unl, d_ed, batch, 0.2)
    terms["loss"].backward()
    assert float(terms["loss"].detach()) == 0.0
    assert all(float(p.grad.abs().sum()) == 0.0 for p in a1.parameters())


def test_supervised_term_ignores_withheld_labels(graphs):
    """A labelled and an unlabelled graph in one batch: the supervised MSE is over the labelled
    graph's nodes only (the NaN targets of the other never reach the loss)."""
    torch.manual_seed(5)
    model = build_model(small(named_config("paper")), 0.1).eval()
    u = graphs[1].clone()
    u.y = torch.full_like(u.y, float("nan"))
    u.labelled = torch.tensor([False])
    batch = Batch.from_data_list([graphs[0], u])
    with torch.no_grad():
        d_unl, d_ed = model(batch)
        terms = loss_terms(d_unl, d_ed, batch, 0.2)
    n0 = graphs[0].num_nodes
    expected = torch.mean((d_unl[:n0] - graphs[0].y) ** 2)
    torch.testing.assert_close(terms["sup"], expected)
    assert terms["labelled_nodes"] == n0 and torch.isfinite(terms["loss"])


def test_reverse_term_supervises_the_reverse_decoder(graphs):
    """R1: on labelled graphs the reverse decoder, applied to the true unloaded mesh, is fitted to
    −y (its own MSE, hand-computed); `paper` computes no such term; withheld labels give zero."""
    torch.manual_seed(6)
    cfg = small(named_config("R1"))
    model = build_model(cfg, 0.1).eval()
    batch = Batch.from_data_list(graphs)
    with torch.no_grad():
        d_unl, d_ed, d_rev = model(batch, reverse=True)
        terms = loss_terms(d_unl, d_ed, batch, cfg.lambda_cycle, d_rev, cfg.reverse_weight)
        x_true = batch.x + model.disp_to_coord * batch.y
        by_hand = model.dec_ed(model.encode(x_true, batch.edge_index, batch.batch, batch.params, batch.region, 2),
                               batch.edge_index)
    torch.testing.assert_close(d_rev, by_hand)
    torch.testing.assert_close(terms["reverse"], torch.mean((d_rev + batch.y) ** 2))
    torch.testing.assert_close(terms["loss"], terms["sup"] + cfg.lambda_cycle * terms["cycle"] + terms["reverse"])
    assert build_model(small(named_config("paper")), 0.1)(batch, reverse=True)[2] is None

    mixed = [graphs[0], graphs[1].clone()]
    mixed[1].y = torch.full_like(mixed[1].y, float("nan"))
    mixed[1].labelled = torch.tensor([False])
    mb = Batch.from_data_list(mixed)
    with torch.no_grad():
        d_rev_mixed = model(mb, reverse=True)[2]
    n0 = graphs[0].num_nodes
    torch.testing.assert_close(d_rev_mixed, by_hand[:n0])  # the labelled graph's nodes only

    hidden = [g.clone() for g in graphs]
    for h in hidden:
        h.y = torch.full_like(h.y, float("nan"))
        h.labelled = torch.tensor([False])
    hb = Batch.from_data_list(hidden)
    d_unl, d_ed, d_rev = model(hb, reverse=True)
    terms = loss_terms(d_unl, d_ed, hb, cfg.lambda_cycle, d_rev, cfg.reverse_weight)
    assert d_rev.shape == (0, 3)
    assert float(terms["reverse"].detach()) == 0.0 and torch.isfinite(terms["loss"])
    terms["loss"].backward()  # every reverse-decoder weight still gets a (zero) gradient, as DDP needs
    assert all(p.grad is not None for p in model.dec_ed.parameters())


def test_reverse_pass_on_a_mixed_batch_keeps_each_node_input(graphs):
    """R5-resp-d0: the reverse pass on the labelled graphs of a mixed batch takes those graphs' own
    wall coordinates and linear response (a sub-batch of the node input), so it equals the pass on
    the labelled graph alone."""
    torch.manual_seed(8)
    model = build_model(small(named_config("R5-resp-d0")), 0.1).eval()
    unlabelled = graphs[0].clone()
    unlabelled.y = torch.full_like(unlabelled.y, float("nan"))
    unlabelled.labelled = torch.tensor([False])
    with torch.no_grad():
        alone = model(Batch.from_data_list([graphs[1]]), reverse=True)[2]
        mixed = model(Batch.from_data_list([unlabelled, graphs[1]]), reverse=True)[2]
    assert mixed.shape == (graphs[1].num_nodes, 3)
    torch.testing.assert_close(mixed, alone, atol=1e-5, rtol=1e-4)


def test_unloading_only_cycle_gradient(graphs):
    """cycle_grad="unloading" (R3): same outputs as the shared pass; the cycle term's gradient
    reaches the unloading decoder exactly as before (through the reconstruction pass's input) but
    not the reverse decoder."""
    torch.manual_seed(7)
    cfg = replace(small(named_config("R3")), dropout=0.0)  # train mode, identical forwards
    r3 = build_model(cfg, 0.1).train()
    both = build_model(replace(cfg, cycle_grad="both"), 0.1).train()
    both.load_state_dict(r3.state_dict())
    batch = Batch.from_data_list(graphs)
    grads = {}
    for name, model in (("r3", r3), ("both", both)):
        d_unl, d_ed = model(batch)
        (d_unl + d_ed).pow(2).mean().backward()
        grads[name] = (d_ed.detach(), {n: p.grad for n, p in model.named_parameters()})
    torch.testing.assert_close(grads["r3"][0], grads["both"][0])
    g3, gb = grads["r3"][1], grads["both"][1]
    for n in g3:
        if n.startswith("dec_unloaded."):
            torch.testing.assert_close(g3[n], gb[n])
        if n.startswith("dec_ed."):
            assert g3[n] is None and float(gb[n].abs().sum()) > 0


def test_teacher_cycle_runs_the_reconstruction_on_the_given_weights(graphs):
    """cycle_grad="teacher" (mean-teacher): the reconstruction pass is the teacher network's (another set of
    weights) applied to this model's unloading; the cycle gradient reaches the unloading decoder
    and never the reverse decoder. Without teacher weights it is the stop-gradient pass of R3."""
    torch.manual_seed(3)
    cfg = replace(small(named_config("mean-teacher")), dropout=0.0)
    student, teacher = build_model(cfg, 0.1).train(), build_model(cfg, 0.1).train()
    batch = Batch.from_data_list(graphs)
    weights = {n: p.detach() for n, p in teacher.named_parameters()}
    d_unl, d_ed = student(batch, teacher=weights)
    expected = teacher(batch, _reconstruct_from=batch.x + 0.1 * d_unl.detach())
    torch.testing.assert_close(d_ed.detach(), expected.detach())
    (d_unl + d_ed).pow(2).mean().backward()
    for n, p in student.named_parameters():
        if n.startswith("dec_ed."):
            assert p.grad is None
        if n.startswith("dec_unloaded."):
            assert p.grad is not None and float(p.grad.abs().sum()) > 0
    r3 = build_model(replace(cfg, cycle_grad="unloading", ema_decay=0.0), 0.1).train()
    r3.load_state_dict(student.state_dict())
    torch.testing.assert_close(student(batch)[1], r3(batch)[1])


def test_teacher_and_weight_average_settings_are_checked():
    with pytest.raises(TrainerError, match="ema_decay > 0"):
        replace(named_config("mean-teacher"), ema_decay=0.0)
    with pytest.raises(TrainerError, match="ema_decay must be in"):
        replace(named_config("A1"), ema_decay=1.0)
    with pytest.raises(TrainerError, match="reverse_weight > 0"):
        replace(named_config("R5"), reverse_weight=0.0)
    assert named_config("a1EMA").ema_decay == 0.99 and not named_config("A1ema").cycle
