"""`heartctl bench ablation`: train several configurations on one store and one split, one after
another with the plain PyTorch loop, and tabulate their held-out metrics — the paper's ablation
table, measured on our data. Each configuration gets its own run directory under the root, so a
rerun resumes unfinished runs and re-evaluates finished ones."""
from __future__ import annotations

import statistics
from dataclasses import replace
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


def ablation_study(store: str, root: Path, configs: str, seeds: str, device: str, log=print, **options) -> dict:
    """`heartctl bench ablation`: the comma-separated `configs` trained on one split (TrainConfig's
    `options`), once (run_ablation) or once per seed of the comma-separated `seeds` (run_ablation_seeds,
    whose result has "seeds")."""
    names = [c.strip() for c in configs.split(",") if c.strip()]
    seed_list = parse_seeds(seeds)
    check_study(store, root, options.get("split", "shape"), device)
    base = TrainConfig(store=store, model=PAPER, **options)
    if seed_list:
        return run_ablation_seeds(base, names, seed_list, root, device, log)
    return run_ablation(base, names, root, device, log)


def run_name(config: str, sr: float) -> str:
    return config if sr == 1 else f"{config}_sr{sr:g}"


def run_ablation(base: TrainConfig, configs: list, root: Path, device: str = "cpu", log=print) -> dict:
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
        row = row_from_run(replace(base, config_name=name, model=model), run_dir, device, log, bundle)
        rows.append({"config": name, "code": code_of(name), **row})
    result = {"store": base.store, "split": base.split, "sr": base.sr, "seed": base.seed, "epochs": base.epochs,
              "rows": rows, "best": best_per_metric(rows)}
    write_csv(root / "ablation.csv", rows)
    write_json(root / "ablation.json", result)
    return result


def row_from_run(cfg: TrainConfig, run_dir: Path, device: str = "cpu", log=print, bundle=None) -> dict:
    """Train (or resume) cfg in run_dir with the plain loop, evaluate it on the test split, and return
    the table row: the TABLE_METRICS, ms per case, test cases, epochs, parameters, training cases."""
    summary = fit(cfg, run_dir, Dist(device=torch.device(device), log=log), bundle=bundle)
    report = evaluate_run(run_dir, cfg.store, "test", device, plots=False)
    return {**{k: report.mean(k) for k in (*HEADLINE, "nn_md_mm")}, "ms_per_case": report.ms_per_case,
            "cases": report.cases, "epochs": summary.epoch, "best_epoch": summary.best_epoch,
            "parameters": summary.n_parameters, "labelled_cases": summary.labelled_cases,
            "train_cases": summary.train_cases}


def run_ablation_seeds(base: TrainConfig, configs: list, seeds: list, root: Path, device: str = "cpu",
                       log=print) -> dict:
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
    write_json(root / "ablation_seeds.json", result)
    return result


def summarise_seeds(per_seed: list) -> dict:
    """Mean and sample SD of every metric per configuration over the seeds' ablation results, and for
    every pair of configurations the seed-paired comparison: on how many seeds the first is better,
    and the mean ± SD of the paired difference (first − second)."""
    seeds = [r["seed"] for r in per_seed]
    by_seed = [{row["config"]: row for row in r["rows"]} for r in per_seed]
    names = [row["config"] for row in per_seed[0]["rows"]]

    def sd(values):
        return statistics.stdev(values) if len(values) > 1 else 0.0

    configs = {}
    for name in names:
        configs[name] = {key: {"mean": statistics.fmean(rows[name][key] for rows in by_seed),
                               "sd": sd([rows[name][key] for rows in by_seed])} for key, _, _ in TABLE_METRICS}
    pairs = {}
    for a in names:
        for b in names:
            if a == b:
                continue
            entry = {}
            for key, _, sense in TABLE_METRICS:
                diff = [rows[a][key] - rows[b][key] for rows in by_seed]
                better = sum((d < 0) if sense == "min" else (d > 0) for d in diff)
                entry[key] = {"better_seeds": better, "mean_diff": statistics.fmean(diff), "sd_diff": sd(diff)}
            pairs[f"{a} vs {b}"] = entry
    return {"seeds": seeds, "store": per_seed[0]["store"], "split": per_seed[0]["split"], "sr": per_seed[0]["sr"],
            "epochs": per_seed[0]["epochs"], "cases": [r["rows"][0]["cases"] for r in per_seed],
            "configs": configs, "pairs": pairs, "per_seed": per_seed}


def best_per_metric(rows: list) -> dict:
    """Metric → name of the configuration that does best on it."""
    out = {}
    for key, _, sense in TABLE_METRICS:
        pick = min if sense == "min" else max
        out[key] = pick(rows, key=lambda r: r[key])["config"]
    return out


def beats(rows: list, name: str, others: list) -> dict:
    """Metric → whether `name` is strictly better than every one of `others` (present in rows)."""
    by = {r["config"]: r for r in rows}
    if name not in by:
        return {}
    rivals = [by[o] for o in others if o in by and o != name]
    result = {}
    for key, _, sense in TABLE_METRICS:
        mine = by[name][key]
        result[key] = all((mine < r[key]) if sense == "min" else (mine > r[key]) for r in rivals) if rivals else None
    return result
