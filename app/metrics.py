"""Prometheus metrics of one app (``GET /metrics``): HTTP requests by route template, localize
stage timings and outcomes, and, read at each scrape, the admission queue, the retrieval cache,
the size of the largest maps, whether the database and the blob store answer, and the process
(``process_*``, ``python_*``)."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence

from anyio import to_thread
from fastapi import APIRouter, Depends, Request, Response
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    GC_COLLECTOR,
    PLATFORM_COLLECTOR,
    PROCESS_COLLECTOR,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.metrics_core import Metric
from prometheus_client.registry import Collector
from sqlalchemy.exc import SQLAlchemyError
from starlette.datastructures import State
from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.auth import API_KEY_HEADER, RoleCheck
from app.blob_probe import BLOB_PROBE_TTL_S, blob_probe_ready, blob_store_ok
from app.usecases.evaluations import Evaluator
from db.repositories.maps import MapRepository
from services.localization.answer import LocalizationResult

logger = logging.getLogger(__name__)

# seconds; HTTP answers range from a cached health probe to a localize near its time budget
REQUEST_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
STAGE_BUCKETS_S = (0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
# the route label of a request that matched no route (keeps the label set bounded)
UNMATCHED_ROUTE = "unmatched"
# the method label's values: a request with any other method (HTTP lets a client make one up)
# is counted as OTHER_METHOD, so that clients cannot add series without bound
KNOWN_METHODS = frozenset(
    ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS", "CONNECT", "TRACE")
)
OTHER_METHOD = "other"
# maps reported by `slloc_map_images` at each scrape, the largest first
MAX_MAP_SERIES = 1000


class ServiceMetrics:
    """The app's metrics in a registry of their own (two apps in one process never share
    series). ``state`` is the app's state, read at scrape time for the gauges."""

    def __init__(self, state: State) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "slloc_http_requests",
            "HTTP requests answered, by method (other: not a standard one), route template "
            "and status code",
            ("method", "route", "status"),
            registry=self.registry,
        )
        self.request_seconds = Histogram(
            "slloc_http_request_duration_seconds",
            "Time from a request's arrival to the end of its answer, by route template",
            ("method", "route"),
            buckets=REQUEST_BUCKETS_S,
            registry=self.registry,
        )
        self.stage_seconds = Histogram(
            "slloc_localize_stage_seconds",
            "Localize time per engine stage (decode, extract, retrieve, match, estimate) and "
            "in total; stages a request never reached are not observed",
            ("stage",),
            buckets=STAGE_BUCKETS_S,
            registry=self.registry,
        )
        self.outcomes = Counter(
            "slloc_localize_outcomes",
            "Localize answers (HTTP 200) by estimator and outcome; reason is none when localized",
            ("estimator", "localized", "reason"),
            registry=self.registry,
        )
        self.wider_retrievals = Counter(
            "slloc_localize_wider_retrievals",
            "Localize answers whose query was retrieved a second time with its references "
            "spread wider (its first answer below confidence 0.5)",
            registry=self.registry,
        )
        self.second_opinions = Counter(
            "slloc_localize_second_opinions",
            "Localize answers whose query another feature configuration localized again, the "
            "map's own having found no answer, by that configuration and its outcome",
            ("features", "localized"),
            registry=self.registry,
        )
        self.agreed_opinions = Counter(
            "slloc_localize_agreed_opinions",
            "Localize answers whose map's configuration and second opinion both withheld a pose "
            "below min_confidence and the two agreed, by the second configuration and whether "
            "the query was localized so",
            ("features", "localized"),
            registry=self.registry,
        )
        self.registry.register(_StateCollector(state))
        # the process (process_*: CPU, resident memory, open file descriptors, start time),
        # the interpreter (python_info) and its garbage collector (python_gc_*), as the default
        # registry has them: read at scrape time, shared by every app of the process
        for collector in (PROCESS_COLLECTOR, PLATFORM_COLLECTOR, GC_COLLECTOR):
            self.registry.register(collector)

    def observe_localization(self, result: LocalizationResult) -> None:
        """Count one localize answer: its outcome, its stages' times (a stage at 0 ms was not
        reached), whether its query was retrieved again wider and its second opinion."""
        reason = result.reason
        self.outcomes.labels(result.estimator, str(reason is None).lower(), reason or "none").inc()
        if result.wider_retrieval:
            self.wider_retrievals.inc()
        opinion = result.second_opinion
        if opinion is not None:
            self.second_opinions.labels(opinion.features, str(opinion.localized).lower()).inc()
            if opinion.agreed:
                localized = str(result.localized).lower()
                self.agreed_opinions.labels(opinion.features, localized).inc()
        for stage, ms in result.timings_ms.items():
            if ms > 0.0:
                self.stage_seconds.labels(stage).observe(ms / 1000.0)

    def exposition(self) -> bytes:
        """The registry in the Prometheus text format."""
        return generate_latest(self.registry)


