"""A trained run as a predictor (network or PCA baseline), and unloading a user's ED mesh by the
network (`gnn`) or by the network's guess refined with inverse FE (`hybrid`)."""
from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from trainer.training.memory import tune_allocator
from trainer.data.augment import rotate_xy
from trainer.training.checkpoint import check_finite_weights, load_run
from trainer.config import TrainConfig
from trainer.errors import TrainerError
from trainer.data.store_cases import fingerprint_value
from trainer.data.features import MeshFeatures, case_graph, mesh_features
from trainer.data.normalisation import Normalisation


class Predictor:
    """Unloading displacement X − x_ED (mm) of ED meshes, from a run's best checkpoint.

    rotations K > 1: test-time averaging over the long-axis symmetry (trainer.data.augment). Each case is
    predicted K times, turned about z by 2πj/K (j = 0…K−1) with every prediction turned back by
    −2πj/K, and the K displacements are averaged: exact for the FE problem, it averages out the
    network's lack of symmetry, at K times the inference cost. Best with a network trained with
    `--rotate-deg 180`, which has seen every orientation (docs/training.md, "Accuracy")."""

    def __init__(self, state: dict, device: str | torch.device = "cpu", which: str = "best_model",
                 rotations: int = 1):
        tune_allocator()
        if int(rotations) < 1:
            raise TrainerError(f"`rotations` must be ≥ 1, got {rotations}")
        self.rotations = int(rotations)
        self._attention: dict = {}  # id(mesh edges) → (edges, AttentionGraph on self.device)
        self._runners: OrderedDict = OrderedDict()  # id(MeshFeatures) → (features, PreparedCase), last few
        self.state = state
        self.cfg = TrainConfig.from_dict(state["train_config"])
        self.norm = Normalisation.from_dict(state["normalisation"])
        self.kind = state["kind"]
        self.device = torch.device(device)
        weights = state.get(which) or state.get("model")
        if weights is None:
            raise TrainerError("checkpoint holds no model weights")
        if not isinstance(weights, dict) or not all(isinstance(v, torch.Tensor) for v in weights.values()):
            raise TrainerError("checkpoint is damaged: its model weights are not a dict of tensors")
        check_finite_weights(weights, self.cfg.config_name)
        if self.kind == "pca":
            if self.rotations > 1:
                raise TrainerError("`rotations` averages a network; the PCA baseline takes no rotations")
            from trainer.network.pca import PCABaseline

            self.pca = PCABaseline.from_checkpoint(weights)
            self.model = None
        elif self.kind == "gnn":
            from trainer.network.model import build_model

            self.model = build_model(self.cfg.model, self.norm.disp_to_coord, self.norm.load_coef, self.norm.load_box)
            try:
                self.model.load_state_dict(weights)
            except (RuntimeError, KeyError) as exc:
                raise TrainerError(f"checkpoint weights do not fit the {self.cfg.config_name} model: "
                                   f"{str(exc).splitlines()[0][:120]}") from None
            self.model.to(self.device).eval()
        else:
            raise TrainerError(f"checkpoint of unknown kind {self.kind!r}")

    @classmethod
    def from_run(cls, run_dir, device: str = "cpu", rotations: int = 1) -> "Predictor":
        return cls(load_run(run_dir), device, rotations=rotations)

    @property
    def run_label(self) -> str:
        label = f"{self.cfg.config_name} ({self.kind})"
        return f"shipped with heartctl, {label}, docs/model-card.md" if self.state.get("shipped") else label

    def sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @torch.no_grad()
    def predict_many(self, items: list, batch_size: int = 32) -> list:
        """items: [(MeshFeatures, params [4], cache key or None)] → [displacement mm [n,3]]."""
        if self.kind == "pca":
            return _finite([self.pca.predict(f, p, self.norm, key) for f, p, key in items], self.run_label)
        if self._single_cases(batch_size):
            return _finite([self._mm(self._single(f, p)) for f, p, _ in items], self.run_label)
        out = []
        for i in range(0, len(items), batch_size):
            chunk = items[i:i + batch_size]
            d = self._mm(self._forward(self._batch(chunk)))
            sizes = [f.ed_mm.shape[0] for f, _, _ in chunk]
            out.extend(np.split(d, np.cumsum(sizes)[:-1]))
        return _finite(out, self.run_label)

    def _mm(self, d: torch.Tensor) -> np.ndarray:
        return (d.float() * self.norm.disp_scale_mm).cpu().numpy().astype(np.float64)

    def _single_cases(self, batch_size: int) -> bool:
        """One case at a time through a PreparedCase (trainer.network.prepared): everything that depends on the
        mesh only done once per mesh, and on a GPU the forward pass replayed as a CUDA graph."""
        return batch_size == 1 and self.rotations == 1 and self.kind == "gnn"

    def _single(self, feat: MeshFeatures, params, keep: int = 8) -> torch.Tensor:
        """Normalised displacement [n, 3] of one case by its mesh's PreparedCase, made on first use and
        kept by the features' identity (the features kept with it, so the id stays theirs) for the
        last `keep` meshes."""
        from torch_geometric.data import Batch

        from trainer.network.prepared import PreparedCase

        key, g = id(feat), self.graph(feat, params)
        if key in self._runners:
            self._runners.move_to_end(key)
        else:
            self._runners[key] = (feat, PreparedCase(self.model, Batch.from_data_list([g]).to(self.device)))
        while len(self._runners) > keep:
            self._runners.popitem(last=False)
        return self._runners[key][1](g.x.to(self.device), g.params.to(self.device))

    def _batch(self, items: list):
        """The cases [(MeshFeatures, params, key)] as one batch on the device; for the sparse GAT
        kernel it carries its attention graph, assembled from each mesh's (built once per mesh)."""
        from torch_geometric.data import Batch

        batch = Batch.from_data_list([self.graph(f, p) for f, p, _ in items]).to(self.device)
        if self.cfg.model.uses_attention_graph:
            from trainer.network.sparse_gat import AttentionGraph

            batch.attention_graph = AttentionGraph.direct_sum([self._mesh_attention(f) for f, _, _ in items])
        return batch

    def _mesh_attention(self, feat: MeshFeatures):
        key = id(feat.edge_index)
        if key not in self._attention:  # the edges are kept with it, so the id stays theirs
            from trainer.network.sparse_gat import AttentionGraph

            edges = feat.edge_index
            self._attention[key] = (edges, AttentionGraph.from_edge_index(edges.to(self.device), feat.ed_mm.shape[0]))
        return self._attention[key][1]

    def graph(self, feat: MeshFeatures, params):
        """One unlabelled case as this network's input graph."""
        return case_graph(feat, params, self.norm, response=self.cfg.model.uses_response)

    def _forward(self, batch) -> torch.Tensor:
        """Normalised unloading displacement of a batch [N, 3], averaged over self.rotations turns."""
        if self.rotations == 1:
            return self.model(batch, cycle=False)[0]
        x, response = batch.x, getattr(batch, "response", None)
        total = None
        for j in range(self.rotations):
            angle = torch.full((x.shape[0],), 2.0 * math.pi * j / self.rotations, device=x.device)
            batch.x = rotate_xy(x, angle)
            if response is not None:
                batch.response = rotate_xy(response, angle)
            d = rotate_xy(self.model(batch, cycle=False)[0].float(), -angle)
            total = d if total is None else total + d
        batch.x = x
        if response is not None:
            batch.response = response
        return total / self.rotations

    def predict(self, feat: MeshFeatures, params, key=None) -> np.ndarray:
        return self.predict_many([(feat, params, key)], 1)[0]

    def time_ms_per_case(self, items: list, batch_size: int = 1, repeats: int = 1, warmup: int = 2) -> float:
        """Mean wall time per case of the model alone at a batch size, ms (graph building and
        host→device copies excluded; `warmup` untimed calls first)."""
        if not items:
            return float("nan")
        if self.kind == "pca":
            t = time.perf_counter()
            for f, p, key in items:
                self.pca.predict(f, p, self.norm, key)
            return (time.perf_counter() - t) / len(items) * 1e3
        with torch.no_grad():
            if self._single_cases(batch_size):  # as predict_many: a prepared runner per mesh, made untimed
                keep = max(8, len({id(f) for f, _, _ in items}))  # (those predict_many made are reused)
                for f, p, _ in items:
                    self._single(f, p, keep)
                runners = self._runners
                inputs = [(runners[id(f)][1], g.x.to(self.device), g.params.to(self.device))
                          for f, g in ((f, self.graph(f, p)) for f, p, _ in items)]
                calls = [lambda run=run, x=x, p=p: run(x, p) for run, x, p in inputs]
            else:
                graphs = [self._batch(items[i:i + batch_size]) for i in range(0, len(items), batch_size)]
                calls = [lambda g=g: self._forward(g) for g in graphs]
            for _ in range(warmup):
                calls[0]()
            self.sync()
            t = time.perf_counter()
            for _ in range(repeats):
                for call in calls:
                    call()
            self.sync()
        return (time.perf_counter() - t) / (len(items) * repeats) * 1e3


