"""A synchronous client of the slloc v1 API over httpx."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import IO, Any, TypeVar
from urllib.parse import quote

import httpx
from pydantic import BaseModel

from slloc_client.errors import ProblemError, retry_after_s
from slloc_client.models import (
    CameraSchema,
    EvaluationOut,
    EvaluationPage,
    FeatureCreate,
    FeaturePatch,
    FrameIn,
    GeoPoseReq,
    GeoPoseResp,
    GeoRegistrationIn,
    GeoRegistrationOut,
    GpsSchema,
    GravityIn,
    HealthOut,
    ImageMetadata,
    ImageOut,
    ImagePage,
    LocalizeParamsIn,
    LocalizeResult,
    MapOut,
    MapPage,
    PoseSchema,
    ReindexOut,
)

Model = TypeVar("Model", bound=BaseModel)
#: An upload: its bytes, a path to read them from, or an open binary file.
ImageInput = bytes | os.PathLike[str] | IO[bytes]
#: A request object: the generated model, or the same as a plain JSON-like mapping.
Json = Mapping[str, Any]

RETRYABLE_STATUSES = frozenset({429, 503})


def _q(segment: str) -> str:
    return quote(segment, safe="")


def _map_fields(
    description: str | None,
    default_estimator: str | None,
    features: FeatureCreate | FeaturePatch | Json | None,
) -> dict[str, Any]:
    """A map's optional fields that were given, as JSON."""
    fields: dict[str, Any] = {"description": description, "default_estimator": default_estimator}
    if features is not None:
        fields["features"] = _json(features)
    return {key: value for key, value in fields.items() if value is not None}


def _json(value: BaseModel | Json) -> Any:
    """A request object as JSON: a model's fields that were set, or a mapping as given (the
    server validates it and answers 422 naming what is wrong)."""
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json", exclude_unset=True, by_alias=True)
    return dict(value)


def _upload(value: ImageInput, default_name: str) -> tuple[str, bytes, str]:
    """``(filename, bytes, content type)`` of an upload, read once so retries can resend it."""
    if isinstance(value, bytes):
        data, name = value, None
    elif isinstance(value, os.PathLike):
        path = Path(value)
        data, name = path.read_bytes(), path.name
    else:
        data = value.read()
        name = Path(str(getattr(value, "name", ""))).name or None
    if data.startswith(b"\xff\xd8"):
        kind, suffix = "image/jpeg", ".jpg"
    elif data.startswith(b"\x89PNG"):
        kind, suffix = "image/png", ".png"
    else:
        kind, suffix = "application/octet-stream", ".bin"
    return name or default_name + suffix, data, kind


