"""Runners: load references into a fresh map and localize queries, either in this process
(the server's own code path on a temporary SQLite database) or against a running server over
HTTP exactly as a client does (multipart uploads with ``metadata`` / ``params`` JSON).

Both take the localize ``params`` as the API's JSON object and answer ``QueryOutcome``s.
In process, a query is described and matched once for all the estimators compared on it;
over HTTP it is sent once per estimator.
"""

from __future__ import annotations

import contextlib
import json
import sys
import tempfile
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import httpx

from app.schemas.geometry import CameraSchema, PoseSchema
from app.schemas.images import ImageMetadata
from app.schemas.localize import LocalizeParamsIn, SecondOpinionOut
from app.usecases.compare_estimators import localize_with_each
from app.usecases.errors import ConflictError
from app.usecases.images import add_reference_image
from app.usecases.localize import LocalizeContext, localize
from app.usecases.maps import FeatureChoice, create_map
from app.usecases.reindex import reindex_map
from db.blobs import FileBlobStore
from db.migrate import upgrade
from db.session import make_engine, make_session_factory
from services.components import EngineConfig, Localizers, build_localizer
from services.estimators.base import FailureReason
from services.estimators.registry import (
    DEFAULT_ESTIMATOR,
    DEPTH_ESTIMATORS,
    DEPTH_USING_ESTIMATORS,
)
from services.localization.answer import LocalizationResult
from services.localization.second_opinion import DescribedCache
from services.retrieval.cache import RetrievalIndexCache
from services.retrieval.policy import MIN_IMAGES
from services.runtime.memory import SECOND_OPINION_DESCRIBED
from tools.evaluation.datasets import PosedImage


class ServiceBusyError(RuntimeError):
    """The server refused the request for now (503); ``retry_after_s`` from its header."""

    def __init__(self, message: str, retry_after_s: float) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


@dataclass(frozen=True)
class QueryOutcome:
    """A localize answer as the evaluation needs it.

    Attributes:
        cam_from_world: the pose as the API's ``{"rotation": [w, x, y, z], "translation"}``.
        retrieved: names of the retrieved references, best first.
        timings_ms: the answer's stages plus ``client`` (wall time seen by the evaluator).
        stats: the engine's numbers about the estimate; over HTTP only ``wider_retrieval``
            (1 when the answer says its query was retrieved again wider, else 0).
        estimator_used: the estimator whose answer it is (``auto`` names its choice).
        candidate: a ``low_confidence`` answer's pose, withheld below ``min_confidence``.
    """

    localized: bool
    reason: str | None
    cam_from_world: PoseSchema | None
    num_inliers: int
    confidence: float
    retrieved: list[str]
    timings_ms: dict[str, float]
    stats: dict[str, float] = field(default_factory=dict)
    estimator_used: str | None = None
    candidate: PoseSchema | None = None

    @classmethod
    def not_localized(cls, reason: str, stats: dict[str, float] | None = None) -> QueryOutcome:
        """An outcome with no pose, no inliers and nothing retrieved, for ``reason``."""
        return cls(
            localized=False,
            reason=reason,
            cam_from_world=None,
            num_inliers=0,
            confidence=0.0,
            retrieved=[],
            timings_ms={},
            stats=stats or {},
        )


class Runner(Protocol):
    """One map of references under one feature configuration."""

    features: str

    def add_reference(self, image: PosedImage, depth: bytes | None) -> None: ...

    def index_references(self, count: int) -> None:
        """After the ``count`` references are in: train the map's retrieval vocabulary on all of
        them when the map is big enough for one, as an admin does after a bulk load, so
        every mode searches the same index whatever the background trainer did meanwhile."""
        ...

    def localize(self, image: bytes, depth: bytes | None, params: dict[str, Any]) -> QueryOutcome:
        """``params``: the API's localize ``params`` object."""
        ...

    def localize_each(
        self,
        image: bytes,
        depth: bytes | None,
        params: dict[str, Any],
        estimators: Sequence[str],
    ) -> list[QueryOutcome]:
        """One outcome per estimator (``params["estimator"]`` is not used); ``depth`` reaches
        the estimators that need it."""
        ...

    def close(self) -> None: ...


