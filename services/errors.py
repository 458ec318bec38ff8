"""Domain errors of the engine. The app layer maps them to HTTP problems."""


class SllocError(Exception):
    """Base class of every error the engine raises on purpose."""


class InvalidInputError(SllocError):
    """The caller handed the engine something it cannot use (bad image, camera, pose, params)."""


class ImageDecodeError(InvalidInputError):
    """The bytes are not a decodable JPEG or PNG image."""


class ImageTooLargeError(InvalidInputError):
    """The image has more pixels than the configured limit."""


class UnknownComponentError(InvalidInputError):
    """A name (estimator, extractor, ...) that no registry knows."""
