"""Graph attention (GATConv's mathematics) with the neighbour sum done as one sparse-matrix product.

PyG's GATConv gathers every neighbour's transformed features onto its edge (an E × heads × C
tensor), scales them by the attention weights and scatters them back. On LV meshes (≈ 11 edges per
node with self loops, 512 features) those edge tensors dominate time and memory. Here the heads
are folded into one block-diagonal CSR matrix A of size (N·H) × (N·H) with A[iH+h, jH+h] = α_ij^h,
so the aggregation is A @ X̂ with X̂ = (Θx) viewed as (N·H) × C: one SpMM forward, one SpMM with Aᵀ
and one sampled dense product (SDDMM) backward; nothing of size E × C is stored. The parameters
have GATConv's names and shapes, so state dicts load either way (tests check outputs and
gradients against torch_geometric.nn.GATConv)."""
from __future__ import annotations

import itertools
import math
import warnings
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch_geometric.utils import add_self_loops, remove_self_loops, softmax


@dataclass(frozen=True)
class HeadCSR:
    """The head-folded CSR pattern of one graph for `heads` heads, and its transpose.

    val_perm maps edge-major attention weights α.reshape(-1) ([E, H] row-major) to CSR order."""

    size: int  # N · H
    crow: Tensor
    col: Tensor
    val_perm: Tensor
    crow_t: Tensor
    col_t: Tensor
    t_perm: Tensor  # CSR order of Aᵀ, as indices into A's values


def _csr(crow: Tensor, col: Tensor, values: Tensor, size: int) -> Tensor:
    with warnings.catch_warnings():  # "sparse CSR support is in beta": the kernels used here are tested
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, col, values, (size, size), check_invariants=False)


def shifted_cat(tensors: list, shifts: list, spread: bool | None = None) -> Tensor:
    """torch.cat(tensors, dim=-1) with tensors[k] shifted by the integer shifts[k].

    spread (the default on a GPU): in a fixed number of kernels however many tensors there are —
    one add per tensor would be thousands of launches per batch there. The shifts and lengths
    reach the device in one copy from pinned memory, which does not wait for the work queued
    there, and are spread along the result by repeat_interleave. On a CPU one add per tensor is
    faster (a third of the time for 128 meshes' patterns)."""
    if spread is None:
        spread = tensors[0].is_cuda
    if not spread:
        return torch.cat([t + s for t, s in zip(tensors, shifts)], dim=-1)
    flat = torch.cat(tensors, dim=-1)
    host = torch.tensor([list(shifts), [t.shape[-1] for t in tensors]], dtype=flat.dtype)
    small = host.pin_memory().to(flat.device, non_blocking=True) if flat.is_cuda else host
    return flat + torch.repeat_interleave(small[0], small[1], output_size=flat.shape[-1])


def _summed_row_pointers(pointers: list, offsets: list) -> Tensor:
    """CSR row pointers of a block-diagonal matrix from its blocks': each block's but its last entry,
    shifted by the entries before it, then the last block's closing entry."""
    return shifted_cat([p[:-1] for p in pointers] + [pointers[-1][-1:]], list(offsets) + [offsets[-1]])


def _crow(rows: Tensor, n_rows: int) -> Tensor:
    crow = torch.zeros(n_rows + 1, dtype=torch.long, device=rows.device)
    crow[1:] = torch.cumsum(torch.bincount(rows, minlength=n_rows), 0)
    return crow


