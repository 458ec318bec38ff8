"""A camera pose as an OGC GeoPose (Basic-Quaternion): the camera centre as WGS84 latitude,
longitude and height, and its orientation as the rotation from the camera frame to the local
East-North-Up frame *at the camera's position*.

The camera frame of the quaternion is the OpenGL / WebXR / ARKit one (x right, y up,
z backward: the camera looks along −z), so an identity quaternion is a camera looking down
with its top towards North."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geo.geodesy import Geodetic, ecef_from_enu_rotation
from services.geo.registration import GeoRegistration
from services.geometry.rigid import Rigid3d, matrix_to_quaternion
from services.types import FloatArray

# the OpenGL camera's axes in the COLMAP camera frame (x right, y down, z forward)
CV_FROM_GL = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class GeoPose:
    """position: WGS84 point of the camera centre. enu_from_camera: (3, 3) rotation from the
    OpenGL camera frame to ENU at ``position``."""

    position: Geodetic
    enu_from_camera: FloatArray

    @property
    def quaternion_xyzw(self) -> FloatArray:
        w, x, y, z = matrix_to_quaternion(self.enu_from_camera)
        return np.array([x, y, z, w])


@dataclass(frozen=True)
class GeoPoseAccuracy:
    """1-σ accuracies: horizontal and vertical position in metres, yaw (heading) in degrees."""

    horizontal_m: float
    vertical_m: float
    yaw_deg: float


def geopose_of(cam_from_world: Rigid3d, registration: GeoRegistration) -> GeoPose:
    """The GeoPose of a camera posed in a registered map."""
    center = cam_from_world.center
    lat_lon_h = registration.geodetic_from_map(center[None])[0]
    position = Geodetic(*map(float, lat_lon_h))
    enu0_from_cam = registration.rotation @ cam_from_world.rotation.T @ CV_FROM_GL
    ecef_from_cam = ecef_from_enu_rotation(registration.origin) @ enu0_from_cam
    return GeoPose(position, ecef_from_enu_rotation(position).T @ ecef_from_cam)


def geopose_accuracy(
    registration: GeoRegistration,
    position_sigma: float | None,
    rotation_sigma_deg: float | None,
) -> GeoPoseAccuracy:
    """Accuracies of a GeoPose from the pose's own RMS errors (``position_sigma``: of the
    camera centre in map units; ``rotation_sigma_deg``: of its rotation angle; None when
    unknown, counted as zero) and the registration's, added in quadrature. A 3-D RMS error is
    split as if isotropic: √(2/3) of it horizontally, √(1/3) vertically; the rotation's whole
    RMS angle bounds the yaw's."""
    pose_m = (position_sigma or 0.0) * registration.scale
    position = float(np.hypot(pose_m, registration.position_sigma_m))
    yaw = float(np.hypot(rotation_sigma_deg or 0.0, registration.rotation_sigma_deg))
    return GeoPoseAccuracy(
        horizontal_m=position * float(np.sqrt(2.0 / 3.0)),
        vertical_m=position * float(np.sqrt(1.0 / 3.0)),
        yaw_deg=yaw,
    )
