"""Done cases of a store as PyG graphs (one per case, edges from tet edges both ways), the
normalisation fitted on the training split only, and the store fingerprint a run is tied to."""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch_geometric.data import Data

from storage.store import PARAM_NAMES, PairReader, reading_store

from .config import TrainerError
from .splits import make_split, subsample_shapes, supervised_subset

if TYPE_CHECKING:
    from .finetune import Parent

N_REGIONS = 6  # base / mid / apex × endo / epi half of the wall
TET_EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


# --------------------------------------------------------------------------- normalisation


def load_features(p_hat, box):
    """[B, 8] regressors of a case's displacement size from its normalised parameters p̂ [B, 4]
    (NumPy or torch; clipped to the grid box [0, 1]): 1, ln P, ln C, (ln P)², (ln C)², ln P · ln C,
    θ̂endo, θ̂epi, with P (mmHg) and C (Pa) recovered from p̂ by box = (P_lo, C_lo, P_hi, C_hi)."""
    if isinstance(p_hat, torch.Tensor):
        p, stack, log = p_hat.clamp(0.0, 1.0), torch.stack, torch.log
    else:
        p, stack, log = np.clip(np.asarray(p_hat, dtype=np.float64), 0.0, 1.0), np.stack, np.log
    lo_p, lo_c, hi_p, hi_c = (float(v) for v in box)
    P = log(lo_p + p[:, 0] * (hi_p - lo_p) + 1e-9)
    C = log(lo_c + p[:, 1] * (hi_c - lo_c) + 1e-9)
    return stack([P * 0 + 1, P, C, P * P, C * C, P * C, p[:, 2], p[:, 3]], 1)


N_LOAD_FEATURES = 8
LOAD_RIDGE = 1e-6  # on the non-constant regressors of the displacement-size fit: only to keep it well posed


def fit_load_scale(p_hat: np.ndarray, box, rms_mm: np.ndarray, disp_scale_mm: float) -> tuple:
    """Coefficients a of log(rms / disp_scale) ≈ load_features(p̂, box) · a: the typical size of a case's
    unloading displacement from its loading (pressure, stiffness; helix angles linearly), fitted by
    ridge least squares on the labelled training cases' RMS displacement (mm)."""
    A = load_features(p_hat, box)
    b = np.log(np.maximum(np.asarray(rms_mm, dtype=np.float64), 1e-9) / disp_scale_mm)
    reg = np.diag([0.0] + [LOAD_RIDGE] * (A.shape[1] - 1)) * len(b)
    coef = np.linalg.solve(A.T @ A + reg + 1e-12 * np.eye(A.shape[1]), A.T @ b)
    return tuple(float(v) for v in coef)


def placed_nodes(nodes_mm: np.ndarray, base_nodes: np.ndarray) -> np.ndarray:
    """A mesh's nodes (mm) moved so that their centroid lies on the z axis and the base plane (mean z
    of the base nodes) at z = 0: the frame the generator makes meshes in, whatever the input's placement."""
    x = np.asarray(nodes_mm, dtype=np.float64)
    return x - np.array([*x[:, :2].mean(axis=0), x[np.asarray(base_nodes), 2].mean()])


