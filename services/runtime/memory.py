"""The service's memory bound: what its resident memory can reach, term by term, from the
settings that size each term (the server computes it at start-up from ``app.settings``, logs
it and shows it in ``GET /v1/health``).

The bound is the sum of:

- ``runtime``: the interpreter with the service's libraries (FastAPI, SQLAlchemy, OpenCV,
  onnxruntime, numpy, faiss) imported;
- ``models``: the ONNX sessions of the feature configuration, in proportion to the size of
  their files;
- ``reference_cache``: the decoded reference features kept between requests
  (``SLLOC_REFERENCE_CACHE_MIB``);
- ``extraction``: per localize worker, one feature extraction of a square image at the
  largest ``max_side`` a map may ask for (``SLLOC_MAX_SIDE``): the feature network's
  activations grow with the pixels it sees;
- ``decode``: per worker, one decoded image at the pixel limit (``SLLOC_MAX_IMAGE_PIXELS``;
  RGB uint8) and a depth upload of as many pixels (16-bit PNG decoded to float32);
- ``matching``: per worker, the retrieved references' features (``SLLOC_MAX_TOP_K`` ×
  ``SLLOC_MAX_KEYPOINTS``) and the matcher's buffers;
- ``uploads``: per admitted request (workers + ``SLLOC_MAX_QUEUED``), its image and depth
  uploads read into memory (``SLLOC_MAX_UPLOAD_BYTES`` each);
- ``bodies``: per open connection (``SLLOC_LIMIT_CONCURRENCY``), a request body being
  received (at most the body limit: two uploads and 1 MiB of form fields); multipart parts
  over 1 MiB are spooled to temporary files, so this is the worst case of many small parts
  or a JSON body;
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
# peak MiB one aliked-n16 extraction adds per megapixel it sees: 1027 MiB at 640², 3092 at
# 1024², 11612 at 2048² (2507, 2949, 2769 MiB/Mpx; memory_terms, 2026-11-24): the largest
EXTRACTION_MIB_PER_MEGAPIXEL = 2950.0
# decoded bytes per pixel: RGB uint8 (3) + a depth upload of as many pixels, its 16-bit PNG
# (2) and float32 (4) at once; a 40 Mpx PNG decode peaked at +230 MiB = 6.0 B/px for the RGB
# alone (the decoder's row buffers on top of the 3 B/px result; memory_terms, 2026-11-24)
DECODE_BYTES_PER_PIXEL = 6.0 + 2.0 + 4.0
# a reference's features per keypoint: (x, y) float32, a 128-float32 descriptor, a score;
# held twice while decoding from the database (stored row, float32 array)
FEATURE_BYTES_PER_KEYPOINT = 2 * (8 + 128 * 4 + 4)
# the matcher's buffers matching one query against 10 references: 44–46 MiB at 512, 1024 and
# 2048 keypoints (nearest neighbours pair by pair, LightGlue on 512 keypoints; memory_terms,
# 2026-11-24)
MATCHER_MIB = 50.0
# form fields a request may carry besides its uploads (app.main's body limit)
FORM_FIELDS_BYTES = 1 * MIB


@dataclass(frozen=True)
class MemoryInputs:
    """The settings the bound depends on. ``model_file_bytes``: the sizes of the ONNX files
    the feature configuration loads; ``workers``: localize workers (the thread plan);
    ``queued``: admission queue (``SLLOC_MAX_QUEUED``); ``connections``: open connections at
    once (``SLLOC_LIMIT_CONCURRENCY``)."""

    model_file_bytes: int
    workers: int
    queued: int
    connections: int
    max_upload_bytes: int
    max_image_pixels: int
    max_side: int
    max_keypoints: int
    max_top_k: int
    reference_cache_mib: int


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


def memory_bound(inputs: MemoryInputs) -> MemoryBound:
    """The bound's terms in MiB from ``inputs`` (the module docstring says what each holds)."""
    i = inputs
    megapixels = i.max_side * i.max_side / 1e6
    body_bytes = 2 * i.max_upload_bytes + FORM_FIELDS_BYTES
    terms = {
        "runtime": RUNTIME_MIB,
        "models": MODEL_RESIDENT_PER_FILE_MIB * i.model_file_bytes / MIB,
        "reference_cache": float(i.reference_cache_mib),
        "extraction": i.workers * EXTRACTION_MIB_PER_MEGAPIXEL * megapixels,
        "decode": i.workers * DECODE_BYTES_PER_PIXEL * i.max_image_pixels / MIB,
        "matching": i.workers
        * (MATCHER_MIB + i.max_top_k * i.max_keypoints * FEATURE_BYTES_PER_KEYPOINT / MIB),
        "uploads": (i.workers + i.queued) * 2 * i.max_upload_bytes / MIB,
        "bodies": i.connections * body_bytes / MIB,
    }
    return MemoryBound({name: round(mib, 1) for name, mib in terms.items()})
