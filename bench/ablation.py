"""`heartctl bench ablation`: train several configurations on one store and one split, one after
another with the plain PyTorch loop, and tabulate their held-out metrics — the paper's ablation
table, measured on our data. Each configuration gets its own run directory under the root, so a
rerun resumes unfinished runs and re-evaluates finished ones."""
from __future__ import annotations

import statistics
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from trainer.config import PAPER, TrainConfig, canonical_name, check_device, code_of, named_config
from trainer.errors import TrainerError
from trainer.data.store_cases import training_data
from trainer.evaluation.evaluate import HEADLINE, evaluate_run
from trainer.files import write_csv, write_json
from trainer.training.loop import Dist, fit

TABLE_METRICS = (("md_mm", "MD mm", "min"), ("hd_mm", "HD mm", "min"), ("sd_mm", "SD mm", "min"),
                 ("dsc_1mm", "DSC@1mm", "max"), ("dsc_01mm", "DSC@0.1mm", "max"), ("nn_md_mm", "NN-MD mm", "min"))
# the comparisons a table reports below itself: configuration → the rivals it should beat
KEY_COMPARISONS = (("paper", ("gcn", "pca")), ("paper", ("no-cycle",)), ("reverse", ("no-cycle",)),
                   ("reverse-rampup", ("no-cycle",)), ("fixed-teacher", ("no-cycle",)),
                   ("fixed-teacher-full-cycle", ("no-cycle",)), ("A1ema", ("no-cycle",)), ("mean-teacher", ("A1ema",)),
                   ("mean-teacher", ("no-cycle",)), ("mean-teacher", ("fixed-teacher-full-cycle",)))



@dataclass(frozen=True, kw_only=True)
class RunScore:
    """A trained run scored on its test split: evaluate's HEADLINE metrics and the nearest-node MD (means
    over the cases; mm or fractions), ms per case, test cases, epochs run and the best one, parameters, and
    the labelled and training cases it saw."""

    dsc_1mm: float
    dsc_01mm: float
    hd_mm: float
    md_mm: float
    sd_mm: float
    nn_md_mm: float
    ms_per_case: float
    cases: int
    epochs: int
    best_epoch: int
    parameters: int
    labelled_cases: int
    train_cases: int

    def metric(self, key: str) -> float:
        """One of TABLE_METRICS by its key."""
        return getattr(self, key)


@dataclass(frozen=True, kw_only=True)
class AblationRow:
    """One configuration of the table: its name, its code in the paper's tables ("" for none), its score."""

    config: str
    code: str
    score: RunScore

    def as_dict(self) -> dict:
        return {"config": self.config, "code": self.code, **asdict(self.score)}


@dataclass(frozen=True, kw_only=True)
class AblationResult:
    """`bench ablation` at one seed: the store, split, SR, seed and epoch budget, a row per configuration,
    and per TABLE_METRICS key the configuration that does best on it."""

    store: str
    split: str
    sr: float
    seed: int
    epochs: int
    rows: list[AblationRow]
    best: dict[str, str]

    def as_dict(self) -> dict:
        return {"store": self.store, "split": self.split, "sr": self.sr, "seed": self.seed, "epochs": self.epochs,
                "rows": [r.as_dict() for r in self.rows], "best": self.best}


@dataclass(frozen=True, kw_only=True)
class Spread:
    """A metric over the seeds: mean and sample SD (0 for one seed)."""

    mean: float
    sd: float


@dataclass(frozen=True, kw_only=True)
class PairedDifference:
    """One metric, configuration a against b over the seeds: the seeds on which a is better, and the mean
    and SD of the paired difference a − b."""

    better_seeds: int
    mean_diff: float
    sd_diff: float


