"""EXIF read from an upload's header by Pillow: orientation and GPS, no pixel decoded, no
size check."""

from __future__ import annotations

import io
import struct
import warnings

import numpy as np
import pytest
from PIL import ExifTags, Image, ImageFile

from services.geo.gps import gps_from_exif
from services.imaging.decode import decode_image
from services.imaging.exif import header_exif
from services.localization.exif_orientation import exif_orientation

GPS = {1: "S", 2: (33.0, 51.0, 54.0), 3: "E", 4: (151.0, 12.0, 36.0), 5: b"\x01", 6: 12.5}


def _saved(image_format: str, orientation: int | None = None, gps: bool = False) -> bytes:
    exif = Image.Exif()
    if orientation is not None:
        exif[ExifTags.Base.Orientation] = orientation
    if gps:
        exif.get_ifd(ExifTags.IFD.GPSInfo).update(GPS)
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(buffer, image_format, exif=exif)
    return buffer.getvalue()


def _claiming(data: bytes, width: int, height: int) -> bytes:
    """A JPEG whose frame header claims ``width`` × ``height`` pixels."""
    sof = data.index(b"\xff\xc0")
    return data[: sof + 5] + struct.pack(">HH", height, width) + data[sof + 9 :]


class TestHeaderExif:
    @pytest.mark.parametrize("image_format", ["JPEG", "PNG"])
    def test_orientation_and_gps_match_pillows_getexif(self, image_format: str) -> None:
        data = _saved(image_format, orientation=6, gps=True)
        with Image.open(io.BytesIO(data)) as image:
            expected = image.getexif()
        exif = header_exif(data)
        assert exif[ExifTags.Base.Orientation] == expected[ExifTags.Base.Orientation] == 6
        gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
        assert gps == expected.get_ifd(ExifTags.IFD.GPSInfo) and gps[2] == GPS[2]

    @pytest.mark.parametrize("image_format", ["JPEG", "PNG"])
    @pytest.mark.parametrize("with_exif", [True, False])
    def test_no_pixel_is_decoded(
        self, image_format: str, with_exif: bool, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        """A PNG's ``getexif`` decodes the pixels when no eXIf precedes them; this does not."""

        def refuse(self: ImageFile.ImageFile) -> None:
            raise AssertionError("pixels decoded")

        data = _saved(image_format, orientation=3 if with_exif else None)
        monkeypatch.setattr(ImageFile.ImageFile, "load", refuse)
        assert exif_orientation(data) == (3 if with_exif else None)
        assert gps_from_exif(data) is None

    def test_header_claiming_a_decompression_bomb_is_read_without_warning(self) -> None:
        data = _claiming(_saved("JPEG", orientation=8, gps=True), 20_000, 10_000)
        with pytest.raises(Image.DecompressionBombError):  # over 2 × Image.MAX_IMAGE_PIXELS
            Image.open(io.BytesIO(data))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert exif_orientation(data) == 8
            fix = gps_from_exif(data)
        assert fix is not None
        assert fix.latitude == pytest.approx(-(33 + 51 / 60 + 54 / 3600))
        assert fix.longitude == pytest.approx(151 + 12 / 60 + 36 / 3600)
        assert fix.height == pytest.approx(-12.5)

    @pytest.mark.parametrize("data", [b"", b"GIF89a", b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n"])
    def test_not_an_image_has_no_exif(self, data: bytes) -> None:
        assert not header_exif(data)
        assert exif_orientation(data) is None and gps_from_exif(data) is None

    def test_png_orientation_is_the_turn_opencv_applies(self) -> None:
        data = _saved("PNG", orientation=6)
        assert decode_image(data, 10**6).shape[:2] == (64, 48)  # turned by 90°
        assert exif_orientation(data) == 6
