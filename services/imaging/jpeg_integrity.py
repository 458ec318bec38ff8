"""Whether a JPEG codes every pixel it declares. libjpeg decodes a stream whose coded data
runs out (a file cut short with an end marker appended, a header claiming more pixels than are
coded) without an error: it fills the missing blocks and only prints a warning. The checks here
find such streams from the marker structure and from the decoder itself.

A progressive stream cut exactly after one of its scans decodes without any warning; it is
found from what its scans code: a complete stream (as every common encoder writes it) brings
each coefficient of each component down to its last bit (successive approximation Al = 0)."""

from __future__ import annotations

import io
import math
import re
import struct
from dataclasses import dataclass, field

import numpy as np
from PIL import JpegImagePlugin

from services.errors import ImageDecodeError
from services.types import UInt8Array

_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_PROGRESSIVE_SOF = {0xC2, 0xC6, 0xCA, 0xCE}
_SOS, _EOI, _DRI = 0xDA, 0xD9, 0xDD
# in coded data 0xFF is followed by 0x00 (a stuffed byte), a restart marker (0xD0-0xD7) or a
# fill byte (0xFF); any other byte after it makes the marker that ends the scan
_SCAN_END = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
_RESTART = re.compile(rb"\xff[\xd0-\xd7]")
# bytes slipped in at the end of every scan: a decoder that has all of a scan's blocks coded
# skips them as extraneous; one whose data ran out reads them as coefficients instead
_PROBE = bytes(range(1, 255)) * 2


@dataclass
class _Layout:
    """What the marker walk found: frame size, sampling per component id, restart interval,
    and per scan its component ids, where its coded data ends and how many restart markers it
    holds."""

    width: int = 0
    height: int = 0
    progressive: bool = False
    sampling: dict[int, tuple[int, int]] = field(default_factory=dict)
    restart_interval: int = 0
    scan_ends: list[int] = field(default_factory=list)
    short_scans: int = 0
    # progressive: per component id, per coefficient, the lowest bit coded so far (64 = none)
    lowest_bit: dict[int, list[int]] = field(default_factory=dict)

    def progressive_incomplete(self) -> bool:
        """Whether a progressive stream leaves a coefficient of a component short of its
        last bit (a stream cut at a scan boundary)."""
        return self.progressive and any(
            max(self.lowest_bit.get(component, [64])) > 0 for component in self.sampling
        )


def check_jpeg_complete(data: bytes) -> None:
    """Refuse a JPEG whose coded data ends before its last block.

    Raises:
        ImageDecodeError: no end-of-image marker, fewer restart intervals than blocks need,
            progressive scans that stop before the last bit of every coefficient, or blocks
            that the decoder filled in for want of data.
    """
    layout = _walk(data)
    if layout.short_scans:
        raise ImageDecodeError("truncated JPEG: a scan has fewer restart intervals than blocks")
    if layout.progressive_incomplete():
        raise ImageDecodeError(
            "truncated JPEG: the progressive scans end before every coefficient is complete"
        )
    pieces, start = [], 0
    for end in layout.scan_ends:
        pieces += [data[start:end], _PROBE]
        start = end
    probed = b"".join([*pieces, data[start:]])
    # a sequential stream's missing blocks show in their DC terms, so 1/8 scale (all data still
    # entropy-decoded, little computed) suffices; a progressive stream's later scans refine the
    # AC terms only, which need the full-size decode
    reduced = not layout.progressive
    plain, probe = _pixels(data, reduced), _pixels(probed, reduced)
    if plain is None or probe is None or not np.array_equal(plain, probe):
        raise ImageDecodeError("corrupt JPEG: its coded data ends before the last pixel")


