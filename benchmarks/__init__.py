"""Performance benchmarks: ``make bench`` (``python -m benchmarks [NAME ...]``).

Each figure is printed as one JSON line: name, value, unit, target, and whether it met the
target. Figures are medians / percentiles of many runs, always beside a floor measured in
the same process, because these machines are noisy.
"""
