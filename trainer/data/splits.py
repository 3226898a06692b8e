"""Train / validation / test splits of a store's done cases (by shape, leave-one-value-out, or the
store's own split) and the supervision-ratio mask (which training cases keep their label)."""
from __future__ import annotations

import math

import numpy as np

from storage.schema import PARAM_NAMES

from trainer.errors import TrainerError

AXIS_ALIASES = {
    "p": "pressure_mmhg", "pressure": "pressure_mmhg", "pressure_mmhg": "pressure_mmhg",
    "c": "stiffness_pa", "stiffness": "stiffness_pa", "stiffness_pa": "stiffness_pa",
    "endo": "helix_endo_deg", "helix_endo_deg": "helix_endo_deg",
    "epi": "helix_epi_deg", "helix_epi_deg": "helix_epi_deg",
}
TEST_FRACTION = 0.3  # of shapes
VAL_SHAPE_FRACTION = 0.15  # of training shapes, when there are ≥ 4 of them
VAL_CASE_FRACTION = 0.1  # of training cases otherwise (validation only steers LR and early stopping)

Key = tuple  # (shape_id, k)


def parse_split(spec: str) -> dict:
    """'shape' | 'shape:F' (test fraction F of the shapes, 0 < F < 1; 'shape' is F = TEST_FRACTION) |
    'lovo:P=10' (also C=, endo=, epi=) | 'source' → a dict describing the split."""
    text = str(spec).strip()
    if text == "shape":
        return {"kind": "shape"}
    if text.startswith("shape:"):
        try:
            fraction = float(text[len("shape:"):])
        except ValueError:
            fraction = float("nan")
        if not 0.0 < fraction < 1.0:
            raise TrainerError(f"split={spec!r}: write shape:F with a test fraction of the shapes 0 < F < 1, "
                               f"e.g. shape:0.1")
        return {"kind": "shape", "test_fraction": fraction}
    if text == "source":
        return {"kind": "source"}
    if text.startswith("lovo:"):
        body = text[len("lovo:"):]
        if "=" not in body:
            raise TrainerError(f"split={spec!r}: write lovo:AXIS=VALUE, e.g. lovo:P=10 (axes P, C, endo, epi)")
        axis, value = body.split("=", 1)
        name = AXIS_ALIASES.get(axis.strip().lower())
        if name is None:
            raise TrainerError(f"split={spec!r}: unknown axis {axis.strip()!r}; use P, C, endo or epi")
        try:
            v = float(value)
        except ValueError:
            raise TrainerError(f"split={spec!r}: {value.strip()!r} is not a number") from None
        if not math.isfinite(v):
            raise TrainerError(f"split={spec!r}: the value must be finite")
        return {"kind": "lovo", "axis": name, "value": v}
    raise TrainerError(f"unknown split={spec!r}; use shape, lovo:P=10 (or C=, endo=, epi=) or source")


def _case_val_split(train: list, seed: int) -> tuple[list, list]:
    if len(train) < 2:
        return train, []
    rng = np.random.default_rng([seed, 1])
    n_val = max(1, int(round(VAL_CASE_FRACTION * len(train))))
    idx = rng.permutation(len(train))
    val = sorted(train[i] for i in idx[:n_val])
    keep = sorted(train[i] for i in idx[n_val:])
    return keep, val


