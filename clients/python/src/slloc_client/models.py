# ruff: noqa: E501, N815  (descriptions as written; the GeoPose protocol's camelCase)
"""Models of the slloc API, generated from openapi/openapi.json by
clients/python/generate_models.py: do not edit by hand."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

EstimatorName = Literal[
    "auto",
    "e3p1",
    "e5p1",
    "essential_3pt_depth",
    "essential_5pt",
    "local_tri_all",
    "local_tri_pairs",
    "motion_averaging",
    "pose_approx",
]

FailureReason = Literal[
    "no_references",
    "too_few_matches",
    "degenerate_geometry",
    "no_consensus",
    "missing_depth",
    "time_budget_exceeded",
    "focal_unobservable",
    "gravity_mismatch",
    "inconsistent_frames",
    "low_confidence",
]
"""Why a query was not localized. Values are API strings."""


class BodyAddCaptureFrame(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    depth: bytes | None = Field(
        default=None, description="Optional depth: 16-bit PNG in millimetres or .npy float32 metres"
    )
    image: bytes = Field(description="JPEG or PNG")
    metadata: str = Field(
        description='JSON string (schema CaptureFrameMetadata): {"name": str, "camera": {"model": "PINHOLE", "width": int, "height": int, "params": [fx, fy, cx, cy]}, and the pose in the session: "session_pose": {"matrix": 4×4} (ARKit / ARCore, OpenGL axes) or "cam_from_session": {"rotation": [qw, qx, qy, qz], "translation": [tx, ty, tz]} (COLMAP), and optionally "gps": {"latitude", "longitude", "height"?, "accuracy_m"?} (default: the image\'s EXIF GPS)}'
    )


class BodyAddImage(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    depth: bytes | None = Field(
        default=None, description="Optional depth: 16-bit PNG in millimetres or .npy float32 metres"
    )
    image: bytes = Field(description="JPEG or PNG")
    metadata: str = Field(
        description='JSON string (schema ImageMetadata): {"name": str, "camera": {"model": "PINHOLE", "width": int, "height": int, "params": [fx, fy, cx, cy]}, "cam_from_world": {"rotation": [qw, qx, qy, qz], "translation": [tx, ty, tz]}}'
    )


class BodyLocalize(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    depth: bytes | None = Field(
        default=None,
        description="Optional query depth: 16-bit PNG in millimetres or .npy float32 m",
    )
    image: list[bytes] = Field(
        description="Query image, JPEG or PNG; repeat the part for several frames (each described by params.frames, in order; together within the upload limit)"
    )
    params: str = Field(
        default="{}",
        description='JSON string (schema LocalizeParamsIn), all keys optional: {"camera": {...}, "estimator": "auto", "top_k": 10, "prior": {"position": [x, y, z], "radius": m}, "return_inliers": false, "max_error_px": 12}',
    )


class BootstrapGeoRegistrationOut(BaseModel):
    """The geo-registration a session that started an empty map gave it from its frames'
    GPS fixes.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    num_inliers: int | None = Field(default=None, description="Of those, the fit's inliers")
    num_references: int | None = Field(default=None, description="References with GPS")
    reason: str | None = Field(default=None, description="Why none was set")
    residual_rms_m: float | None = Field(
        default=None,
        description="RMS distance between the inliers' centres and their GPS positions",
    )
    set: bool = Field(
        description="The registration was estimated and stored (GET /v1/maps/{map_id}/geo-registration)"
    )


class CameraAdaptationOut(BaseModel):
    """How the request's camera was adapted to the upload."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    camera: CameraSchema = Field(description="The upload's intrinsics, as used")
    exif_orientation: int | None = Field(description="The upload's EXIF orientation tag")
    rotation_deg: int = Field(
        description="Clockwise quarter turn from the camera's image to the upload"
    )
    scale: float = Field(description="Upload pixels per camera pixel (mean of x and y)")


class CameraParam(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    model: str | None = Field(
        default=None,
        description="COLMAP model name (UNKNOWN_CAMERA, UNKNOWN or absent: no intrinsics)",
    )
    modelParams: list[float] | None = Field(default=None, description="COLMAP parameter order")


class CameraReading(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    imageBytes: str = Field(description="base64")
    imageFormat: str | None = Field(
        default=None,
        description="JPG, JPEG or PNG (encoded bytes), or RGBA32, RGB24, GRAY8 (raw pixels of ``size``). JPEG and PNG bytes are recognised by their signature whatever the label says",
    )
    imageOrientation: ImageOrientation | None = Field(default=None)
    params: CameraParam | None = Field(default=None)
    sensorId: str | int | None = Field(default=None)
    sequenceNumber: int | None = Field(default=None)
    size: list[int] | None = Field(
        default=None, description="width, height; optional for JPEG and PNG (read from the image)"
    )


class CameraSchema(BaseModel):
    """A COLMAP camera. Pixel coordinates use COLMAP's convention: the centre of the top-left
    pixel is (0.5, 0.5), so an ideal principal point of a W×H image is (W/2, H/2).
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    height: int
    model: Literal[
        "SIMPLE_PINHOLE",
        "PINHOLE",
        "SIMPLE_RADIAL",
        "RADIAL",
        "OPENCV",
        "OPENCV_FISHEYE",
        "FULL_OPENCV",
        "FOV",
        "SIMPLE_RADIAL_FISHEYE",
        "RADIAL_FISHEYE",
        "THIN_PRISM_FISHEYE",
        "RAD_TAN_THIN_PRISM_FISHEYE",
    ]
    params: list[float] = Field(
        description="COLMAP order: SIMPLE_PINHOLE: f, cx, cy; PINHOLE: fx, fy, cx, cy; SIMPLE_RADIAL: f, cx, cy, k; RADIAL: f, cx, cy, k1, k2; OPENCV: fx, fy, cx, cy, k1, k2, p1, p2; OPENCV_FISHEYE: fx, fy, cx, cy, k1, k2, k3, k4; FULL_OPENCV: fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6; FOV: fx, fy, cx, cy, omega; SIMPLE_RADIAL_FISHEYE: f, cx, cy, k; RADIAL_FISHEYE: f, cx, cy, k1, k2; THIN_PRISM_FISHEYE: fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1; RAD_TAN_THIN_PRISM_FISHEYE: fx, fy, cx, cy, k0, k1, k2, k3, k4, k5, p0, p1, s0, s1, s2, s3. Plausible: focal lengths 0.05–100 × the longer image side, the principal point within the image extended by its size, distortion within ±10"
    )
    width: int


class CaptureAlignmentOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    added: int | None = Field(default=None, description="Frames added as references")
    agreeing: int | None = Field(
        default=None, description="Of those, the frames within the tolerance"
    )
    checked: list[CheckedFrameOut]
    confident: int | None = Field(
        default=None, description="Checked frames localized with confidence ≥ 0.8"
    )
    drift_correction_m: DriftCorrectionOut | None = Field(
        default=None,
        description="How far the agreeing frames' centres were moved onto where the map localized them; the frames between two of them are corrected by interpolation",
    )
    geo_registration: BootstrapGeoRegistrationOut | None = Field(
        default=None,
        description="bootstrap only, once added: the map's geo-registration estimated from the frames' GPS fixes (when the map had none and at least 3 frames carry GPS with height), or why none was set. A session aligned to a map never changes its registration",
    )
    map_from_session: SessionTransformOut | None = Field(
        description="null when the session was refused"
    )
    mode: Literal["aligned", "bootstrap"] = Field(
        description="bootstrap: the map was empty and the session defined its frame"
    )
    path_length_m: float = Field(description="Length of the session's path (session units)")
    position_stderr_m: float | None = Field(
        default=None, description="Standard error of the alignment's position (RMS / √(n − 1))"
    )
    reason: str | None = Field(default=None, description="Why the session was refused")
    rms_position_m: float | None = Field(
        default=None, description="RMS of the agreeing frames' errors"
    )
    rms_rotation_deg: float | None = Field(default=None)
    rotation_stderr_deg: float | None = Field(default=None)
    skipped: int | None = Field(
        default=None,
        description="Frames not added: beyond the anchors' reach (unanchored), or their views were in the map already (unless keep_all)",
    )
    spacing_m: float | None = Field(
        default=None, description="The map's spacing that decided which frames add a view"
    )
    stale: list[StaleReferenceOut] | None = Field(
        default=None, description="References the session's frames no longer match, flagged stale"
    )
    tolerance_m: float | None = Field(
        default=None, description="max(5 cm, 1 % of the path): how far an agreeing frame may lie"
    )
    unanchored: int | None = Field(
        default=None,
        description="Frames farther than 5 m along the path from every frame the map localized: their drift is unmeasured, they are not added",
    )


class CaptureFrameMetadata(BaseModel):
    """The ``metadata`` form field of a frame upload (a JSON string): its pose in the
    session, as an AR framework reports it (``session_pose``) or as COLMAP writes it
    (``cam_from_session``).
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    cam_from_session: PoseSchema | None = Field(
        default=None, description="x_cam = R · x_session + t, COLMAP camera axes (x right, y down)"
    )
    camera: CameraSchema | None = Field(
        default=None, description="Its intrinsics; default: the default camera for the image size"
    )
    gps: GpsSchema | None = Field(
        default=None,
        description="The device's GPS fix when the frame was taken, kept on the reference it becomes; default: the image's EXIF GPS. A session that starts an empty map geo-registers it from its frames' fixes (with height)",
    )
    name: str | None = Field(default=None, description="Unique in the session; default: 00000, …")
    session_pose: SessionPoseSchema | None = Field(
        default=None,
        description="session_from_camera with OpenGL camera axes (ARKit camera.transform, ARCore Pose, WebXR), as the localize endpoint takes it",
    )


class CaptureFrameOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    camera: CameraSchema
    created_at: datetime
    gps: GpsSchema | None = Field(
        description="Its GPS fix (sent, or read from its EXIF); null when it has none"
    )
    id: str = Field(description="The id of the reference it becomes once added")
    name: str
    position: int = Field(description="Its place in the capture order (upload order)")


class CaptureProgress(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    done: int = Field(description="Frames checked, then frames added")
    total: int


class CaptureSessionCreate(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    keep_all: bool = Field(
        default=False,
        description="Add every frame within the anchors' reach. false: a frame is added only where it adds a view, i.e. no reference or frame kept before it lies within the map's spacing (the median distance between neighbouring references) looking within 15° of its direction; a session that starts an empty map adds every frame",
    )
    metric: bool = Field(
        default=True,
        description="The frames' poses are in metres (ARKit, ARCore, a metric SLAM): the session is aligned rigidly. false: its scale is estimated (a similarity; a session of unknown scale cannot start an empty map)",
    )
    name: str | None = Field(
        default=None,
        description="Unique in the map; the references its frames become are named <session name>/<frame name>. Default: session-<8 hex digits>",
    )


class CaptureSessionOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    alignment: CaptureAlignmentOut | None = Field(
        description="Set once the session is aligned or refused"
    )
    created_at: datetime
    error: str | None
    finished_at: datetime | None
    frames: int = Field(description="Frames uploaded")
    id: str
    keep_all: bool
    map_id: str
    metric: bool
    name: str
    progress: CaptureProgress
    started_at: datetime | None
    state: Literal["open", "queued", "aligning", "adding", "added", "refused", "failed"]


class CaptureSessionPage(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    items: list[CaptureSessionOut] = Field(description="Newest first")
    limit: int
    offset: int
    total: int


class CheckedFrameOut(BaseModel):
    """A frame localized against the map to align the session."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    agrees: bool = Field(description="Within the tolerance and 2°: it took part in the fit")
    confidence: float
    frame: str
    localized: bool
    position_error_m: float | None = Field(
        description="Distance between where the alignment and the map put it (confident frames only)"
    )
    rotation_error_deg: float | None