def _pixels(data: bytes, reduced: bool) -> UInt8Array | None:
    """The decoded samples (at 1/8 scale when ``reduced``), None when undecodable.

    Pillow decodes, with libjpeg-turbo as OpenCV's decoder does: it keeps libjpeg's warnings
    to itself, where OpenCV's decoder prints each to the process's stderr (the probe draws
    one, "extraneous bytes", from every complete stream). The reader is constructed
    directly, which leaves the pixel limit to the caller, as ``services.imaging.exif`` does.
    """
    try:
        with JpegImagePlugin.JpegImageFile(io.BytesIO(data)) as image:
            scale = 8 if reduced else 1
            # a colour stream left in YCbCr: no colour conversion, the same comparison
            image.draft("YCbCr", (max(1, image.width // scale), max(1, image.height // scale)))
            image.load()
            return np.asarray(image)
    except (OSError, SyntaxError, ValueError, EOFError, struct.error):
        return None


def _walk(data: bytes) -> _Layout:
    """The marker structure of the first image in ``data`` (bytes after its end-of-image marker,
    such as a phone's appended secondary image, are not looked at)."""
    layout = _Layout()
    i = 2
    while i + 1 < len(data):
        marker = data[i + 1]
        if data[i] != 0xFF or marker == 0xFF:  # stray or fill byte, skipped as libjpeg does
            i += 1
            continue
        if marker == _EOI:
            return layout
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            i += 2
            continue
        if i + 4 > len(data):
            break
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        segment = data[i + 4 : i + 2 + length]
        i += 2 + length
        if marker in _SOF and len(segment) >= 6:
            _read_frame(layout, marker, segment)
        elif marker == _DRI and len(segment) >= 2:
            (layout.restart_interval,) = struct.unpack(">H", segment[:2])
        elif marker == _SOS:
            scan_end = _SCAN_END.search(data, i)
            if scan_end is None:
                break
            restarts = len(_RESTART.findall(data, i, scan_end.start()))
            components = [segment[1 + 2 * k] for k in range(segment[0])] if segment else []
            if restarts < _restarts_needed(layout, components):
                layout.short_scans += 1
            if layout.progressive:
                _record_coefficients(layout, segment, components)
            i = scan_end.start()
            layout.scan_ends.append(i)
    raise ImageDecodeError("truncated JPEG: no end-of-image marker")


def _read_frame(layout: _Layout, marker: int, segment: bytes) -> None:
    layout.height, layout.width = struct.unpack(">HH", segment[1:5])
    layout.progressive = marker in _PROGRESSIVE_SOF
    for k in range(segment[5]):
        component = segment[6 + 3 * k : 9 + 3 * k]
        if len(component) == 3:
            layout.sampling[component[0]] = (component[1] >> 4, component[1] & 0x0F)


def _record_coefficients(layout: _Layout, segment: bytes, components: list[int]) -> None:
    """Note the coefficients (spectral selection Ss…Se) and bit (Al) a progressive scan codes."""
    tail = 1 + 2 * len(components)
    if len(segment) < tail + 3:
        return
    start, end, al = segment[tail], min(segment[tail + 1], 63), segment[tail + 2] & 0x0F
    for component in components:
        bits = layout.lowest_bit.setdefault(component, [64] * 64)
        for k in range(start, end + 1):
            bits[k] = min(bits[k], al)


def _restarts_needed(layout: _Layout, components: list[int]) -> int:
    """Restart markers a complete scan of these components holds: one between intervals."""
    if not layout.restart_interval or not layout.sampling or not components:
        return 0
    h_max = max(h for h, _ in layout.sampling.values())
    v_max = max(v for _, v in layout.sampling.values())
    if len(components) > 1:  # interleaved: MCUs of h_max × v_max blocks
        units = math.ceil(layout.width / (8 * h_max)) * math.ceil(layout.height / (8 * v_max))
    else:  # one component: its own blocks
        h, v = layout.sampling.get(components[0], (h_max, v_max))
        units = math.ceil(math.ceil(layout.width * h / h_max) / 8) * math.ceil(
            math.ceil(layout.height * v / v_max) / 8
        )
    return max(math.ceil(units / layout.restart_interval) - 1, 0)