def make_split(keys: list, params: dict, spec: str | dict, seed: int, store_attrs: dict | None = None) -> dict:
    """Split case keys [(shape_id, k)] into {"train", "val", "test"} (sorted lists of keys).

    shape: 30 % of the shapes (seeded) are test (shape:F: the fraction F, at least one shape); of the
           rest, 15 % of shapes are validation when there are at least 4, else 10 % of the training
           cases. No shape is in train and test.
    lovo:  the cases whose parameter equals the value are test; validation is 10 % of the rest.
    source: the store's root attribute `splits` = {"train": [shape ids], "test": [...], "val": [...]}.
    `params` maps a key to its 4 parameters (PARAM_NAMES order)."""
    s = parse_split(spec) if isinstance(spec, str) else spec
    keys = sorted((int(a), int(b)) for a, b in keys)
    if not keys:
        raise TrainerError("the store has no done cases to split")
    shapes = sorted({k[0] for k in keys})
    if s["kind"] == "shape":
        if len(shapes) < 2:
            raise TrainerError(f"`split` shape needs ≥ 2 shapes with done cases, the store has {len(shapes)}")
        rng = np.random.default_rng([seed, 0])
        order = [shapes[i] for i in rng.permutation(len(shapes))]
        n_test = min(len(shapes) - 1, max(1, int(round(s.get("test_fraction", TEST_FRACTION) * len(shapes)))))
        test_shapes = set(order[:n_test])
        rest = order[n_test:]
        val_shapes = set(rest[:max(1, int(round(VAL_SHAPE_FRACTION * len(rest))))]) if len(rest) >= 4 else set()
        test = [k for k in keys if k[0] in test_shapes]
        if val_shapes:
            train = [k for k in keys if k[0] not in test_shapes and k[0] not in val_shapes]
            val = [k for k in keys if k[0] in val_shapes]
        else:
            train, val = _case_val_split([k for k in keys if k[0] not in test_shapes], seed)
    elif s["kind"] == "lovo":
        col = PARAM_NAMES.index(s["axis"])
        values = sorted({float(params[k][col]) for k in keys})
        held = [k for k in keys if math.isclose(float(params[k][col]), s["value"], rel_tol=0, abs_tol=1e-9)]
        if not held:
            raise TrainerError(f"`split` lovo: no done case has {s['axis']} = {s['value']:g}; "
                               f"the store has {', '.join(f'{v:g}' for v in values)}")
        if len(held) == len(keys):
            raise TrainerError(f"`split` lovo: every case has {s['axis']} = {s['value']:g}, nothing is left to train on")
        held_set = set(held)
        train, val = _case_val_split([k for k in keys if k not in held_set], seed)
        test = held
    elif s["kind"] == "source":
        sets = source_shape_sets(store_attrs or {})
        if sets["train"] & sets["test"] or sets["train"] & sets["val"] or sets["val"] & sets["test"]:
            raise TrainerError("`split` source: the store's splits share shapes")
        train = [k for k in keys if k[0] in sets["train"]]
        test = [k for k in keys if k[0] in sets["test"]]
        val = [k for k in keys if k[0] in sets["val"]]
        if not val:
            train, val = _case_val_split(train, seed)
    else:  # pragma: no cover
        raise TrainerError(f"unknown split kind {s['kind']!r}")
    if not train:
        raise TrainerError(f"split={spec if isinstance(spec, str) else s['kind']}: no training cases")
    return {"train": sorted(train), "val": sorted(val), "test": sorted(test)}


SOURCE_NAMES = {"train": "train", "training": "train", "val": "val", "valid": "val", "validation": "val",
                "test": "test", "testing": "test"}


def source_shape_sets(attrs: dict) -> dict:
    """{"train", "val", "test"} → shape ids, from the store root's `splits` attribute or from the
    shapes' `source_split` attributes (stores imported from the paper's dataset)."""
    src = attrs.get("splits")
    if isinstance(src, dict) and "train" in src and "test" in src:
        return {name: {int(v) for v in src.get(name, [])} for name in ("train", "val", "test")}
    per_shape = attrs.get("shape_source_split") or {}
    sets = {"train": set(), "val": set(), "test": set()}
    for shape, name in per_shape.items():
        if name is not None and str(name).lower() in SOURCE_NAMES:
            sets[SOURCE_NAMES[str(name).lower()]].add(int(shape))
    if not sets["train"] or not sets["test"]:
        raise TrainerError("`split` source: the store records no source split with train and test shapes "
                           "(root attribute 'splits' or per-shape 'source_split')")
    return sets


def subsample_shapes(train: list, fraction: float, seed: int) -> list:
    """The training cases of round(fraction · n) of the training shapes (at least 1), seeded; for
    learning curves. Validation and test are left as they are. The kept shapes are a prefix of one
    seeded order, so a smaller fraction keeps a subset of a larger one's shapes (nested curves)."""
    if fraction >= 1.0:
        return sorted(train)
    shapes = sorted({k[0] for k in train})
    n = max(1, int(round(fraction * len(shapes))))
    rng = np.random.default_rng([seed, 3])
    kept = {shapes[i] for i in rng.permutation(len(shapes))[:n]}
    return sorted(k for k in train if k[0] in kept)


def supervised_subset(train: list, sr: float, seed: int) -> set:
    """The training cases that keep their label: round(SR · n) of them (at least 1), seeded.
    The others contribute only the cycle term (their targets are removed from the graphs)."""
    train = sorted(train)
    if sr >= 1.0:
        return set(train)
    n = max(1, int(round(sr * len(train))))
    rng = np.random.default_rng([seed, 2])
    return {train[i] for i in rng.permutation(len(train))[:n]}
