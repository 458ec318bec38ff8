"""A map's geo-registration: set by hand, estimated from the references' GPS, read, removed."""

from __future__ import annotations

from fastapi import APIRouter, Response

from app.api.deps import AdminKey, ClientKey, SessionsDep
from app.errors import problem_responses
from app.schemas.geo import (
    GeoRegistrationEstimateIn,
    GeoRegistrationIn,
    GeoRegistrationOut,
    ResidualOut,
)
from app.usecases import geo

router = APIRouter(prefix="/v1/maps/{map_id}/geo-registration", tags=["geo"])


@router.put(
    "",
    operation_id="set_geo_registration",
    dependencies=[AdminKey],
    responses=problem_responses(400, 401, 403, 404, 413, 422),
)
def set_geo_registration(
    map_id: str, body: GeoRegistrationIn, sessions: SessionsDep
) -> GeoRegistrationOut:
    """Set the similarity from the map frame to East-North-Up at a WGS84 origin by hand."""
    return GeoRegistrationOut.from_stored(
        geo.set_registration(sessions, map_id, body.to_registration())
    )


@router.post(
    "/estimate",
    operation_id="estimate_geo_registration",
    dependencies=[AdminKey],
    responses=problem_responses(400, 401, 403, 404, 413, 422),
)
def estimate_geo_registration(
    map_id: str, sessions: SessionsDep, body: GeoRegistrationEstimateIn | None = None
) -> GeoRegistrationOut:
    """Estimate the registration from the camera centres of the references that carry a GPS
    position (with height): pycolmap's robust similarity, then least squares over the
    positions within ``max_error_m``. Stores and returns it with each reference's residual.
    422 when fewer than three references have GPS or they lie on a line."""
    body = body or GeoRegistrationEstimateIn()
    stored, residuals = geo.estimate_map_registration(sessions, map_id, body.max_error_m)
    return GeoRegistrationOut.from_stored(
        stored,
        [
            ResidualOut(image_id=r.image_id, name=r.name, residual_m=r.residual_m, inlier=r.inlier)
            for r in residuals
        ],
    )


@router.get(
    "",
    operation_id="get_geo_registration",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404),
)
def get_geo_registration(map_id: str, sessions: SessionsDep) -> GeoRegistrationOut:
    return GeoRegistrationOut.from_stored(geo.get_registration(sessions, map_id))


@router.delete(
    "",
    status_code=204,
    operation_id="delete_geo_registration",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404),
)
def delete_geo_registration(map_id: str, sessions: SessionsDep) -> Response:
    geo.delete_registration(sessions, map_id)
    return Response(status_code=204)
