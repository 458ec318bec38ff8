import io
import re
import struct

import cv2
import numpy as np
import pytest
from numpy.lib import format as npy_format
from PIL import Image

from services.errors import ImageDecodeError, ImageTooLargeError, InvalidInputError
from services.geometry.camera import Camera, check_plausible, default_camera
from services.imaging.decode import decode_depth, decode_image, image_size_from_header


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
        check_plausible(cam)

    @pytest.mark.parametrize(
        ("model", "params", "message"),
        [
            ("PINHOLE", (1e-300, 1e-300, 320, 240), "fx = 1e-300 px is implausible"),
            ("SIMPLE_PINHOLE", (31.9, 320, 240), "f = 31.9 px"),
            ("PINHOLE", (500, 64_001, 320, 240), "fy = 64001 px"),
            ("PINHOLE", (500, 500, 1281, 240), "cx = 1281 px"),
            ("PINHOLE", (500, 500, 320, -481), "cy = -481 px"),
            ("RADIAL", (500, 320, 240, 0.1, -10.5), "k2 = -10.5 is implausible"),
            ("OPENCV", (500, 500, 320, 240, 0, 0, 11, 0), "p1 = 11"),
        ],
    )
    def test_implausible_refused(self, model: str, params: tuple[float, ...], message: str) -> None:
        """Issue 14: intrinsics no camera has are refused, naming the parameter."""
        with pytest.raises(InvalidInputError, match=message):
            check_plausible(Camera(model, 640, 480, params))

    @pytest.mark.parametrize(
        ("model", "params"),
        [
            ("SIMPLE_PINHOLE", (32, 320, 240)),  # 0.05 × 640: a ~169° field of view
            ("PINHOLE", (64_000, 64_000, -640, 960)),
            ("OPENCV", (300, 300, 320, 240, -0.4, 0.2, 0.001, -0.001)),
        ],
    )
    def test_plausible_edges_accepted(self, model: str, params: tuple[float, ...]) -> None:
        check_plausible(Camera(model, 640, 480, params))


def _textured(height: int, width: int) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 255, (height, width, 3), dtype=np.uint8)


def _npy_header(shape: tuple[int, ...], descr: str = "<f4", fortran: bool = False) -> bytes:
    buf = io.BytesIO()
    npy_format.write_array_header_1_0(
        buf, {"descr": descr, "fortran_order": fortran, "shape": shape}
    )
    return buf.getvalue()


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

    def test_truncated_jpeg_with_end_marker_refused(self) -> None:
        """Issue 14: libjpeg fills what is missing and only warns; the upload is refused."""
        data = _encode(".jpg", _textured(480, 640))
        with pytest.raises(ImageDecodeError, match="coded data ends before the last pixel"):
            decode_image(data[: len(data) // 3] + b"\xff\xd9", max_pixels=10**8)
        with pytest.raises(ImageDecodeError, match="no end-of-image marker"):
            decode_image(data[: len(data) // 2], max_pixels=10**8)

    @pytest.mark.parametrize(
        "params",
        [[], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1], [cv2.IMWRITE_JPEG_RST_INTERVAL, 4]],
        ids=["baseline", "progressive", "restart-intervals"],
    )
    def test_jpeg_header_claiming_more_pixels_refused(self, params: list[int]) -> None:
        image = _textured(480, 640)
        ok, buf = cv2.imencode(".jpg", image, params)
        assert ok
        data = bytearray(buf.tobytes())
        assert decode_image(bytes(data), max_pixels=10**8).shape == (480, 640, 3)
        sof = max(data.find(b"\xff\xc0"), data.find(b"\xff\xc2"))
        data[sof + 5 : sof + 9] = struct.pack(">HH", 6000, 6000)
        with pytest.raises(ImageDecodeError, match=r"truncated|corrupt"):
            decode_image(bytes(data), max_pixels=10**8)

    @pytest.mark.parametrize("encoder", ["opencv", "pillow"])
    @pytest.mark.parametrize("channels", [3, 1], ids=["colour", "grey"])
    def test_progressive_jpeg_cut_at_a_scan_boundary_refused(
        self, encoder: str, channels: int
    ) -> None:
        """Issue 14: a progressive JPEG cut after any of its scans (an end marker appended)
        decodes without a warning; it is refused, the whole stream accepted."""
        image = cv2.GaussianBlur(_textured(240, 320), (0, 0), 2)
        image = image if channels == 3 else image[:, :, 0]
        if encoder == "opencv":
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
            assert ok
            data = buf.tobytes()
        else:
            out = io.BytesIO()
            Image.fromarray(image).save(out, "JPEG", progressive=True, quality=90)
            data = out.getvalue()
        assert decode_image(data, max_pixels=10**8).shape == (240, 320, 3)
        scan_starts = [m.start() for m in re.finditer(b"\xff\xda", data)]
        assert len(scan_starts) >= 5
        for cut in scan_starts[1:]:  # after the first, second, … scan
            with pytest.raises(ImageDecodeError, match="progressive scans end"):
                decode_image(data[:cut] + b"\xff\xd9", max_pixels=10**8)

    @pytest.mark.parametrize(
        "params", [[], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]], ids=["baseline", "progressive"]
    )
    def test_jpeg_checked_and_decoded_without_a_line_on_stderr(
        self, params: list[int], capfd: pytest.CaptureFixture[str]
    ) -> None:
        """The integrity probe draws a libjpeg warning from every complete stream; it stays
        out of the process's stderr, where it would break a JSON log stream."""
        ok, buf = cv2.imencode(".jpg", _textured(480, 640), params)
        assert ok
        capfd.readouterr()
        assert decode_image(buf.tobytes(), max_pixels=10**8).shape == (480, 640, 3)
        assert capfd.readouterr().err == ""

    def test_jpeg_with_bytes_after_the_image_accepted(self) -> None:
        """Phones append data (a second image, a video) after the end-of-image marker."""
        data = _encode(".jpg", _textured(48, 64)) + b"\xff\xd8appended\xff\xd9"
        assert decode_image(data, max_pixels=10**8).shape == (48, 64, 3)

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

    @pytest.mark.parametrize(
        ("data", "message"),
        [
            (_npy_header((100_000, 100_000)) + bytes(16), "depth map is 100000×100000"),
            (_npy_header((2, 2, 1)) + bytes(16), "2-D float32 or float64"),
            (_npy_header((2, 2), "<i4") + bytes(16), "2-D float32 or float64"),
            (_npy_header((2, 2), "|O") + bytes(16), "2-D float32 or float64"),
            (_npy_header((2, 2)) + bytes(8), "does not match its header"),
            (b"\x93NUMPY\x01\x00\x04\x00{'de", "header could not be read"),
        ],
    )
    def test_npy_header_checked_before_allocating(self, data: bytes, message: str) -> None:
        """Issue 14: a 144-byte .npy claiming 40 GB is refused from its header alone."""
        with pytest.raises(InvalidInputError, match=message):
            decode_depth(data, 2, 2, 100)

    def test_npy_fortran_order_and_float64(self) -> None:
        depth = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
        buf = io.BytesIO()
        np.save(buf, np.asfortranarray(depth))
        assert np.array_equal(decode_depth(buf.getvalue(), 3, 2, 100), depth)

    def test_png_depth_of_wrong_size_refused_before_decoding(self) -> None:
        with pytest.raises(InvalidInputError, match="depth map is 3×2, the image is 2×2"):
            decode_depth(_encode(".png", np.zeros((2, 3), np.uint16)), 2, 2, 100)
