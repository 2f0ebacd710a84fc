"""Benchmarks: measured on this machine, reported as ratios against baselines run alongside."""
