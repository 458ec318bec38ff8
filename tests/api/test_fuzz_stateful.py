"""Stateful fuzz: sequences of requests on the real app, each a story of "add odd data, then
localize", on SQLite and PostgreSQL, with auth on and off.

A hypothesis state machine creates maps (odd unicode names, extreme feature options), adds
real rendered references with odd but schema-valid metadata (every camera model, focal lengths
and principal points at the edges of the plausible range, extreme distortion, extreme but
allowed poses and translations, odd depth maps, GPS at the poles and the antimeridian),
registers maps in geographic coordinates with extreme values, localizes (one frame or several,
with and without a camera, every estimator, odd options), deletes images and maps and
localizes again, and reads everything back.

Every answer must be no server error (a documented 503 aside), of a documented status code,
content type and headers, and of the documented body schema; and after every step each map
still alive, its images and the map list must read back (stored data never makes later
requests fail). The budget is fixed and every run seeded, so a run is the same everywhere."""

from __future__ import annotations

import io
import itertools
import json
import math
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, Phase, seed, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    precondition,
    rule,
    run_state_machine_as_test,
)
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from services.geometry.camera import CAMERA_MODELS, FOCAL_RANGE, MAX_DISTORTION
from services.geometry.rigid import MAX_TRANSLATION_M
from services.localization.localizer import Localizer
from tests.api.test_fuzz import DOCUMENT, _json_form_values, _without_binary_format
from tests.conftest import fresh_postgres_database, make_client
from tools.synthetic.scene import SyntheticView, encode_depth_png, encode_png

ADMIN_KEY = "stateful-admin"
# the budget: sequences per run and steps per sequence; the four runs (two databases, auth on
# and off) take about 60 s on two cores
MAX_SEQUENCES = 6
STEPS_PER_SEQUENCE = 12
# a seed per run: the runs explore different sequences, each the same everywhere
SEEDS = {("sqlite", True): 1, ("sqlite", False): 2, ("postgres", True): 3, ("postgres", False): 4}

CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
]


def _schema(auth: bool) -> Any:
    """The published document, as schemathesis validates answers against it: a 503 is
    allowed where an operation documents it (busy, database or blob store down)."""
    config: dict[str, Any] = {
        "checks": {"not_a_server_error": {"expected-statuses": ["2XX", "3XX", "4XX", "503"]}}
    }
    if auth:
        config["auth"] = {"openapi": {"APIKeyHeader": {"api_key": ADMIN_KEY}}}
    return schemathesis.openapi.from_dict(
        _without_binary_format(DOCUMENT), config=schemathesis.Config.from_dict(config)
    )


SCHEMAS = {True: _schema(True), False: _schema(False)}
# anything the published schema allows as a localize's params (single frame)
SCHEMA_PARAMS = _json_form_values("LocalizeParamsIn").filter(
    lambda p: isinstance(p, dict) and not p.get("frames")
)
ESTIMATORS: list[str] = DOCUMENT["components"]["schemas"]["EstimatorName"]["enum"]
_unique = itertools.count()
# a plain query's params (without the search over quarter turns, which quadruples a failing
# query's time)
PLAIN = {"rotation_search": False}


# --- odd but schema-valid values -------------------------------------------------------

# what a name may not hold (the published pattern): C0/C1 controls, line and paragraph
# separators, bidi controls; and it must hold something besides spaces
_NAME_FORBIDDEN = "".join(
    [chr(c) for c in range(0x20)]
    + [chr(c) for c in range(0x7F, 0xA0)]
    + ["\u2028", "\u2029", "\u061c", "\u200e", "\u200f"]
    + [chr(c) for c in range(0x202A, 0x202F)]
    + [chr(c) for c in range(0x2066, 0x206A)]
)
_SPACES = " \u00a0\u1680\u2000\u2001\u2002\u2003\u2004\u2005\u2006\u2007\u2008\u2009\u200a"
_SPACES += "\u202f\u205f\u3000"
ODD_NAMES = [
    "e\u0301",  # NFD of é
    "\u00e9",  # NFC of é
    "\U0001f469\u200d\U0001f4bb",  # a ZWJ emoji sequence
    "\u05e9\u05dc\u05d5\u05dd",  # Hebrew, right to left
    "\ufeffbom",
    "\uff33\uff2c\uff2c\uff2f\uff23",  # fullwidth
    "a\u0300\u0301\u0302\u0303\u0304",  # stacked combining marks
    "\U0010fffd",  # a private-use plane's last character
    " padded ",
    "../../etc/passwd",
    "%00%2F",
    "'; DROP TABLE maps; --",
    "x" * 255,
    "\U0001f600" * 255,  # 255 characters, 1020 UTF-8 bytes
]


