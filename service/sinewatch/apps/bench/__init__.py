"""Benchmarks: ``sinewatch bench kernels|e2e|accuracy|scenarios|startup``, one module
each (the accuracy bench in several: see :mod:`sinewatch.apps.bench.accuracy`); their command
line is :mod:`sinewatch.apps.bench.args`, which imports nothing heavy. Figures are reported as
ratios against baselines measured in the same run, never asserted as timings in tests."""
