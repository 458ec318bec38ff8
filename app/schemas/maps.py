from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from app.schemas.estimators import EstimatorEnum, EstimatorName
from app.schemas.text import Description, Name
from app.usecases.maps import MapRecord
from app.usecases.reindex import Reindexed
from services.estimators.registry import DEFAULT_ESTIMATOR


class FeatureOptions(BaseModel):
    """Per-map local-feature options; null keeps the service's default."""

    max_keypoints: int | None = Field(
        None, ge=1, le=20_000, description="Keypoint budget per image (ALIKED: at most 2048)"
    )
    max_side: int | None = Field(
        None, ge=64, le=8192, description="Longer image side features are extracted at (px)"
    )


class MapCreate(BaseModel):
    name: Name
    description: Description | None = None
    default_estimator: EstimatorName = Field(
        EstimatorEnum(DEFAULT_ESTIMATOR),
        description="Estimator used when a localize request names none",
    )
    features: FeatureOptions = Field(
        default_factory=FeatureOptions,
        description="Keypoint budget and image size for this map's references and queries",
    )


class MapOut(BaseModel):
    id: str
    name: str
    description: str | None
    default_estimator: EstimatorName
    features: FeatureOptions
    image_count: int
    created_at: datetime

    @classmethod
    def from_record(cls, record: MapRecord) -> MapOut:
        return cls(
            id=record.id,
            name=record.name,
            description=record.description,
            default_estimator=record.default_estimator,
            features=FeatureOptions(max_keypoints=record.max_keypoints, max_side=record.max_side),
            image_count=record.image_count,
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