class _StateCollector(Collector):
    """Gauges read from the app's state at each scrape."""

    def __init__(self, state: State) -> None:
        self.state = state

    def collect(self) -> Iterable[Metric]:
        # the attributes appear when the app's lifespan starts
        admission = getattr(self.state, "admission", None)
        if admission is not None:
            admitted = admission.admitted
            yield _gauge(
                "slloc_admission_admitted",
                "Localize and add requests admitted: computing or waiting for a worker",
                admitted,
            )
            yield _gauge(
                "slloc_admission_queue_depth",
                "Admitted localize and add requests beyond the worker count (waiting)",
                max(0, admitted - admission.workers),
            )
            yield _gauge(
                "slloc_admission_capacity",
                "Localize and add requests admitted at most (workers + queue); more get 503",
                admission.capacity,
            )
            slots = admission.slots
            yield _gauge(
                "slloc_computing_memory_held_mib",
                "Memory the computing requests hold, MiB (of slloc_computing_memory_mib)",
                slots.held_mib,
            )
            yield _gauge(
                "slloc_computing_memory_mib",
                "Memory the requests computing at once may hold together, MiB",
                slots.memory_mib,
            )
            yield _gauge(
                "slloc_computing_memory_waiting",
                "Requests holding a worker and waiting for memory the others hold",
                slots.waiting,
            )
        cache = getattr(self.state, "retrieval_cache", None)
        if cache is not None:
            size = cache.size()
            yield _gauge(
                "slloc_retrieval_cache_indexes",
                "Retrieval indexes held in memory (one per map and feature model)",
                size.indexes,
            )
            yield _gauge(
                "slloc_retrieval_cache_references",
                "References in the retrieval indexes held in memory",
                size.references,
            )
            yield _gauge(
                "slloc_retrieval_cache_bytes",
                "Bytes of the descriptor and position arrays of the cached retrieval indexes",
                size.nbytes,
            )
        jobs = GaugeMetricFamily(
            "slloc_background_jobs",
            "Training jobs queued or running off the request path, by what they train",
            labels=("kind",),
        )
        reextractor = getattr(self.state, "reextractor", None)
        trainers = [getattr(self.state, a, None) for a in ("vocabulary_trainer", "ann_builder")]
        if reextractor is not None:
            trainers.append(reextractor.worker)
            yield CounterMetricFamily(
                "slloc_references_described_again",
                "References described anew from their originals after their map's feature "
                "options changed, since start-up",
                value=reextractor.described,
            )
        evaluator = getattr(self.state, "evaluator", None)
        if evaluator is not None:
            trainers.append(evaluator.worker)
            yield from _evaluation_metrics(evaluator)
        runner = getattr(self.state, "capture_runner", None)
        if runner is not None:
            trainers.append(runner.worker)
            ended = CounterMetricFamily(
                "slloc_capture_sessions",
                "Capture sessions ended since start-up, by how they ended",
                labels=("state",),
            )
            for state in ("added", "refused", "failed"):
                ended.add_metric((state,), runner.finished.get(state, 0))
            yield ended
        growth = getattr(self.state, "query_growth", None)
        if growth is not None:
            trainers.append(growth.worker)
            yield CounterMetricFamily(
                "slloc_queries_added",
                "Queries added to maps that grow from them (grow_from_queries) since start-up",
                value=growth.added,
            )
        for trainer in trainers:
            if trainer is not None:
                jobs.add_metric((trainer.name,), trainer.pending())
        yield jobs
        sessions = getattr(self.state, "sessions", None)
        if sessions is not None:
            maps = GaugeMetricFamily(
                "slloc_map_images",
                f"Reference images per map (the {MAX_MAP_SERIES} largest maps)",
                labels=("map_id", "map"),
            )
            try:
                with sessions() as session:
                    largest = MapRepository(session).largest(MAX_MAP_SERIES)
            except SQLAlchemyError:
                logger.warning("metrics: map sizes left out, the database is unreachable")
                database_up = False
            else:
                for map_id, name, count in largest:
                    maps.add_metric((map_id, name), count)
                yield maps
                database_up = True
            yield _gauge(
                "slloc_database_up",
                "1 when the database answered this scrape's query of the map sizes, else 0",
                float(database_up),
            )
        probed: tuple[float, bool] | None = getattr(self.state, "blob_probe", None)
        if probed is not None:
            yield _gauge(
                "slloc_blob_store_up",
                "1 when the blob store of the originals took writes at its latest probe (at "
                f"most {BLOB_PROBE_TTL_S:g} s before the scrape), else 0",
                float(probed[1]),
            )


