"""Maps on the globe: a map's geo-registration (set, estimated, read, removed), GPS hints of
queries, and the GeoPose of a localized query."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from app.usecases.errors import NotFoundError
from app.usecases.localize import LocalizeRequest
from app.usecases.maps import require_map
from db.geo import StoredRegistration, from_document, to_document
from db.repositories.images import ImageRepository
from db.store import gps_of, pose_of
from services.errors import InvalidInputError
from services.geo.geopose import GeoPose, GeoPoseAccuracy, geopose_accuracy, geopose_of
from services.geo.gps import GpsFix
from services.geo.registration import GeoRegistration, estimate_registration
from services.localization.answer import LocalizationResult
from services.retrieval.search import PositionPrior

# a query's GPS hint keeps references within this many of its 1-σ accuracies, horizontally
GPS_PRIOR_SIGMAS = 3.0
# the accuracy assumed for a GPS hint that states none (a phone outdoors), and the least radius
DEFAULT_GPS_ACCURACY_M = 10.0
MIN_GPS_PRIOR_RADIUS_M = 10.0

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Residual:
    image_id: str
    name: str
    residual_m: float
    inlier: bool


def set_registration(
    sessions: sessionmaker[Session], map_id: str, registration: GeoRegistration
) -> StoredRegistration:
    """Store a registration set by hand, replacing any.

    Raises:
        NotFoundError: unknown map.
    """
    stored = StoredRegistration(registration, "manual")
    with sessions.begin() as session:
        require_map(session, map_id).geo_registration = to_document(stored)
    return stored


def get_registration(sessions: sessionmaker[Session], map_id: str) -> StoredRegistration:
    """Raises:
    NotFoundError: unknown map, or a map without a registration.
    """
    stored = find_registration(sessions, map_id)
    if stored is None:
        raise NotFoundError("geo-registration of map", map_id)
    return stored


def find_registration(sessions: sessionmaker[Session], map_id: str) -> StoredRegistration | None:
    """The map's registration, None when it has none.

    Raises:
        NotFoundError: unknown map.
    """
    with sessions() as session:
        document = require_map(session, map_id).geo_registration
    if document is None:
        return None
    try:
        return from_document(document)
    except InvalidInputError as exc:  # stored before its values were range-checked
        logger.warning("map %s: stored geo-registration ignored: %s", map_id, exc)
        return None


def map_registration(sessions: sessionmaker[Session], map_id: str) -> GeoRegistration | None:
    """The map's registration, None when it has none.

    Raises:
        NotFoundError: unknown map.
    """
    stored = find_registration(sessions, map_id)
    return None if stored is None else stored.registration


def delete_registration(sessions: sessionmaker[Session], map_id: str) -> None:
    """Raises:
    NotFoundError: unknown map, or a map without a registration.
    """
    with sessions.begin() as session:
        row = require_map(session, map_id)
        if row.geo_registration is None:
            raise NotFoundError("geo-registration of map", map_id)
        row.geo_registration = None


def estimate_map_registration(
    sessions: sessionmaker[Session], map_id: str, max_error_m: float
) -> tuple[StoredRegistration, list[Residual]]:
    """Estimate the registration from the references that carry a GPS position and store it.

    Raises:
        NotFoundError: unknown map.
        InvalidInputError: too few references with GPS, or their layout leaves it unobservable.
    """
    with sessions() as session:
        require_map(session, map_id)
        rows = [row for row in ImageRepository(session).with_gps(map_id)]
        ids = [row.id for row in rows]
        names = [row.name for row in rows]
        centers = np.array([pose_of(row).center for row in rows]).reshape(-1, 3)
        fixes = [gps_of(row) for row in rows]
    gps = np.array([fix.geodetic().array() for fix in fixes if fix is not None]).reshape(-1, 3)
    if any(fix is not None and fix.height is None for fix in fixes):
        raise InvalidInputError(
            "estimating a geo-registration needs the height of every GPS position; "
            f"{sum(f is not None and f.height is None for f in fixes)} references lack it"
        )
    fit = estimate_registration(centers, gps, max_error_m)
    stored = StoredRegistration(
        fit.registration,
        "estimated",
        num_references=len(rows),
        num_inliers=int(fit.inliers.sum()),
        residual_rms_m=fit.rms_m,
    )
    with sessions.begin() as session:
        require_map(session, map_id).geo_registration = to_document(stored)
    residuals = [
        Residual(i, n, float(r), bool(inl))
        for i, n, r, inl in zip(ids, names, fit.residuals_m, fit.inliers, strict=True)
    ]
    return stored, residuals


def gps_prior(registration: GeoRegistration | None, fix: GpsFix) -> PositionPrior:
    """The retrieval prior of a query's GPS hint: references whose camera centre lies within
    3 × its accuracy (at least 10 m) of it horizontally, at any height.

    Raises:
        InvalidInputError: the map has no geo-registration.
    """
    if registration is None:
        raise InvalidInputError(
            "gps: the map has no geo-registration; set or estimate one "
            "(PUT or POST /v1/maps/{map_id}/geo-registration…) or pass a map-frame prior"
        )
    accuracy = fix.accuracy_m or DEFAULT_GPS_ACCURACY_M
    radius_m = max(GPS_PRIOR_SIGMAS * accuracy, MIN_GPS_PRIOR_RADIUS_M)
    radius_m += GPS_PRIOR_SIGMAS * registration.position_sigma_m
    position = registration.map_from_geodetic(fix.geodetic().array()[None])[0]
    return PositionPrior(position, radius_m / registration.scale, up=registration.map_up())


def with_gps_hint(
    sessions: sessionmaker[Session], map_id: str, request: LocalizeRequest, gps: GpsFix | None
) -> tuple[LocalizeRequest, GeoRegistration | None]:
    """``request`` narrowed by the GPS hint (unchanged without one), and the map's
    registration (None when it has none).

    Raises:
        NotFoundError: unknown map.
        InvalidInputError: a GPS hint on a map without a registration, or with a map-frame
            prior too.
    """
    registration = map_registration(sessions, map_id)
    if gps is not None:
        if request.prior is not None:
            raise InvalidInputError("give either prior (map frame) or gps, not both")
        request = replace(request, prior=gps_prior(registration, gps))
    return request, registration


def geopose_answer(
    registration: GeoRegistration | None, result: LocalizationResult
) -> tuple[GeoPose, GeoPoseAccuracy] | None:
    """The query's GeoPose and its accuracy, for a localized query on a registered map; None
    also when they are not finite numbers (a pose far outside the registered region)."""
    if registration is None or not result.localized or result.cam_from_world is None:
        return None
    with np.errstate(all="ignore"):
        pose = geopose_of(result.cam_from_world, registration)
        uncertainty = result.uncertainty
        accuracy = geopose_accuracy(
            registration,
            uncertainty.position_m if uncertainty is not None else None,
            uncertainty.rotation_deg if uncertainty is not None else None,
        )
    p = pose.position
    numbers = [
        p.latitude,
        p.longitude,
        p.height,
        *pose.quaternion_xyzw,
        accuracy.horizontal_m,
        accuracy.vertical_m,
        accuracy.yaw_deg,
    ]
    if not np.all(np.isfinite(np.asarray(numbers, np.float64))):
        logger.warning("geopose left out: not finite (a pose far outside the registered region)")
        return None
    return pose, accuracy