@dataclass(frozen=True)
class Normalisation:
    """x̂ = (x − centre) / scale for coordinates (mm); ŷ = (X − x) / disp_scale for the unloading
    displacement (mm); p̂ = (p − lo) / (hi − lo) per parameter, lo/hi the store grid's bounds (an axis
    with one value maps to 0); load_coef: log of a case's expected displacement size (in disp_scale
    units) as load_features(p̂) · load_coef (fit_load_scale; () when not fitted). Fitted on the
    training split only."""

    centre_mm: tuple
    scale_mm: float
    disp_scale_mm: float
    param_lo: tuple
    param_hi: tuple
    load_coef: tuple = ()

    @property
    def load_box(self) -> tuple:
        """(P_lo, C_lo, P_hi, C_hi): the grid's pressure (mmHg) and stiffness (Pa) bounds, for load_features."""
        return (float(self.param_lo[0]), float(self.param_lo[1]), float(self.param_hi[0]), float(self.param_hi[1]))

    @property
    def disp_to_coord(self) -> float:
        """A normalised displacement expressed in normalised coordinates (disp_scale / scale)."""
        return self.disp_scale_mm / self.scale_mm

    def coords(self, nodes_mm: np.ndarray, base_nodes: np.ndarray | None = None) -> np.ndarray:
        """Normalised coordinates x̂ = (x − centre) / scale. With `base_nodes` (indices of the mesh's
        base surface nodes) the mesh is first placed in the training frame, whatever its placement
        (placed_nodes: node centroid on the z axis, base plane at z = 0, the frame every generated
        mesh is made in, DESIGN.md), and x̂ = (placed − (0, 0, centre_z)) / scale. The FE answer does
        not depend on where a mesh lies; placed, neither does the network's. A generated mesh moves by
        its centroid's distance from the axis (< 1 mm)."""
        centre = np.asarray(self.centre_mm, dtype=np.float64)
        if base_nodes is not None and len(base_nodes):
            return (placed_nodes(nodes_mm, base_nodes) - np.array([0.0, 0.0, centre[2]])) / self.scale_mm
        return (np.asarray(nodes_mm, dtype=np.float64) - centre) / self.scale_mm

    def params(self, values) -> np.ndarray:
        lo, hi = np.asarray(self.param_lo), np.asarray(self.param_hi)
        span = np.where(hi > lo, hi - lo, 1.0)
        return np.where(hi > lo, (np.asarray(values, dtype=np.float64) - lo) / span, 0.0)

    def as_dict(self) -> dict:
        return {"centre_mm": [float(v) for v in self.centre_mm], "scale_mm": float(self.scale_mm),
                "disp_scale_mm": float(self.disp_scale_mm), "param_lo": [float(v) for v in self.param_lo],
                "param_hi": [float(v) for v in self.param_hi], "load_coef": [float(v) for v in self.load_coef]}

    @classmethod
    def from_dict(cls, d: dict) -> "Normalisation":
        return cls(tuple(d["centre_mm"]), float(d["scale_mm"]), float(d["disp_scale_mm"]), tuple(d["param_lo"]),
                   tuple(d["param_hi"]), tuple(d.get("load_coef", ())))

    @classmethod
    def fit(cls, ed_nodes: list, displacements: list, grid: dict, params: list | None = None) -> "Normalisation":
        """ed_nodes: the ED node arrays of the training cases (placed_nodes: the frame coords works in,
        so that meshes lying anywhere do not inflate the scale); displacements: unloaded − ED of the
        labelled training cases (mm); grid: the store's parameter axes; params: the labelled cases'
        parameters [4] (in `displacements` order), to fit load_coef (None: not fitted)."""
        allx = np.concatenate([np.asarray(x, dtype=np.float64) for x in ed_nodes])
        centre = allx.mean(axis=0)
        scale = float(np.sqrt(((allx - centre) ** 2).sum(axis=1).mean()))
        d = np.concatenate([np.asarray(u, dtype=np.float64) for u in displacements]) if displacements else np.zeros((1, 3))
        disp_scale = float(np.sqrt((d**2).mean()))
        if not (scale > 0 and math.isfinite(scale)):
            raise TrainerError("training ED coordinates have no spread; cannot normalise")
        if not (disp_scale > 1e-9 and math.isfinite(disp_scale)):
            disp_scale = 1.0
        lo = tuple(float(min(grid[a])) for a in PARAM_NAMES)
        hi = tuple(float(max(grid[a])) for a in PARAM_NAMES)
        norm = cls(tuple(float(v) for v in centre), scale, disp_scale, lo, hi)
        if params is None or not displacements:
            return norm
        rms = [float(np.sqrt(np.mean(np.asarray(u, dtype=np.float64) ** 2))) for u in displacements]
        p_hat = np.stack([norm.params(p) for p in params])
        return replace(norm, load_coef=fit_load_scale(p_hat, norm.load_box, rms, disp_scale))


# --------------------------------------------------------------------------- mesh features


def mesh_edges(tets: np.ndarray) -> torch.Tensor:
    """[2, E] long: every tet edge once in each direction, sorted, no duplicates."""
    t = np.asarray(tets, dtype=np.int64)
    e = np.concatenate([t[:, [a, b]] for a, b in TET_EDGES])
    e = np.unique(np.sort(e, axis=1), axis=0)
    both = np.concatenate([e, e[:, ::-1]])
    both = both[np.lexsort((both[:, 1], both[:, 0]))]
    return torch.from_numpy(np.ascontiguousarray(both.T))


