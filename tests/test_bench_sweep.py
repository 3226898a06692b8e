"""`bench sweep`'s figures against the first CPU count and the plain serial loop (the Ray runs themselves
are what `heartctl bench sweep` times)."""
from __future__ import annotations

import pytest

from bench.sweep_speed import CpuRun, SweepBenchResult


def _run(cpus: int, pairs_per_s: float) -> CpuRun:
    return CpuRun(cpus=cpus, cases=8, done=8, failed=0, phase2_s=8 / pairs_per_s, throughput_cases_per_s=pairs_per_s,
                  solve_s_median=0.5, solve_s_mean=0.55, submit_to_start_s_median=0.05, result_to_stored_s_median=0.01,
                  driver_store_s_per_case=0.01, idle_core_s_per_task=0.1, noop_roundtrip_s_median=0.002)


def test_speedup_efficiency_and_overheads_follow_the_first_run_and_the_plain_loop():
    one, two = _run(1, 1.6), _run(2, 2.4)
    first, second = one.compared(one, plain_per_s=2.0), two.compared(one, plain_per_s=2.0)
    assert first.speedup_vs_1 == 1.0 and first.parallel_efficiency == 1.0
    assert second.speedup_vs_1 == pytest.approx(1.5) and second.parallel_efficiency == pytest.approx(0.75)
    assert second.throughput_vs_plain == pytest.approx(0.6)  # 2.4 pairs/s on 2 CPUs against 2.0 on one
    assert second.overhead_submit_to_start_pct == pytest.approx(10.0) and second.overhead_idle_core_pct == pytest.approx(20.0)
    result = SweepBenchResult(nodes=200, cases=8, plain_serial_s_per_case=0.5, chained_serial_s_per_case=0.4,
                              plain_solve_s_median=0.5, rows=[first, second])
    assert result.as_dict()["rows"][1]["parallel_efficiency"] == pytest.approx(0.75)
