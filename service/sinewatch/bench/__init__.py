"""Benchmarks: `sinewatch bench kernels|e2e|accuracy|scenarios`. Figures are reported as
ratios against baselines measured in the same run, never asserted as timings in tests."""