def _names() -> st.SearchStrategy[str]:
    generated = st.text(
        st.characters(codec="utf-8", exclude_characters=_NAME_FORBIDDEN),
        min_size=1,
        max_size=40,
    ).filter(lambda s: s.strip(_SPACES) != "")
    return st.one_of(st.sampled_from(ODD_NAMES), generated)


def _edge(low: float, high: float, typical: float) -> st.SearchStrategy[float]:
    """A value at either edge of [low, high], the typical one, or anywhere between."""
    return st.one_of(
        st.sampled_from([low, high, typical, typical]),
        st.floats(low, high, allow_nan=False, allow_infinity=False),
    )


@st.composite
def _camera(
    draw: st.DrawFn, width: int, height: int, true_params: tuple[float, ...]
) -> dict[str, Any]:
    """A camera for an image of ``width`` × ``height``: any model, focal length, principal
    point and distortion within the plausible range, often at its edges; or the image's true
    pinhole."""
    fx, fy, cx, cy = true_params
    if not draw(st.booleans()):
        return {"model": "PINHOLE", "width": width, "height": height, "params": [fx, fy, cx, cy]}
    model = draw(st.sampled_from(sorted(CAMERA_MODELS)))
    side = max(width, height)
    focal = _edge(FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side, fx)
    distortion = st.one_of(
        st.sampled_from([0.0, 0.0, -MAX_DISTORTION, MAX_DISTORTION, 1e-300, -0.0]),
        st.floats(-MAX_DISTORTION, MAX_DISTORTION),
    )
    params = []
    for name in CAMERA_MODELS[model]:
        if name in ("f", "fx", "fy"):
            params.append(draw(focal))
        elif name == "cx":
            params.append(draw(_edge(-width, 2 * width, cx)))
        elif name == "cy":
            params.append(draw(_edge(-height, 2 * height, cy)))
        else:
            params.append(draw(distortion))
    return {"model": model, "width": width, "height": height, "params": params}


def _quaternion_from(values: list[float]) -> list[float]:
    norm = math.sqrt(sum(v * v for v in values)) or 1.0
    return [v / norm for v in values]


_QUATERNIONS = st.one_of(
    st.sampled_from(
        [[1.0, 0.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 0.0]]
    ),
    st.lists(st.floats(-1, 1), min_size=4, max_size=4)
    .filter(lambda q: sum(v * v for v in q) > 1e-6)
    .map(_quaternion_from),
    # off unit by up to the tolerance the schema allows
    st.sampled_from([[1.000999, 0.0, 0.0, 0.0], [0.999001, 0.0, 0.0, 0.0]]),
)


@st.composite
def _translation(draw: st.DrawFn) -> list[float]:
    """A translation of any size up to the allowed |t| ≤ 1e7 m, often at the edge."""
    direction = draw(st.lists(st.floats(-1, 1), min_size=3, max_size=3))
    norm = math.sqrt(sum(v * v for v in direction))
    if norm < 1e-9:
        return [0.0, 0.0, 0.0]
    length = draw(_edge(0.0, MAX_TRANSLATION_M * 0.999999, 1.0))
    return [v / norm * length for v in direction]


_LATITUDES = _edge(-90.0, 90.0, 47.37)
_LONGITUDES = _edge(-180.0, 180.0, 8.54)


@st.composite
def _gps(draw: st.DrawFn) -> dict[str, Any]:
    gps: dict[str, Any] = {"latitude": draw(_LATITUDES), "longitude": draw(_LONGITUDES)}
    if draw(st.booleans()):
        gps["height"] = draw(_edge(-12000.0, 100000.0, 400.0))
    if draw(st.booleans()):
        gps["accuracy_m"] = draw(st.sampled_from([5e-324, 1e-9, 5.0, 40_000_000.0]))
    return gps


@st.composite
def _geo_registration(draw: st.DrawFn) -> dict[str, Any]:
    """A registration set by hand with extreme values (the published schema's edges)."""
    origin: dict[str, Any] = {"latitude": draw(_LATITUDES), "longitude": draw(_LONGITUDES)}
    if draw(st.booleans()):
        origin["height"] = draw(_edge(-12000.0, 100000.0, 0.0))
    body: dict[str, Any] = {"origin": origin}
    if draw(st.booleans()):
        body["scale"] = draw(_edge(1e-6, 1e6, 1.0))
    if draw(st.booleans()):
        translation = draw(st.lists(_edge(-1e7, 1e7, 0.0), min_size=3, max_size=3))
        body["enu_from_map"] = {"rotation": draw(_QUATERNIONS), "translation": translation}
    return body


