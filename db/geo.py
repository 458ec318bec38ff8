"""How a map's geo-registration is stored: one JSON document in ``maps.geo_registration``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from services.geo.geodesy import Geodetic
from services.geo.registration import GeoRegistration


@dataclass(frozen=True)
class StoredRegistration:
    """A registration and where it came from: ``source`` "manual" (set by an admin) or
    "estimated" (from the references' GPS positions, with the fit's inlier count and
    residual RMS in metres)."""

    registration: GeoRegistration
    source: str
    num_references: int | None = None
    num_inliers: int | None = None
    residual_rms_m: float | None = None


def to_document(stored: StoredRegistration) -> dict[str, Any]:
    r = stored.registration
    return {
        "origin": [r.origin.latitude, r.origin.longitude, r.origin.height],
        "rotation": [float(v) for v in r.quaternion],
        "translation": [float(v) for v in r.translation],
        "scale": float(r.scale),
        "position_sigma_m": float(r.position_sigma_m),
        "rotation_sigma_deg": float(r.rotation_sigma_deg),
        "source": stored.source,
        "num_references": stored.num_references,
        "num_inliers": stored.num_inliers,
        "residual_rms_m": stored.residual_rms_m,
    }


def from_document(document: dict[str, Any]) -> StoredRegistration:
    registration = GeoRegistration.from_quaternion(
        Geodetic(*(float(v) for v in document["origin"])),
        np.asarray(document["rotation"], np.float64),
        np.asarray(document["translation"], np.float64),
        float(document["scale"]),
        float(document.get("position_sigma_m", 0.0)),
        float(document.get("rotation_sigma_deg", 0.0)),
    )
    return StoredRegistration(
        registration,
        str(document["source"]),
        document.get("num_references"),
        document.get("num_inliers"),
        document.get("residual_rms_m"),
    )
