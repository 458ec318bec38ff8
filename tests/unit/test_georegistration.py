"""Geodesy, geo-registration and GeoPose: known points, hand-computed orientations, and a
registration estimated from noisy GPS against its exact ground truth."""

from __future__ import annotations

import io

import numpy as np
import pycolmap
import pytest
from PIL import ExifTags, Image

from services.errors import InvalidInputError
from services.geo.geodesy import (
    Geodetic,
    ecef_from_enu_rotation,
    ecef_from_geodetic,
    enu_from_geodetic,
    geodetic_from_ecef,
    geodetic_from_enu,
)
from services.geo.geopose import CV_FROM_GL, geopose_accuracy, geopose_of
from services.geo.gps import GpsFix, gps_from_exif
from services.geo.registration import GeoRegistration, estimate_registration
from services.geometry.rigid import Rigid3d, quaternion_to_matrix, rotation_error_deg
from services.retrieval.search import PositionPrior, top_k

ZURICH = Geodetic(47.3769, 8.5417, 408.0)
# the synthetic scenes' world frame (x right, y down, z forward) laid with z North, x East
ENU_FROM_SCENE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
WGS84_A, WGS84_B = 6378137.0, 6356752.314245


class TestGeodesy:
    def test_known_points(self) -> None:
        ecef = ecef_from_geodetic(np.array([[0.0, 0.0, 0.0], [90.0, 0.0, 0.0], [0.0, 90.0, 10.0]]))
        np.testing.assert_allclose(
            ecef, [[WGS84_A, 0, 0], [0, 0, WGS84_B], [0, WGS84_A + 10, 0]], atol=1e-3
        )

    def test_round_trips(self) -> None:
        points = np.array([[47.3769, 8.5417, 408.0], [-33.86, 151.21, 5.0], [64.1, -21.9, 50]])
        np.testing.assert_allclose(
            geodetic_from_ecef(ecef_from_geodetic(points)), points, atol=1e-7
        )
        enu = enu_from_geodetic(points[:1], ZURICH)
        np.testing.assert_allclose(enu, [[0.0, 0.0, 0.0]], atol=1e-6)
        offsets = np.array([[100.0, -50.0, 3.0], [-2000.0, 1500.0, -20.0]])
        np.testing.assert_allclose(
            enu_from_geodetic(geodetic_from_enu(offsets, ZURICH), ZURICH), offsets, atol=1e-6
        )

    def test_enu_axes_at_the_equator_and_prime_meridian(self) -> None:
        # East is ECEF +y, North is +z, Up is +x
        np.testing.assert_allclose(
            ecef_from_enu_rotation(Geodetic(0.0, 0.0, 0.0)),
            [[0, 0, 1], [1, 0, 0], [0, 1, 0]],
            atol=1e-9,
        )

    def test_enu_rotation_matches_pycolmap_offsets(self) -> None:
        rotation = ecef_from_enu_rotation(ZURICH)
        gps = pycolmap.GPSTransform(pycolmap.GPSTransformEllipsoid.WGS84)
        enu = np.array([[30.0, -40.0, 5.0]])
        ecef = gps.enu_to_ecef(enu, ZURICH.latitude, ZURICH.longitude, ZURICH.height)
        origin = gps.ellipsoid_to_ecef(ZURICH.array()[None])
        np.testing.assert_allclose(rotation @ enu[0], (ecef - origin)[0], atol=1e-6)


