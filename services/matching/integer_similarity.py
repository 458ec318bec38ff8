"""Cosine similarities of two sets of unit descriptors as 8-bit integer matrix products, a
block of query rows at a time.

The product alone of a 4096-keypoint query and a 4096-keypoint reference (128-d RootSIFT)
takes ~57 ms in float32 on one core of the development machine and ~12 ms as ONNX Runtime's
``MatMulInteger`` (docs/benchmarks/2026-11-30-integer-matching.md). Each set is scaled so
that its largest component reaches the integer range:

- the query to signed 8 bits, sent as ``uint8`` with zero point 128;
- the reference to 7 bits (±63). On x86 processors without VNNI, ONNX Runtime adds ``uint8``
  × ``int8`` pairs into saturating 16-bit sums; 255 × 63 × 2 stays below 2¹⁵, so every
  processor computes the same exact integers.

A similarity is then its integer divided by the two scales; a rounding step changes a cosine
by about 1e-3, so only pairs at the edge of a ratio test come out otherwise.
"""

from __future__ import annotations

from collections.abc import Iterator
from functools import cache
from typing import Any, NamedTuple

import numpy as np
from onnx import TensorProto, helper

from services.runtime.onnx import OnnxOptions, create_session
from services.types import Float32Array, Int32Array, UInt8Array

QUERY_LEVELS = 127  # signed 8 bits
REFERENCE_LEVELS = 63  # 7 bits: no saturated 16-bit sums (see the module's docstring)
ZERO_POINT = 128  # the query's: uint8 128 is its 0


@cache
def _session() -> Any:
    """One single-threaded session for the process (``run`` may be called from any thread):
    a request's matching already runs on its worker's thread."""
    graph = helper.make_graph(
        [helper.make_node("MatMulInteger", ["query", "reference", "zero"], ["similarity"])],
        "integer_similarity",
        [
            helper.make_tensor_value_info("query", TensorProto.UINT8, ["n", "d"]),
            helper.make_tensor_value_info("reference", TensorProto.INT8, ["d", "m"]),
            helper.make_tensor_value_info("zero", TensorProto.UINT8, []),
        ],
        [helper.make_tensor_value_info("similarity", TensorProto.INT32, ["n", "m"])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    options = OnnxOptions(intra_op_threads=1, memory_arena=False, memory_pattern=False)
    return create_session(model.SerializeToString(), options)


def _scale(descriptors: Float32Array, levels: int) -> float:
    largest = max(float(descriptors.max(initial=0.0)), -float(descriptors.min(initial=0.0)))
    return levels / largest if largest > 0.0 else 1.0


class QuantizedQuery(NamedTuple):
    """A query's descriptors as ``uint8`` around ``ZERO_POINT``, and the scale they were
    multiplied by: quantized once for all the references it is matched with."""

    values: UInt8Array
    scale: float


def quantize_query(descriptors: Float32Array) -> QuantizedQuery:
    scale = _scale(descriptors, QUERY_LEVELS)
    return QuantizedQuery((np.rint(descriptors * scale) + ZERO_POINT).astype(np.uint8), scale)


class IntegerSimilarity:
    """The integer similarities of a quantized ``query`` (N, D) and ``reference`` (M, D),
    computed by blocks of query rows; ``cosine`` turns them into cosines (for unit
    descriptors)."""

    def __init__(self, query: QuantizedQuery, reference: Float32Array) -> None:
        reference_scale = _scale(reference, REFERENCE_LEVELS)
        self.query = query.values
        # rounded in the rows' order, then turned as bytes: half the time of turning floats
        scaled = reference * np.float32(reference_scale)
        self.reference = np.ascontiguousarray(np.rint(scaled, out=scaled).astype(np.int8).T)
        self.cosine = 1.0 / (query.scale * reference_scale)

    def blocks(self, rows: int) -> Iterator[tuple[int, Int32Array]]:
        """(first row, (≤ ``rows``, M) similarities) for each block of ``rows`` query rows in
        order. Every block is written over the previous one's buffer: a caller reads each
        before it asks for the next."""
        session = _session()
        zero = np.array(ZERO_POINT, np.uint8)
        buffer = np.empty((min(rows, len(self.query)), self.reference.shape[1]), np.int32)
        for start in range(0, len(self.query), rows):
            query = self.query[start : start + rows]
            block = buffer[: len(query)]
            binding = session.io_binding()
            binding.bind_cpu_input("query", query)
            binding.bind_cpu_input("reference", self.reference)
            binding.bind_cpu_input("zero", zero)
            # written in place: no buffer of onnxruntime's own
            binding.bind_output("similarity", "cpu", 0, np.int32, block.shape, block.ctypes.data)
            session.run_with_iobinding(binding)
            yield start, block
