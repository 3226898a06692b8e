"""Benchmarks and reports: how fast and how accurate the solver and the network are (convergence,
stability at the box's extremes, the speed–accuracy trade, ablations, learning curves, timings).
Nothing here makes a user's answer; `heartctl bench …` runs it."""
