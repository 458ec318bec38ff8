"""Deterministic synthetic scenes with exact ground truth, for tests and demos.

A room of textured planes (floor, ceiling, three walls and two free-standing panels that give
parallax) is ray-cast per pixel with numpy: every pixel's ray is intersected with every plane,
the nearest hit wins, and its texture is sampled with ``cv2.remap``. Intrinsics, poses and
depth are therefore exact. World frame: x right, y down, z forward; cameras look along +z.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import numpy as np

from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.types import Float32Array, FloatArray, UInt8Array

TEXTURE_SIZE = 1024


@dataclass(frozen=True)
class TexturedPlane:
    """A rectangle ``origin + a·u + b·v`` for a, b in [0, 1] carrying an RGB texture."""

    origin: FloatArray
    u: FloatArray
    v: FloatArray
    texture: UInt8Array


@dataclass(frozen=True)
class SyntheticView:
    """A rendered view: RGB image (H, W, 3) uint8 and z-depth (H, W) float32 metres (0 = none)."""

    name: str
    camera: Camera
    cam_from_world: Rigid3d
    image: UInt8Array
    depth: Float32Array


def procedural_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> UInt8Array:
    """Rich, non-repeating texture: multi-scale noise under random coloured shapes."""
    base = np.zeros((size, size, 3), np.float32)
    for cells in (4, 16, 64):
        noise = rng.random((cells, cells, 3)).astype(np.float32)
        base += cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC) * (64 / cells**0.3)
    image = np.clip(base / base.max() * 200, 0, 255).astype(np.uint8)
    for _ in range(350):
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        center = tuple(int(c) for c in rng.integers(0, size, 2))
        kind = rng.integers(0, 3)
        if kind == 0:
            axes = tuple(int(a) for a in rng.integers(4, 40, 2))
            angle = float(rng.uniform(0, 180))
            cv2.ellipse(image, center, axes, angle, 0, 360, color, -1, cv2.LINE_AA)
        elif kind == 1:
            corner = tuple(int(c + d) for c, d in zip(center, rng.integers(6, 50, 2), strict=True))
            cv2.rectangle(image, center, corner, color, -1, cv2.LINE_AA)
        else:
            end = tuple(int(c + d) for c, d in zip(center, rng.integers(-60, 60, 2), strict=True))
            cv2.line(image, center, end, color, int(rng.integers(2, 6)), cv2.LINE_AA)
    return np.asarray(cv2.GaussianBlur(image, (0, 0), 1.0), dtype=np.uint8)


class SyntheticScene:
    """A textured room about 12 × 6 × 14 units; ``extent`` is its bounding-box diagonal.

    Args:
        seed: fixes the textures and every sampled pose.
        width, height, focal: intrinsics of the rendered views (PINHOLE, principal point at the
            image centre in COLMAP convention).
    """

    def __init__(self, seed: int = 0, width: int = 640, height: int = 480, focal: float = 500.0):
        self.seed = seed
        self.camera = Camera("PINHOLE", width, height, (focal, focal, width / 2.0, height / 2.0))
        rng = np.random.default_rng(seed)

        def plane(origin: list[float], u: list[float], v: list[float]) -> TexturedPlane:
            return TexturedPlane(
                np.array(origin, float),
                np.array(u, float),
                np.array(v, float),
                procedural_texture(rng),
            )

        self.planes = [
            plane([-6, -3, 8], [12, 0, 0], [0, 6, 0]),  # back wall
            plane([-6, -3, -6], [0, 0, 14], [0, 6, 0]),  # left wall
            plane([6, -3, 8], [0, 0, -14], [0, 6, 0]),  # right wall
            plane([-6, 3, 8], [12, 0, 0], [0, 0, -14]),  # floor
            plane([-6, -3, -6], [12, 0, 0], [0, 0, 14]),  # ceiling
            plane([-3.5, -1.5, 4.0], [2.5, 0, 0.5], [0, 3.5, 0]),  # free-standing panel
            plane([1.2, -2.0, 5.5], [2.5, 0, -0.6], [0, 3.5, 0]),  # free-standing panel
        ]
        corners = np.array([[-6, -3, -6], [6, 3, 8]], float)
        self.extent = float(np.linalg.norm(corners[1] - corners[0]))

    def render(
        self, cam_from_world: Rigid3d, camera: Camera | None = None
    ) -> tuple[UInt8Array, Float32Array]:
        """Ray-cast the scene through ``camera`` (a pinhole; default: the scene's): (H, W, 3)
        RGB uint8 image and (H, W) float32 z-depth."""
        cam = camera or self.camera
        # pixel centres in COLMAP convention, as rays with unit z in camera coordinates
        u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        rays_cam = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(cam.K).T
        rays_world = rays_cam @ cam_from_world.rotation  # R.T @ r for each ray
        center = cam_from_world.center
        image = np.zeros((cam.height, cam.width, 3), np.uint8)
        depth = np.full((cam.height, cam.width), np.inf, np.float32)
        for p in self.planes:
            normal = np.cross(p.u, p.v)
            denom = rays_world @ normal
            with np.errstate(divide="ignore", invalid="ignore"):
                s = ((p.origin - center) @ normal) / denom
            hit = center + s[..., None] * rays_world - p.origin
            a = hit @ p.u / (p.u @ p.u)
            b = hit @ p.v / (p.v @ p.v)
            visible = (s > 1e-3) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1) & (s < depth)
            if not visible.any():
                continue
            size = p.texture.shape[0]
            map_x = (a * size - 0.5).astype(np.float32)
            map_y = (b * size - 0.5).astype(np.float32)
            sampled = cv2.remap(
                p.texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
            )
            image[visible] = sampled[visible]
            depth[visible] = s[visible]
        depth[~np.isfinite(depth)] = 0.0
        return image, depth

    def sample_pose(self, rng: np.random.Generator) -> Rigid3d:
        """A camera inside the room's front half looking roughly towards the back wall."""
        center = rng.uniform([-2.5, -1.0, -3.0], [2.5, 1.0, 1.0])
        yaw, pitch, roll = np.radians(rng.uniform([-20, -8, -5], [20, 8, 5]))
        R_yaw = cv2.Rodrigues(np.array([0.0, yaw, 0.0]))[0]
        R_pitch = cv2.Rodrigues(np.array([pitch, 0.0, 0.0]))[0]
        R_roll = cv2.Rodrigues(np.array([0.0, 0.0, roll]))[0]
        world_from_cam_R = R_yaw @ R_pitch @ R_roll
        R = world_from_cam_R.T
        return Rigid3d(R, -R @ center)

    def views(self, count: int, stream: int, prefix: str) -> list[SyntheticView]:
        """``count`` rendered views with poses drawn from random stream ``stream`` (so reference
        and query sets drawn from different streams never coincide)."""
        rng = np.random.default_rng([self.seed, stream])
        out = []
        for i in range(count):
            pose = self.sample_pose(rng)
            image, depth = self.render(pose)
            out.append(SyntheticView(f"{prefix}{i:04d}.png", self.camera, pose, image, depth))
        return out

    def forward_views(self, distances: list[float], prefix: str) -> list[SyntheticView]:
        """Frames of a camera moving straight ahead, as from a driving vehicle: centres at
        ``(0, 0, z)`` for each z in ``distances``, every frame looking along that line (+z,
        no rotation), so each centre lies on the others' optical axes."""
        out = []
        for i, z in enumerate(distances):
            pose = Rigid3d(np.eye(3), np.array([0.0, 0.0, -float(z)]))
            image, depth = self.render(pose)
            out.append(SyntheticView(f"{prefix}{i:04d}.png", self.camera, pose, image, depth))
        return out


def unrelated_image(seed: int, width: int = 640, height: int = 480) -> UInt8Array:
    """An image of texture that appears nowhere in any ``SyntheticScene``."""
    texture = procedural_texture(np.random.default_rng([seed, 999_983]), size=max(width, height))
    return np.ascontiguousarray(texture[:height, :width])


def encode_png(image: UInt8Array) -> bytes:
    """PNG bytes of an (H, W, 3) RGB or (H, W) uint8/uint16 image."""
    data = image[:, :, ::-1] if image.ndim == 3 else image
    ok, buf = cv2.imencode(".png", data)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def encode_jpeg(image: UInt8Array, orientation: int | None = None, quality: int = 95) -> bytes:
    """JPEG bytes of an (H, W, 3) RGB image, with an EXIF block holding only the orientation
    tag (1–8) when ``orientation`` is given: the pixels are stored as they are and a viewer
    turns (or mirrors) them for display, as phones save portrait photos."""
    ok, buf = cv2.imencode(".jpg", image[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    data = buf.tobytes()
    if orientation is None:
        return data
    # little-endian TIFF: header, one IFD with one SHORT entry (tag 0x0112), no next IFD
    tiff = b"II*\x00" + struct.pack("<IHHHIHHI", 8, 1, 0x0112, 3, 1, orientation, 0, 0)
    payload = b"Exif\x00\x00" + tiff
    app1 = b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    return data[:2] + app1 + data[2:]


def encode_depth_png(depth: Float32Array) -> bytes:
    """16-bit PNG in millimetres of a depth map in metres (0 = unknown)."""
    return encode_png(np.clip(np.round(depth * 1000.0), 0, 65534).astype(np.uint16))
