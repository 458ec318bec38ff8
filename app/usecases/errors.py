"""Domain errors of the use cases (the engine's own are in ``services.errors``)."""

from __future__ import annotations


class NotFoundError(Exception):
    """A map or image that does not exist."""

    def __init__(self, kind: str, ident: str) -> None:
        super().__init__(f"{kind} {ident!r} does not exist")


class ConflictError(Exception):
    """The request contradicts the stored state (a name taken, nothing to reindex)."""


class NameTakenError(ConflictError):
    """A map of that name exists, or the map has an image of that name."""
