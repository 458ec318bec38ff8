from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, Field, StrictBool

from app.schemas.estimators import EstimatorEnum, EstimatorName
from app.schemas.text import Description, Name
from app.usecases.maps import MapRecord
from app.usecases.reindex import Reindexed
from app.usecases.served_features import MapServing
from db.repositories.reextraction import Progress
from services.estimators.registry import DEFAULT_ESTIMATOR


class FeatureOptions(BaseModel):
    """Per-map local-feature options; null keeps the service's default. JSON integers only:
    a string ("1024") or a boolean is refused."""

    max_keypoints: int | None = Field(
        None,
        ge=1,
        le=20_000,
        strict=True,
        description="Keypoint budget per image (ALIKED: at most 2048)",
    )
    max_side: int | None = Field(
        None,
        ge=64,
        le=8192,
        strict=True,
        description="Longer image side features are extracted at (px)",
    )


class FeatureProgressOut(BaseModel):
    described: int = Field(description="References described for the pending options")
    total: int = Field(description="References that have their original to be described from")


class PendingFeaturesOut(FeatureOptions):
    preset: str = Field(description="The feature configuration they are described with")


class MapFeaturesOut(FeatureOptions):
    """The feature configuration and options the map serves with, whether it follows its
    self-evaluation and, while the references are described anew, what they are described
    for and how far."""

    preset: str = Field(
        description="The feature configuration whose extractor describes the map's queries "
        "and references: the server's (SLLOC_FEATURES) until the map chooses another"
    )
    auto: bool = Field(
        description="The map takes the configuration its self-evaluation recommends, "
        "evaluated on its own as it grows (docs: self-evaluation)"
    )
    state: Literal["ready", "evaluating", "re-extracting"] = Field(
        description="evaluating: a self-evaluation of the map is queued or running; "
        "re-extracting: the references are being described anew from their originals for "
        "`pending`; the map answers with its current descriptions until every one is, then "
        "switches at once"
    )
    pending: PendingFeaturesOut | None = Field(
        None, description="What the references are being described for"
    )
    progress: FeatureProgressOut | None = None


class FeatureCreate(FeatureOptions):
    preset: str = Field(
        "auto",
        description="The feature configuration: `auto` (the server's, SLLOC_FEATURES, until "
        "the map's self-evaluation recommends one of those the server serves) or one of "
        "them by name (the server's and SLLOC_EVALUATION_FEATURES'; another is refused, 422)",
    )


GROW_HELP = (
    "Queries localized with confidence ≥ 0.95 and their intrinsics that add a view the map "
    "lacks (no reference within the map's spacing looking within 15° of it) are added as "
    "references, named query/<time>-<id>: the map fills in where it is used, at most one "
    "reference per place and direction"
)


RETIRE_HELP = (
    "References a capture session flags stale (its frames that cover them no longer match "
    "them) are deleted at once instead of listed for an admin to retire"
)


class MapCreate(BaseModel):
    name: Name
    description: Description | None = None
    default_estimator: EstimatorName = Field(
        EstimatorEnum(DEFAULT_ESTIMATOR),
        description="Estimator used when a localize request names none",
    )
    features: FeatureCreate = Field(
        default_factory=FeatureCreate,
        description="Feature configuration, keypoint budget and image size for this map's "
        "references and queries",
    )
    grow_from_queries: StrictBool = Field(False, description=GROW_HELP)
    retire_stale: StrictBool = Field(False, description=RETIRE_HELP)


class FeaturePatch(FeatureOptions):
    preset: str | None = Field(
        None,
        description="The feature configuration: `auto` (follow the map's self-evaluation), or "
        "one the server serves by name (its own, SLLOC_FEATURES, and those of "
        "SLLOC_EVALUATION_FEATURES; another is refused, 422); null keeps the map's",
    )


class MapPatch(BaseModel):
    """The fields to change; those left out keep their value."""

    grow_from_queries: StrictBool | None = Field(None, description=GROW_HELP)
    retire_stale: StrictBool | None = Field(None, description=RETIRE_HELP)
    description: Description | None = None
    default_estimator: EstimatorName | None = Field(
        None, description="Estimator used when a localize request names none"
    )
    features: FeaturePatch | None = Field(
        None,
        description="New feature configuration, keypoint budget or image size: the map's "
        "references are described anew from their originals in the background "
        "(`features.state` re-extracting) while the map answers with the current ones, then "
        "it switches at once; what it serves cancels a re-description in progress. 409 when "
        "references were added before originals were kept",
    )


