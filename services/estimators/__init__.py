"""Structureless pose estimators: a protocol, a registry, and one module per method."""