@dataclass(frozen=True)
class AttentionGraph:
    """The edges of a (batched) graph as GATConv uses them: existing self loops removed, one self
    loop per node added, sorted by target node i then source j (CSR rows = targets). Built once per
    forward and shared by every attention layer; head-folded patterns are cached per head count."""

    n_nodes: int
    src: Tensor  # j
    dst: Tensor  # i, sorted
    crow: Tensor  # [N + 1]
    _heads: dict = field(default_factory=dict, repr=False, compare=False)
    _parts: tuple | None = field(default=None, repr=False, compare=False)  # (graphs, node offsets, edge offsets)

    @classmethod
    def from_edge_index(cls, edge_index: Tensor, n_nodes: int) -> "AttentionGraph":
        ei, _ = remove_self_loops(edge_index)
        ei, _ = add_self_loops(ei, num_nodes=n_nodes)
        src, dst = ei[0], ei[1]
        order = torch.argsort(dst * n_nodes + src)
        src, dst = src[order], dst[order]
        return cls(n_nodes, src, dst, _crow(dst, n_nodes))

    @classmethod
    def direct_sum(cls, parts: list) -> "AttentionGraph":
        """The graph of a batch from the graphs of its members, in order (block diagonal: each
        member's CSR rows follow the previous member's, its node numbers shifted by their node
        counts). Equals from_edge_index on the batched edge_index without sorting anything, and
        its head-folded patterns are assembled from the members' (cached per member)."""
        n = [p.n_nodes for p in parts]
        e = [p.n_edges for p in parts]
        node_off = [0, *itertools.accumulate(n)][:-1]
        edge_off = [0, *itertools.accumulate(e)][:-1]
        src = shifted_cat([p.src for p in parts], node_off)
        dst = shifted_cat([p.dst for p in parts], node_off)
        crow = _summed_row_pointers([p.crow for p in parts], edge_off)
        return cls(sum(n), src, dst, crow, _parts=(tuple(parts), node_off, edge_off))

    @property
    def n_edges(self) -> int:
        return int(self.src.shape[0])

    @property
    def members(self) -> tuple | None:
        """The graphs a direct_sum was made of, in order (None for a graph built from edges)."""
        return None if self._parts is None else self._parts[0]

    def heads(self, h: int) -> HeadCSR:
        if h not in self._heads:
            self._heads[h] = self._head_csr(h) if self._parts is None else self._summed_head_csr(h)
        return self._heads[h]

    def _summed_head_csr(self, h: int) -> HeadCSR:
        """The head-folded pattern of a direct sum: the members' patterns, shifted block by block."""
        parts, node_off, edge_off = self._parts
        pats = [p.heads(h) for p in parts]

        def cat(name: str, offsets):
            return shifted_cat([getattr(q, name) for q in pats], [o * h for o in offsets])

        def pointers(name: str):
            return _summed_row_pointers([getattr(q, name) for q in pats], [o * h for o in edge_off])

        return HeadCSR(self.n_nodes * h, pointers("crow"), cat("col", node_off), cat("val_perm", edge_off),
                       pointers("crow_t"), cat("col_t", node_off), cat("t_perm", edge_off))

    def _head_csr(self, h: int) -> HeadCSR:
        n, e, dev = self.n_nodes, self.n_edges, self.src.device
        deg = self.crow[1:] - self.crow[:-1]
        ar_h = torch.arange(h, device=dev)
        pos = torch.arange(e, device=dev) - self.crow[self.dst]  # rank of the edge in its row
        # CSR position of (edge, head): row block of node i, then head h (deg_i entries each), then rank
        place = (self.crow[self.dst] * h).unsqueeze(1) + ar_h.unsqueeze(0) * deg[self.dst].unsqueeze(1) + pos.unsqueeze(1)
        val_perm = torch.empty(e * h, dtype=torch.long, device=dev)
        val_perm[place.reshape(-1)] = torch.arange(e * h, device=dev)
        col = (self.src.unsqueeze(1) * h + ar_h).reshape(-1)[val_perm]
        row = (self.dst.unsqueeze(1) * h + ar_h).reshape(-1)[val_perm]
        size = n * h
        t_perm = torch.argsort(col * size + row)
        return HeadCSR(size, _crow(row, size), col, val_perm, _crow(col, size), row[t_perm], t_perm)