def wall_coordinates(nodes: np.ndarray, endo_nodes: np.ndarray, epi_nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ζ, τ) per node: ζ = 0 at the base plane … 1 at the apex (by z), τ = d_endo / (d_endo + d_epi)
    (0 on the endocardium, 1 on the epicardium), from distances to the surface nodes."""
    from scipy.spatial import cKDTree

    z = nodes[:, 2]
    zeta = (z.max() - z) / max(z.max() - z.min(), 1e-12)
    if len(endo_nodes) == 0 or len(epi_nodes) == 0:
        return zeta, np.full(len(nodes), 0.5)
    d_en = cKDTree(nodes[endo_nodes]).query(nodes)[0]
    d_ep = cKDTree(nodes[epi_nodes]).query(nodes)[0]
    tau = d_en / np.maximum(d_en + d_ep, 1e-12)
    return zeta, tau


def node_regions(zeta: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Region id 0..5 = 3 · [τ ≥ ½] + (base, mid, apex third of ζ)."""
    third = np.minimum((zeta * 3).astype(np.int64), 2)
    return third + 3 * (tau >= 0.5).astype(np.int64)


RESPONSE_STIFFNESS_PA = 150.0  # the linear response's material: Guccione C (mid grid), helix ±65°
RESPONSE_PRESSURE_PA = 4000.0  # ũ = u(this pressure) / R: of order 1 on the shape model's LVs


def linear_response_feature(mesh) -> np.ndarray:
    """[n, 3] the dimensionless linear response ũ = u_lin · RESPONSE_PRESSURE_PA / R of a TetMesh
    taken as stress-free: u_lin the nodal displacement per Pa of one linear FE solve at zero strain
    (solver.lv.linear_response; sliding base, Laplace fibres at ±65°, C = RESPONSE_STIFFNESS_PA),
    R the RMS distance of the nodes from their centroid (mm). How this whole shape gives under
    pressure, which a few message-passing hops cannot work out. ũ is unchanged when the mesh is
    scaled and turns with it about z, as the unloading displacement does (trainer.augment).
    Raises TrainerError when the solve fails."""
    from solver.forward import SolveError
    from solver.lv import linear_response
    from solver.parameters import CaseParameters

    nodes = np.asarray(mesh.nodes, dtype=np.float64)
    radius = float(np.sqrt(((nodes - nodes.mean(axis=0)) ** 2).sum(axis=1).mean()))
    try:
        u = linear_response(mesh, CaseParameters(1.0, RESPONSE_STIFFNESS_PA, 65.0, -65.0), "fast")
    except (SolveError, ValueError) as exc:
        raise TrainerError(f"linear response of the mesh failed: {str(exc).splitlines()[0]}") from None
    return u * RESPONSE_PRESSURE_PA / max(radius, 1e-12)


@dataclass
class MeshFeatures:
    """What one mesh topology contributes to its graphs (shared by all cases of a shape)."""

    ed_mm: np.ndarray  # [n,3]
    edge_index: torch.Tensor  # [2,E]
    region: torch.Tensor  # [n] long
    zeta: np.ndarray
    tau: np.ndarray
    tets: np.ndarray = field(repr=False, default=None)
    mesh: object = field(repr=False, default=None)  # the solver TetMesh (surfaces), for the linear response
    base_nodes: np.ndarray | None = field(repr=False, default=None)  # base surface nodes: placement (coords)

    @property
    def coords_placed(self):
        """ed_mm with its base nodes, for Normalisation.coords (the mesh placed in the training frame)."""
        if self.base_nodes is None or not len(self.base_nodes):
            raise TrainerError("these mesh features carry no base nodes to place the mesh by (build them with "
                               "mesh_features from a mesh with a tagged base)")
        return self.ed_mm, self.base_nodes

    @cached_property
    def wall(self) -> torch.Tensor:
        """[n, 2] float32: (ζ, τ) per node."""
        return torch.from_numpy(np.stack([self.zeta, self.tau], axis=1).astype(np.float32))

    @cached_property
    def response(self) -> torch.Tensor:
        """[n, 3] float32: the linear response ũ of this ED geometry (linear_response_feature),
        computed on first use (~45 ms for 350 nodes, ~0.1 s for 700, one core) and shared by every
        case of the shape; an imported case with its own ED geometry (StoreCases.case_features)
        pays its own solve."""
        if self.mesh is None:
            raise TrainerError("these mesh features carry no mesh to compute the linear response on")
        mesh = self.mesh if np.array_equal(self.mesh.nodes, self.ed_mm) else self.mesh.with_nodes(self.ed_mm)
        return torch.from_numpy(linear_response_feature(mesh).astype(np.float32))