# --- real images and odd uploads ---------------------------------------------------------


@dataclass(frozen=True)
class Upload:
    """An image as uploaded, its size and true pinhole intrinsics (fx, fy, cx, cy) at that
    size, its pose, and depth maps to send with it (true and odd ones; None: none)."""

    name: str
    data: bytes = field(repr=False)
    width: int
    height: int
    params: tuple[float, float, float, float] = field(repr=False)
    rotation: list[float] = field(repr=False)
    translation: list[float] = field(repr=False)
    depths: tuple[bytes | None, ...] = field(repr=False)


def _uploads(view: SyntheticView) -> list[Upload]:
    """A rendered view uploaded several ways: PNG, JPEG, half size, grey, with alpha."""
    fx, fy, cx, cy = (float(v) for v in view.camera.params[:4])
    pose = (
        [float(v) for v in view.cam_from_world.quaternion],
        [float(v) for v in view.cam_from_world.translation],
    )
    h, w = view.image.shape[:2]
    bgr = cv2.cvtColor(view.image, cv2.COLOR_RGB2BGR)
    half = cv2.resize(view.image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    grey = cv2.cvtColor(view.image, cv2.COLOR_RGB2GRAY)
    rgba = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)
    rgba[::7, :, 3] = 0
    jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 40])[1].tobytes()

    def png(image: np.ndarray) -> bytes:
        return bytes(cv2.imencode(".png", image)[1].tobytes())

    full = (fx, fy, cx, cy)
    depths = _depths(view.depth)
    return [
        Upload("png", encode_png(view.image), w, h, full, *pose, depths),
        Upload("jpeg", jpeg, w, h, full, *pose, depths),
        Upload(
            "half",
            encode_png(half),
            w // 2,
            h // 2,
            (fx / 2, fy / 2, cx / 2, cy / 2),
            *pose,
            _depths(view.depth[::2, ::2]),
        ),
        Upload("grey", png(grey), w, h, full, *pose, depths),
        Upload("rgba", png(rgba), w, h, full, *pose, depths),
    ]


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array.astype(np.float32))
    return buffer.getvalue()


