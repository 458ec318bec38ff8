"""Repositories: typed queries over one session; callers own the transaction."""
