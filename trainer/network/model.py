"""HeartUnloadNet as a composition of small modules: mesh encoder, mesh context (pooling +
cross-attention), parameter encoder, fusion, decoders, and the cycle through the shared encoder."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from torch_geometric.nn import GATConv, GATv2Conv, GCNConv, SAGEConv
from torch_geometric.utils import scatter, to_dense_batch

from trainer.config import ModelConfig
from trainer.data.features import N_REGIONS
from trainer.data.normalisation import N_LOAD_FEATURES, load_features
from trainer.network.sparse_gat import AttentionGraph, SparseGATConv

N_PARAMS = 4
N_WALL = 2  # wall coordinates ζ, τ
N_RESPONSE = 3  # the mesh's linear response ũ


def _gat(in_dim: int, hidden: int, heads: int, kernel: str, concat: bool = True) -> nn.Module:
    return (SparseGATConv if kernel == "sparse" else GATConv)(in_dim, hidden, heads=heads, concat=concat)


def _conv(kind: str, in_dim: int, hidden: int, heads: int, gat_kernel: str = "sparse") -> nn.Module:
    width = hidden * heads
    if kind == "gat":
        return _gat(in_dim, hidden, heads, gat_kernel)
    if kind == "gatv2":
        return GATv2Conv(in_dim, hidden, heads=heads, concat=True)
    if kind == "gcn":
        return GCNConv(in_dim, width)
    if kind == "sage":
        return SAGEConv(in_dim, width)
    raise ValueError(kind)


class MeshEncoder(nn.Module):
    r"""Graph encoder of node coordinates (paper Eq. 1–2):

    .. math:: h^{l+1}_i = \mathrm{Dropout}(\mathrm{ReLU}(\mathrm{Conv}(h^l)_i)) + R^l h^l_i,

    Conv = GATConv with `heads` heads of `hidden` features concatenated (or GATv2 / GCN / SAGE);
    R^l is the identity, or a linear map where the width changes (the first layer).
    `edges` is an edge_index, or for the sparse GAT kernel an AttentionGraph built once per batch."""

    def __init__(self, in_dim: int, conv: str = "gat", hidden: int = 128, heads: int = 4, layers: int = 3,
                 dropout: float = 0.1, gat_kernel: str = "sparse"):
        super().__init__()
        width = hidden * heads
        dims = [in_dim] + [width] * layers
        self.convs = nn.ModuleList(_conv(conv, dims[i], hidden, heads, gat_kernel) for i in range(layers))
        self.skips = nn.ModuleList(nn.Linear(dims[i], width) if dims[i] != width else nn.Identity()
                                   for i in range(layers))
        self.dropout = dropout

    def reset_parameters(self):
        for m in list(self.convs) + list(self.skips):
            if hasattr(m, "reset_parameters"):
                m.reset_parameters()

    def forward(self, x: torch.Tensor, edges) -> torch.Tensor:
        h = x
        for conv, skip in zip(self.convs, self.skips):
            h = F.dropout(F.relu(conv(h, edges)), self.dropout, self.training) + skip(h)
        return h


class MeshPooling(nn.Module):
    r"""Context tokens of a mesh from its node features (paper Eq. 3): g_mesh = mean_i h_i (or max).
    `regional` adds one pool per region (base/mid/apex × endo/epi): 1 + 6 tokens; a region with no
    node in a graph is masked. Returns tokens [B, T, W] and mask [B, T] (True = missing)."""

    def __init__(self, reduce: str = "mean", regional: bool = False):
        super().__init__()
        self.reduce = reduce
        self.regional = regional

    @property
    def n_tokens(self) -> int:
        return 1 + (N_REGIONS if self.regional else 0)

    def forward(self, h, batch, region, num_graphs: int):
        g = scatter(h, batch, dim=0, dim_size=num_graphs, reduce=self.reduce).unsqueeze(1)
        mask = torch.zeros(num_graphs, 1, dtype=torch.bool, device=h.device)
        if not self.regional:
            return g, mask
        idx = batch * N_REGIONS + region
        r = scatter(h, idx, dim=0, dim_size=num_graphs * N_REGIONS, reduce=self.reduce).view(num_graphs, N_REGIONS, -1)
        count = torch.bincount(idx, minlength=num_graphs * N_REGIONS).view(num_graphs, N_REGIONS)
        return torch.cat([g, r], dim=1), torch.cat([mask, count == 0], dim=1)


class CrossAttention(nn.Module):
    r"""Nodes (queries) attend to their graph's context tokens (keys/values), residual + LayerNorm
    (paper Eq. 4 and 6):

    .. math:: h_i \leftarrow \mathrm{LN}\Big(h_i + W_o \sum_t \mathrm{softmax}_t
              \big(\tfrac{(W_q h_i)\cdot(W_k c_t)}{\sqrt{d}}\big) W_v c_t\Big)  \text{(per head)}.

    With a single token (`n_tokens=1`, the paper's configuration) the softmax weight is exactly 1,
    so this is h_i ← LN(h_i + W_o W_v c): no query/key weights are held (they would get no gradient
    and change nothing), and nothing of size nodes × tokens is computed."""

    def __init__(self, dim: int, context_dim: int | None = None, heads: int = 4, n_tokens: int = 1):
        super().__init__()
        context_dim = context_dim or dim
        if dim % heads:
            raise ValueError(f"attention width {dim} is not divisible by {heads} heads")
        self.heads, self.n_tokens = heads, n_tokens
        self.v = nn.Linear(context_dim, dim)
        self.o = nn.Linear(dim, dim)
        if n_tokens > 1:
            self.q = nn.Linear(dim, dim)
            self.k = nn.Linear(context_dim, dim)
        self.norm = nn.LayerNorm(dim)

    def forward(self, h, batch, tokens, mask=None):
        B, T, _ = tokens.shape
        if self.n_tokens == 1:
            return self.norm(h + self.o(self.v(tokens[:, 0])).index_select(0, batch))
        hd, node_mask = to_dense_batch(h, batch, batch_size=B)  # [B, Nmax, D]
        D = h.shape[1]
        dh = D // self.heads
        q = self.q(hd).view(B, -1, self.heads, dh).transpose(1, 2)  # [B, H, Nmax, dh]
        k = self.k(tokens).view(B, T, self.heads, dh).transpose(1, 2)  # [B, H, T, dh]
        v = self.v(tokens).view(B, T, self.heads, dh).transpose(1, 2)
        attn_mask = None if mask is None else (~mask).view(B, 1, 1, T)  # True = take part
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)  # [B, H, Nmax, dh]
        out = out.transpose(1, 2).reshape(B, -1, D)[node_mask]
        return self.norm(h + self.o(out))


class ParameterEncoder(nn.Module):
    r"""Global encoder of the physiological parameters p̂ = (P, C, θendo, θepi) ∈ [0,1]⁴ (paper Eq. 5):
    g_param = MLP(p̂), one token. `per_parameter` adds one token per parameter,
    t_j = MLP_tok([p̂_j, e_j]) (e_j one-hot of the parameter): 1 + 4 tokens."""

    def __init__(self, width: int, hidden: int = 128, per_parameter: bool = False):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(N_PARAMS, hidden), nn.ReLU(), nn.Linear(hidden, width))
        self.per_parameter = per_parameter
        if per_parameter:
            self.tok = nn.Sequential(nn.Linear(1 + N_PARAMS, hidden), nn.ReLU(), nn.Linear(hidden, width))

    @property
    def n_tokens(self) -> int:
        return 1 + (N_PARAMS if self.per_parameter else 0)

    def forward(self, p):  # p [B, 4] → [B, T, W]
        g = self.mlp(p).unsqueeze(1)
        if not self.per_parameter:
            return g
        eye = torch.eye(N_PARAMS, device=p.device, dtype=p.dtype).expand(p.shape[0], -1, -1)
        return torch.cat([g, self.tok(torch.cat([p.unsqueeze(-1), eye], dim=-1))], dim=1)


class ConcatFusion(nn.Module):
    r"""The concat-fusion ablation (the paper's A2): h_i ← LN(h_i + W [h_i ‖ g_param]) instead of cross-attention."""

    def __init__(self, dim: int):
        super().__init__()
        self.lin = nn.Linear(2 * dim, dim)
        self.norm = nn.LayerNorm(dim)

    def forward(self, h, batch, tokens, mask=None):
        return self.norm(h + self.lin(torch.cat([h, tokens[:, 0].index_select(0, batch)], dim=1)))


class MLPDecoder(nn.Module):
    """Node-wise MLP with dropout: features → 3 displacement components (normalised)."""

    def __init__(self, dim: int, hidden=(256, 128), dropout: float = 0.1):
        super().__init__()
        layers, d = [], dim
        for w in hidden:
            layers += [nn.Linear(d, w), nn.ReLU(), nn.Dropout(dropout)]
            d = w
        layers.append(nn.Linear(d, 3))
        self.net = nn.Sequential(*layers)

    def forward(self, h, edge_index):
        return self.net(h)


class GATDecoder(nn.Module):
    """The gat-decoder baseline (the paper's C5): two GAT layers (4 heads of 64, then 1 head of 3) instead of the MLP."""

    def __init__(self, dim: int, dropout: float = 0.1, hidden: int = 64, heads: int = 4, gat_kernel: str = "sparse"):
        super().__init__()
        self.c1 = _gat(dim, hidden, heads, gat_kernel)
        self.c2 = _gat(hidden * heads, 3, 1, gat_kernel)
        self.dropout = dropout

    def forward(self, h, edge_index):
        return self.c2(F.dropout(F.relu(self.c1(h, edge_index)), self.dropout, self.training), edge_index)


class HeartUnloadNet(nn.Module):
    r"""ED mesh + parameters → unloading displacement, with a cycle back to ED.

    encode(x, p): h = MeshEncoder(x [‖ ζ, τ]) → h ← CrossAttn(h, Pool(h)) → h ← Fuse(h, ParamEncoder(p))
    d_unl = Dec_unl(encode(x̂_ED, p))                         (normalised X − x_ED)
    d_ed  = Dec_ed(encode(x̂_ED + ρ d_unl, p))                (normalised x_ED − X̂; ρ = disp/coord scale)
    loss  = MSE(d_unl, y)[labelled] + λ_cycle · MSE(d_unl + d_ed, 0)   (= reconstructed ED − ED)
            [+ λ_rev · MSE(Dec_ed(encode(x̂_ED + ρ y, p)), −y)[labelled]  when reverse_weight λ_rev > 0]
    With output_scale = "load" each decoder's output is multiplied by its graph's expected
    displacement size s(p) = exp(load_features(p̂) · a) (trainer.data.normalisation.fit_load_scale).
    With cycle_grad = "unloading" the d_ed pass runs on detached weights: the cycle term moves
    d_unl only (through the frozen pass's input), never Dec_ed or the encoder's second use; with
    "teacher" it runs on the weight average the training loop passes in (a mean teacher).
    """

    def __init__(self, cfg: ModelConfig, disp_to_coord: float = 0.1, load_coef: tuple = (),
                 load_box: tuple = (4.0, 50.0, 14.0, 300.0)):
        super().__init__()
        self.cfg = cfg
        W = cfg.width
        broadcast = cfg.fusion == "broadcast"
        n_in = 3 + (N_WALL if cfg.uses_wall else 0) + (N_RESPONSE if cfg.uses_response else 0) \
            + (N_PARAMS if broadcast else 0)
        self.encoder = MeshEncoder(n_in, cfg.conv, cfg.hidden, cfg.heads, cfg.layers,
                                   cfg.dropout, cfg.gat_kernel)
        regional = cfg.tokens == "regional"
        self.pool = None if cfg.pooling == "none" else MeshPooling(cfg.pooling, regional)
        self.mesh_attn = None if self.pool is None else CrossAttention(W, W, cfg.heads, self.pool.n_tokens)
        self.param_encoder = None if broadcast else ParameterEncoder(W, cfg.param_hidden, regional)
        if cfg.fusion == "attention":
            self.fusion = CrossAttention(W, W, cfg.heads, self.param_encoder.n_tokens)
        elif cfg.fusion == "concat":
            self.fusion = ConcatFusion(W)
        else:
            self.fusion = None
        make_dec = (lambda: MLPDecoder(W, cfg.decoder_hidden, cfg.dropout)) if cfg.decoder == "mlp" else \
            (lambda: GATDecoder(W, cfg.dropout, gat_kernel=cfg.gat_kernel))
        self.dec_unloaded = make_dec()
        self.dec_ed = make_dec() if cfg.cycle else None
        self.register_buffer("disp_to_coord", torch.tensor(float(disp_to_coord)))
        if cfg.output_scale == "load":  # only then: checkpoints of the other configurations load as before
            coef = torch.zeros(N_LOAD_FEATURES) if not load_coef else torch.tensor(load_coef, dtype=torch.float32)
            if coef.shape != (N_LOAD_FEATURES,):
                raise ValueError(f"load_coef must hold {N_LOAD_FEATURES} values, got {tuple(coef.shape)}")
            self.register_buffer("load_coef", coef)
            self.load_box = tuple(float(v) for v in load_box)  # from the Normalisation, as disp_to_coord

    def output_scale(self, params: torch.Tensor) -> torch.Tensor | None:
        """[B] per-graph factor on the decoders' output: exp(load_features(p̂, box) · a) with
        output_scale="load", else None (the global displacement scale only)."""
        if self.cfg.output_scale != "load":
            return None
        return torch.exp(load_features(params.float(), self.load_box) @ self.load_coef)

    def encode(self, x, edge_index, batch, params, region, num_graphs: int, wall=None):
        """Node features [N, W] of coordinates x [N, 3]; `wall` [N, 2] = (ζ, τ), used when
        cfg.node_features is "wall" — with "wall-response", [N, 5] = (ζ, τ, ũ)."""
        if self.cfg.uses_wall:
            x = torch.cat([x, wall.to(x.dtype)], dim=1)
        if self.param_encoder is None:  # A5: parameters broadcast to the nodes
            x = torch.cat([x, params.index_select(0, batch)], dim=1)
        h = self.encoder(x, edge_index)
        if self.pool is not None:
            tokens, mask = self.pool(h, batch, region, num_graphs)
            h = self.mesh_attn(h, batch, tokens, mask)
        if self.fusion is not None:
            h = self.fusion(h, batch, self.param_encoder(params), None)
        return h

    def forward(self, data, cycle: bool | None = None, reverse: bool = False, graph: AttentionGraph | None = None,
                *, teacher: dict | None = None, _reconstruct_from: torch.Tensor | None = None):
        """Returns (d_unl [N,3], d_ed [N,3] or None), both normalised displacements; with
        reverse=True a third item, d_rev [N_lab,3] or None: the reverse decoder applied to the true
        unloaded meshes x̂_ED + ρ y of the labelled graphs only (their nodes in batch order; [0,3]
        when none is labelled). Computed only when cfg.reverse_weight > 0.
        graph: data.edge_index already as an AttentionGraph (repeated inference on one mesh); when
        None, data.attention_graph if the batch carries one (trainer.data.batching.GraphTable), else built.
        teacher: with cycle_grad="teacher", the weights (name → tensor, no gradient) the
        reconstruction pass runs on in training; when None, this model's own detached weights.
        _reconstruct_from: internal — only the reconstruction pass Dec_ed(encode(·)), which the
        cycle_grad="unloading" configuration runs with detached weights."""
        cycle = self.cfg.cycle if cycle is None else (cycle and self.cfg.cycle)
        x, ei, batch = data.x, data.edge_index, data.batch
        if batch is None:
            batch = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
        B = int(data.num_graphs) if hasattr(data, "num_graphs") and data.num_graphs else 1
        params, region, wall = data.params, data.region, self._node_extras(data)
        if graph is None and self._uses_attention_graph:  # once for every attention layer and pass
            graph = getattr(data, "attention_graph", None)  # a GraphTable batch brings it assembled
            if graph is None:
                graph = AttentionGraph.from_edge_index(ei, x.shape[0])
        if _reconstruct_from is not None:
            return self._run(self.dec_ed, _reconstruct_from, ei, graph, batch, params, region, B, wall)
        d_unl = self._run(self.dec_unloaded, x, ei, graph, batch, params, region, B, wall)
        d_ed = d_rev = None
        if cycle:
            x_unl = x + self.disp_to_coord * d_unl
            if self.cfg.cycle_grad != "both" and self.training:
                frozen = teacher if self.cfg.cycle_grad == "teacher" and teacher is not None else \
                    {name: p.detach() for name, p in self.named_parameters()}
                d_ed = torch.func.functional_call(self, frozen, (data,), {"graph": graph, "_reconstruct_from": x_unl})
            else:
                d_ed = self._run(self.dec_ed, x_unl, ei, graph, batch, params, region, B, wall)
        if reverse and cycle and self.cfg.reverse_weight > 0:
            d_rev = self._reverse_on_labelled(data, batch, B, graph)
        return (d_unl, d_ed, d_rev) if reverse else (d_unl, d_ed)

    def _node_extras(self, data):
        """The node input besides coordinates: (ζ, τ) [N, 2], with the linear response [N, 5]."""
        wall = getattr(data, "wall", None)
        if not self.cfg.uses_response:
            return wall
        response = getattr(data, "response", None)
        if response is None:
            raise ValueError(f"the {self.cfg.node_features} model needs graphs built with response=True")
        return torch.cat([wall, response.to(wall.dtype)], dim=1)

    @property
    def _uses_attention_graph(self) -> bool:
        return self.cfg.uses_attention_graph

    def _run(self, decoder, x_in, ei, graph, batch, params, region, B: int, wall=None):
        enc_edges = graph if graph is not None and self.cfg.conv == "gat" else ei
        dec_edges = graph if graph is not None and self.cfg.decoder == "gat" else ei
        d = decoder(self.encode(x_in, enc_edges, batch, params, region, B, wall), dec_edges)
        size = self.output_scale(params)
        return d if size is None else d * size.to(d.dtype).index_select(0, batch).unsqueeze(1)

    def _reverse_on_labelled(self, data, batch, B: int, graph: AttentionGraph | None):
        """Dec_ed(encode(x̂_ED + ρ y)) on the labelled graphs' sub-batch (the loss ignores the others)."""
        lab = data.labelled.reshape(-1)[:B].to(torch.bool)
        n_lab = int(lab.sum())
        if n_lab == 0:  # a zero that still touches Dec_ed, so DDP sees a gradient for every weight
            touch = sum(p.sum() for p in self.dec_ed.parameters()) * 0.0
            return touch.expand(0, 3)
        node = lab[batch]
        x_true = data.x + self.disp_to_coord * torch.nan_to_num(data.y, nan=0.0).to(data.x.dtype)
        wall = self._node_extras(data)
        if n_lab == B:
            sub_ei, sub_batch, params, region = data.edge_index, batch, data.params, data.region
        else:
            new_id = torch.cumsum(node.to(torch.long), 0) - 1
            e = node[data.edge_index[0]]  # edges never cross graphs
            sub_ei = new_id[data.edge_index[:, e]]
            sub_batch = (torch.cumsum(lab.to(torch.long), 0) - 1)[batch[node]]
            params, region, x_true = data.params[lab], data.region[node], x_true[node]
            wall = None if wall is None else wall[node]
            if graph is not None and graph.members is not None:  # a direct sum: keep the labelled members
                graph = AttentionGraph.direct_sum([graph.members[i] for i in lab.nonzero().view(-1).tolist()])
            elif self._uses_attention_graph:
                graph = AttentionGraph.from_edge_index(sub_ei, x_true.shape[0])
            else:
                graph = None
        return self._run(self.dec_ed, x_true, sub_ei, graph, sub_batch, params, region, n_lab, wall)


def loss_terms(d_unl, d_ed, data, lambda_cycle: float, d_rev=None, reverse_weight: float = 0.0) -> dict:
    """Supervised MSE over the nodes of labelled graphs (0 when none), cycle MSE over all nodes,
    and (d_rev given: one row per labelled node) the reverse decoder's MSE against −y."""
    node_lab = data.labelled[data.batch] if data.batch is not None else data.labelled.expand(d_unl.shape[0])
    any_lab = bool(node_lab.any())
    if any_lab:
        sup = F.mse_loss(d_unl[node_lab].float(), data.y[node_lab])
    else:
        sup = d_unl.float().sum() * 0.0  # keeps the graph (DDP) with a zero gradient
    if d_ed is None:
        cyc = torch.zeros((), device=d_unl.device)
        total = sup
    else:
        cyc = (d_unl.float() + d_ed.float()).pow(2).mean()
        total = sup + lambda_cycle * cyc
    rev = torch.zeros((), device=d_unl.device)
    if d_rev is not None:  # d_rev holds the labelled graphs' nodes only
        rev = F.mse_loss(d_rev.float(), -data.y[node_lab]) if any_lab else d_rev.float().sum() * 0.0
        total = total + reverse_weight * rev
    return {"loss": total, "sup": sup, "cycle": cyc, "reverse": rev, "labelled_nodes": int(node_lab.sum())}


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def build_model(cfg: ModelConfig, disp_to_coord: float = 0.1, load_coef: tuple = (),
                load_box: tuple = (4.0, 50.0, 14.0, 300.0)) -> HeartUnloadNet:
    """The network of a configuration; disp_to_coord, load_coef and load_box from the run's
    Normalisation (used by output_scale="load" only; load_coef () = a neutral factor of 1)."""
    if cfg.kind != "gnn":
        raise ValueError("build_model builds the graph network; the PCA baseline lives in trainer.network.pca")
    return HeartUnloadNet(cfg, disp_to_coord, load_coef, load_box)


__all__ = ["HeartUnloadNet", "MeshEncoder", "MeshPooling", "CrossAttention", "ParameterEncoder", "ConcatFusion",
           "MLPDecoder", "GATDecoder", "loss_terms", "count_parameters", "build_model"]
