from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field


class MapCreate(BaseModel):
    name: str = Field(min_length=1, max_length=255)
    description: str | None = Field(None, max_length=10_000)


class MapOut(BaseModel):
    id: str
    name: str
    description: str | None
    image_count: int
    created_at: datetime


class MapPage(BaseModel):
    items: list[MapOut]
    total: int
    offset: int
    limit: int
