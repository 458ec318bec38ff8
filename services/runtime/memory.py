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
- ``extraction``: per localize worker, one feature extraction of a square image at the
  largest ``max_side`` a map may ask for (``SLLOC_MAX_SIDE``, or a configuration's own
  when larger) by the most demanding extractor served: the feature network's activations
  grow with the pixels it sees, at a rate of its own;
- ``decode``: per worker, one decoded image at the pixel limit (``SLLOC_MAX_IMAGE_PIXELS``;
  RGB uint8) and a depth upload of as many pixels (16-bit PNG decoded to float32);
- ``matching``: per worker, the retrieved references' features (``SLLOC_MAX_TOP_K`` ×
  ``SLLOC_MAX_KEYPOINTS`` of the largest descriptor served) and the matcher's buffers, which
  grow with the keypoint pairs LightGlue sees;
- ``bodies``: request bodies and the uploads read from them, which the server admits only
  within ``SLLOC_BODY_MEMORY_MIB`` (``app/limits.py`` reserves each body's share before it
  is read and frees it when the answer is sent);
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
# decoded bytes per pixel: RGB uint8 (3) + a depth upload of as many pixels, its 16-bit PNG
# (2) and float32 (4) at once; a 40 Mpx PNG decode peaked at +230 MiB = 6.0 B/px for the RGB
# alone (the decoder's row buffers on top of the 3 B/px result; memory_terms, 2026-11-24)
DECODE_BYTES_PER_PIXEL = 6.0 + 2.0 + 4.0
# a reference's features per keypoint: (x, y) float32, a descriptor of float32, a score;
# held twice while decoding from the database (stored row, float32 array)
FEATURE_BYTES_PER_KEYPOINT = 8 + 4
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


@dataclass(frozen=True)
class MemoryInputs:
    """The settings the bound depends on. ``model_file_bytes``: the sizes of the ONNX files
    the feature configuration loads; ``extractor``: its extractor's name; ``lightglue_keypoints``:
    the keypoints LightGlue sees of each image (0: no LightGlue); ``workers``: localize workers
    (the thread plan); ``body_memory_mib``: ``SLLOC_BODY_MEMORY_MIB``."""

    model_file_bytes: int
    extractor: str
    lightglue_keypoints: int
    workers: int
    body_memory_mib: int
    max_image_pixels: int
    max_side: int
    max_keypoints: int
    max_top_k: int
    reference_cache_mib: int
    reference_image_cache_mib: int = 0
    # the other configurations maps may be served with and self-evaluations measure:
    # (model file bytes, extractor, default longer image side) of each
    other_configurations: tuple[tuple[int, str, int], ...] = ()


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
    """Peak MiB per megapixel of ``extractor`` (an unknown one: the largest known)."""
    return EXTRACTION_MIB_PER_MEGAPIXEL.get(extractor, max(EXTRACTION_MIB_PER_MEGAPIXEL.values()))


def memory_bound(inputs: MemoryInputs) -> MemoryBound:
    """The bound's terms in MiB from ``inputs`` (the module docstring says what each holds)."""
    i = inputs
    # every configuration served may be loaded at once (each map's own), and a worker may
    # extract and match with any of them: the models add up, the per-worker terms take the
    # largest
    served = [(i.model_file_bytes, i.extractor, i.max_side)]
    configurations = served + [
        (files, extractor, max(side, i.max_side))
        for files, extractor, side in i.other_configurations
    ]
    extraction = max(_extraction_rate(e) * side * side / 1e6 for _, e, side in configurations)
    feature_bytes = max(
        FEATURE_BYTES_PER_KEYPOINT + 4 * DESCRIPTOR_DIMS.get(e, 128) for _, e, _ in configurations
    )
    matcher = MATCHER_MIB + LIGHTGLUE_MIB_PER_MILLION_PAIRS * i.lightglue_keypoints**2 / 1e6
    terms = {
        "runtime": RUNTIME_MIB,
        "models": MODEL_RESIDENT_PER_FILE_MIB * sum(f for f, _, _ in configurations) / MIB,
        "reference_cache": float(i.reference_cache_mib),
        "reference_images": float(i.reference_image_cache_mib),
        "extraction": i.workers * extraction,
        "decode": i.workers * DECODE_BYTES_PER_PIXEL * i.max_image_pixels / MIB,
        "matching": i.workers * (matcher + i.max_top_k * i.max_keypoints * 2 * feature_bytes / MIB),
        "bodies": float(i.body_memory_mib),
        # a self-evaluation computes in a localize worker's place (it holds a worker slot),
        # plus the references it keeps described
        "self_evaluation": EVALUATION_DESCRIBED * i.max_keypoints * feature_bytes / MIB,
    }
    return MemoryBound({name: round(mib, 1) for name, mib in terms.items()})
