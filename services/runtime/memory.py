"""The service's memory bound: what its resident memory can reach, term by term, from the
settings that size each term (the server computes it at start-up from ``app.settings``, logs
it and shows it in ``GET /v1/health``).

The bound is the sum of:

- ``runtime``: the interpreter with the service's libraries (FastAPI, SQLAlchemy, OpenCV,
  onnxruntime, numpy, faiss) imported;
- ``models``: the ONNX sessions of the feature configurations served (the server's and
  ``SLLOC_EVALUATION_FEATURES``'), in proportion to the size of their files;
- ``reference_cache``: the decoded reference features kept between requests
  (``SLLOC_REFERENCE_CACHE_MIB``);
- ``reference_images``: the reference images kept decoded for the sub-pixel refinement of
  matches (``SLLOC_REFERENCE_IMAGE_CACHE_MIB``);
- ``computing``: the memory the requests computing at once may hold together
  (``SLLOC_COMPUTING_MEMORY_MIB``, at least one largest request's). Each computing request
  reserves what its own shape needs (``request_memory_mib``: the largest of its stages, the
  decode of its upload and depth, one feature extraction at its map's ``max_side`` and the
  matching of its retrieved references' features, each beside the pixels it holds) before it
  computes, and waits while that does not fit beside the others
  (``services.runtime.worker_slots``): small requests run on every worker at once, a
  request at the limits runs alone;
- ``bodies``: request bodies and the uploads read from them, which the server admits only
  within ``SLLOC_BODY_MEMORY_MIB`` (``app/limits.py`` reserves each body's share before it
  is read and frees it when the answer is sent);
- ``self_evaluation``: the references a self-evaluation keeps described;
- ``second_opinion``: the references described for second opinions, kept between requests;
- ``vocabulary``: one training of a map's retrieval vocabulary, which reads the stored
  descriptors ``VOCABULARY_READ`` references at a time and keeps a sample of them;
- ``retrieval_index``: the retrieval indexes of the maps localized against, which grow with
  the references stored (a descriptor per reference) and have no setting: the service shows
  their present size.

Reference depth maps, where a map stores them, come on top: each retrieved reference's
depth (float32 per pixel) is held by the request matching it, and by the reference cache
within its bound.

Each constant below names where it was measured (``python -m tools.benchmarks.memory_terms``,
one process per operation, one thread per operation, onnxruntime's memory arena off as the
service runs it).
"""

from __future__ import annotations

from dataclasses import dataclass

MIB = 2**20