def _finite(displacements: list, label: str) -> list:
    """The predictions, or TrainerError if one is not finite (a network that overflows on this input)."""
    for d in displacements:
        if not np.isfinite(d).all():
            raise TrainerError(f"the network {label} predicts a non-finite displacement for this mesh and loading")
    return displacements


class Ensemble:
    """Several trained runs as one predictor: the mean of their unloading displacements (mm), and
    their spread. Members may differ in configuration, seed and normalisation (each builds its own
    graphs); the first member speaks for the ensemble (its grid bounds, normalisation and
    fingerprint). Inference costs the sum of the members'. Independently trained networks err
    partly independently, so the mean is usually closer to the FE answer than any member, and
    where the members disagree the answer is less certain (`spread_mm`)."""

    def __init__(self, members: list):
        if not members:
            raise TrainerError("an ensemble needs at least one run")
        self.members = list(members)
        first = self.members[0]
        self.state, self.cfg, self.norm, self.kind = first.state, first.cfg, first.norm, first.kind
        self.device, self.rotations = first.device, first.rotations

    @classmethod
    def from_runs(cls, run_dirs, device: str = "cpu", rotations: int = 1) -> "Ensemble":
        return cls([Predictor.from_run(Path(d), device, rotations) for d in run_dirs])

    @property
    def run_label(self) -> str:
        return " + ".join(m.run_label for m in self.members)

    @property
    def uses_response(self) -> bool:
        """Whether a member network takes the mesh's linear FE response as node input (one extra
        linear solve per mesh, on the CPU, before its first case)."""
        return any(m.kind == "gnn" and m.cfg.model.uses_response for m in self.members)

    def sync(self) -> None:
        self.members[0].sync()

    def predict_many_with_spread(self, items: list, batch_size: int = 32) -> tuple[list, list]:
        """([mean displacement mm [n,3]], [member spread mm [n]: RMS distance of the members'
        displacements from their mean, 0 for one member]) per item."""
        each = [m.predict_many(items, batch_size) for m in self.members]
        means, spreads = [], []
        for per_case in zip(*each):
            stack = np.stack(per_case)
            mean = stack.mean(axis=0)
            means.append(mean)
            spreads.append(np.sqrt(((stack - mean) ** 2).sum(axis=2).mean(axis=0)))
        return means, spreads

    def predict_many(self, items: list, batch_size: int = 32) -> list:
        return self.predict_many_with_spread(items, batch_size)[0]

    def predict(self, feat: MeshFeatures, params, key=None) -> np.ndarray:
        return self.predict_many([(feat, params, key)], 1)[0]

    def time_ms_per_case(self, items: list, batch_size: int = 1, repeats: int = 1, warmup: int = 2) -> float:
        return sum(m.time_ms_per_case(items, batch_size, repeats, warmup) for m in self.members)