class DescribedByOut(BaseModel):
    feature_model: str = Field(description="The extractor that described them, e.g. xfeat-1024-640")
    descriptor_model: str = Field(description="The global descriptor that described them")
    image_count: int
    served: bool = Field(description="This server describes queries alike: they are searched")


class MapFeatureModelsOut(BaseModel):
    """What the map's references were described by, and whether this server can serve
    them."""

    server_feature_model: str = Field(
        description="The extractor this server describes the map's queries with (its model, "
        "keypoint budget and image side)"
    )
    server_descriptor_model: str = Field(description="This server's global descriptor")
    described_by: list[DescribedByOut] = Field(
        description="The map's references grouped by what described them, most first"
    )
    servable: bool = Field(
        description="Some reference (or none: an empty map) is described as this server "
        "describes queries; false: every localize on the map answers 409 "
        "feature-models-missing"
    )
    unserved_image_count: int = Field(description="References this server does not search")
    missing_models: list[str] = Field(
        description="Exported models the unserved references need that this server lacks"
    )
    configurations: list[str] = Field(
        description="SLLOC_FEATURES values whose extractor described the unserved references"
    )
    detail: str | None = Field(None, description="What is wrong and what to do")

    @classmethod
    def from_serving(cls, serving: MapServing) -> MapFeatureModelsOut:
        return cls(
            server_feature_model=serving.feature_model,
            server_descriptor_model=serving.descriptor_model,
            described_by=[
                DescribedByOut(
                    feature_model=g.feature_model,
                    descriptor_model=g.descriptor_model,
                    image_count=g.image_count,
                    served=g.served,
                )
                for g in serving.described_by
            ],
            servable=serving.servable,
            unserved_image_count=serving.unserved_count,
            missing_models=list(serving.missing_models),
            configurations=list(serving.configurations),
            detail=serving.detail,
        )


class MapOut(BaseModel):
    id: str
    name: str
    description: str | None
    default_estimator: EstimatorName
    features: MapFeaturesOut
    image_count: int
    references_without_original: int = Field(
        description="Images added before originals were kept (has_original false): they "
        "serve their stored features but cannot be described again"
    )
    feature_models: MapFeatureModelsOut
    grow_from_queries: bool = Field(description=GROW_HELP)
    retire_stale: bool = Field(description=RETIRE_HELP)
    created_at: datetime

    @classmethod
    def from_record(
        cls, record: MapRecord, serving: MapServing, served: str, progress: Progress | None
    ) -> MapOut:
        """``served``: the server's feature configuration (what a map that has not chosen
        one is served with)."""
        pending = (
            PendingFeaturesOut(
                preset=record.pending_preset or served,
                max_keypoints=record.pending_max_keypoints,
                max_side=record.pending_max_side,
            )
            if record.reextracting
            else None
        )
        state: Literal["ready", "evaluating", "re-extracting"] = "ready"
        if record.reextracting:
            state = "re-extracting"
        elif record.evaluating:
            state = "evaluating"
        features = MapFeaturesOut(
            max_keypoints=record.max_keypoints,
            max_side=record.max_side,
            preset=record.feature_preset or served,
            auto=record.features_auto,
            state=state,
            pending=pending,
            progress=None
            if progress is None
            else FeatureProgressOut(described=progress.described, total=progress.total),
        )
        return cls(
            id=record.id,
            name=record.name,
            description=record.description,
            default_estimator=record.default_estimator,
            features=features,
            image_count=record.image_count,
            grow_from_queries=record.grow_from_queries,
            retire_stale=record.retire_stale,
            references_without_original=record.without_original,
            feature_models=MapFeatureModelsOut.from_serving(serving),
            created_at=record.created_at,
        )


class MapPage(BaseModel):
    items: list[MapOut]
    total: int
    offset: int
    limit: int


class ReindexOut(BaseModel):
    """A new VLAD vocabulary for the map's references of the service's feature model."""

    map_id: str
    feature_model: str
    vocabulary_version: int = Field(description="Grows by one with every training")
    num_centers: int = Field(description="k-means centres K (VLAD length K × descriptor size)")
    trained_images: int = Field(description="References in the map when it was trained")
    encoded_images: int = Field(description="References re-encoded with it")
    seconds: float

    @classmethod
    def from_reindexed(cls, reindexed: Reindexed) -> ReindexOut:
        return cls(
            map_id=reindexed.map_id,
            feature_model=reindexed.feature_model,
            vocabulary_version=reindexed.vocabulary_version,
            num_centers=reindexed.num_centers,
            trained_images=reindexed.trained_images,
            encoded_images=reindexed.encoded_images,
            seconds=round(reindexed.seconds, 3),
        )
