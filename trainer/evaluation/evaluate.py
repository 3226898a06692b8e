"""Evaluation of a run on a split of its store: metrics table (mean ± SD over cases), per-case CSV,
breakdown per parameter value, inference time, PNG plots and a VTU error map."""
from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from storage.schema import PARAM_NAMES

from trainer.training.checkpoint import load_run
from trainer.config import check_device, describe_run
from trainer.errors import TrainerError
from trainer.data.store_cases import check_fingerprint, open_reader, read_store, store_fingerprint
from trainer.data.features import MeshFeatures
from trainer.files import write_csv, write_json
from trainer.evaluation.metrics import aggregate, case_metrics, nodewise_error
from trainer.evaluation.predict import Ensemble, Predictor
from trainer.evaluation.reference import check_reference_fidelity, match_reference, reference_rows, reference_summary

SPLITS = ("test", "val", "train", "all")
HEADLINE = ("dsc_1mm", "dsc_01mm", "hd_mm", "md_mm", "sd_mm")  # the metrics of the paper's table


@dataclass(frozen=True)
class EvaluatedNetwork:
    """What was evaluated: the configuration of each ensemble member (describe_run), their joint
    name, gnn or pca, the device, and the test-time turns about the long axis."""

    config: str
    configuration: list
    kind: str
    device: str
    members: int
    rotations: int


@dataclass(frozen=True)
class Evaluation:
    """A run's (or an ensemble's) scores on a split of a store. Distances in mm, DSC as fractions of
    nodes, times in ms.

    aggregate: metric → (mean, SD over cases) against the store's own labels (`labels_fidelity`)
    reference: the same against the converged solution, when a reference store was given
        (trainer.evaluation.reference.reference_summary), else None
    rows: one metrics row per case (cases.csv); by_parameter: the means per parameter value
    ms_per_case: the network alone, batch 1; ms_per_case_batched at `batch_size`;
    response_ms_per_mesh: the linear FE response, once per mesh, for networks that take it (else None)
    unfinished_runs: {"run", "epoch", "epochs"} of members whose training had not finished
    out_dir, files: where the artefacts went"""

    split: str
    network: EvaluatedNetwork
    aggregate: dict
    rows: list
    by_parameter: list
    ms_per_case: float
    ms_per_case_batched: float
    batch_size: int
    response_ms_per_mesh: float | None
    labels_fidelity: str | None
    unfinished_runs: list
    reference: dict | None
    out_dir: str
    files: list

    @property
    def cases(self) -> int:
        return len(self.rows)

    def mean(self, metric: str) -> float:
        """The mean over cases of `metric` (a key of `aggregate`, e.g. md_mm) against the labels."""
        return self.aggregate[metric][0]

    @property
    def worst_parameter(self) -> dict:
        """The by_parameter row with the largest mean MD."""
        return max(self.by_parameter, key=lambda r: r["md_mm_mean"])

    def as_dict(self) -> dict:
        """The headline figures and facts as one JSON object (`evaluate --json`, summary.json adds
        `aggregate`): the HEADLINE means, ms per case, cases, then the rest."""
        n = self.network
        return {**{k: self.mean(k) for k in HEADLINE}, "ms_per_case": self.ms_per_case, "cases": self.cases,
                "nn_md_mm": self.mean("nn_md_mm"), "ms_per_case_batched": self.ms_per_case_batched,
                "batch_size": self.batch_size, "response_ms_per_mesh": self.response_ms_per_mesh, "split": self.split,
                "rotations": n.rotations, "members": n.members, "config": n.config, "kind": n.kind,
                "configuration": n.configuration, "device": n.device,
                "sd_over_cases": {k: v[1] for k, v in self.aggregate.items()},
                "labels_fidelity": self.labels_fidelity, "unfinished_runs": self.unfinished_runs,
                **({"reference": self.reference} if self.reference is not None else {})}


def _keys_for(state: dict, split: str) -> list | None:
    if split not in SPLITS:
        raise TrainerError(f"unknown split={split!r}; choose {', '.join(SPLITS)}")
    if split == "all":
        return None
    keys = [tuple(int(v) for v in k) for k in state["split"].get(split, [])]
    if not keys:
        raise TrainerError(f"the run's {split} split is empty (split {state['train_config'].get('split')!r})")
    return keys


