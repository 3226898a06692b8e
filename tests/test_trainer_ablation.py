"""Multi-seed ablation summary: mean ± SD per configuration and seed-paired comparisons."""
from __future__ import annotations

import statistics

import pytest

from bench.ablation import TABLE_METRICS, AblationResult, AblationRow, RunScore, summarise_seeds


def _result(seed: int, md: dict) -> AblationResult:
    rows = []
    for name, value in md.items():  # every metric scales with MD; DSC falls as MD grows
        score = RunScore(md_mm=value, hd_mm=2 * value, sd_mm=value / 2, nn_md_mm=value, dsc_1mm=1 - value / 10,
                         dsc_01mm=0.1 - value / 100, ms_per_case=1.0, cases=5, epochs=30, best_epoch=30,
                         parameters=1000, labelled_cases=10, train_cases=10)
        rows.append(AblationRow(config=name, code="", score=score))
    return AblationResult(store="s.zarr", split="shape", sr=0.03, seed=seed, epochs=30, rows=rows, best={})


def test_summarise_seeds_by_hand():
    per_seed = [_result(0, {"A1": 1.0, "R3": 0.9}), _result(1, {"A1": 1.1, "R3": 1.2}),
                _result(2, {"A1": 1.2, "R3": 1.0})]
    s = summarise_seeds(per_seed)
    assert s.seeds == [0, 1, 2] and s.cases == [5, 5, 5]
    assert s.configs["A1"]["md_mm"].mean == pytest.approx(1.1)
    assert s.configs["R3"]["md_mm"].sd == pytest.approx(statistics.stdev([0.9, 1.2, 1.0]))
    assert s.configs["R3"]["hd_mm"].mean == pytest.approx(2 * statistics.fmean([0.9, 1.2, 1.0]))
    pair = s.pairs["R3 vs A1"]
    assert pair["md_mm"].better_seeds == 2  # lower MD on seeds 0 and 2
    assert pair["dsc_1mm"].better_seeds == 2  # higher DSC on the same seeds
    assert pair["md_mm"].mean_diff == pytest.approx(statistics.fmean([-0.1, 0.1, -0.2]))
    assert pair["md_mm"].sd_diff == pytest.approx(statistics.stdev([-0.1, 0.1, -0.2]))
    assert s.pairs["A1 vs R3"]["md_mm"].better_seeds == 1
    assert set(pair) == {k for k, _, _ in TABLE_METRICS}
    written = s.as_dict()  # ablation_seeds.json
    assert written["pairs"]["R3 vs A1"]["md_mm"]["better_seeds"] == 2 and written["per_seed"][1]["rows"][0]["md_mm"] == 1.1


def test_summarise_one_seed_has_zero_sd():
    s = summarise_seeds([_result(4, {"A1": 1.0, "paper": 1.0})])
    assert s.configs["A1"]["md_mm"].sd == 0.0
    assert s.pairs["paper vs A1"]["md_mm"].better_seeds == 0  # a tie is not a win


def test_learning_curve_power_law_by_hand():
    from trainer.errors import TrainerError
    from bench.learning_curve import fit_power_law, pairs_for, parse_fractions

    n = [100, 200, 400, 800]
    law = fit_power_law(n, [3.0 * v ** -0.5 for v in n])
    assert law.a == pytest.approx(3.0) and law.b == pytest.approx(0.5) and law.r2 == pytest.approx(1.0)
    assert pairs_for(law, 0.15) == pytest.approx((3.0 / 0.15) ** 2)  # 400 pairs
    assert pairs_for(fit_power_law([10, 20], [1.0, 1.2]), 0.5) is None  # error grows: never reached
    assert parse_fractions("1, 0.25,0.5,0.25") == [0.25, 0.5, 1.0]
    for bad in ("1", "0,1", "0.5,2", "a,b", "0.5,nan"):
        with pytest.raises(TrainerError, match="fractions"):
            parse_fractions(bad)
    with pytest.raises(TrainerError, match="distinct"):
        fit_power_law([10, 10], [1.0, 0.9])