def metadata_of(image: PosedImage) -> ImageMetadata:
    return ImageMetadata(
        name=image.name,
        camera=CameraSchema.from_camera(image.camera),
        cam_from_world=PoseSchema.from_rigid(image.cam_from_world),
    )


class InProcessRunner:
    """The server's use cases without HTTP: ``add_reference_image`` into a temporary SQLite
    database (the originals in a folder beside it) and ``localize`` against it."""

    def __init__(
        self,
        features: str,
        models_dir: Path,
        max_pixels: int = 40_000_000,
        max_keypoints: int | None = None,
        max_side: int | None = None,
        second_opinion: str = "",
    ) -> None:
        """``max_keypoints``, ``max_side``: the map's feature options (None: the default);
        ``second_opinion``: the configuration that localizes again a query the map's does not
        (``LocalizeContext.second_opinion``; empty: none)."""
        engine = EngineConfig.resolve(models_dir, max_pixels, features)
        others = (second_opinion,) if second_opinion else ()
        self.localizers = Localizers(engine, build_localizer(engine), others)
        self.features = features
        self._tmp = tempfile.TemporaryDirectory(prefix="slloc-eval-")
        self._engine = make_engine(f"sqlite:///{self._tmp.name}/eval.db")
        upgrade(self._engine)
        self.sessions = make_session_factory(self._engine)
        options = FeatureChoice(features, max_keypoints, max_side)
        self.map_id = create_map(
            self.sessions, self.localizers, "eval", None, DEFAULT_ESTIMATOR, options
        ).id
        self.blobs = FileBlobStore(Path(self._tmp.name) / "blobs")
        self._context = LocalizeContext(
            self.sessions,
            self.localizers,
            max_top_k=1_000_000,
            cache=RetrievalIndexCache(),
            blobs=self.blobs,
            second_opinion=second_opinion,
            described=DescribedCache(SECOND_OPINION_DESCRIBED) if second_opinion else None,
        )

    @property
    def context(self) -> LocalizeContext:
        """What the map's localizations share (``localize``'s and ``localize_with_session``'s
        first argument)."""
        return self._context

    def add_reference(self, image: PosedImage, depth: bytes | None) -> None:
        add_reference_image(
            self.sessions,
            self.localizers,
            self.map_id,
            metadata_of(image).to_new_image(),
            image.image_path.read_bytes(),
            depth,
            blobs=self.blobs,
        )

    def index_references(self, count: int) -> None:
        if count < MIN_IMAGES:
            return
        with contextlib.suppress(ConflictError):  # too few descriptors: global descriptors
            reindex_map(self.sessions, self.localizers, self.map_id, vlad=True)

    def localize(self, image: bytes, depth: bytes | None, params: dict[str, Any]) -> QueryOutcome:
        start = time.perf_counter()
        result = localize(
            self._context,
            self.map_id,
            LocalizeParamsIn.model_validate(params).to_request(),
            image,
            depth,
        )
        return _outcome(result, (time.perf_counter() - start) * 1000.0)

    def localize_each(
        self,
        image: bytes,
        depth: bytes | None,
        params: dict[str, Any],
        estimators: Sequence[str],
    ) -> list[QueryOutcome]:
        """The query described and matched once; ``client`` is that shared time plus the
        estimator's own. With a second opinion and one estimator: ``localize``'s answer."""
        if self._context.second_opinion and len(estimators) == 1:
            return [self.localize(image, depth, {**params, "estimator": estimators[0]})]
        start = time.perf_counter()
        results = localize_with_each(
            self._context,
            self.map_id,
            LocalizeParamsIn.model_validate(params).to_request(),
            estimators,
            image,
            depth if any(name in DEPTH_USING_ESTIMATORS for name in estimators) else None,
        )
        elapsed_ms = (time.perf_counter() - start) * 1000.0
        estimates_ms = sum(r.timings_ms["estimate"] for r in results)
        return [_outcome(r, elapsed_ms - estimates_ms + r.timings_ms["estimate"]) for r in results]

    def close(self) -> None:
        self._engine.dispose()
        self._tmp.cleanup()