def mesh_features(mesh) -> MeshFeatures:
    """Features of a solver TetMesh (nodes in mm)."""
    nodes = np.asarray(mesh.nodes, dtype=np.float64)
    zeta, tau = wall_coordinates(nodes, mesh.endo_nodes(), mesh.epi_nodes())
    return MeshFeatures(nodes, mesh_edges(mesh.tets), torch.from_numpy(node_regions(zeta, tau)), zeta, tau,
                        np.asarray(mesh.tets), mesh, np.asarray(mesh.base_nodes()))


def case_graph(feat: MeshFeatures, params, norm: Normalisation, unloaded_mm: np.ndarray | None = None,
               labelled: bool = True, key=(-1, -1), response: bool = False) -> Data:
    """One case as a graph: x = normalised ED coordinates [n,3] of the mesh placed in the training
    frame (Normalisation.coords); y = normalised unloading
    displacement (NaN when the label is withheld or unknown); params [1,4] in [0,1]; wall [n,2] =
    the wall coordinates (ζ, τ), region [n] their base/mid/apex × endo/epi cell; with `response`,
    response [n,3] = the mesh's linear response ũ (MeshFeatures.response)."""
    x = norm.coords(*feat.coords_placed)
    if unloaded_mm is not None and labelled:
        y = (np.asarray(unloaded_mm, dtype=np.float64) - feat.ed_mm) / norm.disp_scale_mm
    else:
        y = np.full_like(x, np.nan)
    extra = {"response": feat.response} if response else {}
    return Data(x=torch.from_numpy(x.astype(np.float32)), edge_index=feat.edge_index,
                y=torch.from_numpy(y.astype(np.float32)),
                params=torch.from_numpy(norm.params(params).astype(np.float32)).view(1, -1),
                region=feat.region, wall=feat.wall,
                labelled=torch.tensor([bool(labelled and unloaded_mm is not None)]),
                key=torch.tensor([[int(key[0]), int(key[1])]], dtype=torch.long), **extra)


# --------------------------------------------------------------------------- the store


@dataclass
class StoreCases:
    """Done cases of a store in memory: per shape its mesh features, per case params and unloaded."""

    attrs: dict
    features: dict  # shape_id → MeshFeatures
    params: dict  # (s, k) → np.ndarray [4]
    unloaded: dict  # (s, k) → np.ndarray [n,3] mm
    loaded: dict = field(default_factory=dict)  # (s, k) → ED [n,3] mm where it differs from the shape's mesh

    @property
    def keys(self) -> list:
        return sorted(self.params)

    def ed(self, key) -> np.ndarray:
        """The case's own ED geometry (imported datasets: it varies a little within a shape)."""
        return self.loaded.get(key, self.features[key[0]].ed_mm)

    def case_features(self, key) -> MeshFeatures:
        f = self.features[key[0]]
        return replace(f, ed_mm=self.loaded[key]) if key in self.loaded else f

    def displacement(self, key) -> np.ndarray:
        """Unloading displacement X − x_ED of the case, mm."""
        return self.unloaded[key] - self.ed(key)


def open_reader(location) -> PairReader:
    with reading_store(location, keep=(TrainerError,)):
        return PairReader(str(location))


ED_TOLERANCE_MM = 1e-3  # a case whose ED differs more from its shape's mesh keeps its own ED


def read_store(location, keys: list | None = None) -> StoreCases:
    """Read done cases (all, or the given keys) of a store into memory. Generated pairs reproduce
    their shape's ED mesh (round trip ≤ 1e-4 mm); an imported case whose ED differs by more than
    ED_TOLERANCE_MM keeps its own ED, the network's input and the origin of its label."""
    with reading_store(location, keep=(TrainerError,)):
        return _read_store(open_reader(location), keys)


def _read_store(reader: PairReader, keys: list | None) -> StoreCases:
    wanted = None if keys is None else {(int(a), int(b)) for a, b in keys}
    shape_ids = reader.shape_ids() if wanted is None else sorted({k[0] for k in wanted} & set(reader.shape_ids()))
    features, params, unloaded, loaded = {}, {}, {}, {}
    attrs = _split_attrs(reader, shape_ids)
    for case in reader.iter_done(shape_ids):
        key = (case.shape_id, case.index)
        if wanted is not None and key not in wanted:
            continue
        if case.shape_id not in features:
            features[case.shape_id] = mesh_features(reader.mesh(case.shape_id))
        params[key] = np.array([case.params[a] for a in PARAM_NAMES], dtype=np.float64)
        unloaded[key] = np.asarray(case.unloaded, dtype=np.float64)
        ed = np.asarray(case.loaded, dtype=np.float64)
        if np.abs(ed - features[case.shape_id].ed_mm).max() > ED_TOLERANCE_MM:
            loaded[key] = ed
    return StoreCases(attrs, features, params, unloaded, loaded)


