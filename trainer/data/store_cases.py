"""Done cases of a store as PyG graphs (one per case, edges from tet edges both ways), the
normalisation fitted on the training split only, and the store fingerprint a run is tied to."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from storage.location import reading_store
from storage.reader import PairReader
from storage.schema import PARAM_NAMES

from trainer.errors import TrainerError
from trainer.data.features import MeshFeatures, case_graph, mesh_features
from trainer.data.normalisation import Normalisation, placed_nodes
from trainer.data.splits import make_split, subsample_shapes, supervised_subset

if TYPE_CHECKING:
    from trainer.training.finetune import Parent


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
                           f"shapes; train on the grown store with a new `run_dir`")
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
        from trainer.training.finetune import load_parent  # (finetune imports this module)

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