# the interpreter after `import app.main`: 258 MiB peak (tools/benchmarks/memory_terms.py,
# aliked, 2026-11-24)
RUNTIME_MIB = 260.0
# resident MiB per MiB of ONNX files: aliked-n16 + lightglue-aliked, 48 MiB of files → 137 MiB
# resident after building their sessions (memory_terms, 2026-11-24)
MODEL_RESIDENT_PER_FILE_MIB = 2.9
# peak MiB one extraction adds per megapixel it sees (memory_terms, 2026-11-24 and -26):
# aliked-n16 1027 / 3092 / 11612 MiB at 640² / 1024² / 2048² (2507–2949 MiB/Mpx), disk
# 655 / 2153 / 11002 (1600–2623), xfeat 52 / 123 / 493 (117–127), sift 88 / 232 / 940
# (215–224); each the largest of its sizes. An extractor not listed counts as the largest.
EXTRACTION_MIB_PER_MEGAPIXEL = {"aliked-n16": 2950.0, "disk": 2650.0, "xfeat": 130.0, "sift": 230.0}
# decoded bytes per pixel of an image: a 40 Mpx PNG decode peaked at +230 MiB = 6.0 B/px (the
# decoder's row buffers on top of the 3 B/px RGB result; memory_terms, 2026-11-24)
IMAGE_DECODE_BYTES_PER_PIXEL = 6.0
# and of a depth upload of as many pixels: its 16-bit PNG (2) and float32 (4) at once
DEPTH_DECODE_BYTES_PER_PIXEL = 2.0 + 4.0
# bytes per pixel a query holds from its decode to its answer: its RGB pixels, and a copy
# turned by 90°, 180° or 270° while that turn is matched (services.localization.turns)
IMAGE_HELD_BYTES_PER_PIXEL = 3.0 + 3.0
# and of its depth map: float32
DEPTH_HELD_BYTES_PER_PIXEL = 4.0
# a reference's features per keypoint: (x, y) float32, a descriptor of float32, a score
FEATURE_BYTES_PER_KEYPOINT = 8 + 4
# copies of each retrieved reference's features a localize may hold: the stored row and its
# float32 arrays while a batch is read from the database, and the wider retrieval's
# references beside the first ones (services.localization.widen)
REFERENCE_COPIES = 3
DESCRIPTOR_DIMS = {"xfeat": 64}  # the others' descriptors: 128 floats
# the matcher matching one query against 10 references: nearest neighbours pair by pair
# (sift 0 / 4 / 16 MiB at 512 / 1024 / 2048 keypoints) and LightGlue on the pairs it runs on,
# which grows with the keypoints it sees squared (disk, every keypoint: 45 / 121 / 384 MiB;
# aliked and xfeat at their 512: 44–46 and 16–32 MiB; memory_terms, 2026-11-24 and -26)
MATCHER_MIB = 30.0
LIGHTGLUE_MIB_PER_MILLION_PAIRS = 90.0
# a JSON body's peak while parsed, per byte: 81 MiB for a 49 MiB GeoPose request (its text,
# the parsed string, the decoded image); a multipart body costs its size (parts past 1 MiB
# are spooled to files and read back once)
JSON_BODY_FACTOR = 1.7
# references a self-evaluation keeps described between its held-out queries
EVALUATION_DESCRIBED = 60
# references described for second opinions, kept between requests
# (services.localization.second_opinion)
SECOND_OPINION_DESCRIBED = 20
# a map's retrieval vocabulary (services.retrieval.vlad_index): the references whose stored
# descriptors its training and its encoding read at once, and the descriptors its k-means
# samples from them
VOCABULARY_READ = 25
VOCABULARY_SAMPLE = 100_000
# copies of the sample a training holds: the per-reference samples, their concatenation, and
# k-means' distances and assignments beside them
VOCABULARY_SAMPLE_COPIES = 3


@dataclass(frozen=True)
class RequestShape:
    """What one computing request's memory depends on: the upload's ``pixels`` and whether a
    depth map of as many comes with it, the ``extracted_pixels`` its extractor sees (the image
    shrunk to the map's ``max_side``), the ``extractor`` (its name or family: ``sift``,
    ``xfeat``, ``aliked-n16``, ``disk``), the ``keypoints`` of each image, the ``references``
    it is matched against (0: described only) and the keypoints LightGlue sees of each image
    (0: no LightGlue)."""

    pixels: int
    depth: bool
    extracted_pixels: float
    extractor: str
    keypoints: int
    references: int = 0
    lightglue_keypoints: int = 0


def request_memory_mib(shape: RequestShape) -> float:
    """The peak MiB a request of ``shape`` adds while it computes. Its stages peak one after
    the other: the decode; then one extraction, and then the matching, each beside the pixels
    the decode left (the image, its turned copy and the depth map are held until the answer).
    The largest of the three is the request's (a request at the limits reached 0.85 of it,
    ``python -m tools.benchmarks.worst_request``, 2026-11-30)."""
    decode = shape.pixels * (
        IMAGE_DECODE_BYTES_PER_PIXEL + (DEPTH_DECODE_BYTES_PER_PIXEL if shape.depth else 0.0)
    )
    held = shape.pixels * (
        IMAGE_HELD_BYTES_PER_PIXEL + (DEPTH_HELD_BYTES_PER_PIXEL if shape.depth else 0.0)
    )
    extraction = _extraction_rate(shape.extractor) * shape.extracted_pixels / 1e6
    if shape.references == 0:
        return max(decode / MIB, held / MIB + extraction)
    references = REFERENCE_COPIES * shape.references * shape.keypoints
    matching = (
        MATCHER_MIB
        + LIGHTGLUE_MIB_PER_MILLION_PAIRS * shape.lightglue_keypoints**2 / 1e6
        + references * _feature_bytes(shape.extractor) / MIB
    )
    return max(decode / MIB, held / MIB + extraction, held / MIB + matching)