def unfinished_run(run_dir, state: dict) -> dict | None:
    """{"run", "epoch", "epochs"} of a run whose checkpoint is not its last (killed in training, or
    training still), else None; a checkpoint that does not say is taken as finished."""
    if state.get("finished", True):
        return None
    from trainer.config import TrainConfig

    return {"run": str(run_dir), "epoch": int(state["epoch"]),
            "epochs": TrainConfig.from_dict(state["train_config"]).epochs}


def _member(run_dir: Path, first: dict, split: str, keys, device: str, rotations: int) -> tuple[Predictor, dict]:
    """Another run of an ensemble, checked against the first run's store and split, and its checkpoint."""
    state = load_run(run_dir)
    if state["fingerprint"] != first["fingerprint"]:
        raise TrainerError(f"ensemble run {run_dir} was trained on another store than the first run")
    if keys is not None and _keys_for(state, split) != keys:
        raise TrainerError(f"ensemble run {run_dir} has another {split} split than the first run "
                           f"(another `split` or split seed; `split_seed` fixes it across `seed` values): "
                           f"its training cases would be scored")
    return Predictor(state, device, rotations=rotations), state


def evaluate_run(run_dir, store, split: str = "test", device: str = "cpu", out_dir=None, plots: bool = True,
                 batch_size: int = 32, timing_cases: int = 50, rotations: int = 1, members=(),
                 reference=None) -> Evaluation:
    """Predict every case of the split and compare with the FE unloaded geometry (mm); `rotations`:
    test-time averaging over turns about the long axis (Predictor); `members`: more run directories
    whose networks are averaged with run_dir's (Ensemble). They must have been trained on the same
    store with the same split, so that the split's cases are unseen by every member. `reference`: a
    store of the same ED meshes at converged fidelity; the cases it has are also scored against it,
    the network's answer and the store's own labels (trainer.evaluation.reference). `device`: cpu | cuda."""
    check_device(device)
    run_dir = Path(run_dir)
    state = load_run(run_dir)
    keys = _keys_for(state, split)
    others = [_member(Path(d), state, split, keys, device, rotations) for d in members]
    pred = Ensemble([Predictor(state, device, rotations=rotations)] + [member for member, _ in others])
    unfinished = [u for u in (unfinished_run(run_dir, state), *(unfinished_run(d, st) for d, (_, st) in
                                                                zip(members, others))) if u is not None]
    default = (f"eval_{split}" + (f"_rot{pred.rotations}" if pred.rotations > 1 else "")
               + (f"_ensemble{len(pred.members)}" if len(pred.members) > 1 else ""))
    cases, keys = _evaluated_cases(state, store, split, keys)
    ref_cases = matches = None
    if reference is not None:
        check_reference_fidelity(str(reference), open_reader(reference).attrs.get("fidelity"),
                                 cases.attrs.get("fidelity"))
        ref_cases = read_store(reference)
        matches = match_reference(cases, keys, ref_cases, str(reference))
    # the folder is made once store and run are known to match (no empty folder after a refusal), and
    # checked before the minutes of predicting
    out_dir = _writable_folder(Path(out_dir) if out_dir else run_dir / default)
    items = [(cases.case_features(k), cases.params[k], k[0]) for k in keys]
    disps = pred.predict_many(items, batch_size)
    single_ms = pred.time_ms_per_case(items[:timing_cases], 1)
    batched_ms = pred.time_ms_per_case(items[:max(timing_cases, batch_size)], batch_size)
    response_ms = _response_ms_per_mesh(pred, items[0][0])
    rows, errors, guesses = _case_rows(cases, keys, items, disps)
    if matches is not None:
        ref_rows = reference_rows(guesses, cases, ref_cases, matches)
        nan_row = dict.fromkeys(next(iter(ref_rows.values())), float("nan"))
        for r in rows:
            r.update(ref_rows.get((r["shape_id"], r["case"]), nan_row))
    agg = aggregate(rows)
    scored = Evaluation(
        split=split, network=_network_facts(pred), aggregate=agg,
        rows=rows, by_parameter=_by_parameter(rows), ms_per_case=single_ms, ms_per_case_batched=batched_ms,
        batch_size=batch_size, response_ms_per_mesh=response_ms, labels_fidelity=cases.attrs.get("fidelity"),
        unfinished_runs=unfinished, out_dir=str(out_dir), files=[],
        reference=None if matches is None else reference_summary(ref_rows, reference, ref_cases,
                                                                  cases.attrs.get("fidelity")))
    median = int(np.argsort([r["md_mm"] for r in rows])[len(rows) // 2])

    def write(folder: Path) -> list:
        for name in ARTEFACTS:  # an earlier evaluation's files go first, its summary.json before the rest
            (folder / name).unlink(missing_ok=True)
        write_csv(folder / "cases.csv", rows)
        write_csv(folder / "by_parameter.csv", scored.by_parameter)
        files = ["cases.csv", "by_parameter.csv"]
        files += _error_map_vtu(folder, store, keys[median], cases.ed(keys[median]) + disps[median], errors[median])
        if plots:
            files += _plots(folder, errors, rows[median], items[median][0], errors[median], state.get("history", []))
        write_json(folder / "summary.json", {**scored.as_dict(), "aggregate": agg})  # last: marks a complete evaluation
        return files + ["summary.json"]

    return replace(scored, files=_write_artefacts(out_dir, write))


def _evaluated_cases(state: dict, store, split: str, keys: list | None):
    """(the store's cases, the keys scored): the run's split's cases, from the store it was trained on
    (or one grown from it); with no split (all), every done case of the store."""
    cases = read_store(store, keys)
    if keys is not None:
        check_fingerprint(state["fingerprint"], store_fingerprint(cases.attrs, cases.features), store, grown_ok=True)
        missing = [k for k in keys if k not in cases.params]
        if missing:
            raise TrainerError(f"store {store} lacks {len(missing)} of the run's {len(keys)} {split} cases "
                               f"(e.g. shape {missing[0][0]} case {missing[0][1]}): not the store the run was trained on")
        return cases, keys
    if not cases.keys:
        raise TrainerError(f"store {store} has no done cases")
    return cases, cases.keys


def _case_rows(cases, keys: list, items: list, disps: list) -> tuple[list, list, dict]:
    """(a metrics row per case, each case's nodal errors, each case's predicted unloaded geometry)."""
    rows, errors, guesses = [], [], {}
    for k, (feat, params, _), d in zip(keys, items, disps):
        true = cases.unloaded[k]
        guess = guesses[k] = feat.ed_mm + d
        errors.append(nodewise_error(guess, true))
        rows.append({"shape_id": k[0], "case": k[1], **dict(zip(PARAM_NAMES, map(float, params))),
                     "nodes": int(feat.ed_mm.shape[0]), **case_metrics(guess, true)})
    return rows, errors, guesses


def _network_facts(pred) -> EvaluatedNetwork:
    """What was evaluated: test-time rotations, ensemble members, their configurations, the device."""
    return EvaluatedNetwork(config=" + ".join(m.cfg.config_name for m in pred.members),
                            configuration=[describe_run(m.cfg) for m in pred.members], kind=pred.kind,
                            device=str(pred.device), members=len(pred.members), rotations=pred.rotations)


def _response_ms_per_mesh(pred, feat, repeats: int = 3) -> float | None:
    """ms to compute the linear FE response of one mesh (the fastest of `repeats`, on the CPU) when a
    member network takes it as node input: paid once per mesh, however many parameter sets it is
    unloaded at, on top of ms_per_case (which times the network alone). None otherwise."""
    if not pred.uses_response:
        return None
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        MeshFeatures.response.func(feat)  # computed afresh, not the cached value
        times.append(time.perf_counter() - t)
    return min(times) * 1e3


def _by_parameter(rows: list) -> list:
    out = []
    for axis in PARAM_NAMES:
        for v in sorted({r[axis] for r in rows}):
            sel = [r for r in rows if r[axis] == v]
            a = aggregate(sel, ("md_mm", "hd_mm", "dsc_1mm", "dsc_01mm"))
            out.append({"parameter": axis, "value": v, "cases": len(sel),
                        **{f"{k}_mean": a[k][0] for k in a}, **{f"{k}_sd": a[k][1] for k in a}})
    return out


# what an evaluation writes; an earlier evaluation's are removed first (summary.json first of all), so
# the folder never mixes two evaluations and holds a summary only once all of this one's files are in
ARTEFACTS = ("summary.json", "cases.csv", "by_parameter.csv", "error_map_median_case.vtu", "error_histogram.png",
             "error_map.png", "training_curves.png")


def _writable_folder(out_dir: Path) -> Path:
    """Create the output folder; it must take files (a probe file is written and removed)."""
    if out_dir.exists() and not out_dir.is_dir():
        raise TrainerError(f"out={out_dir} is a file, not a folder")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out_dir, prefix=".heartctl-probe-"):
            pass
    except OSError as exc:
        raise TrainerError(f"cannot write the evaluation to {out_dir}: {exc.strerror or exc}") from None
    return out_dir


def _write_artefacts(out_dir: Path, write) -> list:
    """Run write(out_dir) → [file names]; an OS error (disk full, permissions) is one line."""
    try:
        return write(out_dir)
    except OSError as exc:
        raise TrainerError(f"cannot write the evaluation to {out_dir}: {exc.strerror or exc}") from None


def _error_map_vtu(out_dir: Path, store, key, pred_mm, err) -> list:
    from storage.meshfiles import write_mesh

    try:
        mesh = open_reader(store).mesh(key[0])
        write_mesh(out_dir / "error_map_median_case.vtu", mesh, pred_mm,
                   point_data={"error_mm": err, "ed_mm": mesh.nodes}, units="mm")
        return ["error_map_median_case.vtu"]
    except OSError:
        raise  # the folder failed us (disk full, permissions): one line, by _write_artefacts
    except Exception:  # an optional artefact (e.g. the mesh does not read back); the metrics stand without it
        return []


def _plots(out_dir: Path, errors: list, row: dict, feat, err, history: list) -> list:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    files = []
    allerr = np.concatenate(errors)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.hist(allerr, bins=60, color="tab:blue")
    for t in (0.1, 1.0):
        ax.axvline(t, color="k", ls="--", lw=0.8)
    ax.set_xlabel("node-wise error (mm)")
    ax.set_ylabel("nodes")
    ax.set_title(f"error histogram, {len(errors)} cases (MD {allerr.mean():.3f} mm)")
    fig.tight_layout()
    fig.savefig(out_dir / "error_histogram.png", dpi=120)
    plt.close(fig)
    files.append("error_histogram.png")

    fig, axes = plt.subplots(1, 2, figsize=(9, 4.5))
    x = feat.ed_mm
    for ax, (i, j, name) in zip(axes, ((0, 2, "x–z"), (1, 2, "y–z"))):
        sc = ax.scatter(x[:, i], x[:, j], c=err, s=8, cmap="viridis")
        ax.set_aspect("equal")
        ax.set_title(f"{name} (mm)")
    fig.colorbar(sc, ax=axes, label="error (mm)")
    fig.suptitle(f"median case: shape {row['shape_id']} case {row['case']}, MD {row['md_mm']:.3f} mm, "
                 f"HD {row['hd_mm']:.3f} mm")
    fig.savefig(out_dir / "error_map.png", dpi=120)
    plt.close(fig)
    files.append("error_map.png")

    if history:
        ep = [h["epoch"] for h in history]
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
        def series(name: str) -> list:  # an entry without the value (or None: no validation cases) → a gap
            return [np.nan if h.get(name) is None else float(h[name]) for h in history]

        a1.semilogy(ep, series("train_loss"), label="train loss")
        a1.semilogy(ep, series("train_sup"), label="train supervised")
        a1.semilogy(ep, series("val_loss"), label="validation (supervised)")
        a1.set_xlabel("epoch")
        a1.legend()
        a2.plot(ep, series("val_md_mm"))
        a2.set_xlabel("epoch")
        a2.set_ylabel("validation MD (mm)")
        fig.tight_layout()
        fig.savefig(out_dir / "training_curves.png", dpi=120)
        plt.close(fig)
        files.append("training_curves.png")
    return files