class Client:
    """The slloc v1 API.

    ``api_key`` is sent as ``X-API-Key``. A 503 or 429 answer with ``Retry-After`` is retried
    after that many seconds, at most ``max_retries`` times and only while the wait is at most
    ``max_retry_wait_s``; past that, and for every other non-2xx answer, :class:`ProblemError`
    is raised. Use it as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        api_key: str | None = None,
        timeout: float = 60.0,
        max_retries: int = 3,
        max_retry_wait_s: float = 30.0,
        transport: httpx.BaseTransport | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ):
        headers = {"X-API-Key": api_key} if api_key else {}
        self._http = httpx.Client(
            base_url=base_url.rstrip("/"), headers=headers, timeout=timeout, transport=transport
        )
        self.max_retries = max_retries
        self.max_retry_wait_s = max_retry_wait_s
        self._sleep = sleep

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- transport -------------------------------------------------------------------------

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """Send one request (``kwargs`` as for ``httpx.Client.request``), retrying a 503 or 429
        as the class says; a non-2xx answer raises :class:`ProblemError`."""
        attempt = 0
        while True:
            response = self._http.request(method, path, **kwargs)
            if response.is_success:
                return response
            response.read()
            wait = retry_after_s(response)
            if (
                response.status_code in RETRYABLE_STATUSES
                and wait is not None
                and wait <= self.max_retry_wait_s
                and attempt < self.max_retries
            ):
                attempt += 1
                self._sleep(wait)
                continue
            raise ProblemError.from_response(response)

    def _get(self, model: type[Model], path: str, **kwargs: Any) -> Model:
        return model.model_validate(self.request("GET", path, **kwargs).json())

    def _send(self, model: type[Model], method: str, path: str, **kwargs: Any) -> Model:
        return model.model_validate(self.request(method, path, **kwargs).json())

    # -- service ---------------------------------------------------------------------------

    def health(self) -> HealthOut:
        return self._get(HealthOut, "/v1/health")

    # -- maps ------------------------------------------------------------------------------

    def create_map(
        self,
        name: str,
        *,
        description: str | None = None,
        default_estimator: str | None = None,
        features: FeatureCreate | Json | None = None,
    ) -> MapOut:
        """A new map (admin); 409 ``map-name-taken`` when the name is in use. ``features``
        preset ``auto`` (the default): the map takes the configuration its self-evaluation
        recommends."""
        body = {"name": name, **_map_fields(description, default_estimator, features)}
        return self._send(MapOut, "POST", "/v1/maps", json=body)

    def update_map(
        self,
        map_id: str,
        *,
        description: str | None = None,
        default_estimator: str | None = None,
        features: FeaturePatch | Json | None = None,
    ) -> MapOut:
        """Changes the fields given (admin). New ``features`` describe the map's references
        again from their originals in the background: ``features.state`` is
        ``re-extracting`` until the map switches."""
        body = _map_fields(description, default_estimator, features)
        return self._send(MapOut, "PATCH", f"/v1/maps/{_q(map_id)}", json=body)

    def list_maps(self, *, offset: int = 0, limit: int = 100) -> MapPage:
        return self._get(MapPage, "/v1/maps", params={"offset": offset, "limit": limit})

    def iter_maps(self, *, page_size: int = 100) -> Iterator[MapOut]:
        """Every map, page by page."""
        offset = 0
        while True:
            page = self.list_maps(offset=offset, limit=page_size)
            yield from page.items
            offset += len(page.items)
            if not page.items or offset >= page.total:
                return

    def get_map(self, map_id: str) -> MapOut:
        return self._get(MapOut, f"/v1/maps/{_q(map_id)}")

    def delete_map(self, map_id: str) -> None:
        """Delete the map with its images (admin)."""
        self.request("DELETE", f"/v1/maps/{_q(map_id)}")

    def reindex_map(self, map_id: str) -> ReindexOut:
        """Retrain the map's retrieval vocabulary now (admin)."""
        return self._send(ReindexOut, "POST", f"/v1/maps/{_q(map_id)}/reindex")

    # -- self-evaluations ----------------------------------------------------------------

    def start_evaluation(
        self,
        map_id: str,
        *,
        configurations: Sequence[str] | None = None,
        sample_size: int | None = None,
        holdout_radius_m: float | None = None,
        top_k: int | None = None,
        estimator: str | None = None,
    ) -> EvaluationOut:
        """Start measuring the map on its own references in the background (admin); the
        fields not given take the server's defaults. ``wait_for_evaluation`` follows it."""
        body = {
            key: value
            for key, value in (
                ("configurations", list(configurations) if configurations else None),
                ("sample_size", sample_size),
                ("holdout_radius_m", holdout_radius_m),
                ("top_k", top_k),
                ("estimator", estimator),
            )
            if value is not None
        }
        return self._send(EvaluationOut, "POST", f"/v1/maps/{_q(map_id)}/evaluations", json=body)

    def get_evaluation(self, map_id: str, evaluation_id: str) -> EvaluationOut:
        return self._get(EvaluationOut, f"/v1/maps/{_q(map_id)}/evaluations/{_q(evaluation_id)}")

    def list_evaluations(self, map_id: str, *, offset: int = 0, limit: int = 20) -> EvaluationPage:
        """The map's evaluations, newest first, without their per-reference rows."""
        return self._get(
            EvaluationPage,
            f"/v1/maps/{_q(map_id)}/evaluations",
            params={"offset": offset, "limit": limit},
        )

    def delete_evaluation(self, map_id: str, evaluation_id: str) -> None:
        """Cancel an unfinished evaluation, or delete a finished one (admin)."""
        self.request("DELETE", f"/v1/maps/{_q(map_id)}/evaluations/{_q(evaluation_id)}")

    def wait_for_evaluation(
        self,
        map_id: str,
        evaluation_id: str,
        *,
        timeout_s: float = 3600.0,
        poll_s: float = 2.0,
        on_progress: Callable[[EvaluationOut], None] | None = None,
    ) -> EvaluationOut:
        """The evaluation once it has ended (done, failed or cancelled); ``on_progress``
        sees it at each poll.

        Raises:
            TimeoutError: it had not ended after ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            evaluation = self.get_evaluation(map_id, evaluation_id)
            if on_progress is not None:
                on_progress(evaluation)
            if evaluation.state not in ("queued", "running"):
                return evaluation
            if time.monotonic() > deadline:
                raise TimeoutError(f"evaluation {evaluation_id} still {evaluation.state}")
            time.sleep(poll_s)

    # -- images ----------------------------------------------------------------------------

    def add_image(
        self,
        map_id: str,
        image: ImageInput,
        *,
        name: str,
        camera: CameraSchema | Json,
        cam_from_world: PoseSchema | Json,
        gps: GpsSchema | Json | None = None,
        depth: ImageInput | None = None,
    ) -> ImageOut:
        """Add a posed reference image (admin): JPEG or PNG bytes, its ``camera`` (COLMAP
        model) and ``cam_from_world`` (``x_cam = R(q)·x_world + t``, q = [w, x, y, z]);
        ``depth``: a 16-bit PNG in millimetres or a ``.npy`` float32 array in metres.
        409 ``image-name-taken`` when the map has an image of that name."""
        metadata: dict[str, Any] = {
            "name": name,
            "camera": _json(camera),
            "cam_from_world": _json(cam_from_world),
        }
        if gps is not None:
            metadata["gps"] = _json(gps)
        return self.add_image_metadata(map_id, image, metadata, depth=depth)

    def add_image_metadata(
        self,
        map_id: str,
        image: ImageInput,
        metadata: ImageMetadata | Json,
        *,
        depth: ImageInput | None = None,
    ) -> ImageOut:
        """:meth:`add_image` with the ``metadata`` form field as one object (e.g. the JSON
        files ``slloc synth`` writes beside each reference)."""
        files = [("image", _upload(image, "image"))]
        if depth is not None:
            files.append(("depth", _upload(depth, "depth")))
        data = {"metadata": json.dumps(_json(metadata))}
        return self._send(ImageOut, "POST", f"/v1/maps/{_q(map_id)}/images", files=files, data=data)

    def list_images(self, map_id: str, *, offset: int = 0, limit: int = 100) -> ImagePage:
        return self._get(
            ImagePage, f"/v1/maps/{_q(map_id)}/images", params={"offset": offset, "limit": limit}
        )

    def iter_images(self, map_id: str, *, page_size: int = 100) -> Iterator[ImageOut]:
        """Every image of the map, page by page."""
        offset = 0
        while True:
            page = self.list_images(map_id, offset=offset, limit=page_size)
            yield from page.items
            offset += len(page.items)
            if not page.items or offset >= page.total:
                return

    def get_image(self, map_id: str, image_id: str) -> ImageOut:
        return self._get(ImageOut, f"/v1/maps/{_q(map_id)}/images/{_q(image_id)}")

    def get_image_original(self, map_id: str, image_id: str) -> bytes:
        """The reference's upload, bytes as sent."""
        return self.request("GET", f"/v1/maps/{_q(map_id)}/images/{_q(image_id)}/original").content

    def get_image_preview(self, map_id: str, image_id: str) -> bytes:
        """A JPEG preview of the reference."""
        return self.request("GET", f"/v1/maps/{_q(map_id)}/images/{_q(image_id)}/preview").content

    def delete_image(self, map_id: str, image_id: str) -> None:
        self.request("DELETE", f"/v1/maps/{_q(map_id)}/images/{_q(image_id)}")

    # -- localization ----------------------------------------------------------------------

    def localize(
        self,
        map_id: str,
        image: ImageInput,
        *,
        params: LocalizeParamsIn | Json | None = None,
        camera: CameraSchema | Json | None = None,
        gravity: GravityIn | Json | None = None,
        depth: ImageInput | None = None,
    ) -> LocalizeResult:
        """Localize one query image. ``params`` is the ``params`` form field (estimator, top_k,
        prior, gps, output, ...); ``camera`` and ``gravity`` are set into it. A query that
        cannot be localized is a result with ``localized`` false and a ``reason``, not an
        error."""
        return self.localize_frames(
            map_id, [image], None, params=params, camera=camera, gravity=gravity, depth=depth
        )

    def localize_frames(
        self,
        map_id: str,
        images: Sequence[ImageInput],
        frames: Sequence[FrameIn | Json] | None,
        *,
        params: LocalizeParamsIn | Json | None = None,
        camera: CameraSchema | Json | None = None,
        gravity: GravityIn | Json | None = None,
        depth: ImageInput | None = None,
    ) -> LocalizeResult:
        """Localize several frames of one AR session jointly: ``frames[i]`` (its
        ``session_pose`` and optional ``camera``) goes with ``images[i]``; the answer adds
        ``map_from_session`` and per-frame poses."""
        fields: dict[str, Any] = _json(params) if params is not None else {}
        if camera is not None:
            fields["camera"] = _json(camera)
        if gravity is not None:
            fields["gravity"] = _json(gravity)
        if frames is not None:
            if len(frames) != len(images):
                raise ValueError(f"{len(images)} images but {len(frames)} frames")
            fields["frames"] = [_json(frame) for frame in frames]
        files = [
            ("image", _upload(image, f"frame{i}" if len(images) > 1 else "query"))
            for i, image in enumerate(images)
        ]
        if depth is not None:
            files.append(("depth", _upload(depth, "depth")))
        return self._send(
            LocalizeResult,
            "POST",
            f"/v1/maps/{_q(map_id)}/localize",
            files=files,
            data={"params": json.dumps(fields)},
        )

    def geopose(
        self, map_id: str, request: GeoPoseReq | Json, *, camera_axes: str | None = None
    ) -> GeoPoseResp:
        """Open AR Cloud GeoPose Protocol request on a geo-registered map."""
        params = {"camera_axes": camera_axes} if camera_axes else None
        return self._send(
            GeoPoseResp,
            "POST",
            f"/v1/maps/{_q(map_id)}/geopose",
            json=_json(request),
            params=params,
        )

    # -- geo-registration ------------------------------------------------------------------

    def get_geo_registration(self, map_id: str) -> GeoRegistrationOut:
        return self._get(GeoRegistrationOut, f"/v1/maps/{_q(map_id)}/geo-registration")

    def set_geo_registration(
        self, map_id: str, registration: GeoRegistrationIn | Json
    ) -> GeoRegistrationOut:
        """Set the map's registration by hand (admin): ``x_enu = scale · R · x_map + t``."""
        return self._send(
            GeoRegistrationOut,
            "PUT",
            f"/v1/maps/{_q(map_id)}/geo-registration",
            json=_json(registration),
        )

    def estimate_geo_registration(
        self, map_id: str, *, max_error_m: float | None = None
    ) -> GeoRegistrationOut:
        """Estimate the registration from the references' GPS positions (admin)."""
        body = {"max_error_m": max_error_m} if max_error_m is not None else None
        return self._send(
            GeoRegistrationOut,
            "POST",
            f"/v1/maps/{_q(map_id)}/geo-registration/estimate",
            json=body,
        )

    def delete_geo_registration(self, map_id: str) -> None:
        self.request("DELETE", f"/v1/maps/{_q(map_id)}/geo-registration")