class ConfidenceCheck(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    confident: int = Field(description="Answers above the threshold")
    precision: float | None = Field(
        description="Of the answers above the threshold, the share within (0.25 m, 5°)"
    )
    recall: float | None = Field(
        description="Of the answers within (0.25 m, 5°), the share above the threshold"
    )
    threshold: float = Field(description="The confidence an answer is taken as sure above")


class ConfigurationResult(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    confidence: ConfidenceCheck
    duration_s: float = Field(description="Time this configuration's measurement took")
    failures: dict[str, int] = Field(description="Held-out references not localized, by reason")
    held_out: int = Field(description="References localized against the map without them")
    latency_ms: Latency
    localized: int
    nearest_reference_m: Distance
    position_error_m: Percentiles = Field(description="Failures count as infinite")
    recall: dict[str, float] = Field(
        description="Share of the held-out references localized within each threshold (keys like 5cm_5deg)"
    )
    references: list[HeldOutOut] | None = Field(
        default=None, description="Per held-out reference (left out of listings)"
    )
    rotation_error_deg: Percentiles


class CoverageCellOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    center: list[float] = Field(description="The cell's centre in map coordinates")
    failed: int = Field(
        description="Of those, not localized or off by more than 25 cm or 5° from their pose"
    )
    held_out: int = Field(description="Its references held out by the latest self-evaluation")
    i: int = Field(description="Index along the plane's u axis")
    j: int = Field(description="Index along the plane's v axis")
    median_error_m: float | None = Field(description="Of the held-out ones localized")
    queries_failed: int = Field(
        description="Single-frame queries not localized whose best retrieved reference lies here"
    )
    queries_localized: int = Field(
        description="Single-frame queries localized whose best retrieved reference lies here"
    )
    references: int
    weak: bool
    why: list[str] = Field(description="Why the cell is weak")


class CoverageOut(BaseModel):
    """The map's references on their ground plane, cell by cell, with its latest
    self-evaluation: where a query is least likely to be answered well.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    cell_m: float
    cells: list[CoverageCellOut]
    evaluation_id: str | None = Field(
        description="The self-evaluation read; null when the map has no finished one (cells then say only how many references they hold)"
    )
    plane: GroundPlaneOut
    weak: int = Field(description="Weak cells")


class DescribedByOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    descriptor_model: str = Field(description="The global descriptor that described them")
    feature_model: str = Field(description="The extractor that described them, e.g. xfeat-1024-640")
    image_count: int
    served: bool = Field(description="This server describes queries alike: they are searched")


class Distance(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    median: float | None = Field(
        description="From a held-out reference to the nearest reference it was localized against (map units): compare with how far your queries are from the map"
    )


class DriftCorrectionOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    max: float
    median: float


class EnuFromMapSchema(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    rotation: list[float] = Field(
        default=[1.0, 0.0, 0.0, 0.0], description="enu_from_map rotation quaternion [w, x, y, z]"
    )
    translation: list[float] = Field(
        default=[0.0, 0.0, 0.0], description="metres in ENU; |translation| at most 1e+07"
    )


class EvaluationCreate(BaseModel):
    """What to measure; every field has a default (an empty body measures every configuration
    the server can run).
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    configurations: list[str] | None = Field(
        default=None,
        description="Feature configurations to measure (names as SLLOC_FEATURES takes); null: the server's, the automatic choices (xfeat-lg, aliked) and sift, of those whose models are built",
    )
    estimator: EstimatorName | None = Field(
        default=None, description="The estimator of the held-out queries; null: the map's default"
    )
    holdout_radius_m: float = Field(
        default=0.0,
        description="References whose centre lies within this distance of a held-out one are held out with it, so that it is as far from the map as a real query (map units)",
    )
    sample_size: int = Field(
        default=30,
        description="References held out, spread over the map (farthest-point sampling of their camera centres)",
    )
    top_k: int = Field(default=10, description="References retrieved per held-out query")


class EvaluationOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    created_at: datetime
    error: str | None
    finished_at: datetime | None
    id: str
    map_id: str
    progress: EvaluationProgress
    request: EvaluationCreate
    result: EvaluationResult | None
    started_at: datetime | None
    state: Literal["queued", "running", "done", "failed", "cancelled"]


class EvaluationPage(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    items: list[EvaluationOut] = Field(description="Newest first, without per-reference rows")
    limit: int
    offset: int
    total: int


class EvaluationProgress(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    done: int = Field(description="Held-out queries localized, over every configuration")
    total: int


class EvaluationResult(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    configurations: dict[str, ConfigurationResult]
    recommended: str | None = Field(
        description="The fastest configuration within 5 points of the best recall at every threshold and within 1.25x (or 5 mm) of the best median position error; null when none localized anything"
    )
    references: int = Field(description="The map's references with their originals")
    served: str = Field(description="The server's feature configuration at the time")
    stale: list[StaleReferenceOut] | None = Field(
        default=None,
        description="References that no longer match the held-out references that cover them, flagged stale (measured with the served configuration)",
    )


class FeatureCreate(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    max_keypoints: int | None = Field(
        default=None, description="Keypoint budget per image (ALIKED: at most 2048)"
    )
    max_side: int | None = Field(
        default=None, description="Longer image side features are extracted at (px)"
    )
    preset: str = Field(
        default="auto",
        description="The feature configuration: `auto` (the server's, SLLOC_FEATURES, until the map's self-evaluation recommends one of those the server serves) or one of them by name (the server's and SLLOC_EVALUATION_FEATURES'; another is refused, 422)",
    )


class FeaturePatch(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    max_keypoints: int | None = Field(
        default=None, description="Keypoint budget per image (ALIKED: at most 2048)"
    )
    max_side: int | None = Field(
        default=None, description="Longer image side features are extracted at (px)"
    )
    preset: str | None = Field(
        default=None,
        description="The feature configuration: `auto` (follow the map's self-evaluation), or one the server serves by name (its own, SLLOC_FEATURES, and those of SLLOC_EVALUATION_FEATURES; another is refused, 422); null keeps the map's",
    )


class FeatureProgressOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    described: int = Field(description="References described for the pending options")
    total: int = Field(description="References that have their original to be described from")


class FrameIn(BaseModel):
    """One uploaded image's camera and session pose (``params.frames[i]`` goes with the
    i-th ``image`` part).
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    camera: CameraSchema | None = Field(
        default=None,
        description="This frame's intrinsics; default: params.camera, else the default",
    )
    session_pose: SessionPoseSchema


class FrameOut(BaseModel):
    """One uploaded frame of a query with session poses."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    cam_from_world: PoseSchema | None
    camera_center: list[float] | None
    inliers: list[InliersOut] | None = Field(default=None)
    num_inliers: int = Field(description="Matches within the inlier threshold of its pose")
    num_point_inliers: int = Field(
        description="Its 2D–3D inliers in the joint estimate (0 for a single frame)"
    )
    retrieved: list[RetrievedOut]


class FramePoseOut(BaseModel):
    """Camera-to-world in one convention."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    matrix: list[list[float]] = Field(
        description="4×4 world_from_cam, row-major, column vectors: x_world = M · x_cam"
    )
    position: list[float] = Field(description="Camera position in the world")
    rotation: list[float] = Field(description="Unit quaternion [w, x, y, z] of M's rotation")


class GeoPoseAccuracy(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    orientation: float = Field(description="degrees: the mean of the three angles' 1-σ")
    position: float = Field(description="metres: the mean of the three axes' 1-σ")


class GeoPoseAccuracySchema(BaseModel):
    """1-σ: horizontal and vertical position in metres, yaw (heading) in degrees."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    horizontal_m: float
    vertical_m: float
    yaw_deg: float


class GeoPoseReq(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    id: str
    priorPoses: list[PriorPose] | None = Field(
        default=None,
        description="earlier answers: the last one with a geopose narrows retrieval (before the GPS fix)",
    )
    sensorReadings: SensorReadings | list[SensorReadingV1] = Field(
        description="version 2: an object of per-kind lists; version 1: a list of {sensorId, reading}"
    )
    sensors: list[Sensor] | None = Field(default=None)
    timestamp: float | str | None = Field(default=None)
    type: str = Field(default="geopose")


class GeoPoseResp(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    accuracy: GeoPoseAccuracy
    geopose: GeoPoseSchema
    id: str
    timestamp: float = Field(description="milliseconds since the Unix epoch")
    type: str = Field(default="geopose")


class GeoPoseSchema(BaseModel):
    """OGC GeoPose Basic-Quaternion: ``quaternion`` rotates the camera frame (OpenGL axes:
    x right, y up, z backward) into East-North-Up at ``position``.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    position: GeoPositionSchema
    quaternion: QuaternionXyzwSchema


class GeoPositionSchema(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    h: float
    lat: float
    lon: float


class GeoRegistrationEstimateIn(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    max_error_m: float = Field(
        default=10.0,
        description="RANSAC inlier threshold in metres between a registered camera centre and its GPS position (about 3 × the GPS accuracy)",
    )


class GeoRegistrationIn(BaseModel):
    """A registration set by hand: ``x_enu = scale · R · x_map + t``, with ENU (x East,
    y North, z Up, metres) anchored at ``origin``. A map whose frame is already metric with
    z up and x East has the identity rotation and scale 1.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    enu_from_map: EnuFromMapSchema = Field(
        default_factory=lambda: EnuFromMapSchema.model_validate(
            {"rotation": [1.0, 0.0, 0.0, 0.0], "translation": [0.0, 0.0, 0.0]}
        )
    )
    origin: GeodeticSchema
    scale: float = Field(default=1.0, description="metres per map unit")


class GeoRegistrationOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    enu_from_map: EnuFromMapSchema
    num_inliers: int | None = Field(default=None)
    num_references: int | None = Field(default=None, description="references with GPS (estimated)")
    origin: GeodeticSchema
    position_sigma_m: float = Field(description="1-σ of a registered position (0 when manual)")
    residual_rms_m: float | None = Field(default=None)
    residuals: list[ResidualOut] | None = Field(
        default=None, description="per reference, in the answer of an estimate"
    )
    rotation_sigma_deg: float = Field(description="1-σ of a registered orientation")
    scale: float
    source: Literal["manual", "estimated"]


class GeodeticSchema(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    height: float = Field(default=0.0, description="metres above the WGS84 ellipsoid")
    latitude: float = Field(description="WGS84 degrees")
    longitude: float = Field(description="WGS84 degrees")


class GeolocationReading(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    accuracy: float | None = Field(
        default=None, description="horizontal 1-σ in metres; 0 or absent: unknown"
    )
    altitude: float | None = Field(default=None)
    latitude: float
    longitude: float
    sensorId: str | int | None = Field(default=None)


class GpsSchema(BaseModel):
    """A GPS position (WGS84). ``height`` in metres above the ellipsoid (EXIF altitudes, above
    sea level, are taken as they are); ``accuracy_m`` the horizontal 1-σ in metres.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    accuracy_m: float | None = Field(default=None)
    height: float | None = Field(default=None)
    latitude: float = Field(description="WGS84 degrees")
    longitude: float = Field(description="WGS84 degrees")


class GravityIn(BaseModel):
    """Measured gravity of the query frame."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    down: list[float] = Field(
        description="Direction of gravity (pointing to the earth, any length) in the frame of `camera` (of the upload when `camera` is absent), COLMAP axes: x right, y down, z forward. A level landscape camera has [0, 1, 0]."
    )
    map_down: list[float] | None = Field(
        default=None,
        description="The map's down in world coordinates; default: the retrieved references' mean image down (references captured roughly upright)",
    )
    max_angle_deg: float = Field(
        default=5.0,
        description="A pose whose gravity is further off is answered localized: false, reason gravity_mismatch",
    )


class GroundPlaneOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    origin: list[float]
    u: list[float] = Field(description="Unit axis of the cells' i")
    v: list[float] = Field(description="Unit axis of the cells' j")


class HealthOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    blob_store: str = Field(
        default="ok",
        description="ok; unavailable when the store of the references' originals cannot take writes (a folder missing or read-only, a bucket unreachable or refusing the credentials; the server's log says why): adds answer 503 blob-store-unavailable, localize goes on. Probed at most every 15 s",
    )
    models: ModelsOut
    runtime: RuntimeOut
    status: str = Field(
        description="ok; degraded when the database is down, some map cannot be served (unservable_maps) or the blob store cannot take writes (blob_store)"
    )
    unservable_map_count: int = Field(
        default=0,
        description="Maps with references none of which this server describes alike: their localize answers 409 feature-models-missing",
    )
    unservable_maps: list[UnservableMapOut] | None = Field(
        default=None,
        description="The first 20 of them, most references first (refreshed every 15 s)",
    )
    version: str


class HeldOutOut(BaseModel):
    """One reference localized against the map without it (errors against its stored pose;
    null when not localized).
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    confidence: float
    image_id: str
    latency_ms: float
    localized: bool
    name: str
    nearest_reference_m: float | None = Field(
        description="From its camera centre to the nearest reference it was localized against"
    )
    num_inliers: int
    position_error_m: float | None
    reason: str | None
    rotation_error_deg: float | None


class ImageMetadata(BaseModel):
    """The ``metadata`` form field of an image upload (a JSON string)."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    cam_from_world: PoseSchema
    camera: CameraSchema
    gps: GpsSchema | None = Field(
        default=None, description="Where it was taken; when absent, the image's EXIF GPS if any"
    )
    name: str


class ImageOrientation(BaseModel):
    """Only the upright, unmirrored image (rotation a multiple of 360°, mirrored false) is
    served; other values are answered 422 rather than localized wrongly.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    mirrored: bool = Field(default=False)
    rotation: float = Field(default=0.0, description="degrees")


class ImageOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    cam_from_world: PoseSchema
    camera: CameraSchema
    created_at: datetime
    gps: GpsSchema | None = Field(default=None)
    has_depth: bool
    has_original: bool = Field(
        description="Its bytes as uploaded are kept (GET …/original; false for images added before originals were kept: they serve their stored features but cannot be described again)"
    )
    id: str
    name: str
    num_keypoints: int
    original_sha256: str | None = Field(
        default=None, description="SHA-256 of the original bytes (hex), when kept"
    )
    stale: StaleOut | None = Field(
        default=None,
        description="Flagged stale: frames of a capture session that cover it no longer match it (the place changed, or the image is not of it); delete it to retire it",
    )


class ImagePage(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    items: list[ImageOut]
    limit: int
    offset: int
    total: int


class InliersOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    image_id: str
    query_xy: list[list[float]] = Field(description="(K, 2) COLMAP pixel coordinates")
    reference_xy: list[list[float]]


class Latency(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    median: float | None = Field(description="Median time of a held-out query (ms)")


class LocalizeParamsIn(BaseModel):
    """The ``params`` form field of a localize request (a JSON string; all optional)."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    camera: CameraSchema | None = Field(
        default=None,
        description="Query intrinsics. When absent, the focal length is estimated from the matches (SIMPLE_PINHOLE, principal point at the image centre; answer camera_source 'estimated'), or the answer is localized: false with reason focal_unobservable.",
    )
    camera_rotation_deg: Literal[0, 90, 180, 270] | None = Field(
        default=None,
        description="Clockwise turn from the image `camera` describes to the upload as displayed (EXIF applied). Default: decided by the sizes (the camera may be given for any uniform scale of the upload) and EXIF, a swapped aspect taken as 90°",
    )
    estimator: EstimatorName | None = Field(
        default=None, description="Estimator name; default: the map's default_estimator"
    )
    frames: list[FrameIn] | None = Field(
        default=None,
        description="One entry per `image` part, in order: the frame's AR-session pose and optional camera. With frames the answer adds map_from_session and per-frame poses; two or more frames (at most SLLOC_MAX_FRAMES) are localized jointly. See the docs' AR page, 'Several frames'",
    )
    gps: GpsSchema | None = Field(
        default=None,
        description="The device's GPS fix. On a geo-registered map, retrieval keeps the references within 3 × accuracy_m (default 10 m, at least 10 m) of it horizontally; 422 on a map without a registration",
    )
    gravity: GravityIn | None = Field(default=None)
    max_error_px: float | None = Field(
        default=None, description="Inlier threshold in pixels (default 12)"
    )
    min_confidence: float = Field(
        default=0.3,
        description="A pose less confident than this is not an answer: localized: false, reason low_confidence, the pose as `candidate`. 0 answers every verified pose",
    )
    output: OutputIn | None = Field(default=None)
    prior: PriorSchema | None = Field(default=None)
    return_inliers: bool = Field(default=False)
    rotation_search: bool = Field(
        default=True,
        description="Without a gravity hint, also try the upload turned by 90°, 270° and 180° (within the time budget) when it fails as uploaded",
    )
    second_opinion: bool = Field(
        default=True,
        description="When the map's feature configuration retrieves references but does not localize the query (too_few_matches, no_consensus, degenerate_geometry, focal_unobservable, low_confidence), localize it again with the server's second configuration (SLLOC_SECOND_OPINION) against those references, within the time budget left; false answers at once. See the docs' API page, 'A second opinion'",
    )
    time_budget_s: float | None = Field(
        default=None,
        description="Wall-clock budget in seconds, at most the service's (SLLOC_LOCALIZE_TIME_BUDGET_S, its default); past it the answer is localized: false with reason time_budget_exceeded",
    )
    top_k: int = Field(default=10)


class LocalizeResult(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    cam_from_world: PoseSchema | None
    camera: CameraSchema | None = Field(
        default=None, description="The query camera used: the request's, or the estimated one"
    )
    camera_adaptation: CameraAdaptationOut | None = Field(
        default=None, description="How `camera` was adapted to the upload (when a camera was given)"
    )
    camera_center: list[float] | None
    camera_source: Literal["request", "estimated"] | None = Field(default=None)
    candidate: PoseSchema | None = Field(
        default=None,
        description="With reason low_confidence: the pose found, less confident than params.min_confidence (not an answer; `confidence` is its confidence)",
    )
    confidence: float = Field(description="In [0, 1]; see the docs' API page, 'Reading the result'")
    estimator: EstimatorName = Field(description="The estimator asked for")
    estimator_reason: str | None = Field(
        default=None,
        description="Why `auto` chose `estimator_used` (null for the other estimators)",
    )
    estimator_used: EstimatorName = Field(
        description="The estimator whose answer this is: the one asked for, or the one `auto` chose"
    )
    frames: list[FrameOut] | None = Field(
        default=None, description="With params.frames: one per uploaded frame, in order"
    )
    geopose: GeoPoseSchema | None = Field(
        default=None,
        description="OGC GeoPose of the camera, on a geo-registered map when localized",
    )
    geopose_accuracy: GeoPoseAccuracySchema | None = Field(default=None)
    gravity_error_deg: float | None = Field(
        default=None,
        description="Angle between the gravity hint and the pose's (with a gravity hint)",
    )
    inliers: list[InliersOut] | None = Field(default=None)
    localized: bool
    map_from_session: SessionAlignmentOut | None = Field(
        default=None,
        description="With params.frames, once localized: the transform from the AR session to the map (the docs' AR page, 'Several frames')",
    )
    num_inliers: int
    reason: FailureReason | None
    retrieved: list[RetrievedOut]
    second_opinion: SecondOpinionOut | None = Field(
        default=None,
        description="When the map's configuration found no answer and another localized the query again (params.second_opinion): what it answered; null when none was asked",
    )
    timings_ms: Timings
    uncertainty: UncertaintyOut | None = Field(
        default=None, description="Pose uncertainty; null without a pose or enough verified points"
    )
    upright_turn_deg: int = Field(
        default=0, description="Clockwise turn of the upload at which it was matched"
    )
    wider_retrieval: bool = Field(
        default=False,
        description="Whether the query was retrieved a second time with its references spread wider, its first answer being below confidence 0.5; the answer is the more confident of the two (the docs' Models page, 'An unsure answer gets a wider spread')",
    )
    world_from_cam: dict[str, FramePoseOut] | None = Field(
        default=None, description="The pose of `output.pose_of` in the conventions `output.frames`"
    )


class MapCreate(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    default_estimator: EstimatorName = Field(
        default="auto", description="Estimator used when a localize request names none"
    )
    description: str | None = Field(default=None)
    features: FeatureCreate | None = Field(
        default=None,
        description="Feature configuration, keypoint budget and image size for this map's references and queries",
    )
    grow_from_queries: bool = Field(
        default=False,
        description="Queries localized with confidence ≥ 0.95 and their intrinsics that add a view the map lacks (no reference within the map's spacing looking within 15° of it) are added as references, named query/<time>-<id>: the map fills in where it is used, at most one reference per place and direction",
    )
    name: str
    retire_stale: bool = Field(
        default=False,
        description="References a capture session flags stale (its frames that cover them no longer match them) are deleted at once instead of listed for an admin to retire",
    )


class MapFeatureModelsOut(BaseModel):
    """What the map's references were described by, and whether this server can serve
    them.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    configurations: list[str] = Field(
        description="SLLOC_FEATURES values whose extractor described the unserved references"
    )
    described_by: list[DescribedByOut] = Field(
        description="The map's references grouped by what described them, most first"
    )
    detail: str | None = Field(default=None, description="What is wrong and what to do")
    missing_models: list[str] = Field(
        description="Exported models the unserved references need that this server lacks"
    )
    servable: bool = Field(
        description="Some reference (or none: an empty map) is described as this server describes queries; false: every localize on the map answers 409 feature-models-missing"
    )
    server_descriptor_model: str = Field(description="This server's global descriptor")
    server_feature_model: str = Field(
        description="The extractor this server describes the map's queries with (its model, keypoint budget and image side)"
    )
    unserved_image_count: int = Field(description="References this server does not search")


class MapFeaturesOut(BaseModel):
    """The feature configuration and options the map serves with, whether it follows its
    self-evaluation and, while the references are described anew, what they are described
    for and how far.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    auto: bool = Field(
        description="The map takes the configuration its self-evaluation recommends, evaluated on its own as it grows (docs: self-evaluation)"
    )
    max_keypoints: int | None = Field(
        default=None, description="Keypoint budget per image (ALIKED: at most 2048)"
    )
    max_side: int | None = Field(
        default=None, description="Longer image side features are extracted at (px)"
    )
    pending: PendingFeaturesOut | None = Field(
        default=None, description="What the references are being described for"
    )
    preset: str = Field(
        description="The feature configuration whose extractor describes the map's queries and references: the server's (SLLOC_FEATURES) until the map chooses another"
    )
    progress: FeatureProgressOut | None = Field(default=None)
    state: Literal["ready", "evaluating", "re-extracting"] = Field(
        description="evaluating: a self-evaluation of the map is queued or running; re-extracting: the references are being described anew from their originals for `pending`; the map answers with its current descriptions until every one is, then switches at once"
    )


class MapOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    created_at: datetime
    default_estimator: EstimatorName
    description: str | None
    feature_models: MapFeatureModelsOut
    features: MapFeaturesOut
    grow_from_queries: bool = Field(
        description="Queries localized with confidence ≥ 0.95 and their intrinsics that add a view the map lacks (no reference within the map's spacing looking within 15° of it) are added as references, named query/<time>-<id>: the map fills in where it is used, at most one reference per place and direction"
    )
    id: str
    image_count: int
    name: str
    references_without_original: int = Field(
        description="Images added before originals were kept (has_original false): they serve their stored features but cannot be described again"
    )
    retire_stale: bool = Field(
        description="References a capture session flags stale (its frames that cover them no longer match them) are deleted at once instead of listed for an admin to retire"
    )


class MapPage(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    items: list[MapOut]
    limit: int
    offset: int
    total: int


class MapPatch(BaseModel):
    """The fields to change; those left out keep their value."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    default_estimator: EstimatorName | None = Field(
        default=None, description="Estimator used when a localize request names none"
    )
    description: str | None = Field(default=None)
    features: FeaturePatch | None = Field(
        default=None,
        description="New feature configuration, keypoint budget or image size: the map's references are described anew from their originals in the background (`features.state` re-extracting) while the map answers with the current ones, then it switches at once; what it serves cancels a re-description in progress. 409 when references were added before originals were kept",
    )
    grow_from_queries: bool | None = Field(
        default=None,
        description="Queries localized with confidence ≥ 0.95 and their intrinsics that add a view the map lacks (no reference within the map's spacing looking within 15° of it) are added as references, named query/<time>-<id>: the map fills in where it is used, at most one reference per place and direction",
    )
    retire_stale: bool | None = Field(
        default=None,
        description="References a capture session flags stale (its frames that cover them no longer match them) are deleted at once instead of listed for an admin to retire",
    )


class ModelsOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    estimators: list[EstimatorName]
    feature_configurations: list[str] = Field(
        description="The feature configurations maps may be served with: the server's (SLLOC_FEATURES) first, then those of SLLOC_EVALUATION_FEATURES whose models are built"
    )
    features: str
    global_descriptor: str
    matcher: str


class OutputIn(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    frames: list[Literal["colmap", "opengl", "unity"]] | None = Field(
        default=None,
        description="Also answer world_from_cam in these conventions (the docs' AR page, 'Pose conventions')",
    )
    pose_of: Literal["upload", "camera"] = Field(
        default="upload",
        description="Whose world_from_cam: the uploaded image's camera, or the camera of `camera` before camera_adaptation's turn (the frame of ARKit's camera.transform and ARCore's Camera.getPose, which give landscape sensor intrinsics)",
    )


class PendingFeaturesOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    max_keypoints: int | None = Field(
        default=None, description="Keypoint budget per image (ALIKED: at most 2048)"
    )
    max_side: int | None = Field(
        default=None, description="Longer image side features are extracted at (px)"
    )
    preset: str = Field(description="The feature configuration they are described with")


class Percentiles(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    median: float | None = Field(description="null: more than half of the answers failed")
    p90: float | None = Field(description="null: more than a tenth of the answers failed")


class PoseSchema(BaseModel):
    """``cam_from_world``: x_cam = R(rotation) · x_world + translation."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    rotation: list[float] = Field(description="unit quaternion [w, x, y, z]")
    translation: list[float] = Field(
        description="metres (map units); on input |translation| (the camera centre's distance from the map's origin) at most 1e+07"
    )


class PriorAccuracy(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    position: float | None = Field(default=None)


class PriorGeoPose(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    position: PriorPosition


class PriorPose(BaseModel):
    """A GeoPose answer received before (``GeoPoseResp``): its position narrows retrieval
    like a GPS fix of its position accuracy. Entries without a ``geopose`` are ignored.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    accuracy: PriorAccuracy | None = Field(default=None)
    geopose: PriorGeoPose | None = Field(default=None)
    timestamp: float | str | None = Field(default=None)


class PriorPosition(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    h: float | None = Field(default=None)
    lat: float
    lon: float


class PriorSchema(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    position: list[float]
    radius: float


class Problem(BaseModel):
    """RFC 9457 problem details. ``type`` is a stable URI naming the kind of problem."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    detail: str | None = Field(default=None)
    errors: list[dict[str, Any]] | None = Field(default=None)
    instance: str | None = Field(default=None)
    request_id: str | None = Field(
        default=None,
        description="The request's id, as in its X-Request-ID header and its log lines",
    )
    status: int
    title: str
    type: str


class QuaternionXyzwSchema(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    w: float
    x: float
    y: float
    z: float


class ReindexOut(BaseModel):
    """A new VLAD vocabulary for the map's references of the service's feature model."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    encoded_images: int = Field(description="References re-encoded with it")
    feature_model: str
    map_id: str
    num_centers: int = Field(description="k-means centres K (VLAD length K × descriptor size)")
    seconds: float
    trained_images: int = Field(description="References in the map when it was trained")
    vocabulary_version: int = Field(description="Grows by one with every training")


class ResidualOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    image_id: str
    inlier: bool
    name: str
    residual_m: float


class RetrievedOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    image_id: str
    name: str
    num_inliers: int
    num_matches: int
    score: float


class RuntimeOut(BaseModel):
    """The thread policy, the reference-feature cache and the memory bound
    (``SLLOC_LOCALIZE_WORKERS``, ``SLLOC_ONNX_THREADS``, ``SLLOC_CPU_CORES``,
    ``SLLOC_REFERENCE_CACHE_MIB``; the bound: ``services/runtime/memory.py``).
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    computing_memory_held_mib: float = Field(
        description="Memory the requests computing now hold, out of the computing term"
    )
    cores: int = Field(description="Cores the thread policy divides")
    idle_workers_lent: int = Field(
        description="Worker slots a request may borrow while they are idle, for its matching, a multi-frame query's extraction, and a query's ONNX extraction when all are idle (localize_workers - 1)"
    )
    localize_workers: int = Field(description="Localize and add requests computing at once")
    memory_bound_mib: float = Field(
        description="What the server's resident memory can reach with these settings: the sum of memory_terms_mib (the docs' Deploying page, Memory)"
    )
    memory_terms_mib: dict[str, float] = Field(
        description="The bound's terms, MiB: runtime, models, reference_cache, reference_images, computing (what the requests computing at once may hold together), bodies, self_evaluation (sized by the settings) and retrieval_index (the retrieval indexes held now; they grow with the references)"
    )
    reference_cache_mib: float = Field(description="Bound of the reference-feature cache")
    reference_cache_used_mib: float = Field(description="Decoded features it holds now")
    threads_per_worker: int = Field(
        description="Threads one operation may use (onnxruntime intra-op, OpenCV, BLAS)"
    )


class SecondOpinionOut(BaseModel):
    """What the second configuration answered; the answer is its own when it localized."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    agreed: bool = Field(
        default=False,
        description="Both configurations withheld a pose below min_confidence and the two agree (within 15 cm and 3°): the answer is the more confident of them, its confidence raised to 0.5 at most as its uncertainty allows, localized where that reaches min_confidence",
    )
    confidence: float
    described: int = Field(
        description="References it described from their originals (the others were kept from earlier second opinions)"
    )
    elapsed_ms: float = Field(
        description="Its time, in timings_ms too: the references it described from their originals (counted in extract) and its localization"
    )
    features: str = Field(description="The feature configuration asked")
    localized: bool
    reason: FailureReason | None


class Sensor(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    id: str | int | None = Field(default=None)
    params: CameraParam | None = Field(
        default=None, description="a camera's intrinsics (version 1 puts them here)"
    )
    type: str | None = Field(default=None, description="camera, geolocation, wifi, …")


class SensorReadingV1(BaseModel):
    """Version 1's reading: its kind is that of the sensor ``sensorId`` in ``sensors`` (or,
    without one, what its fields are: ``imageBytes`` a camera, ``latitude`` a geolocation).
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    reading: dict[str, Any] | None = Field(default=None)
    sensorId: str | int | None = Field(default=None)
    timestamp: float | str | None = Field(default=None)


class SensorReadings(BaseModel):
    """Version 2's readings. ``geoLocationReadings`` (as @oarc/gpp-access spells it) is read
    like ``geolocationReadings``.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    cameraReadings: list[CameraReading] = Field(description="the first one is localized")
    geolocationReadings: list[GeolocationReading] | None = Field(
        default=None,
        description="the first one narrows retrieval (also read as geoLocationReadings)",
    )


class SessionAlignmentOut(BaseModel):
    """``map_from_session``: x_map = R(rotation) · x_session + translation, metres (the map
    is taken to be metric). An AR app parents map content to an anchor with this transform:
    content at map point X appears at session point ``map_from_session⁻¹ · X``.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    matrix: list[list[float]] = Field(description="4×4 homogeneous transform, row-major")
    rotation: list[float] = Field(description="unit quaternion [w, x, y, z]")
    translation: list[float]


class SessionPoseSchema(BaseModel):
    """``session_from_camera`` with OpenGL camera axes (ARKit ``camera.transform``): either
    ``matrix`` or ``position`` with ``orientation``.
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    matrix: list[list[float]] | None = Field(
        default=None,
        description="4×4 homogeneous transform, row-major (rows of [R | t], last row [0, 0, 0, 1]); R must be a rotation. ARKit's simd_float4x4 is column-major: send its transpose (rows = [columns.0.x, columns.1.x, columns.2.x, columns.3.x], …)",
    )
    orientation: list[float] | None = Field(
        default=None,
        description="unit quaternion [w, x, y, z] of the camera-to-session rotation (ARKit simd_quatf and Unity list it as x, y, z, w: reorder)",
    )
    position: list[float] | None = Field(
        default=None, description="camera centre in the session, metres"
    )


class SessionTransformOut(BaseModel):
    """``map_from_session``: x_map = scale · R(rotation) · x_session + translation."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    matrix: list[list[float]] = Field(description="4×4 homogeneous transform, row-major")
    rotation: list[float] = Field(description="unit quaternion [w, x, y, z]")
    scale: float = Field(description="1 for a metric session")
    translation: list[float]


class StaleOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    reason: str
    since: datetime


class StaleReferenceOut(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    image_id: str
    name: str
    reason: str
    retired: bool = Field(default=False, description="Deleted at once (the map's retire_stale)")


class Timings(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)
    decode: float
    estimate: float
    extract: float
    match: float
    retrieve: float
    total: float


class UncertaintyOut(BaseModel):
    """First-order uncertainty of the returned pose (the docs' API page, 'Queries
    without intrinsics and the pose uncertainty').
    """

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    num_points: int = Field(description="Verified 3D points the covariance rests on")
    position_m: float = Field(
        description="Root-mean-square camera-centre error predicted by the pose covariance (the verified points' own uncertainty included), in map units (metres on a metric map); 3 × this bounds the error in nearly all cases"
    )
    rotation_deg: float = Field(
        description="Root-mean-square rotation error predicted by the covariance, degrees"
    )


class UnservableMapOut(BaseModel):
    """A map whose references this server cannot search (GET /v1/maps/{id} tells more)."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    described_by: list[str] = Field(description="The feature models of its references")
    detail: str | None
    id: str
    image_count: int
    missing_models: list[str] = Field(description="The exported models this server lacks")
    name: str
