"""Self-evaluations of a map: start, list, read, cancel."""

from __future__ import annotations

from fastapi import APIRouter, Response

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
from app.schemas.evaluations import EvaluationCreate, EvaluationOut, EvaluationPage
from app.usecases import evaluations

router = APIRouter(prefix="/v1/maps/{map_id}/evaluations", tags=["evaluations"])


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
