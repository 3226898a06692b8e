"""Batches of case graphs gathered from flat tensors instead of collated graph by graph.

PyG's DataLoader builds every batch with `Batch.from_data_list`: a Python loop over the graphs and
their attributes, ~0.09 ms per 643-node graph on one core (11 ms for a batch of 128, a fifth of a
training step at the GPU goal of 2,000 graphs/s, and the loop waits for it). The cases of a sweep
share few meshes (one per shape), so a `GraphTable` holds a split once as flat tensors, node
attributes end to end and each distinct mesh's edges once, and builds a batch from a list of case
indices by slicing and concatenating those tensors: the same `Batch` (tested field by field) in a
third of the time on a CPU. On a GPU the table lives on the device: a batch is built there without
waiting for the GPU, and a step copies only its graphs' indices to it."""
from __future__ import annotations

from typing import Iterable, Iterator, Sequence

import numpy as np
import torch
from torch_geometric.data import Batch, Data

from trainer.network.sparse_gat import AttentionGraph, shifted_cat

NODE_KEYS = ("x", "y", "wall", "region", "response")  # one row per node (trainer.data.features.case_graph)
GRAPH_KEYS = ("params", "labelled", "key")  # one row per graph


class GraphTable:
    """The graphs of one split (trainer.data.features.case_graph) as flat tensors on `device`;
    `table.batch(indices)` equals `Batch.from_data_list([graphs[i] for i in indices])`. With
    `attention`, the batch also carries `attention_graph`: the sparse GAT kernel's AttentionGraph,
    assembled from each mesh's (built once) instead of sorted from the batch's edges every step.

    Graphs whose edge_index is the same tensor (the cases of one shape) share one stored copy of
    the edges. Every graph must carry the same attributes, all of them in NODE_KEYS, GRAPH_KEYS or
    edge_index."""

    def __init__(self, graphs: Sequence[Data], device: torch.device | str = "cpu", attention: bool = False,
                 attention_device: torch.device | str | None = None):
        if not len(graphs):
            raise ValueError("a graph table needs at least one graph")
        self.device = torch.device(device)
        keys = set(graphs[0].keys())
        unknown = keys - set(NODE_KEYS) - set(GRAPH_KEYS) - {"edge_index"}
        if unknown or "edge_index" not in keys or "x" not in keys:
            raise ValueError(f"a graph table holds case graphs (x, edge_index, {', '.join(NODE_KEYS[1:] + GRAPH_KEYS)}); "
                             f"got attributes {sorted(keys)}")
        if any(set(g.keys()) != keys for g in graphs):
            raise ValueError("the graphs of a table must all carry the same attributes")
        self.node_keys = [k for k in NODE_KEYS if k in keys]
        self.graph_keys = [k for k in GRAPH_KEYS if k in keys]
        self.n_nodes = np.array([g.num_nodes for g in graphs], dtype=np.int64)
        self.node_start = np.concatenate([[0], np.cumsum(self.n_nodes)[:-1]]).astype(np.int64)
        topo_of: dict = {}
        edges, topology = [], np.empty(len(graphs), dtype=np.int64)
        for i, g in enumerate(graphs):
            ei = g.edge_index
            tag = (ei.data_ptr(), ei.storage_offset(), tuple(ei.shape), g.num_nodes)
            if tag not in topo_of:
                topo_of[tag] = len(edges)
                edges.append(ei)
            topology[i] = topo_of[tag]
        self.topology = topology
        self.n_edges = np.array([int(e.shape[1]) for e in edges], dtype=np.int64)
        self._edge_list = [e.to(self.device) for e in edges]
        self.attention = attention
        # where the attention graphs live: the device the model runs on (a batch's tensors follow it
        # there with Batch.to, its attention graph would not)
        self.attention_device = torch.device(attention_device) if attention_device is not None else self.device
        self._attention: dict = {}  # topology → its AttentionGraph (self loops, CSR order, head patterns)
        self._nodes = {k: torch.cat([g[k] for g in graphs], dim=0).to(self.device) for k in self.node_keys}
        self._graphs = {k: torch.cat([g[k] for g in graphs], dim=0).to(self.device) for k in self.graph_keys}
        for k, v in self._graphs.items():
            if v.shape[0] != len(graphs):
                raise ValueError(f"graph attribute {k!r} must have one row per graph")

    def __len__(self) -> int:
        return len(self.n_nodes)

    @property
    def n_topologies(self) -> int:
        return len(self.n_edges)

    def batch(self, indices: Sequence[int]) -> Batch:
        """The graphs `indices` (in that order) as one PyG Batch on the table's device."""
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        if not idx.size:
            raise ValueError("a batch needs at least one graph")
        dev, b = self.device, len(idx)
        n = self.n_nodes[idx]
        ptr = np.concatenate([[0], np.cumsum(n)])
        # the few per-graph integers reach a GPU in asynchronous copies from pinned memory (a plain
        # copy would wait for the steps still queued there; shifted_cat makes the other); everything
        # else is gathered on the device
        host = torch.from_numpy(np.concatenate([idx, n, ptr]))
        small = host.pin_memory().to(dev, non_blocking=True) if dev.type == "cuda" else host
        idx_t, n_t, ptr_t = small[:b], small[b:2 * b], small[2 * b:]
        spans = [(int(s), int(s + c)) for s, c in zip(self.node_start[idx], n)]
        # graph i's edges, numbered from its first node
        edge_index = shifted_cat([self._edge_list[t] for t in self.topology[idx]], ptr[:-1].tolist())
        out = Batch(edge_index=edge_index, **{k: torch.cat([v[s:e] for s, e in spans]) for k, v in self._nodes.items()},
                    **{k: v[idx_t] for k, v in self._graphs.items()})
        out.batch = torch.repeat_interleave(torch.arange(b, device=dev), n_t, output_size=int(ptr[-1]))
        out.ptr = ptr_t
        out._num_graphs = b
        if self.attention:
            out.attention_graph = AttentionGraph.direct_sum([self._attention_graph(t) for t in self.topology[idx]])
        return out

    def _attention_graph(self, topology: int) -> AttentionGraph:
        """One mesh's AttentionGraph, built on first use and kept (its head patterns too)."""
        if topology not in self._attention:
            edges = self._edge_list[topology].to(self.attention_device)
            n = int(self.n_nodes[np.flatnonzero(self.topology == topology)[0]])
            self._attention[topology] = AttentionGraph.from_edge_index(edges, n)
        return self._attention[topology]

    def batches(self, index_batches: Iterable[Sequence[int]]) -> Iterator[Batch]:
        for indices in index_batches:
            yield self.batch(indices)


def table_device(graphs: list, device: torch.device) -> torch.device:
    """Where a split's GraphTable lives: on a CUDA device when it takes under a quarter of the free
    memory there (batches are then built there, nothing is copied per step), else host memory."""
    if device.type != "cuda" or not graphs:
        return torch.device("cpu")
    edges = {g.edge_index.data_ptr(): g.edge_index for g in graphs}  # shared by the cases of a mesh
    nbytes = sum(v.numel() * v.element_size() for g in graphs for k, v in g.items() if k != "edge_index") \
        + sum(e.numel() * e.element_size() for e in edges.values())
    free, _ = torch.cuda.mem_get_info(device)
    return device if nbytes < 0.25 * free else torch.device("cpu")


def chunks(n: int, size: int) -> list:
    """[0..size), [size..2·size), … covering range(n): the batches of an unshuffled pass."""
    return [list(range(i, min(i + size, n))) for i in range(0, n, size)]


__all__ = ["GraphTable", "chunks", "table_device", "NODE_KEYS", "GRAPH_KEYS"]