def _evaluation_metrics(evaluator: Evaluator) -> Iterable[Metric]:
    """Self-evaluations ended since start-up, and the latest figures of the maps evaluated
    since then (the ``MAX_MAP_SERIES`` most recent)."""
    ended = CounterMetricFamily(
        "slloc_self_evaluations",
        "Self-evaluations of maps ended since start-up, by how they ended",
        labels=("state",),
    )
    for state in ("done", "failed", "cancelled"):
        ended.add_metric((state,), evaluator.finished.get(state, 0))
    yield ended
    yield CounterMetricFamily(
        "slloc_self_evaluation_queries",
        "Held-out references localized by self-evaluations since start-up",
        value=evaluator.held_out,
    )
    recall = GaugeMetricFamily(
        "slloc_map_self_evaluation_recall",
        "Share of a map's held-out references localized within the threshold, by feature "
        "configuration, in its latest self-evaluation",
        labels=("map_id", "map", "configuration", "threshold"),
    )
    median = GaugeMetricFamily(
        "slloc_map_self_evaluation_median_error_meters",
        "Median position error of a map's held-out references (failures infinite), by "
        "feature configuration, in its latest self-evaluation",
        labels=("map_id", "map", "configuration"),
    )
    for map_id, (name, results) in list(evaluator.latest.items())[-MAX_MAP_SERIES:]:
        for configuration, summary in results.items():
            for threshold, value in summary["recall"].items():
                recall.add_metric((map_id, name, configuration, threshold), value)
            error = summary["position_error_m"]["median"]
            median.add_metric(
                (map_id, name, configuration), error if error is not None else float("inf")
            )
    yield recall
    yield median


def _gauge(name: str, documentation: str, value: float) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, documentation, value=value)


class RequestMetrics:
    """ASGI middleware: counts and times every HTTP request under its route template (e.g.
    ``/v1/maps/{map_id}/localize``), so that ids never become label values. The template is
    the route the router picked; for an answer given before routing (a 401 of the key gate)
    it is the first of ``routes`` that matches the path."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics, routes: Sequence[BaseRoute]) -> None:
        self.app = app
        self.metrics = metrics
        self.routes = routes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def send_and_record(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_and_record)
        finally:
            method, route = method_label(scope["method"]), self._template(scope)
            self.metrics.requests.labels(method, route, status_label(status)).inc()
            self.metrics.request_seconds.labels(method, route).observe(time.perf_counter() - start)

    def _template(self, scope: Scope) -> str:
        routed = getattr(scope.get("route"), "path", None)
        if isinstance(routed, str):
            return routed
        partial = None
        for route in self.routes:
            match, _ = route.matches(scope)
            path = getattr(route, "path", None)
            if match is Match.FULL and isinstance(path, str):
                return path
            if match is Match.PARTIAL and partial is None and isinstance(path, str):
                partial = path  # the path of a route with other methods (405)
        return partial or UNMATCHED_ROUTE


def method_label(method: str) -> str:
    """The method as a label value: a standard method, else ``other``."""
    return method if method in KNOWN_METHODS else OTHER_METHOD


def status_label(status: int) -> str:
    """The status code as a label value (a code outside 100–599 is ``other``)."""
    return str(status) if 100 <= status <= 599 else "other"


_ANY_KEY = RoleCheck(("admin", "client"))


async def _metrics_access(request: Request) -> None:
    """With ``SLLOC_METRICS_REQUIRE_KEY`` a scrape needs an admin or client key."""
    settings = request.app.state.settings
    if settings.metrics_require_key:
        _ANY_KEY.check(settings, request.headers.get(API_KEY_HEADER))


router = APIRouter()


@router.get("/metrics", include_in_schema=False, dependencies=[Depends(_metrics_access)])
async def metrics(request: Request) -> Response:
    """Prometheus text exposition: the blob store probed (unless probed lately), then the
    registry read on a worker thread (the map sizes query the database)."""
    state = request.app.state
    if blob_probe_ready(state):
        await blob_store_ok(state)
    registry: ServiceMetrics = state.metrics
    return Response(await to_thread.run_sync(registry.exposition), media_type=CONTENT_TYPE_LATEST)
