"""Generators of documentation pages (docs/)."""