def _outcome(result: LocalizationResult, client_ms: float) -> QueryOutcome:
    pose = result.cam_from_world
    return QueryOutcome(
        localized=result.localized,
        reason=result.reason,
        cam_from_world=PoseSchema.from_rigid(pose) if pose is not None else None,
        num_inliers=result.num_inliers,
        confidence=result.confidence,
        retrieved=[r.name for r in result.retrieved],
        timings_ms={**result.timings_ms, "client": client_ms},
        stats={
            **result.stats,
            **_second_opinion_stats(
                SecondOpinionOut.from_opinion(result.second_opinion).model_dump()
                if result.second_opinion is not None
                else None
            ),
        },
        estimator_used=result.estimator_used,
        candidate=PoseSchema.from_rigid(result.candidate) if result.candidate is not None else None,
    )


def _second_opinion_stats(opinion: dict[str, Any] | None) -> dict[str, float]:
    """Whether an answer's ``second_opinion`` localized the query, whether its withheld pose
    agreed with the map's, and its time."""
    if opinion is None:
        return {}
    return {
        "second_opinion_localized": float(bool(opinion["localized"])),
        "second_opinion_agreed": float(bool(opinion.get("agreed", False))),
        "second_opinion_ms": float(opinion["elapsed_ms"]),
    }


def _media_type(name: str) -> str:
    suffix = Path(name).suffix.lower()
    return {".png": "image/png", ".npy": "application/octet-stream"}.get(suffix, "image/jpeg")


