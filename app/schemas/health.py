from __future__ import annotations

from pydantic import BaseModel, Field

from app.schemas.estimators import EstimatorName


class ModelsOut(BaseModel):
    features: str
    matcher: str
    global_descriptor: str
    estimators: list[EstimatorName]
    feature_configurations: list[str] = Field(
        description="The feature configurations maps may be served with: the server's "
        "(SLLOC_FEATURES) first, then those of SLLOC_EVALUATION_FEATURES whose models are "
        "built"
    )


class RuntimeOut(BaseModel):
    """The thread policy, the reference-feature cache and the memory bound
    (``SLLOC_LOCALIZE_WORKERS``, ``SLLOC_ONNX_THREADS``, ``SLLOC_CPU_CORES``,
    ``SLLOC_REFERENCE_CACHE_MIB``; the bound: ``services/runtime/memory.py``)."""

    cores: int = Field(description="Cores the thread policy divides")
    localize_workers: int = Field(description="Localize and add requests computing at once")
    threads_per_worker: int = Field(
        description="Threads one operation may use (onnxruntime intra-op, OpenCV, BLAS)"
    )
    idle_workers_lent: int = Field(
        description="Worker slots a request may borrow while they are idle, for its matching, "
        "a multi-frame query's extraction, and a query's ONNX extraction when all are idle "
        "(localize_workers - 1)"
    )
    reference_cache_mib: float = Field(description="Bound of the reference-feature cache")
    reference_cache_used_mib: float = Field(description="Decoded features it holds now")
    memory_bound_mib: float = Field(
        description="What the server's resident memory can reach with these settings: the "
        "sum of memory_terms_mib (the docs' Deploying page, Memory)"
    )
    memory_terms_mib: dict[str, float] = Field(
        description="The bound's terms, MiB: runtime, models, reference_cache, reference_images, "
        "computing (what the requests computing at once may hold together), bodies, "
        "self_evaluation (sized by the settings) and retrieval_index (the retrieval indexes "
        "held now; they grow with the references)"
    )
    computing_memory_held_mib: float = Field(
        description="Memory the requests computing now hold, out of the computing term"
    )


class UnservableMapOut(BaseModel):
    """A map whose references this server cannot search (GET /v1/maps/{id} tells more)."""

    id: str
    name: str
    image_count: int
    described_by: list[str] = Field(description="The feature models of its references")
    missing_models: list[str] = Field(description="The exported models this server lacks")
    detail: str | None


class HealthOut(BaseModel):
    status: str = Field(
        description="ok; degraded when the database is down, some map cannot be served "
        "(unservable_maps) or the blob store cannot take writes (blob_store)"
    )
    blob_store: str = Field(
        "ok",
        description="ok; unavailable when the store of the references' originals cannot take "
        "writes (a folder missing or read-only, a bucket unreachable or refusing the "
        "credentials; the server's log says why): adds answer 503 blob-store-unavailable, "
        "localize goes on. Probed at most every 15 s",
    )
    version: str
    models: ModelsOut
    runtime: RuntimeOut
    unservable_map_count: int = Field(
        0,
        description="Maps with references none of which this server describes alike: their "
        "localize answers 409 feature-models-missing",
    )
    unservable_maps: list[UnservableMapOut] = Field(
        default_factory=list,
        description="The first 20 of them, most references first (refreshed every 15 s)",
    )
