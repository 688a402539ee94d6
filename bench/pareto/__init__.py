"""Helpers of the run time vs error benchmarks (bench/pareto.py, bench/ppcg.py): machine records,
medians of repeats, and one module per stage front."""