def _each(pred: Predictor | Ensemble) -> list:
    """(label, member) per network: an ensemble's warnings are about each member's training."""
    members = pred.members if isinstance(pred, Ensemble) else [pred]
    return [(f"member {i + 1} ({m.cfg.config_name}): " if len(members) > 1 else "", m) for i, m in enumerate(members)]


def _warnings(pred: Predictor | Ensemble, feat: MeshFeatures, params, units_warned: bool = False) -> list:
    """Inputs outside what the network was trained on. The mesh's length unit is checked once, where
    it is read (storage.meshfiles.units_warning): `units_warned` (that check already warned) leaves
    out the size warning here, which otherwise names a plausible LV the network extrapolates to."""
    out = []
    names = ("pressure", "stiffness", "endo angle", "epi angle")
    r = float(np.sqrt(((feat.ed_mm - feat.ed_mm.mean(axis=0)) ** 2).sum(axis=1).mean()))
    for label, m in _each(pred):
        for name, v, lo, hi in zip(names, params, m.norm.param_lo, m.norm.param_hi):
            if not lo - 1e-9 <= v <= hi + 1e-9:
                out.append(f"{label}{name} {v:g} is outside the training grid [{lo:g}, {hi:g}]: the network extrapolates")
        if not units_warned and not 0.5 <= r / m.norm.scale_mm <= 2.0:
            out.append(f"{label}mesh size {r:.1f} mm (RMS radius) is far from the training meshes' "
                       f"{m.norm.scale_mm:.1f} mm: the network extrapolates")
    return out


