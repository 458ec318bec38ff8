from __future__ import annotations

from pydantic import BaseModel

from app.schemas.estimators import EstimatorName


class ModelsOut(BaseModel):
    features: str
    matcher: str
    global_descriptor: str
    estimators: list[EstimatorName]


class HealthOut(BaseModel):
    status: str
    version: str
    models: ModelsOut
