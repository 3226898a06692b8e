"""`heartctl bench learning-curve`: how held-out error falls with the amount of training data.

One configuration is trained (plain PyTorch loop, in turn) on nested fractions of the training
shapes of one split — validation and test shapes stay the same — and evaluated on the test split.
A power law MD = a · n^(−b) in the number n of training pairs, fitted by least squares in log–log,
then says roughly how many pairs a target error would take at the same training budget. It is an
extrapolation from a few points: read it as an order of magnitude, not a promise."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from trainer.config import TrainConfig
from trainer.data.store_cases import read_store, training_data
from trainer.errors import TrainerError
from trainer.files import write_csv, write_json
from trainer.data.splits import make_split, subsample_shapes

from .ablation import RunScore, check_study, row_from_run

CURVE_METRICS = ("md_mm", "hd_mm", "dsc_1mm")  # fitted: error-like ones as is, DSC as 1 − DSC



@dataclass(frozen=True, kw_only=True)
class PowerLaw:
    """err ≈ a · n^(−b) in the number n of training pairs, and the fit's R² in log–log."""

    a: float
    b: float
    r2: float


@dataclass(frozen=True, kw_only=True)
class CurvePoint:
    """One fraction of the training shapes and its run's RunScore."""

    fraction: float
    score: RunScore

    def as_dict(self) -> dict:
        return {"fraction": self.fraction, **asdict(self.score)}


@dataclass(frozen=True, kw_only=True)
class LearningCurveResult:
    """`bench learning-curve`'s result: store, configuration, split, SR, seed, epoch budget and test cases;
    a CurvePoint per fraction; per fitted metric its PowerLaw; the targets, and the training pairs the law
    says each would take (None when the error does not fall)."""

    store: str
    config: str
    split: str
    sr: float
    seed: int
    epochs: int
    test_cases: int
    rows: list[CurvePoint]
    laws: dict[str, PowerLaw]
    targets: dict[str, float]
    pairs_needed: dict[str, float | None]

    def as_dict(self) -> dict:
        return {"store": self.store, "config": self.config, "split": self.split, "sr": self.sr, "seed": self.seed,
                "epochs": self.epochs, "test_cases": self.test_cases, "rows": [r.as_dict() for r in self.rows],
                "laws": {k: asdict(v) for k, v in self.laws.items()}, "targets": self.targets,
                "pairs_needed": self.pairs_needed}


def parse_fractions(text: str) -> list[float]:
    """'0.25,0.5,1' → sorted distinct fractions in (0, 1]."""
    try:
        values = sorted({float(v) for v in str(text).split(",") if v.strip()})
    except ValueError:
        raise TrainerError(f"`fractions` must be comma-separated numbers, got {text!r}") from None
    if len(values) < 2:
        raise TrainerError(f"`fractions` needs at least two values, got {text!r}")
    if not all(math.isfinite(v) and 0 < v <= 1 for v in values):
        raise TrainerError(f"`fractions` must lie in (0, 1], got {text!r}")
    return values


def fit_power_law(n: list, err: list) -> PowerLaw:
    """Least squares of log err = log a − b log n; b > 0 when the error falls with n. Needs ≥ 2 distinct n
    and positive errors."""
    x, y = np.log(np.asarray(n, float)), np.asarray(err, float)
    if len(set(x.tolist())) < 2 or not (y > 0).all():
        raise TrainerError("a power law needs two or more distinct training sizes and positive errors")
    y = np.log(y)
    slope, intercept = np.polyfit(x, y, 1)
    resid = y - (intercept + slope * x)
    ss = float(((y - y.mean()) ** 2).sum())
    return PowerLaw(a=float(math.exp(intercept)), b=float(-slope),
                    r2=1.0 - float((resid ** 2).sum()) / ss if ss > 0 else 1.0)


def pairs_for(law: PowerLaw, target: float) -> float | None:
    """Training pairs at which the fitted law reaches `target` (None when the error does not fall)."""
    if law.b <= 0 or target <= 0:
        return None
    return (law.a / target) ** (1.0 / law.b)


def run_learning_curve(base: TrainConfig, fractions: list, root: Path, targets: dict, device: str = "cpu",
                       log=print) -> LearningCurveResult:
    """Train base's configuration on each fraction of the training shapes under root/frac<f>/ (a
    rerun resumes), evaluate on the test split, fit MD, HD and 1 − DSC@1mm against the number of
    training pairs. `targets` = {"md_mm": 0.15, "hd_mm": 0.6, "dsc_1mm": 0.99}. Writes
    learning_curve.csv and learning_curve.json under root."""
    cases = read_store(base.store)  # once, for every fraction
    train = make_split(cases.keys, cases.params, base.split, base.data_seed, cases.attrs)["train"]
    if len({len(subsample_shapes(train, f, base.data_seed)) for f in fractions}) < 2:  # before any training
        raise TrainerError("every fraction keeps the same training cases; the split has too few training shapes "
                           "for these fractions")
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    rows = []
    for f in fractions:
        cfg = replace(base, train_fraction=f)
        run_dir = root / f"frac{f:g}"
        log(f"--- {base.config_name}, {f:g} of the training shapes → {run_dir}")
        rows.append(CurvePoint(fraction=f, score=row_from_run(cfg, run_dir, device, log, training_data(cfg, cases))))
    n = [r.score.train_cases for r in rows]
    laws, needed = {}, {}
    for key in CURVE_METRICS:
        err = [(1.0 - r.score.metric(key)) if key == "dsc_1mm" else r.score.metric(key) for r in rows]
        if not all(e > 0 for e in err):
            continue  # a perfect score leaves nothing to fit
        laws[key] = fit_power_law(n, err)
        if key in targets:
            goal = (1.0 - targets[key]) if key == "dsc_1mm" else targets[key]
            needed[key] = pairs_for(laws[key], goal)
    result = LearningCurveResult(store=base.store, config=base.config_name, split=base.split, sr=base.sr,
                                 seed=base.seed, epochs=base.epochs, test_cases=rows[0].score.cases, rows=rows,
                                 laws=laws, targets=targets, pairs_needed=needed)
    write_csv(root / "learning_curve.csv", [r.as_dict() for r in rows])
    write_json(root / "learning_curve.json", result.as_dict())
    return result


def learning_curve_config(store: str, root, config: str, split: str, device: str, training: dict,
                          targets: dict) -> tuple[TrainConfig, dict]:
    """The configuration every fraction trains with (`config` and the preset's training options, those
    in `training` that are given overriding them) and the targets (MD and HD in mm > 0, DSC@1mm in
    (0, 1)); TrainerError for a bad target or a study that cannot run (check_study)."""
    from trainer.config import compose

    model, preset = compose(config)  # a preset brings its training options
    preset.update({k: v for k, v in training.items() if k in ("scale_pct", "lr_schedule") and v is not None})
    if not (targets["md_mm"] > 0 and targets["hd_mm"] > 0 and 0 < targets["dsc_1mm"] < 1):
        raise TrainerError("`target_md` and `target_hd` must be > 0 mm and `target_dsc` in (0, 1)")
    check_study(store, root, split, device)
    rest = {k: v for k, v in training.items() if k not in ("scale_pct", "lr_schedule")}
    return TrainConfig(store=store, config_name=config, model=model, split=split, **rest, **preset), targets