def _shape_warnings(pred: Predictor | Ensemble, mesh, units_warned: bool = False) -> list:
    """One line when the mesh's shape descriptors lie outside the training shapes' (recorded in the
    checkpoint as train_descriptors; a checkpoint without them is not compared). `units_warned`, as
    in `_warnings`: the mesh's lengths are in another unit and that one line says so, so no more."""
    from solver.descriptors import outside_range, range_warning, shape_descriptors

    out, mine = [], None
    if units_warned:
        return out
    for label, m in _each(pred):
        table = m.state.get("train_descriptors")
        if not isinstance(table, dict) or not table:
            continue
        if mine is None:
            try:
                mine = shape_descriptors(mesh)
            except (ValueError, IndexError):
                return out
        line = range_warning(outside_range(mine, table))
        if line:
            out.append(label + line)
    return out


def _model_warnings(pred: Predictor | Ensemble, asked: dict) -> list:
    """Warnings for model choices (`base`, `fibres`) the user asked for that the network was not
    trained with: `--method gnn` can only give the answer of the model its store was generated with."""
    out = []
    for label, m in _each(pred):
        trained = m.state.get("fingerprint", {})
        for name, value in asked.items():
            was = fingerprint_value(trained, name)
            if was is not None and value != was:
                out.append(f"{label}--{name} {value}: the network was trained on a store with {name} {was}, and "
                           f"`method` gnn gives that model's answer; use `method` hybrid or fe for {name} {value}")
    return out


@dataclass
class NetworkUnload:
    """An ED mesh unloaded by the network (gnn) or from its guess (hybrid).

    unloaded_nodes [n, 3] mm; network_ms: one forward pass, warm; first_call_ms: the first, graph building
    and linear response included; warnings: lines for the user; run: the network's label; members: the
    ensemble's size; spread_mm [n]: the members' RMS disagreement per node; with_response: whether the
    network takes the linear FE response. Hybrid: inverse (the InverseResult), fallback (the inverse
    started from the ED mesh), guess_error_mm (the guess's largest distance from the answer),
    guess_attempt_s (time lost on a guess the inverse did not converge from)."""

    unloaded_nodes: np.ndarray
    network_ms: float
    first_call_ms: float
    warnings: list
    run: str
    members: int
    spread_mm: np.ndarray
    with_response: bool
    inverse: object = None
    fallback: bool = False
    guess_error_mm: float | None = None
    guess_attempt_s: float | None = None


HYBRID_TOL_MM = 2e-3  # hybrid's inverse stops at this max nodal mismatch (mm) unless `tol_mm` is given