@dataclass(frozen=True, kw_only=True)
class AblationSeedsResult:
    """`bench ablation --seeds`: the seeds, store, split, SR and epoch budget, each seed's test cases, per
    configuration and metric its Spread, per ordered pair "a vs b" and metric the PairedDifference, and
    each seed's AblationResult."""

    seeds: list[int]
    store: str
    split: str
    sr: float
    epochs: int
    cases: list[int]
    configs: dict[str, dict[str, Spread]]
    pairs: dict[str, dict[str, PairedDifference]]
    per_seed: list[AblationResult]

    def as_dict(self) -> dict:
        return {"seeds": self.seeds, "store": self.store, "split": self.split, "sr": self.sr, "epochs": self.epochs,
                "cases": self.cases,
                "configs": {name: {k: asdict(v) for k, v in m.items()} for name, m in self.configs.items()},
                "pairs": {name: {k: asdict(v) for k, v in m.items()} for name, m in self.pairs.items()},
                "per_seed": [r.as_dict() for r in self.per_seed]}


def check_study(store: str, root: Path, split: str, device: str) -> None:
    """The checks a study of several runs (ablation, learning curve) makes before it trains: the
    split parses, the device exists, the store is a heartctl store, and `root` is no file."""
    from storage.schema import inspect_store

    from trainer.data.splits import parse_split

    parse_split(split)
    check_device(device)
    if inspect_store(store) is None:
        raise TrainerError(f"no heartctl store at {store}")
    if root.exists() and not root.is_dir():
        raise TrainerError(f"root={root} is a file")


def parse_seeds(text: str) -> list[int]:
    """'0,1,2' → [0, 1, 2]; '' → [] (one run at the base seed)."""
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise TrainerError(f"`seeds` must be comma-separated integers, got {text!r}") from None


def ablation_study(store: str, root: Path, configs: str, seeds: str, device: str, log=print,
                   **options) -> AblationResult | AblationSeedsResult:
    """`heartctl bench ablation`: the comma-separated `configs` trained on one split (TrainConfig's
    `options`), once (run_ablation) or once per seed of the comma-separated `seeds` (run_ablation_seeds)."""
    names = [c.strip() for c in configs.split(",") if c.strip()]
    seed_list = parse_seeds(seeds)
    check_study(store, root, options.get("split", "shape"), device)
    base = TrainConfig(store=store, model=PAPER, **options)
    if seed_list:
        return run_ablation_seeds(base, names, seed_list, root, device, log)
    return run_ablation(base, names, root, device, log)


def run_name(config: str, sr: float) -> str:
    return config if sr == 1 else f"{config}_sr{sr:g}"


def run_ablation(base: TrainConfig, configs: list, root: Path, device: str = "cpu", log=print) -> AblationResult:
    """Train (or resume) `configs` with `base`'s data, split, SR, seed and optimisation, evaluate each
    on the test split, write ablation.csv / ablation.json under root, return the rows."""
    if not configs:
        raise TrainerError("`configs` is empty")
    models = {canonical_name(name): named_config(name) for name in configs}  # unknown names fail before any training
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    takes_response = next((m for m in models.values() if m.uses_response), base.model)
    bundle = training_data(replace(base, model=takes_response))  # the response is built once, if any model needs it
    rows = []
    for name, model in models.items():
        run_dir = root / run_name(name, base.sr)
        log(f"--- {name} → {run_dir}")
        score = row_from_run(replace(base, config_name=name, model=model), run_dir, device, log, bundle)
        rows.append(AblationRow(config=name, code=code_of(name), score=score))
    result = AblationResult(store=base.store, split=base.split, sr=base.sr, seed=base.seed, epochs=base.epochs,
                            rows=rows, best=best_per_metric(rows))
    write_csv(root / "ablation.csv", [r.as_dict() for r in rows])
    write_json(root / "ablation.json", result.as_dict())
    return result