class _HeadSpMM(torch.autograd.Function):
    """out = A(values) @ x for the head-folded pattern; gradients for both the values (SDDMM on A's
    pattern) and x (Aᵀ @ grad). fp32 throughout (sparse kernels; autocast casts the inputs)."""

    @staticmethod
    @torch.amp.custom_fwd(device_type="cuda", cast_inputs=torch.float32)
    def forward(ctx, values: Tensor, x: Tensor, pattern: HeadCSR) -> Tensor:
        ctx.save_for_backward(values, x)
        ctx.pattern = pattern
        return torch.sparse.mm(_csr(pattern.crow, pattern.col, values, pattern.size), x)

    @staticmethod
    @torch.amp.custom_bwd(device_type="cuda")
    def backward(ctx, grad_out: Tensor):
        values, x = ctx.saved_tensors
        p: HeadCSR = ctx.pattern
        grad_out = grad_out.contiguous()
        grad_values = grad_x = None
        if ctx.needs_input_grad[1]:
            grad_x = torch.sparse.mm(_csr(p.crow_t, p.col_t, values.index_select(0, p.t_perm), p.size), grad_out)
        if ctx.needs_input_grad[0]:
            grad_values = torch.sparse.sampled_addmm(_csr(p.crow, p.col, torch.zeros_like(values), p.size),
                                                     grad_out, x.t()).values()
        return grad_values, grad_x, None


class SparseGATConv(nn.Module):
    r"""Graph attention layer (Veličković et al.; PyG's GATConv with self loops), heads concatenated
    or averaged:

    .. math::
        x'_i = \big\Vert_{h=1}^{H} \sum_{j \in \mathcal{N}(i) \cup \{i\}} \alpha^h_{ij} \Theta^h x_j + b,
        \qquad \alpha^h_{ij} = \mathrm{softmax}_j\big(\mathrm{LeakyReLU}_{0.2}
        (a^{h\top}_{s} \Theta^h x_j + a^{h\top}_{t} \Theta^h x_i)\big).

    The sum over j is a sparse-matrix product (see the module docstring). forward takes an
    `AttentionGraph` (built once per batch) or a plain edge_index."""

    def __init__(self, in_channels: int, out_channels: int, heads: int = 1, concat: bool = True,
                 negative_slope: float = 0.2, dropout: float = 0.0):
        super().__init__()
        self.in_channels, self.out_channels, self.heads, self.concat = in_channels, out_channels, heads, concat
        self.negative_slope, self.dropout = negative_slope, dropout
        self.lin = nn.Linear(in_channels, heads * out_channels, bias=False)
        self.att_src = nn.Parameter(torch.empty(1, heads, out_channels))
        self.att_dst = nn.Parameter(torch.empty(1, heads, out_channels))
        self.bias = nn.Parameter(torch.empty(heads * out_channels if concat else out_channels))
        self.reset_parameters()

    def reset_parameters(self):
        nn.init.xavier_uniform_(self.lin.weight)
        for att in (self.att_src, self.att_dst):  # PyG's glorot on the last two dimensions
            bound = math.sqrt(6.0 / (att.shape[-2] + att.shape[-1]))
            nn.init.uniform_(att, -bound, bound)
        nn.init.zeros_(self.bias)

    def forward(self, x: Tensor, graph: AttentionGraph | Tensor) -> Tensor:
        if not isinstance(graph, AttentionGraph):
            graph = AttentionGraph.from_edge_index(graph, x.shape[0])
        H, C = self.heads, self.out_channels
        xp = self.lin(x).view(-1, H, C)
        a_src = (xp * self.att_src).sum(-1)  # [N, H]
        a_dst = (xp * self.att_dst).sum(-1)
        # index_select, not x[idx]: its gradient is an index_add, where indexing's sorts the indices
        logits = F.leaky_relu(a_src.index_select(0, graph.src) + a_dst.index_select(0, graph.dst), self.negative_slope)
        alpha = softmax(logits, ptr=graph.crow)  # [E, H]; edges sorted by target: segment reductions
        alpha = F.dropout(alpha, self.dropout, self.training)
        pattern = graph.heads(H)
        values = alpha.reshape(-1).index_select(0, pattern.val_perm)
        out = _HeadSpMM.apply(values, xp.reshape(-1, C), pattern).view(-1, H, C)
        out = out.reshape(-1, H * C) if self.concat else out.mean(dim=1)
        return out + self.bias

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.in_channels}, {self.out_channels}, heads={self.heads})"


__all__ = ["AttentionGraph", "HeadCSR", "SparseGATConv"]
