"""Benchmarks: scripts that print speed ratios against baselines measured in the same run."""
