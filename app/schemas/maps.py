from __future__ import annotations

from datetime import datetime
from typing import Annotated

from pydantic import AfterValidator, BaseModel, Field

from services.errors import UnknownComponentError
from services.estimators.registry import get_estimator


def _known_estimator(name: str) -> str:
    try:
        get_estimator(name)
    except UnknownComponentError as exc:
        raise ValueError(str(exc)) from None
    return name


EstimatorName = Annotated[str, AfterValidator(_known_estimator)]


class FeatureOptions(BaseModel):
    """Per-map local-feature options; null keeps the service's default."""

    max_keypoints: int | None = Field(
        None, ge=1, le=20_000, description="Keypoint budget per image (ALIKED: at most 2048)"
    )
    max_side: int | None = Field(
        None, ge=64, le=8192, description="Longer image side features are extracted at (px)"
    )


class MapCreate(BaseModel):
    name: str = Field(min_length=1, max_length=255)
    description: str | None = Field(None, max_length=10_000)
    default_estimator: EstimatorName = Field(
        "e5p1", description="Estimator used when a localize request names none"
    )
    features: FeatureOptions = Field(
        default_factory=FeatureOptions,
        description="Keypoint budget and image size for this map's references and queries",
    )


class MapOut(BaseModel):
    id: str
    name: str
    description: str | None
    default_estimator: str
    features: FeatureOptions
    image_count: int
    created_at: datetime


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
