from __future__ import annotations

from pydantic import BaseModel


class ModelsOut(BaseModel):
    features: str
    matcher: str
    global_descriptor: str
    estimators: list[str]


class HealthOut(BaseModel):
    status: str
    version: str
    models: ModelsOut
