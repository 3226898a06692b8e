"""Scores against a reference store: pairs of the same ED meshes and parameters solved at converged
fidelity (`heartctl generate --fidelity reference` with the same --seed, --nodes and shapes). A
network is scored against its own labels and, beside that, against the reference; the labels
themselves are scored against the reference too (how far the training preset is from the converged
solution of the same model)."""
from __future__ import annotations

import numpy as np

from trainer.errors import TrainerError
from trainer.data.store_cases import ED_TOLERANCE_MM, StoreCases
from trainer.evaluation.metrics import aggregate, case_metrics

REFERENCE_KEYS = ("md_mm", "hd_mm", "dsc_1mm", "dsc_01mm", "sd_mm", "max_mm")


def check_reference_fidelity(location: str, reference_fidelity, labels_fidelity) -> None:
    """TrainerError (one line) unless the reference store is of the `reference` fidelity and finer than
    the evaluated store's labels: scored against a store no finer, the labels would look converged."""
    if reference_fidelity != "reference":
        raise TrainerError(f"reference store {location} is of the {reference_fidelity!r} fidelity; `reference` takes "
                           f"a store generated with the reference fidelity (same `seed` and `nodes`)")
    if labels_fidelity == "reference":
        raise TrainerError(f"reference store {location} is no finer than the evaluated store's labels (both of the "
                           f"'reference' fidelity); score against a finer reference, or evaluate without `reference`")


def match_reference(cases: StoreCases, keys: list, reference: StoreCases, location: str) -> dict:
    """{key of `cases` → key of `reference`} for the keys whose shape and parameters (P, C, θendo, θepi)
    the reference has. A matched shape must have the same ED mesh (node for node within
    ED_TOLERANCE_MM): else TrainerError, since the reference would answer another geometry."""
    by_params: dict[tuple, tuple] = {}
    for rk in reference.keys:
        by_params[(rk[0], *np.round(reference.params[rk], 9))] = rk
    matches, checked = {}, set()
    for key in keys:
        rk = by_params.get((key[0], *np.round(cases.params[key], 9)))
        if rk is None:
            continue
        if key[0] not in checked:
            ours, theirs = cases.features[key[0]], reference.features[rk[0]]
            same = (ours.ed_mm.shape == theirs.ed_mm.shape
                    and np.abs(ours.ed_mm - theirs.ed_mm).max() <= ED_TOLERANCE_MM)
            if not same:
                raise TrainerError(f"reference store {location}: shape {key[0]} has another ED mesh than the "
                                   f"evaluated store's (made with another `seed` or `nodes`?)")
            checked.add(key[0])
        matches[key] = rk
    if not matches:
        raise TrainerError(f"reference store {location} has none of the {len(keys)} evaluated cases (it needs the "
                           f"same shapes, `seed`, `nodes` and parameter values)")
    return matches


def reference_rows(guesses: dict, cases: StoreCases, reference: StoreCases, matches: dict) -> dict:
    """Per matched case: the network's metrics against the reference (`ref_*`) and its labels'
    (`label_ref_*`). guesses: key → predicted unloaded [n, 3] mm."""
    out = {}
    for key, rk in matches.items():
        truth = reference.unloaded[rk]
        net = case_metrics(guesses[key], truth)
        lab = case_metrics(cases.unloaded[key], truth)
        out[key] = {**{f"ref_{k}": net[k] for k in REFERENCE_KEYS},
                    **{f"label_ref_{k}": lab[k] for k in REFERENCE_KEYS}}
    return out


def reference_summary(rows: dict, location: str, reference: StoreCases, labels_fidelity) -> dict:
    """Mean ± SD over the matched cases of the network and of the labels against the reference."""
    values = list(rows.values())
    net = aggregate([{k: r[f"ref_{k}"] for k in REFERENCE_KEYS} for r in values], REFERENCE_KEYS)
    lab = aggregate([{k: r[f"label_ref_{k}"] for k in REFERENCE_KEYS} for r in values], REFERENCE_KEYS)
    return {"store": str(location), "fidelity": reference.attrs.get("fidelity"), "labels_fidelity": labels_fidelity,
            "cases": len(values), "network": net, "labels": lab}