def _split_attrs(reader: PairReader, shape_ids: list) -> dict:
    """The store's root attributes plus each shape's source split (for --split source)."""
    attrs = dict(reader.attrs)
    attrs["shape_source_split"] = {s: reader._shape(s).attrs.get("source_split") for s in shape_ids}
    return attrs


def check_split(cfg) -> None:
    """Draw the split, training-shape subset and SR subset of a TrainConfig's store from the done
    cases' keys and parameters alone (no meshes, no graphs): TrainerError for a split the store
    cannot give (a LOVO value it lacks, one shape, no recorded source split). A fresh Ray run checks
    this before its workers start, since they would retry a refusal --max-failures times."""
    with reading_store(cfg.store, keep=(TrainerError,)):
        reader = open_reader(cfg.store)
        keys = reader.done_cases()
        shape_ids = sorted({k[0] for k in keys})
        table = {s: reader.case_params(s) for s in shape_ids}
        params = {k: np.asarray(table[k[0]][k[1]], dtype=np.float64) for k in keys}
        attrs = _split_attrs(reader, shape_ids)
    parts = make_split(keys, params, cfg.split, cfg.data_seed, attrs)
    supervised_subset(subsample_shapes(parts["train"], cfg.train_fraction, cfg.data_seed), cfg.sr, cfg.labels_seed)


def store_fingerprint(attrs: dict, features: dict) -> dict:
    """What ties a run to its store: grid, fidelity, seed, base, and the node count of each shape."""
    return {"grid": attrs.get("grid"), "fidelity": attrs.get("fidelity"), "seed": attrs.get("seed"),
            "base": attrs.get("base"), "fibres": attrs.get("fibres", "laplace"),
            "mesh_nodes": attrs.get("mesh_nodes"), "shape_model_version": attrs.get("shape_model_version"),
            "shape_nodes": {str(s): int(f.ed_mm.shape[0]) for s, f in sorted(features.items())}}


def fingerprint_value(fingerprint: dict, name: str):
    """One entry of a run's store fingerprint; runs from before fibre rules were recorded used laplace."""
    return fingerprint.get(name, "laplace" if name == "fibres" else None)


def grown_shapes(saved: dict, now: dict) -> tuple[int, int] | None:
    """(shapes then, shapes now) when the store of fingerprint `now` is the one of `saved` grown by
    more shapes (`heartctl generate` with a larger --shapes: the same grid otherwise), else None."""
    was, grid = saved.get("grid"), now.get("grid")
    if not (isinstance(was, dict) and isinstance(grid, dict) and "shapes" in was and "shapes" in grid):
        return None
    same = {k: v for k, v in was.items() if k != "shapes"} == {k: v for k, v in grid.items() if k != "shapes"}
    return (int(was["shapes"]), int(grid["shapes"])) if same and int(grid["shapes"]) > int(was["shapes"]) else None


def check_fingerprint(saved: dict, now: dict, location, grown_ok: bool = False) -> None:
    """Raise TrainerError (one line) when the store whose store_fingerprint is `now` is not the one
    the run (fingerprint `saved`) was trained on. A store grown by more shapes since (grown_shapes)
    is refused too, as a changed store (a run resumes only on the cases it started with), unless
    `grown_ok`: evaluation, whose cases are the run's own, stored unchanged in the grown store."""
    grown = grown_shapes(saved, now)
    for name in ("grid", "fidelity", "seed", "base", "fibres"):
        if name == "grid" and grown is not None:
            continue
        if fingerprint_value(saved, name) != now.get(name):
            raise TrainerError(f"store {location} does not match the run: {name} is {now.get(name)!r}, "
                               f"the run was trained on {saved.get(name)!r}")
    if grown is not None and not grown_ok:
        raise TrainerError(f"store {location} changed since the run started: it grew from {grown[0]} to {grown[1]} "
                           f"shapes; train on the grown store with a new --run-dir")
    for s, n in now["shape_nodes"].items():
        if s in saved.get("shape_nodes", {}) and saved["shape_nodes"][s] != n:
            raise TrainerError(f"store {location} does not match the run: shape {s} has {n} nodes, "
                               f"the run's store had {saved['shape_nodes'][s]}")