class HttpRunner:
    """A client of a running server: creates a map named ``map_name`` plus a random suffix (or
    uses ``map_id``), uploads references, localizes, and on ``close`` deletes the map it created
    unless ``keep_map``. ``features``: the created map's ``features`` (configuration, keypoint
    budget, image size)."""

    def __init__(
        self,
        url: str,
        api_key: str | None,
        map_name: str = "slloc-eval",
        keep_map: bool = False,
        map_id: str | None = None,
        features: dict[str, Any] | None = None,
    ) -> None:
        headers = {"X-API-Key": api_key} if api_key else {}
        self._client = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=600.0)
        self.keep_map = keep_map or map_id is not None
        self.map_id_given = map_id is not None
        health = self._request("GET", "/v1/health").json()
        self.features = str(health["models"]["features"])
        if map_id is None:
            name = f"{map_name}-{uuid.uuid4().hex[:8]}"
            body: dict[str, Any] = {"name": name, "features": features or {}}
            map_id = str(self._request("POST", "/v1/maps", json=body).json()["id"])
        self.map_id = map_id

    def _request(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        """The response; ServiceBusyError on a 503, RuntimeError on a transport error or
        another error status."""
        try:
            response = self._client.request(method, url, **kwargs)
        except httpx.HTTPError as exc:
            raise RuntimeError(f"{method} {url}: {exc}") from exc
        if response.status_code == 503:
            raise ServiceBusyError(
                f"{method} {url}: 503 {response.text[:200]}",
                float(response.headers.get("Retry-After", "1")),
            )
        if response.is_error:
            raise RuntimeError(
                f"{response.request.method} {response.request.url}: {response.status_code} "
                f"{response.text[:500]}"
            )
        return response

    @staticmethod
    def _files(image: bytes, name: str, depth: bytes | None) -> dict[str, tuple[str, bytes, str]]:
        files = {"image": (name, image, _media_type(name))}
        if depth is not None:
            depth_name = "depth.npy" if depth.startswith(b"\x93NUMPY") else "depth.png"
            files["depth"] = (depth_name, depth, _media_type(depth_name))
        return files

    def add_reference(self, image: PosedImage, depth: bytes | None) -> None:
        self._request(
            "POST",
            f"/v1/maps/{self.map_id}/images",
            files=self._files(image.image_path.read_bytes(), image.image_path.name, depth),
            data={"metadata": metadata_of(image).model_dump_json()},
        )

    def index_references(self, count: int) -> None:
        """Waits until the map is ready (``features.state``) first: a map that follows its
        self-evaluation is evaluated and may take another configuration, which ``features``
        then names, and its vocabulary is trained on the features it settled on."""
        self.features = self.wait_ready()
        if count >= MIN_IMAGES and not self.map_id_given:  # else evaluated as it is
            response = self._client.post(f"/v1/maps/{self.map_id}/reindex")
            if response.status_code != 409:  # 409: retrieval by an ONNX global model
                response.raise_for_status()

    def wait_ready(self, timeout_s: float = 3600.0, poll_s: float = 2.0) -> str:
        """Polls the map until it is neither evaluating nor re-describing its references
        (each change of state on stderr); returns the configuration it is served with."""
        start = time.perf_counter()
        seen = None
        while True:
            features = self._request("GET", f"/v1/maps/{self.map_id}").json()["features"]
            state = features["state"]
            if state != seen:
                print(
                    f"map {self.map_id}: {state} ({features['preset']}) after "
                    f"{time.perf_counter() - start:.0f} s",
                    file=sys.stderr,
                    flush=True,
                )
                seen = state
            if state == "ready":
                return str(features["preset"])
            if time.perf_counter() - start > timeout_s:
                raise RuntimeError(f"map {self.map_id} not ready after {timeout_s:.0f} s")
            time.sleep(poll_s)

    def localize(self, image: bytes, depth: bytes | None, params: dict[str, Any]) -> QueryOutcome:
        start = time.perf_counter()
        name = "query.png" if image.startswith(b"\x89PNG") else "query.jpg"
        response = self._request(
            "POST",
            f"/v1/maps/{self.map_id}/localize",
            files=self._files(image, name, depth),
            data={"params": json.dumps(params)},
        )
        client_ms = (time.perf_counter() - start) * 1000.0
        body = response.json()
        timings = {k: float(v) for k, v in body["timings_ms"].items()}
        timings["client"] = client_ms
        pose, candidate = body["cam_from_world"], body.get("candidate")
        return QueryOutcome(
            localized=bool(body["localized"]),
            reason=body["reason"],
            cam_from_world=PoseSchema.model_validate(pose) if pose is not None else None,
            num_inliers=int(body["num_inliers"]),
            confidence=float(body["confidence"]),
            retrieved=[r["name"] for r in body["retrieved"]],
            timings_ms=timings,
            stats={
                "wider_retrieval": float(bool(body.get("wider_retrieval"))),
                **_second_opinion_stats(body.get("second_opinion")),
            },
            estimator_used=body.get("estimator_used"),
            candidate=PoseSchema.model_validate(candidate) if candidate is not None else None,
        )

    def localize_each(
        self,
        image: bytes,
        depth: bytes | None,
        params: dict[str, Any],
        estimators: Sequence[str],
    ) -> list[QueryOutcome]:
        """One request per estimator: the API localizes with one estimator at a time, sending
        the query's depth to those that use it. An estimator that needs depth is not asked
        without it (the API refuses it with 422): its outcome is ``missing_depth``, as the
        engine answers in process."""
        return [
            self.localize(
                image,
                depth if name in DEPTH_USING_ESTIMATORS else None,
                {**params, "estimator": name},
            )
            if depth is not None or name not in DEPTH_ESTIMATORS
            else QueryOutcome.not_localized(
                FailureReason.MISSING_DEPTH.value, {"wider_retrieval": 0.0}
            )
            for name in estimators
        ]

    def close(self) -> None:
        try:
            if not self.keep_map:
                self._client.delete(f"/v1/maps/{self.map_id}")
        finally:
            self._client.close()