def unload_with_network(mesh, params, run_dirs, method: str = "gnn", fidelity: str = "accurate",
                        base: str = "sliding", tol_mm: float | None = None, device: str = "cpu",
                        fibres: str = "laplace", asked: dict | None = None, rotations: int = 1,
                        max_updates: int | None = None) -> "NetworkUnload":
    """Unload an ED TetMesh (mm) at CaseParameters `params`.

    gnn: X = x_ED + network displacement. hybrid: the network's X as the initial guess of inverse FE
    with `fidelity`, `base` and `fibres` (falls back to X0 = x_ED when the guess folds an element), its
    first forward solve rough (solver.lv.inverse_solve's `rough_first_state`), to a max nodal mismatch of
    `tol_mm` (None: HYBRID_TOL_MM, which keeps the answer a few 1e-3 mm from `method` fe's, far inside
    any preset's discretisation error).
    asked: the model choices the user named explicitly ({"base": …, "fibres": …}); with gnn, those that
    differ from the training store's draw a warning. rotations: test-time averaging (Predictor).
    max_updates: hybrid only, stop after that many inverse updates from the guess (solver.lv.inverse_solve).
    run_dirs: one run directory, or several for an ensemble (their mean; Ensemble).
    Returns a NetworkUnload."""
    if method not in ("gnn", "hybrid"):
        raise TrainerError(f"unknown network method {method!r}")
    run_dirs = [run_dirs] if isinstance(run_dirs, (str, Path)) else list(run_dirs)
    pred = Ensemble.from_runs(run_dirs, device, rotations)
    values = np.array([params.pressure_mmhg, params.stiffness_pa, params.helix_endo_deg, params.helix_epi_deg])
    feat = mesh_features(mesh)
    t = time.perf_counter()
    (disp,), (spread,) = pred.predict_many_with_spread([(feat, values, None)], 1)
    pred.sync()
    first_ms = (time.perf_counter() - t) * 1e3
    net_ms = pred.time_ms_per_case([(feat, values, None)], 1, repeats=5, warmup=3)  # the model alone, warm
    guess = mesh.nodes + disp
    out = NetworkUnload(guess, net_ms, first_ms,
                        _warnings(pred, feat, values, units_warned="units_warning" in mesh.info)
                        + _shape_warnings(pred, mesh, units_warned="units_warning" in mesh.info),
                        pred.run_label, len(pred.members), spread, pred.uses_response)
    if method == "gnn":
        from solver.mesh import MeshError, check_geometry

        out.warnings += _model_warnings(pred, asked or {})
        try:
            check_geometry(guess, mesh.tets)
        except MeshError as exc:
            out.warnings.append(f"the predicted unloaded mesh is not valid ({exc}); use `method` hybrid")
        return out
    from solver.forward import SolveError
    from solver.lv import inverse_solve
    from solver.mesh import MeshError, check_geometry

    fallback = False
    try:
        check_geometry(guess, mesh.tets)
    except MeshError as exc:
        out.warnings.append(f"network guess folds elements ({exc}); inverse FE starts from the ED mesh")
        fallback = True
    tol_mm = HYBRID_TOL_MM if tol_mm is None else tol_mm
    t = time.perf_counter()
    try:
        result = inverse_solve(mesh, params, fidelity, base, initial_unloaded=None if fallback else guess,
                               tol_mm=tol_mm, fibres=fibres, max_updates=max_updates, rough_first_state=True)
    except SolveError as exc:
        if fallback:
            raise
        # the guess is a valid mesh from which inverse FE did not converge: hybrid is never worse than fe
        out.guess_attempt_s = time.perf_counter() - t
        reason = str(exc).splitlines()[0][:100]
        out.warnings.append(f"inverse FE from the network guess did not converge in "
                            f"{out.guess_attempt_s:.1f} s ({reason}); it started again from the ED mesh")
        fallback = True
        try:
            result = inverse_solve(mesh, params, fidelity, base, initial_unloaded=None, tol_mm=tol_mm, fibres=fibres,
                                   max_updates=max_updates)
        except SolveError as again:
            raise SolveError(f"{again} (from the network guess before: {reason})") from None
    out.guess_error_mm = float(np.linalg.norm(guess - result.unloaded_nodes, axis=1).max())
    out.unloaded_nodes, out.inverse, out.fallback = result.unloaded_nodes, result, fallback
    return out
