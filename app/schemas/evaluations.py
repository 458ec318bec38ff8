"""Self-evaluations of a map: the request, its progress and what it measured; the map's
coverage read from them."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

from app.schemas.captures import StaleReferenceOut
from app.schemas.estimators import EstimatorName
from app.usecases.coverage import MapCoverage
from app.usecases.evaluations import DEFAULT_SAMPLE, MAX_SAMPLE, EvaluationRequest
from db.models import MapEvaluation


class EvaluationCreate(BaseModel):
    """What to measure; every field has a default (an empty body measures every configuration
    the server can run)."""

    configurations: list[str] | None = Field(
        None,
        min_length=1,
        max_length=12,
        description="Feature configurations to measure (names as SLLOC_FEATURES takes); null: "
        "the server's, the automatic choices (xfeat-lg, aliked) and sift, of those whose "
        "models are built",
    )
    sample_size: int = Field(
        DEFAULT_SAMPLE,
        ge=1,
        le=MAX_SAMPLE,
        description="References held out, spread over the map (farthest-point sampling of "
        "their camera centres)",
    )
    holdout_radius_m: float = Field(
        0.0,
        ge=0.0,
        le=10_000.0,
        description="References whose centre lies within this distance of a held-out one "
        "are held out with it, so that it is as far from the map as a real query (map units)",
    )
    top_k: int = Field(10, ge=1, le=50, description="References retrieved per held-out query")
    estimator: EstimatorName | None = Field(
        None, description="The estimator of the held-out queries; null: the map's default"
    )

    def to_request(self) -> EvaluationRequest:
        return EvaluationRequest(
            configurations=tuple(self.configurations) if self.configurations else None,
            sample_size=self.sample_size,
            holdout_radius_m=self.holdout_radius_m,
            top_k=self.top_k,
            estimator=self.estimator,
        )


class Percentiles(BaseModel):
    median: float | None = Field(description="null: more than half of the answers failed")
    p90: float | None = Field(description="null: more than a tenth of the answers failed")


class ConfidenceCheck(BaseModel):
    threshold: float = Field(description="The confidence an answer is taken as sure above")
    confident: int = Field(description="Answers above the threshold")
    precision: float | None = Field(
        description="Of the answers above the threshold, the share within (0.25 m, 5°)"
    )
    recall: float | None = Field(
        description="Of the answers within (0.25 m, 5°), the share above the threshold"
    )


class Latency(BaseModel):
    median: float | None = Field(description="Median time of a held-out query (ms)")


class Distance(BaseModel):
    median: float | None = Field(
        description="From a held-out reference to the nearest reference it was localized "
        "against (map units): compare with how far your queries are from the map"
    )


class HeldOutOut(BaseModel):
    """One reference localized against the map without it (errors against its stored pose;
    null when not localized)."""

    image_id: str
    name: str
    localized: bool
    reason: str | None
    position_error_m: float | None
    rotation_error_deg: float | None
    confidence: float
    num_inliers: int
    latency_ms: float
    nearest_reference_m: float | None = Field(
        description="From its camera centre to the nearest reference it was localized against"
    )


class ConfigurationResult(BaseModel):
    held_out: int = Field(description="References localized against the map without them")
    localized: int
    recall: dict[str, float] = Field(
        description="Share of the held-out references localized within each threshold "
        "(keys like 5cm_5deg)"
    )
    position_error_m: Percentiles = Field(description="Failures count as infinite")
    rotation_error_deg: Percentiles
    confidence: ConfidenceCheck
    latency_ms: Latency
    nearest_reference_m: Distance
    failures: dict[str, int] = Field(description="Held-out references not localized, by reason")
    duration_s: float = Field(description="Time this configuration's measurement took")
    references: list[HeldOutOut] | None = Field(
        None, description="Per held-out reference (left out of listings)"
    )


class EvaluationResult(BaseModel):
    configurations: dict[str, ConfigurationResult]
    recommended: str | None = Field(
        description="The fastest configuration within 5 points of the best recall at every "
        "threshold and within 1.25x (or 5 mm) of the best median position error; null when "
        "none localized anything"
    )
    served: str = Field(description="The server's feature configuration at the time")
    references: int = Field(description="The map's references with their originals")
    stale: list[StaleReferenceOut] = Field(
        default_factory=list,
        description="References that no longer match the held-out references that cover "
        "them, flagged stale (measured with the served configuration)",
    )


class EvaluationProgress(BaseModel):
    done: int = Field(description="Held-out queries localized, over every configuration")
    total: int


class EvaluationOut(BaseModel):
    id: str
    map_id: str
    state: Literal["queued", "running", "done", "failed", "cancelled"]
    request: EvaluationCreate
    progress: EvaluationProgress
    result: EvaluationResult | None
    error: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None

    @classmethod
    def from_row(cls, row: MapEvaluation, with_references: bool = True) -> EvaluationOut:
        result: dict[str, Any] | None = row.result
        if result is not None and not with_references:
            result = {
                **result,
                "configurations": {
                    name: {**summary, "references": None}
                    for name, summary in dict(result["configurations"]).items()
                },
            }
        return cls(
            id=row.id,
            map_id=row.map_id,
            state=row.state,
            request=EvaluationCreate.model_validate(row.request),
            progress=EvaluationProgress(done=row.done, total=row.total),
            result=EvaluationResult.model_validate(result) if result is not None else None,
            error=row.error,
            created_at=row.created_at,
            started_at=row.started_at,
            finished_at=row.finished_at,
        )


class EvaluationPage(BaseModel):
    items: list[EvaluationOut] = Field(description="Newest first, without per-reference rows")
    total: int
    offset: int
    limit: int


class CoverageCellOut(BaseModel):
    i: int = Field(description="Index along the plane's u axis")
    j: int = Field(description="Index along the plane's v axis")
    center: list[float] = Field(description="The cell's centre in map coordinates")
    references: int
    held_out: int = Field(description="Its references held out by the latest self-evaluation")
    failed: int = Field(
        description="Of those, not localized or off by more than 25 cm or 5° from their pose"
    )
    median_error_m: float | None = Field(description="Of the held-out ones localized")
    queries_localized: int = Field(
        description="Single-frame queries localized whose best retrieved reference lies here"
    )
    queries_failed: int = Field(
        description="Single-frame queries not localized whose best retrieved reference lies here"
    )
    weak: bool
    why: list[str] = Field(description="Why the cell is weak")


class GroundPlaneOut(BaseModel):
    origin: list[float]
    u: list[float] = Field(description="Unit axis of the cells' i")
    v: list[float] = Field(description="Unit axis of the cells' j")


class CoverageOut(BaseModel):
    """The map's references on their ground plane, cell by cell, with its latest
    self-evaluation: where a query is least likely to be answered well."""

    plane: GroundPlaneOut
    cell_m: float
    evaluation_id: str | None = Field(
        description="The self-evaluation read; null when the map has no finished one (cells "
        "then say only how many references they hold)"
    )
    weak: int = Field(description="Weak cells")
    cells: list[CoverageCellOut]

    @classmethod
    def from_coverage(cls, found: MapCoverage) -> CoverageOut:
        c = found.coverage
        cells = [
            CoverageCellOut(
                i=cell.i,
                j=cell.j,
                center=[float(x) for x in cell.center],
                references=cell.references,
                held_out=cell.held_out,
                failed=cell.failed,
                median_error_m=cell.median_error_m,
                queries_localized=cell.queries_localized,
                queries_failed=cell.queries_failed,
                weak=bool(cell.why_weak),
                why=cell.why_weak,
            )
            for cell in c.cells
        ]
        return cls(
            plane=GroundPlaneOut(
                origin=[float(x) for x in c.origin],
                u=[float(x) for x in c.u],
                v=[float(x) for x in c.v],
            ),
            cell_m=c.cell_m,
            evaluation_id=found.evaluation_id,
            weak=sum(cell.weak for cell in cells),
            cells=cells,
        )