def _depths(depth: np.ndarray) -> tuple[bytes | None, ...]:
    """No depth, the true one, and odd ones: all zero, NaN and infinite values, negative,
    huge, the wrong size."""
    odd = depth.copy()
    odd[::3] = np.nan
    odd[1::3] = np.inf
    return (
        None,
        None,
        encode_depth_png(depth),
        _npy(depth),
        _npy(np.zeros_like(depth)),
        _npy(odd),
        _npy(-depth),
        _npy(np.full_like(depth, 3e38)),
        _npy(depth[: depth.shape[0] // 2]),
    )


# --- the app under test ------------------------------------------------------------------


@dataclass
class Target:
    client: TestClient
    auth: bool

    @property
    def headers(self) -> dict[str, str]:
        return {"X-API-Key": ADMIN_KEY} if self.auth else {}


@contextmanager
def _target(
    request: pytest.FixtureRequest, database: str, auth: bool, tmp: Path, localizer: Localizer
) -> Iterator[Target]:
    url: AbstractContextManager[str]
    if database == "sqlite":
        url = nullcontext(f"sqlite:///{tmp / 'slloc.db'}")
    else:
        url = contextmanager(fresh_postgres_database)(request.getfixturevalue("postgres_admin_url"))
    keys = {"api_keys": f"{ADMIN_KEY}:admin"} if auth else {}
    with url as database_url, make_client(database_url, localizer, data_dir=tmp, **keys) as client:
        yield Target(client, auth)


MAP_FEATURES = [
    None,
    {"max_side": 320},
    {"max_side": 64},
    {"max_keypoints": 1},
    {"max_keypoints": 256, "max_side": 480},
    {"max_keypoints": 20000, "max_side": 8192},
]
LOCALIZE_OPTIONS = {
    "estimator": st.sampled_from(ESTIMATORS),
    "top_k": st.sampled_from([1, 2, 10, 1000]),
    "return_inliers": st.booleans(),
    "max_error_px": st.sampled_from([5e-324, 0.5, 100.0]),
    "min_confidence": st.sampled_from([0.0, 1.0]),
    "gps": _gps(),
    "prior": st.fixed_dictionaries(
        {"position": _translation(), "radius": st.sampled_from([5e-324, 1.0, 1e300])}
    ),
    "gravity": st.fixed_dictionaries(
        {"down": st.sampled_from([[0.0, 1.0, 0.0], [1e-300, 0.0, 0.0], [0.0, -1e300, 1e300]])},
        optional={
            "map_down": st.sampled_from([[0.0, 1.0, 0.0], [1e-300, 1e-300, 0.0]]),
            "max_angle_deg": st.sampled_from([5e-324, 180.0]),
        },
    ),
    "camera_rotation_deg": st.sampled_from([0, 90, 180, 270]),
    "time_budget_s": st.sampled_from([5e-324, 1e300]),
    "rotation_search": st.booleans(),
    "output": st.fixed_dictionaries(
        {
            "frames": st.just(["colmap", "opengl", "unity"]),
            "pose_of": st.sampled_from(["upload", "camera"]),
        }
    ),
}


class OddDataThenLocalize(RuleBasedStateMachine):
    """Maps with odd data added, localized, deleted and localized again. ``target``,
    ``references`` and ``queries`` are set per run (a subclass each)."""

    target: Target
    references: list[list[Upload]]
    queries: list[list[Upload]]

    def __init__(self) -> None:
        super().__init__()
        self.schema = SCHEMAS[self.target.auth]
        self.maps: list[str] = []  # this sequence's maps, alive or deleted
        self.alive: dict[str, str] = {}  # id → default estimator of the maps not deleted
        self.images: list[tuple[str, str]] = []  # (map id, image id), alive or deleted
        self.added = 0

    # -- plumbing

    def _call(
        self,
        operation_id: str,
        method: str,
        url: str,
        path: dict[str, str] | None = None,
        **kwargs: Any,
    ) -> Any:
        """Send a request with the TestClient (full control of the multipart parts) and
        check its answer against the published document."""
        response = self.target.client.request(method, url, headers=self.target.headers, **kwargs)
        operation = self.schema.find_operation_by_id(operation_id)
        case = operation.Case(path_parameters=path or {}, headers=dict(self.target.headers))
        case.validate_response(response, checks=CHECKS)
        return response

    def _localize(self, map_id: str, uploads: list[Upload], params: dict[str, Any]) -> Any:
        files = [
            ("image", (f"{u.name}-{i}.png", u.data, "image/png")) for i, u in enumerate(uploads)
        ]
        response = self._call(
            "localize",
            "POST",
            f"/v1/maps/{map_id}/localize",
            {"map_id": map_id},
            files=files,
            data={"params": json.dumps(params)},
        )
        if set(params) <= set(PLAIN):  # a plain query
            if map_id not in self.alive:
                assert response.status_code == 404, response.text
            elif self.alive[map_id] == "auto":  # answered, whatever the map holds
                assert response.status_code == 200, response.text
        return response

    def _name(self, data: st.DataObject) -> str:
        """An odd name, made unique unless the draw says to take it as it is (then it may
        be taken already)."""
        name = data.draw(_names(), label="name")
        if data.draw(st.booleans(), label="name as it is"):
            return name
        return f"{name[:200]} {next(_unique)}"

    def _new_map(self, data: st.DataObject) -> str:
        body: dict[str, Any] = {
            "name": self._name(data),
            # auto half the time: a plain query on such a map must be answered 200
            "default_estimator": data.draw(
                st.one_of(st.just("auto"), st.sampled_from(ESTIMATORS)), label="estimator"
            ),
        }
        features = data.draw(st.sampled_from(MAP_FEATURES), label="features")
        if features is not None:
            body["features"] = features
        response = self._call("create_map", "POST", "/v1/maps", json=body)
        if response.status_code == 422:  # feature options beyond this server's extractor
            body.pop("features")
            response = self._call("create_map", "POST", "/v1/maps", json=body)
        if response.status_code == 409:  # the name is taken
            body["name"] = f"{body['name'][:200]} {next(_unique)}"
            response = self._call("create_map", "POST", "/v1/maps", json=body)
        assert response.status_code == 201, response.text
        map_id = str(response.json()["id"])
        self.maps.append(map_id)
        self.alive[map_id] = body["default_estimator"]
        return map_id

    def _add_reference(self, map_id: str, data: st.DataObject) -> None:
        # views in turn (a map of one view repeated is degenerate), from a drawn offset
        offset = data.draw(st.integers(0, len(self.references) - 1), label="view")
        self.added += 1
        view = self.references[(self.added + offset) % len(self.references)]
        upload = view[data.draw(st.integers(0, len(view) - 1), label="upload")]
        camera = {
            "model": "PINHOLE",
            "width": upload.width,
            "height": upload.height,
            "params": list(upload.params),
        }
        pose = {"rotation": upload.rotation, "translation": upload.translation}
        if data.draw(st.booleans(), label="odd"):  # else the view's true camera and pose
            camera = data.draw(_camera(upload.width, upload.height, upload.params))
            odd_pose = st.builds(
                lambda r, t: {"rotation": r, "translation": t}, _QUATERNIONS, _translation()
            )
            pose = data.draw(st.one_of(st.just(pose), odd_pose), label="pose")
        metadata: dict[str, Any] = {
            "name": self._name(data),
            "camera": camera,
            "cam_from_world": pose,
        }
        if data.draw(st.booleans(), label="with gps"):
            metadata["gps"] = data.draw(_gps(), label="gps")
        files = [("image", (f"{metadata['name']}.png", upload.data, "image/png"))]
        depth = data.draw(st.sampled_from(upload.depths), label="depth")
        if depth is not None:
            files.append(("depth", ("depth.bin", depth, "application/octet-stream")))
        response = self._call(
            "add_image",
            "POST",
            f"/v1/maps/{map_id}/images",
            {"map_id": map_id},
            files=files,
            data={"metadata": json.dumps(metadata)},
        )
        if response.status_code == 201:
            self.images.append((map_id, str(response.json()["id"])))

    def _query(self, data: st.DataObject) -> Upload:
        views = self.queries + self.references
        view = views[data.draw(st.integers(0, len(views) - 1), label="query view")]
        return view[data.draw(st.integers(0, len(view) - 1), label="query upload")]

    # -- rules

    @initialize(data=st.data())
    def map_with_references(self, data: st.DataObject) -> None:
        """Every sequence starts with a map holding a few odd references."""
        map_id = self._new_map(data)
        for _ in range(data.draw(st.integers(2, 4), label="references")):
            self._add_reference(map_id, data)

    @rule(data=st.data())
    def create_map(self, data: st.DataObject) -> None:
        self._new_map(data)

    @precondition(lambda self: self.maps)
    @rule(data=st.data())
    def add_references_then_localize(self, data: st.DataObject) -> None:
        map_id = data.draw(st.sampled_from(self.maps), label="map")
        for _ in range(data.draw(st.integers(1, 3), label="references")):
            self._add_reference(map_id, data)
        upload = self._query(data)
        camera = {
            "model": "PINHOLE",
            "width": upload.width,
            "height": upload.height,
            "params": list(upload.params),
        }
        params = data.draw(st.sampled_from([PLAIN | {"camera": camera}, PLAIN]), label="params")
        self._localize(map_id, [upload], params)

    @precondition(lambda self: self.maps)
    @rule(data=st.data())
    def localize(self, data: st.DataObject) -> None:
        map_id = data.draw(st.sampled_from(self.maps), label="map")
        upload = self._query(data)
        options = {"camera": _camera(upload.width, upload.height, upload.params)}
        params: dict[str, Any] = data.draw(
            st.one_of(
                st.fixed_dictionaries({}, optional=options | LOCALIZE_OPTIONS),
                SCHEMA_PARAMS,  # anything the published schema allows
            ),
            label="params",
        )
        self._localize(map_id, [upload], params)

    @precondition(lambda self: self.maps)
    @rule(data=st.data())
    def localize_frames(self, data: st.DataObject) -> None:
        map_id = data.draw(st.sampled_from(self.maps), label="map")
        uploads = [self._query(data) for _ in range(data.draw(st.integers(2, 3)))]
        frames = []
        for upload in uploads:
            position = data.draw(_translation(), label="position")
            orientation = data.draw(_QUATERNIONS, label="orientation")
            if data.draw(st.booleans(), label="as a matrix"):
                w, x, y, z = orientation
                rotation = [
                    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                ]
                matrix = [[*row, t] for row, t in zip(rotation, position, strict=True)]
                pose: dict[str, Any] = {"matrix": [*matrix, [0.0, 0.0, 0.0, 1.0]]}
            else:
                pose = {"position": position, "orientation": orientation}
            frame: dict[str, Any] = {"session_pose": pose}
            if data.draw(st.booleans(), label="frame camera"):
                frame["camera"] = data.draw(_camera(upload.width, upload.height, upload.params))
            frames.append(frame)
        params: dict[str, Any] = {"frames": frames}
        estimator = data.draw(st.sampled_from([None, "auto", "local_tri_all"]), label="estimator")
        if estimator is not None:
            params["estimator"] = estimator
        self._localize(map_id, uploads, params)

    @precondition(lambda self: self.maps)
    @rule(data=st.data())
    def geo_registration(self, data: st.DataObject) -> None:
        """Set one with extreme values, estimate one from the references' GPS, or delete it;
        then read it back."""
        map_id = data.draw(st.sampled_from(self.maps), label="map")
        path = f"/v1/maps/{map_id}/geo-registration"
        action = data.draw(st.sampled_from(["set", "estimate", "delete"]), label="action")
        if action == "set":
            body = data.draw(_geo_registration(), label="registration")
            self._call("set_geo_registration", "PUT", path, {"map_id": map_id}, json=body)
        elif action == "estimate":
            body = {"max_error_m": data.draw(st.sampled_from([5e-324, 10.0, 10000.0]))}
            self._call(
                "estimate_geo_registration",
                "POST",
                f"{path}/estimate",
                {"map_id": map_id},
                json=body,
            )
        else:
            self._call("delete_geo_registration", "DELETE", path, {"map_id": map_id})
        self._call("get_geo_registration", "GET", path, {"map_id": map_id})

    @precondition(lambda self: self.images)
    @rule(data=st.data())
    def read_image(self, data: st.DataObject) -> None:
        map_id, image_id = data.draw(st.sampled_from(self.images), label="image")
        path = {"map_id": map_id, "image_id": image_id}
        base = f"/v1/maps/{map_id}/images/{image_id}"
        self._call("get_image", "GET", base, path)
        self._call("get_image_preview", "GET", f"{base}/preview", path)
        self._call("get_image_original", "GET", f"{base}/original", path)
        self._call("reindex_map", "POST", f"/v1/maps/{map_id}/reindex", {"map_id": map_id})

    @precondition(lambda self: self.images)
    @rule(data=st.data())
    def delete_image_then_localize(self, data: st.DataObject) -> None:
        map_id, image_id = data.draw(st.sampled_from(self.images), label="image")
        path = {"map_id": map_id, "image_id": image_id}
        self._call("delete_image", "DELETE", f"/v1/maps/{map_id}/images/{image_id}", path)
        self._localize(map_id, [self._query(data)], PLAIN)

    @precondition(lambda self: self.maps)
    @rule(data=st.data())
    def delete_map_then_localize(self, data: st.DataObject) -> None:
        map_id = data.draw(st.sampled_from(self.maps), label="map")
        self._call("delete_map", "DELETE", f"/v1/maps/{map_id}", {"map_id": map_id})
        self.alive.pop(map_id, None)
        self._localize(map_id, [self._query(data)], PLAIN)

    @invariant()
    def stored_data_reads_back(self) -> None:
        """Every live map, its images and the map list answer 200 as documented."""
        for map_id in sorted(self.alive):
            response = self._call("get_map", "GET", f"/v1/maps/{map_id}", {"map_id": map_id})
            assert response.status_code == 200, response.text
            response = self._call(
                "list_images", "GET", f"/v1/maps/{map_id}/images", {"map_id": map_id}
            )
            assert response.status_code == 200, response.text
        assert self._call("list_maps", "GET", "/v1/maps").status_code == 200

    def teardown(self) -> None:
        assert self._call("health", "GET", "/v1/health").status_code == 200


@pytest.mark.parametrize("auth", [True, False], ids=["auth-on", "auth-off"])
@pytest.mark.parametrize(
    "database", ["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)]
)
def test_odd_data_then_localize(
    request: pytest.FixtureRequest,
    database: str,
    auth: bool,
    tmp_path: Path,
    localizer: Localizer,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    references = [_uploads(view) for view in reference_views[:6]]
    queries = [_uploads(view) for view in query_views[:3]]
    with _target(request, database, auth, tmp_path, localizer) as target:
        machine = type(
            "OddDataThenLocalizeRun",
            (OddDataThenLocalize,),
            {"target": target, "references": references, "queries": queries},
        )
        run_state_machine_as_test(
            seed(SEEDS[database, auth])(machine),
            settings=settings(
                max_examples=MAX_SEQUENCES,
                stateful_step_count=STEPS_PER_SEQUENCE,
                deadline=None,
                database=None,
                phases=[Phase.generate],
                suppress_health_check=list(HealthCheck),
            ),
        )