def row_from_run(cfg: TrainConfig, run_dir: Path, device: str = "cpu", log=print, bundle=None) -> RunScore:
    """Train (or resume) cfg in run_dir with the plain loop, evaluate it on the test split, and return
    its RunScore."""
    summary = fit(cfg, run_dir, Dist(device=torch.device(device), log=log), bundle=bundle)
    report = evaluate_run(run_dir, cfg.store, "test", device, plots=False)
    return RunScore(**{k: report.mean(k) for k in (*HEADLINE, "nn_md_mm")}, ms_per_case=report.ms_per_case,
                    cases=report.cases, epochs=summary.epoch, best_epoch=summary.best_epoch,
                    parameters=summary.n_parameters, labelled_cases=summary.labelled_cases,
                    train_cases=summary.train_cases)


def run_ablation_seeds(base: TrainConfig, configs: list, seeds: list, root: Path, device: str = "cpu",
                       log=print) -> AblationSeedsResult:
    """run_ablation once per seed (each seed draws its own split, SR subset and initialisation) under
    root/seed<N>/, then summarise_seeds; writes ablation_seeds.json under root."""
    if not seeds:
        raise TrainerError("`seeds` is empty")
    if len(set(seeds)) != len(seeds):
        raise TrainerError(f"`seeds` repeats a seed: {seeds}")
    root = Path(root)
    per_seed = []
    for seed in seeds:
        log(f"=== seed {seed}")
        per_seed.append(run_ablation(replace(base, seed=seed), configs, root / f"seed{seed}", device, log))
    result = summarise_seeds(per_seed)
    write_json(root / "ablation_seeds.json", result.as_dict())
    return result


def summarise_seeds(per_seed: list[AblationResult]) -> AblationSeedsResult:
    """Mean and sample SD of every metric per configuration over the seeds' ablation results, and for
    every pair of configurations the seed-paired comparison: on how many seeds the first is better,
    and the mean ± SD of the paired difference (first − second)."""
    by_seed = [{row.config: row.score for row in r.rows} for r in per_seed]
    names = [row.config for row in per_seed[0].rows]

    def sd(values):
        return statistics.stdev(values) if len(values) > 1 else 0.0

    configs = {name: {key: Spread(mean=statistics.fmean(s[name].metric(key) for s in by_seed),
                                  sd=sd([s[name].metric(key) for s in by_seed])) for key, _, _ in TABLE_METRICS}
               for name in names}
    pairs = {}
    for a in names:
        for b in names:
            if a == b:
                continue
            entry = {}
            for key, _, sense in TABLE_METRICS:
                diff = [s[a].metric(key) - s[b].metric(key) for s in by_seed]
                better = sum((d < 0) if sense == "min" else (d > 0) for d in diff)
                entry[key] = PairedDifference(better_seeds=better, mean_diff=statistics.fmean(diff), sd_diff=sd(diff))
            pairs[f"{a} vs {b}"] = entry
    first = per_seed[0]
    return AblationSeedsResult(seeds=[r.seed for r in per_seed], store=first.store, split=first.split, sr=first.sr,
                               epochs=first.epochs, cases=[r.rows[0].score.cases for r in per_seed], configs=configs,
                               pairs=pairs, per_seed=per_seed)


def best_per_metric(rows: list[AblationRow]) -> dict[str, str]:
    """Metric → name of the configuration that does best on it."""
    out = {}
    for key, _, sense in TABLE_METRICS:
        pick = min if sense == "min" else max
        out[key] = pick(rows, key=lambda r: r.score.metric(key)).config
    return out


def beats(rows: list[AblationRow], name: str, others: list) -> dict:
    """Metric → whether `name` is strictly better than every one of `others` (present in rows)."""
    by = {r.config: r.score for r in rows}
    if name not in by:
        return {}
    rivals = [by[o] for o in others if o in by and o != name]
    result = {}
    for key, _, sense in TABLE_METRICS:
        mine = by[name].metric(key)
        result[key] = (all((mine < r.metric(key)) if sense == "min" else (mine > r.metric(key)) for r in rivals)
                       if rivals else None)
    return result
