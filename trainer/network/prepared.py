"""Repeated single-mesh inference with everything that depends only on the mesh done once: the
attention graph (self loops, CSR order, head-folded patterns) is built when the runner is made,
and on a GPU the whole forward pass is captured as a CUDA graph and replayed (one launch instead
of hundreds; the shapes never change for one mesh). New ED coordinates and parameters are copied
into the captured input buffers."""
from __future__ import annotations

import torch

from trainer.network.model import HeartUnloadNet
from trainer.network.sparse_gat import AttentionGraph, SparseGATConv


def _host_sync(fn) -> str | None:
    """Why fn's CUDA work cannot be captured — the first operation in it that waits for the GPU
    (data-dependent shapes: PyG's GATConv removes self loops with a boolean mask) — or None. Checked
    before capturing: a capture that fails part-way leaves the CUDA random generator marked as
    capturing, and every later dropout on that device fails ("Offset increment outside graph
    capture"). The first call, which creates library handles, is not checked."""
    fn()
    previous = torch.cuda.get_sync_debug_mode()
    torch.cuda.set_sync_debug_mode("error")
    try:
        fn()
    except RuntimeError as exc:
        if "synchroniz" not in str(exc):  # out of memory, a real fault: not ours to hide
            raise
        return f"not capturable, it waits for the GPU: {str(exc).splitlines()[0]}"
    finally:
        torch.cuda.set_sync_debug_mode(previous)
    torch.cuda.synchronize()
    return None


class PreparedCase:
    """d_unl = runner(x, params) for graphs with `data`'s mesh (x [N, 3] normalised ED coordinates,
    params [B, 4] scaled parameters). cuda_graph: capture on CUDA devices (falls back to eager,
    with `capture_error` set, when capture fails); bf16: autocast on CUDA."""

    def __init__(self, model: HeartUnloadNet, data, cuda_graph: bool = True, bf16: bool = False):
        self.model = model.eval()
        self.bf16 = bool(bf16 and data.x.is_cuda)
        self.data = data.clone()
        cfg = model.cfg
        self.graph = None
        if cfg.uses_attention_graph:
            self.graph = AttentionGraph.from_edge_index(self.data.edge_index, self.data.num_nodes)
            for h in {m.heads for m in model.modules() if isinstance(m, SparseGATConv)}:
                self.graph.heads(h)
        self.cuda_graph = None
        self.capture_error = None
        self._out = None
        if cuda_graph and self.data.x.is_cuda:
            with torch.cuda.device(self.data.x.device):  # the streams of the data's GPU
                self.capture_error = _host_sync(self._eager)
                if self.capture_error is None:
                    try:
                        self._capture()
                    except Exception as exc:  # some sparse kernels may not be capturable on some CUDA versions
                        self.cuda_graph, self.capture_error = None, f"{type(exc).__name__}: {exc}".splitlines()[0]

    def _eager(self) -> torch.Tensor:
        with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16, enabled=self.bf16):
            return self.model(self.data, cycle=False, graph=self.graph)[0]

    def _capture(self) -> None:
        stream = torch.cuda.Stream()
        stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(stream):
            for _ in range(3):  # warm-up: cuBLAS/cuSPARSE handles and workspaces
                self._eager()
        torch.cuda.current_stream().wait_stream(stream)
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g):
            self._out = self._eager()
        self.cuda_graph = g

    def __call__(self, x: torch.Tensor | None = None, params: torch.Tensor | None = None) -> torch.Tensor:
        if x is not None:
            self.data.x.copy_(x)
        if params is not None:
            self.data.params.copy_(params)
        if self.cuda_graph is None:
            return self._eager()
        with torch.cuda.device(self.data.x.device):
            self.cuda_graph.replay()
            return self._out.clone()


__all__ = ["PreparedCase"]
