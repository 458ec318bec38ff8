import io

import cv2
import numpy as np
import pytest

from services.errors import ImageDecodeError, ImageTooLargeError, InvalidInputError
from services.geometry.camera import Camera, default_camera
from services.imaging import decode_depth, decode_image, image_size_from_header


class TestCamera:
    def test_valid_models(self) -> None:
        assert Camera("SIMPLE_PINHOLE", 640, 480, (500, 320, 240)).focal_lengths == (500, 500)
        cam = Camera("OPENCV", 640, 480, (500, 510, 321, 239, 0.1, 0.01, 0, 0))
        assert cam.principal_point == (321, 239)
        assert np.allclose(cam.K, [[500, 0, 321], [0, 510, 239], [0, 0, 1]])

    @pytest.mark.parametrize(
        ("model", "params", "message"),
        [
            ("PINHOLE", (500, 500, 320), "takes 4 params"),
            ("FISHEYE_X", (1, 2, 3), "unknown camera model"),
            ("PINHOLE", (-500, 500, 320, 240), "focal length must be positive"),
            ("PINHOLE", (np.nan, 500, 320, 240), "finite"),
        ],
    )
    def test_invalid(self, model: str, params: tuple[float, ...], message: str) -> None:
        with pytest.raises(InvalidInputError, match=message):
            Camera(model, 640, 480, params)

    def test_default_camera_is_centred(self) -> None:
        cam = default_camera(640, 480)
        assert cam.principal_point == (320.0, 240.0) and cam.focal_lengths == (768.0, 768.0)


def _encode(ext: str, image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(ext, image)
    assert ok
    return buf.tobytes()


class TestDecode:
    @pytest.mark.parametrize("ext", [".png", ".jpg"])
    def test_header_size_matches_decoder(self, ext: str) -> None:
        image = np.random.default_rng(0).integers(0, 255, (37, 53, 3), dtype=np.uint8)
        data = _encode(ext, image)
        assert image_size_from_header(data) == (53, 37)
        decoded = decode_image(data, max_pixels=10_000)
        assert decoded.shape == (37, 53, 3)
        if ext == ".png":  # lossless: channel order is RGB out of BGR in
            assert np.array_equal(decoded, image[:, :, ::-1])

    def test_progressive_jpeg_header(self) -> None:
        image = np.zeros((20, 30, 3), np.uint8)
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
        assert ok and image_size_from_header(buf.tobytes()) == (30, 20)

    def test_too_many_pixels_refused_before_decoding(self) -> None:
        data = _encode(".png", np.zeros((100, 100, 3), np.uint8))
        with pytest.raises(ImageTooLargeError, match="10000 pixels"):
            decode_image(data, max_pixels=9_999)

    @pytest.mark.parametrize("data", [b"", b"GIF89a....", b"\xff\xd8\xff\xe0\x00\x10JFIF"])
    def test_garbage(self, data: bytes) -> None:
        with pytest.raises(ImageDecodeError):
            decode_image(data, max_pixels=10**8)


class TestDepth:
    def test_png_millimetres(self) -> None:
        raw = np.array([[0, 1500], [65535, 3000]], np.uint16)
        depth = decode_depth(_encode(".png", raw), 2, 2, 100)
        assert np.allclose(depth, [[0, 1.5], [0, 3.0]])

    def test_npy_metres_invalid_to_zero(self) -> None:
        buf = io.BytesIO()
        np.save(buf, np.array([[1.0, np.nan], [-2.0, 4.5]], np.float32))
        assert np.allclose(decode_depth(buf.getvalue(), 2, 2, 100), [[1.0, 0], [0, 4.5]])

    def test_eight_bit_png_refused(self) -> None:
        with pytest.raises(InvalidInputError, match="16-bit"):
            decode_depth(_encode(".png", np.zeros((2, 2), np.uint8)), 2, 2, 100)
