"""Self-evaluations of a map: start, list, read, cancel; the map's coverage read from them."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from app.api.deps import (
    AdminKey,
    ClientKey,
    EvaluatorDep,
    Limit,
    LocalizersDep,
    Offset,
    SessionsDep,
)
from app.errors import problem_responses
from app.schemas.evaluations import CoverageOut, EvaluationCreate, EvaluationOut, EvaluationPage
from app.usecases import coverage, evaluations

router = APIRouter(prefix="/v1/maps/{map_id}/evaluations", tags=["evaluations"])
coverage_router = APIRouter(prefix="/v1/maps/{map_id}/coverage", tags=["evaluations"])


@router.post(
    "",
    status_code=202,
    operation_id="start_evaluation",
    dependencies=[AdminKey],
    responses=problem_responses(400, 401, 403, 404, 409, 413, 422),
)
def start_evaluation(
    map_id: str,
    sessions: SessionsDep,
    localizers: LocalizersDep,
    evaluator: EvaluatorDep,
    response: Response,
    body: EvaluationCreate | None = None,
) -> EvaluationOut:
    """Starts measuring the map on its own references in the background: a spread of them is
    localized, each as a query with its own camera against the rest of the map, for each
    configuration asked for; poll the evaluation (``Location``) for its progress and result.
    409 while another evaluation of the map runs, or when fewer than two references have
    their originals; 422 for a configuration this server does not measure (its own and
    ``SLLOC_EVALUATION_FEATURES``) or whose models it lacks."""
    request = (body or EvaluationCreate()).to_request()
    row = evaluations.start_evaluation(sessions, localizers, map_id, request, evaluator)
    response.headers["Location"] = f"/v1/maps/{map_id}/evaluations/{row.id}"
    return EvaluationOut.from_row(row)


@router.get(
    "",
    operation_id="list_evaluations",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404, 422),
)
def list_evaluations(
    map_id: str, sessions: SessionsDep, offset: Offset = 0, limit: Limit = 20
) -> EvaluationPage:
    rows, total = evaluations.list_evaluations(sessions, map_id, offset, limit)
    items = [EvaluationOut.from_row(row, with_references=False) for row in rows]
    return EvaluationPage(items=items, total=total, offset=offset, limit=limit)


@coverage_router.get(
    "",
    operation_id="get_map_coverage",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404, 422),
)
def get_coverage(
    map_id: str,
    sessions: SessionsDep,
    cell_m: Annotated[
        float | None,
        Query(
            gt=0,
            le=1_000_000,
            description="Cell size in map units (default: 4 × the map's spacing, the median "
            "distance between neighbouring references)",
        ),
    ] = None,
) -> CoverageOut:
    """The map's references on their ground plane (the plane their camera centres spread
    over), cell by cell, with what its latest finished self-evaluation measured of the
    references held out in each: a cell is weak when half or more of them failed, or when it
    holds a single reference. 422 for cells so small that the map would need more than
    20 000."""
    return CoverageOut.from_coverage(coverage.map_coverage(sessions, map_id, cell_m))


@router.get(
    "/{evaluation_id}",
    operation_id="get_evaluation",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404),
)
def get_evaluation(map_id: str, evaluation_id: str, sessions: SessionsDep) -> EvaluationOut:
    """The evaluation with what it measured of each held-out reference."""
    return EvaluationOut.from_row(evaluations.get_evaluation(sessions, map_id, evaluation_id))


@router.delete(
    "/{evaluation_id}",
    status_code=204,
    operation_id="delete_evaluation",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404),
)
def delete_evaluation(map_id: str, evaluation_id: str, sessions: SessionsDep) -> Response:
    """Cancels an evaluation that has not finished (it stays, ``cancelled``); deletes a
    finished one."""
    evaluations.cancel_evaluation(sessions, map_id, evaluation_id)
    return Response(status_code=204)