@dataclass(frozen=True)
class MemoryInputs:
    """The settings the bound depends on, for each configuration maps may be served with and
    self-evaluations measure (the server's first, then ``SLLOC_EVALUATION_FEATURES``'):
    ``configurations`` holds its model files' bytes, its extractor's family, its longer image
    side (at least ``max_side``) and the keypoints its LightGlue sees of each image (0: no
    LightGlue). ``computing_memory_mib``: ``SLLOC_COMPUTING_MEMORY_MIB`` (0: one largest
    request's); ``body_memory_mib``: ``SLLOC_BODY_MEMORY_MIB``."""

    configurations: tuple[tuple[int, str, int, int], ...]
    body_memory_mib: int
    max_image_pixels: int
    max_keypoints: int
    max_top_k: int
    reference_cache_mib: int
    reference_image_cache_mib: int = 0
    computing_memory_mib: int = 0


@dataclass(frozen=True)
class MemoryBound:
    """The bound in MiB and its terms (name → MiB); ``retrieval_index_mib`` is the present
    size of the retrieval indexes, which grow with the references and are not in
    ``fixed_mib``."""

    terms: dict[str, float]
    retrieval_index_mib: float = 0.0

    @property
    def fixed_mib(self) -> float:
        """The terms the settings size."""
        return sum(self.terms.values())

    @property
    def total_mib(self) -> float:
        return self.fixed_mib + self.retrieval_index_mib

    def with_retrieval_index(self, nbytes: int) -> MemoryBound:
        return MemoryBound(self.terms, nbytes / MIB)

    def describe(self) -> str:
        parts = ", ".join(f"{name} {mib:.0f}" for name, mib in self.terms.items())
        return f"{self.total_mib:.0f} MiB ({parts}, retrieval_index {self.retrieval_index_mib:.0f})"


def _extraction_rate(extractor: str) -> float:
    """Peak MiB per megapixel of ``extractor`` (a family, or a name that starts with one; an
    unknown one: the largest known)."""
    return next(
        (
            rate
            for family, rate in EXTRACTION_MIB_PER_MEGAPIXEL.items()
            if extractor.startswith(family)
        ),
        max(EXTRACTION_MIB_PER_MEGAPIXEL.values()),
    )


def _feature_bytes(extractor: str) -> int:
    """Bytes of one keypoint's features (position, score, float32 descriptor)."""
    dims = next((d for family, d in DESCRIPTOR_DIMS.items() if extractor.startswith(family)), 128)
    return FEATURE_BYTES_PER_KEYPOINT + 4 * dims


def largest_request_mib(inputs: MemoryInputs) -> float:
    """The largest request the settings admit: an upload at the pixel limit with its depth,
    extracted at a configuration's side (a square, its most pixels), matched against
    ``max_top_k`` references of ``max_keypoints`` each, by the most demanding configuration."""
    return max(
        request_memory_mib(
            RequestShape(
                pixels=inputs.max_image_pixels,
                depth=True,
                extracted_pixels=float(side * side),
                extractor=extractor,
                keypoints=inputs.max_keypoints,
                references=inputs.max_top_k,
                lightglue_keypoints=lightglue,
            )
        )
        for _, extractor, side, lightglue in inputs.configurations
    )


def memory_bound(inputs: MemoryInputs) -> MemoryBound:
    """The bound's terms in MiB from ``inputs`` (the module docstring says what each holds).
    Every configuration served may be loaded at once (each map's own): their models add up;
    the requests computing at once hold at most ``computing_memory_mib``, never less than one
    largest request."""
    i = inputs
    widest = max(_feature_bytes(c[1]) for c in i.configurations)  # bytes of a keypoint
    terms = {
        "runtime": RUNTIME_MIB,
        "models": MODEL_RESIDENT_PER_FILE_MIB * sum(c[0] for c in i.configurations) / MIB,
        "reference_cache": float(i.reference_cache_mib),
        "reference_images": float(i.reference_image_cache_mib),
        "computing": max(float(i.computing_memory_mib), largest_request_mib(i)),
        "bodies": float(i.body_memory_mib),
        # the references a self-evaluation keeps described (its held-out queries compute as
        # requests do)
        "self_evaluation": EVALUATION_DESCRIBED * i.max_keypoints * widest / MIB,
        # the references described for second opinions (their requests compute as others)
        "second_opinion": SECOND_OPINION_DESCRIBED * i.max_keypoints * widest / MIB,
        # one vocabulary training at a time: a batch of references read, or its sample
        "vocabulary": max(
            VOCABULARY_READ * i.max_keypoints, VOCABULARY_SAMPLE_COPIES * VOCABULARY_SAMPLE
        )
        * widest
        / MIB,
    }
    return MemoryBound({name: round(mib, 1) for name, mib in terms.items()})
