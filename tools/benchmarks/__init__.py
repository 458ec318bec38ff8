"""Timing and accuracy benchmarks, each runnable as ``python -m tools.benchmarks.<name>``."""