class TestGeoPose:
    def test_camera_looking_north_level(self) -> None:
        """COLMAP camera: z forward = North, y down = −Up, x right = East; the OpenGL camera
        axes (x East, y Up, z South) are a +90° turn about East: q = (sin 45°, 0, 0, cos 45°)."""
        registration = GeoRegistration(ZURICH, ENU_FROM_SCENE, np.zeros(3), 1.0)
        pose = geopose_of(Rigid3d.identity(), registration)
        assert pose.position.latitude == pytest.approx(ZURICH.latitude, abs=1e-12)
        assert pose.position.height == pytest.approx(ZURICH.height, abs=1e-6)
        s = np.sqrt(0.5)
        np.testing.assert_allclose(pose.quaternion_xyzw, [s, 0, 0, s], atol=1e-9)

    def test_round_trip_through_ecef(self) -> None:
        """A camera 3 km from the origin: its GeoPose, taken back to ECEF with pycolmap's
        geodesy, is the camera of the registered map (position and axes)."""
        rng = np.random.default_rng(3)
        yaw = np.radians(30.0)
        rotation = np.array(
            [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        )
        registration = GeoRegistration(
            ZURICH, rotation @ ENU_FROM_SCENE, np.array([5.0, -3.0, 2.0]), 2.5
        )
        q = rng.normal(size=4)
        center = np.array([1200.0, -10.0, 300.0])
        R = quaternion_to_matrix(q / np.linalg.norm(q))
        cam_from_world = Rigid3d(R, -R @ center)
        pose = geopose_of(cam_from_world, registration)

        enu0 = registration.enu_from_map(center[None])
        gps = pycolmap.GPSTransform(pycolmap.GPSTransformEllipsoid.WGS84)
        expected_ecef = gps.enu_to_ecef(enu0, ZURICH.latitude, ZURICH.longitude, ZURICH.height)
        got_ecef = gps.ellipsoid_to_ecef(pose.position.array()[None])
        np.testing.assert_allclose(got_ecef, expected_ecef, atol=1e-6)

        x, y, z, w = pose.quaternion_xyzw
        enu_from_cam = quaternion_to_matrix(np.array([w, x, y, z]))
        ecef_from_cam = ecef_from_enu_rotation(pose.position) @ enu_from_cam
        expected = ecef_from_enu_rotation(ZURICH) @ registration.rotation @ R.T @ CV_FROM_GL
        assert rotation_error_deg(ecef_from_cam, expected) < 1e-6

    def test_accuracy_adds_in_quadrature(self) -> None:
        registration = GeoRegistration(ZURICH, np.eye(3), np.zeros(3), 2.0, 0.3, 0.4)
        accuracy = geopose_accuracy(registration, 0.2, 0.3)
        # RMS 3-D error hypot(0.2 × 2, 0.3) = 0.5 m, split as if isotropic
        assert accuracy.horizontal_m == pytest.approx(0.5 * np.sqrt(2 / 3))
        assert accuracy.vertical_m == pytest.approx(0.5 * np.sqrt(1 / 3))
        assert accuracy.yaw_deg == pytest.approx(0.5)


def _street_layout(rng: np.random.Generator, count: int) -> np.ndarray:
    """Camera centres along a 200 m × 40 m street block, 1.5 ± 0.5 m above the ground, in the
    scene frame (y down), in map units of 20 m."""
    east = rng.uniform(-100.0, 100.0, count)
    north = rng.uniform(-20.0, 20.0, count)
    up = rng.normal(1.5, 0.5, count)
    return np.stack([east, -up, north], axis=1) / 20.0


class TestRegistration:
    truth = GeoRegistration(ZURICH, ENU_FROM_SCENE, np.array([12.0, -7.0, 0.5]), 20.0)

    def _noisy_gps(self, rng: np.random.Generator, centers: np.ndarray, sigma: float) -> np.ndarray:
        enu = self.truth.enu_from_map(centers) + rng.normal(0.0, sigma, centers.shape)
        return geodetic_from_enu(enu, self.truth.origin)

    def _errors(self, estimate: GeoRegistration, point: np.ndarray) -> tuple[float, float]:
        """Metres between where the two registrations put ``point``; degrees between their
        orientations (compared in ECEF: the origins differ)."""
        a = ecef_from_geodetic(estimate.geodetic_from_map(point[None]))
        b = ecef_from_geodetic(self.truth.geodetic_from_map(point[None]))
        rotation = rotation_error_deg(
            ecef_from_enu_rotation(estimate.origin) @ estimate.rotation,
            ecef_from_enu_rotation(self.truth.origin) @ self.truth.rotation,
        )
        return float(np.linalg.norm(a - b)), rotation

    def test_exact_gps_gives_the_exact_registration(self) -> None:
        rng = np.random.default_rng(0)
        centers = _street_layout(rng, 50)
        fit = estimate_registration(centers, self.truth.geodetic_from_map(centers))
        position, rotation = self._errors(fit.registration, centers[0])
        assert position < 1e-3 and rotation < 0.01  # pycolmap geodesy: ~mm round trips
        assert fit.registration.scale == pytest.approx(20.0, rel=1e-6)
        assert fit.rms_m < 1e-3 and fit.inliers.all()

    def test_gps_at_3_m_gives_half_a_metre_and_a_degree(self) -> None:
        """The issue's target: references with σ = 3 m GPS → the registration places a query
        inside the block within 0.5 m and orients it within 1°."""
        rng = np.random.default_rng(7)
        centers = _street_layout(rng, 600)
        fit = estimate_registration(centers, self._noisy_gps(rng, centers, 3.0), max_error_m=9.0)
        query = np.array([40.0, -1.6, 10.0]) / 20.0
        position, rotation = self._errors(fit.registration, query)
        assert position < 0.5, position
        assert rotation < 1.0, rotation
        assert 4.0 < fit.rms_m < 6.5  # a 3-D residual of σ = 3 m per axis: ≈ 3√3
        assert 0.05 < fit.registration.position_sigma_m < 0.5

    def test_gross_gps_errors_are_rejected(self) -> None:
        rng = np.random.default_rng(1)
        centers = _street_layout(rng, 200)
        gps = self._noisy_gps(rng, centers, 1.0)
        wrong = rng.choice(len(centers), 30, replace=False)
        enu = enu_from_geodetic(gps[wrong], ZURICH) + rng.choice([-1, 1], (30, 3)) * 60.0
        gps[wrong] = geodetic_from_enu(enu, ZURICH)
        fit = estimate_registration(centers, gps, max_error_m=5.0)
        assert not fit.inliers[wrong].any()
        assert fit.inliers.sum() >= 160
        position, rotation = self._errors(fit.registration, centers.mean(axis=0))
        assert position < 0.5 and rotation < 1.0

    def test_too_few_or_collinear_references_are_refused(self) -> None:
        centers = np.array([[0.0, 0, 0], [1, 0, 0]])
        with pytest.raises(InvalidInputError, match="at least 3"):
            estimate_registration(centers, self.truth.geodetic_from_map(centers))
        line = np.outer(np.arange(10.0), [1.0, 0.0, 0.5])
        with pytest.raises(InvalidInputError, match="line"):
            estimate_registration(line, self.truth.geodetic_from_map(line))

    def test_a_narrow_layout_against_the_gps_scatter_is_refused(self) -> None:
        """Twenty references along 30 m of a 1 m wide corridor with 3 m GPS: no usable
        heading (the rotation about the corridor is fixed to tens of degrees at best)."""
        rng = np.random.default_rng(3)
        centers = (
            np.stack(
                [rng.uniform(-15, 15, 20), rng.normal(-1.5, 0.01, 20), rng.uniform(-0.5, 0.5, 20)],
                axis=1,
            )
            / 20.0
        )
        with pytest.raises(InvalidInputError, match=r"uncertain by about \d+° \(more than 20°\)"):
            estimate_registration(centers, self._noisy_gps(rng, centers, 3.0), max_error_m=9.0)

    def test_map_and_geodetic_round_trip(self) -> None:
        points = np.array([[0.3, -0.1, 2.0], [-4.0, 0.0, 1.0]])
        np.testing.assert_allclose(
            self.truth.map_from_geodetic(self.truth.geodetic_from_map(points)), points, atol=1e-9
        )
        np.testing.assert_allclose(self.truth.map_up(), [0.0, -1.0, 0.0], atol=1e-12)


class TestGpsPrior:
    def test_distance_across_the_vertical_only(self) -> None:
        centers = np.array([[3.0, -50.0, 4.0], [6.0, 0.0, 0.0], [0.0, 9.0, 0.0]])
        prior = PositionPrior(np.zeros(3), 5.5, up=np.array([0.0, -1.0, 0.0]))
        np.testing.assert_allclose(prior.distances(centers), [5.0, 6.0, 0.0])
        descriptors = np.eye(3, dtype=np.float32)
        chosen, _ = top_k(np.ones(3, np.float32) / np.sqrt(3), descriptors, 3, centers, prior)
        assert sorted(chosen.tolist()) == [0, 2]


class TestExifGps:
    def _jpeg(self, gps: dict[int, object]) -> bytes:
        image = Image.fromarray(np.zeros((16, 24, 3), np.uint8))
        exif = Image.Exif()
        exif.get_ifd(ExifTags.IFD.GPSInfo).update(gps)
        buffer = io.BytesIO()
        image.save(buffer, "JPEG", exif=exif)
        return buffer.getvalue()

    def test_reads_degrees_minutes_seconds_and_hemispheres(self) -> None:
        data = self._jpeg(
            {
                1: "S",
                2: (33.0, 51.0, 36.0),
                3: "W",
                4: (70.0, 30.0, 0.0),
                5: b"\x01",
                6: 12.5,
                31: 4.0,
            }
        )
        assert gps_from_exif(data) == GpsFix(-33.86, -70.5, -12.5, 4.0)

    def test_none_without_gps_or_for_garbage(self) -> None:
        assert gps_from_exif(self._jpeg({})) is None
        assert gps_from_exif(b"not an image") is None

    def test_bad_fix_is_refused(self) -> None:
        with pytest.raises(InvalidInputError, match="latitude"):
            GpsFix(91.0, 0.0)