@dataclass
class DataBundle:
    train: list
    val: list
    test: list
    norm: Normalisation
    split: dict  # name → sorted keys
    labelled: set
    fingerprint: dict
    cases: StoreCases = field(repr=False, default=None)
    parent: Parent | None = field(repr=False, default=None)  # the checkpoint a fine-tuning run starts from
    train_descriptors: dict = field(default_factory=dict)  # {"shapes": [ids], name: [values]} of the training shapes


def build_graphs(cases: StoreCases, keys: list, norm: Normalisation, labelled: set | None = None,
                 response: bool = False) -> list:
    out = []
    for key in keys:
        lab = labelled is None or key in labelled
        out.append(case_graph(cases.case_features(key), cases.params[key], norm, cases.unloaded[key], lab, key,
                              response))
    return out


def build_training_data(store, split: str = "shape", seed: int = 0, sr: float = 1.0,
                        cases: StoreCases | None = None, train_fraction: float = 1.0,
                        response: bool = False, label_seed: int | None = None,
                        norm: Normalisation | None = None) -> DataBundle:
    """Read the store, split it, keep `train_fraction` of the training shapes (learning curves),
    withhold labels outside the SR subset, fit the normalisation on the training split (ED
    coordinates of every training case; displacements of labelled ones), or use `norm` (fine-tuning
    keeps its parent's). `label_seed` draws the SR subset (default: `seed`, which draws the split)."""
    cases = cases or read_store(store)
    if not cases.params:
        raise TrainerError(f"store {store} has no done cases to train on")
    parts = make_split(cases.keys, cases.params, split, seed, cases.attrs)
    parts["train"] = subsample_shapes(parts["train"], train_fraction, seed)
    labelled = supervised_subset(parts["train"], sr, seed if label_seed is None else label_seed)
    train_ed = [placed_nodes(cases.ed(k), cases.features[k[0]].base_nodes) for k in parts["train"]]
    train_lab = [k for k in parts["train"] if k in labelled]
    if norm is None:
        norm = Normalisation.fit(train_ed, [cases.displacement(k) for k in train_lab], cases.attrs["grid"],
                                 [cases.params[k] for k in train_lab])
    return DataBundle(build_graphs(cases, parts["train"], norm, labelled, response),
                      build_graphs(cases, parts["val"], norm, response=response),
                      build_graphs(cases, parts["test"], norm, response=response), norm, parts, labelled,
                      store_fingerprint(cases.attrs, cases.features), cases,
                      train_descriptors=training_descriptors(cases, parts["train"]))


def training_descriptors(cases: StoreCases, keys: list) -> dict:
    """Shape descriptors (solver.descriptors) of the training shapes' ED meshes, as the checkpoint
    keeps them: {"shapes": [shape ids], descriptor name: [one value per shape]}. A mesh the
    descriptors cannot read is left out."""
    from solver.descriptors import descriptor_table, shape_descriptors

    shapes, rows = [], []
    for s in sorted({int(k[0]) for k in keys}):
        mesh = cases.features[s].mesh
        try:
            rows.append(shape_descriptors(mesh))
        except (ValueError, IndexError, AttributeError):
            continue
        shapes.append(s)
    return {"shapes": shapes, **descriptor_table(rows)} if rows else {}


def training_data(cfg, cases: StoreCases | None = None) -> DataBundle:
    """build_training_data for a TrainConfig (store, split, seed, SR, training-shape fraction; the
    linear response on the graphs when the model takes it; with init_from, the parent checkpoint's
    normalisation and the parent itself on the bundle)."""
    parent = None
    if cfg.init_from is not None:
        from .finetune import load_parent  # (finetune imports this module)

        parent = load_parent(cfg)
    bundle = build_training_data(cfg.store, cfg.split, cfg.data_seed, cfg.sr, cases, cfg.train_fraction,
                                 cfg.model.uses_response, cfg.labels_seed, None if parent is None else parent.norm)
    bundle.parent = parent
    if parent is not None:  # the network learned the parent's shapes too: its range is both runs' shapes
        bundle.train_descriptors = merge_descriptors(parent.train_descriptors, bundle.train_descriptors)
    return bundle


def merge_descriptors(first: dict, second: dict) -> dict:
    """Two training_descriptors tables as one (every list concatenated; "shapes" keeps each store's ids)."""
    if not first or not second:
        return dict(first or second)
    return {k: list(first.get(k, [])) + list(second.get(k, [])) for k in dict.fromkeys([*first, *second])}
