"""Service configuration from the environment (prefix ``SLLOC_``), validated at start-up."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.features.configs import (
    AUTO,
    AUTO_CHOICES,
    FALLBACK_FEATURES,
    feature_config_names,
)
from services.runtime.memory import JSON_BODY_FACTOR

Role = Literal["admin", "client"]
LogFormat = Literal["text", "json"]


class ApiKey(BaseModel):
    key: SecretStr
    role: Role


class Settings(BaseSettings):
    """Every setting can be given as ``SLLOC_<NAME>`` in the environment or a ``.env`` file."""

    model_config = SettingsConfigDict(env_prefix="SLLOC_", env_file=".env", extra="ignore")

    database_url: str = Field(
        "sqlite:///./data/slloc.db",
        description="SQLAlchemy URL: SQLite (the default) or PostgreSQL, e.g. "
        "postgresql+psycopg://user:pass@host:5432/slloc",
    )
    blob_url: str | None = Field(
        None,
        description="Where the originals of reference images (their bytes as uploaded, and "
        "their depth maps) are kept: s3://bucket/prefix for an S3-compatible object store "
        "that replicas share (credentials, region and endpoint from the standard AWS_* "
        "variables), or file:///path for a folder; default: a folder beside the SQLite file "
        "(<file>.blobs), or SLLOC_DATA_DIR/blobs (docs: Originals and the blob store)",
    )
    data_dir: Path | None = Field(
        None,
        description="Folder of the service's own files: the originals go to <it>/blobs when "
        "SLLOC_BLOB_URL is unset",
    )
    blob_sweep_grace_s: float = Field(
        3600.0,
        ge=0,
        allow_inf_nan=False,
        description="The start-up sweep (and `slloc blobs sweep`) removes blobs without a "
        "reference row last written longer ago than this (s); must exceed the longest add "
        "(an add writes its blobs before its row commits)",
    )
    blob_sweep_on_start: bool = Field(
        True,
        description="Reconcile the blob store with the database in the background at "
        "start-up: remove blobs without a row (past SLLOC_BLOB_SWEEP_GRACE_S), log rows "
        "whose blob is missing",
    )
    models_dir: Path = Field(
        Path("./models"),
        description="Where the exported ONNX models are read from (`slloc models build` "
        "writes them)",
    )
    features: str = Field(
        AUTO,
        description=f"Feature configuration: {AUTO} (the first of {', '.join(AUTO_CHOICES)} "
        "whose models are built, the one the database's references hold before the others; "
        f"else {FALLBACK_FEATURES}) or one of {', '.join(feature_config_names())}; "
        "`slloc features` lists what each runs and the models it needs",
    )
    evaluation_features: str = Field(
        FALLBACK_FEATURES,
        description="Feature configurations besides the server's own that maps may be served "
        "with and self-evaluations measure, comma-separated (e.g. sift,aliked): a map takes "
        "one by name or by its self-evaluation's recommendation (features auto); each loads "
        "its models when first used, those whose models are not built are left out, and the "
        "memory bound counts them all; empty = the server's own configuration only",
    )
    second_opinion: str = Field(
        AUTO,
        description="The feature configuration that localizes a query again when its map's "
        "own retrieves references but finds no answer (too few matches, no consensus, "
        "low confidence), against those references described from their originals: "
        f"{AUTO} = the first configuration served (SLLOC_FEATURES, then "
        "SLLOC_EVALUATION_FEATURES) other than the map's, a name, or empty = none; a request "
        "turns it off with params.second_opinion false",
    )
    auto_evaluation_references: int = Field(
        10,
        ge=0,
        description="A map that follows its self-evaluation (features auto, the default) is "
        "evaluated on its own once it has this many references with their originals, then "
        "again each time it has changed enough (docs: self-evaluation); 0 = only when asked",
    )
    onnx_providers: str = Field(
        "auto",
        description="Comma-separated onnxruntime execution providers in order of preference; "
        "auto = CUDA when this onnxruntime has it, then CPU",
    )
    global_model: Path | None = Field(
        None,
        description="ONNX global-descriptor model for retrieval (contract in "
        "services/retrieval/onnx_global.py); default: weight-free VLAD over each map's own "
        "vocabulary (blurred thumbnails on small maps)",
    )
    onnx_threads: int = Field(
        0,
        ge=0,
        description="Threads one operation of a localize request may use: onnxruntime "
        "intra-op, OpenCV and BLAS / OpenMP; 0 = the usable cores / localize workers",
    )
    onnx_memory_arena: bool = Field(
        False,
        description="Keep onnxruntime's CPU memory arena: a little faster, but it grows to the "
        "largest tensors seen and never gives memory back (aliked: 1.9 GiB peak instead of "
        "1.0 GiB for one worker, `python -m tools.benchmarks.memory`)",
    )
    api_keys: str = Field(
        "",
        description="Comma-separated `key:role` pairs, role admin or client, sent as the "
        "X-API-Key header; empty = auth off (logged as a warning)",
    )
    max_upload_bytes: int = Field(
        25 * 1024 * 1024, gt=0, description="Per-file upload limit in bytes; 413 above it"
    )
    body_memory_mib: int = Field(
        128,
        gt=0,
        description="Memory that request bodies (and the uploads read from them) may hold at "
        "once, MiB: a body's declared length (1.7× for JSON, parsed whole) is reserved before "
        "it is read; a body that does not fit beside the others gets 503 with Retry-After. At "
        "least one largest body: 1.7 × (2 × SLLOC_MAX_UPLOAD_BYTES + 1 MiB)",
    )
    computing_memory_mib: int = Field(
        0,
        ge=0,
        description="Memory the localize and add requests computing at once may hold together, "
        "MiB: each reserves what its image, depth, top_k and its map's keypoints and side need "
        "before it computes and waits while that does not fit beside the others, so small "
        "requests run on every worker at once and one at the limits runs alone; 0 = one "
        "largest request's (a smaller value counts as that too)",
    )
    max_image_pixels: int = Field(
        4096 * 3072,
        gt=0,
        description="Decoded image size limit in pixels (4096×3072: a 12 Mpx phone photo "
        "fits), checked from the header before decoding; 413 above it. Decoding one image this "
        "large with a depth map of as many pixels takes 12 bytes a pixel, 144 MiB at the "
        "default, out of SLLOC_COMPUTING_MEMORY_MIB",
    )
    max_top_k: int = Field(
        50, gt=0, description="Largest top_k a localize request may ask for (422 above)"
    )
    max_frames: int = Field(
        5, ge=1, le=32, description="Most frames (image parts) one localize request may carry"
    )
    max_session_frames: int = Field(
        1000,
        ge=1,
        le=100_000,
        description="Most frames one capture session may hold (each waits in the blob store "
        "until the session is added)",
    )
    auto_migrate: bool = Field(
        True,
        description="Upgrade the schema to head at start-up (`slloc db upgrade` does it by "
        "hand; replicas sharing one database run with false)",
    )
    localize_workers: int = Field(
        0,
        ge=0,
        description="Localize and add requests that compute at once; 0 = the usable cores "
        "(at most 4, fewer when SLLOC_ONNX_THREADS is set); workers × threads per operation "
        "should not exceed the cores",
    )
    cpu_cores: int = Field(
        0,
        ge=0,
        description="Cores the thread policy divides; 0 = the cores this process may run on "
        "(its CPU affinity); set it under a container CPU quota",
    )
    reference_cache_mib: int = Field(
        192,
        ge=0,
        description="Decoded reference features (and depth) kept in memory between "
        "requests, MiB; 0 = off",
    )
    reference_image_cache_mib: int = Field(
        64,
        ge=0,
        description="Reference images kept decoded between requests for the sub-pixel "
        "refinement of matches (configurations whose keypoints are found on shrunken images, "
        "the xfeat family), MiB; 0 = none kept (each is decoded from its original anew)",
    )
    ann_min_references: int = Field(
        50_000,
        gt=0,
        description="Maps with at least this many references are searched through an "
        "approximate faiss index (IVF-SQ8) instead of exactly",
    )
    ann_nprobe: int = Field(
        128,
        gt=0,
        description="Inverted lists (of √N) the approximate index visits per query; more: "
        "higher recall, slower (1M references, 4 candidates per result rescored exactly: "
        "64 → 9 ms, recall@10 0.944; 128 → 17 ms, 0.964; 256 → 33 ms, 0.985)",
    )
    max_queued: int = Field(
        8,
        ge=0,
        description="Localize and add requests that may wait for a worker; more get 503 with "
        "Retry-After",
    )
    max_keypoints: int = Field(
        4096, gt=0, description="Largest keypoint budget a map's feature options may ask for"
    )
    max_side: int = Field(
        1024,
        ge=64,
        description="Largest image side (px) a map's feature options may ask for; one aliked "
        "extraction at S px takes ~2.9 GiB per megapixel of S² (3 GiB at 1024, 11.3 GiB at "
        "2048: docs, Deploying, Memory)",
    )
    localize_time_budget_s: float = Field(
        10.0,
        gt=0,
        allow_inf_nan=False,
        description="Wall-clock budget of one localize (s); a request may ask for less; past it "
        "the answer is localized: false, reason time_budget_exceeded",
    )
    timeout_keep_alive_s: int = Field(
        5,
        gt=0,
        description="`slloc serve`: a connection that has not sent a complete request head "
        "this long (s) after opening or after its last response is closed",
    )
    log_format: LogFormat = Field(
        "text",
        description="`slloc serve`: log lines as text (time level logger [request id]: "
        "message) or as JSON objects, one per line",
    )
    metrics_require_key: bool = Field(
        False,
        description="GET /metrics needs an admin or client X-API-Key (default: open, like "
        "/v1/health; it shows map ids, names and sizes)",
    )
    preview_max_side: int = Field(
        1024,
        ge=0,
        description="Longer side (px) of the JPEG preview kept of each reference image for "
        "the viewer (GET …/images/{image_id}/preview); 0 = keep none",
    )
    limit_concurrency: int = Field(
        64,
        gt=0,
        description="`slloc serve`: requests in flight at once (bodies being received or "
        "requests being handled), over all clients; more get 503 with Retry-After. /livez, "
        "/readyz, /v1/health and /metrics are not counted. Idle connections count for nothing",
    )
    max_requests_per_client: int = Field(
        16,
        gt=0,
        description="`slloc serve`: requests in flight at once from one client address (the "
        "peer, or X-Forwarded-For from a trusted proxy); more get 503 with Retry-After",
    )
    request_body_timeout_s: float = Field(
        60.0,
        gt=0,
        allow_inf_nan=False,
        description="`slloc serve`: a request body must arrive within this long (s) of its "
        "head; else 408 and the connection is closed",
    )

    cors_origins: str = Field(
        "",
        description="Comma-separated origins (scheme://host[:port]) whose browser pages may "
        "call the API (CORS, every route: preflights answered, Access-Control-Allow-Origin "
        "set); * = any origin; empty = CORS off (a browser's cross-origin preflight is "
        "refused)",
    )

    @property
    def max_body_bytes(self) -> int:
        """The largest request body: two uploads (image, depth) and 1 MiB of form fields."""
        return 2 * self.max_upload_bytes + 1024 * 1024

    def parsed_evaluation_features(self) -> tuple[str, ...]:
        """``evaluation_features`` as names, without duplicates."""
        names = (n.strip() for n in self.evaluation_features.split(","))
        return tuple(dict.fromkeys(n for n in names if n))

    @model_validator(mode="after")
    def _check_evaluation_features(self) -> Settings:
        known = feature_config_names()
        unknown = [n for n in self.parsed_evaluation_features() if n not in known]
        if unknown:
            raise ValueError(
                f"evaluation_features: unknown {', '.join(unknown)}; known: {', '.join(known)}"
            )
        return self

    @field_validator("second_opinion")
    @classmethod
    def _check_second_opinion(cls, value: str) -> str:
        value = value.strip()
        known = feature_config_names()
        if value and value != AUTO and value not in known:
            raise ValueError(f"unknown {value}; known: {AUTO}, {', '.join(known)}, or empty")
        return value

    @model_validator(mode="after")
    def _check_body_memory(self) -> Settings:
        largest = JSON_BODY_FACTOR * self.max_body_bytes / 2**20
        if self.body_memory_mib < largest:
            raise ValueError(
                f"body_memory_mib {self.body_memory_mib} is below the largest body's cost, "
                f"{largest:.0f} MiB (1.7 × (2 × max_upload_bytes + 1 MiB))"
            )
        return self

    @field_validator("api_keys")
    @classmethod
    def _check_keys(cls, value: str) -> str:
        parse_api_keys(value)
        return value

    def parsed_api_keys(self) -> list[ApiKey]:
        return parse_api_keys(self.api_keys)

    def parsed_cors_origins(self) -> list[str]:
        return [o.strip().rstrip("/") for o in self.cors_origins.split(",") if o.strip()]


def parse_api_keys(value: str) -> list[ApiKey]:
    keys = []
    for item in filter(None, (part.strip() for part in value.split(","))):
        key, sep, role = item.rpartition(":")
        if not sep or not key or role not in ("admin", "client"):
            raise ValueError(f"API key entries are `key:admin` or `key:client`, got {item!r}")
        keys.append(ApiKey(key=SecretStr(key), role=role))
    return keys


@lru_cache
def get_settings() -> Settings:
    return Settings()
