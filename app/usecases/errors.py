"""Domain errors of the use cases (the engine's own are in ``services.errors``)."""

from __future__ import annotations


class NotFoundError(Exception):
    """A map or image that does not exist."""

    def __init__(self, kind: str, ident: str) -> None:
        super().__init__(f"{kind} {ident!r} does not exist")


class MissingBlobError(NotFoundError):
    """An image whose row names an original that the blob store does not hold (removed by
    hand, or a store restored from an older backup)."""

    def __init__(self, image_id: str) -> None:
        Exception.__init__(  # not NotFoundError's "<kind> <id> does not exist"
            self,
            f"the original of image {image_id!r} is missing from the blob store; the image "
            "still localizes; add it again to keep its original",
        )


class ConflictError(Exception):
    """The request contradicts the stored state (a name taken, nothing to reindex)."""


class NameTakenError(ConflictError):
    """A map of that name exists, or the map has an image of that name."""
