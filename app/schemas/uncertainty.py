from __future__ import annotations

from pydantic import BaseModel, Field

from services.estimators.uncertainty import PoseUncertainty


class UncertaintyOut(BaseModel):
    """First-order uncertainty of the returned pose (the docs' API page, 'Queries
    without intrinsics and the pose uncertainty')."""

    position_m: float = Field(
        description="Root-mean-square camera-centre error predicted by the pose covariance "
        "(the verified points' own uncertainty included), in map units (metres on a metric "
        "map); 3 × this bounds the error in nearly all cases"
    )
    rotation_deg: float = Field(
        description="Root-mean-square rotation error predicted by the covariance, degrees"
    )
    num_points: int = Field(description="Verified 3D points the covariance rests on")

    @classmethod
    def from_uncertainty(cls, uncertainty: PoseUncertainty) -> UncertaintyOut:
        return cls(
            position_m=uncertainty.position_m,
            rotation_deg=uncertainty.rotation_deg,
            num_points=uncertainty.num_points,
        )
