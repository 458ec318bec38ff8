"""Offline tooling around the service: the ``slloc`` command, evaluation and benchmarks, model
export, synthetic scenes and test fixtures, and bulk import."""
