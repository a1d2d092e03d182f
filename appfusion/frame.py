"""Frames, camera intrinsics and rigid transforms: the data every source delivers.

Conventions
-----------
- Camera frames follow OpenCV: x right, y down, z forward; pixel (u, v) = (column, row), the centre
  of the top-left pixel is (0, 0).
- Depth is in metres, float32, NaN where invalid. IR is float32 in linear sensor units (counts).
- RGB is either sRGB-encoded uint8 (``rgb_encoding == "srgb8"``) or linear float32 in [0, 1]
  (``rgb_encoding == "linear"``); :meth:`Frame.rgb_linear` returns linear float32 for both.
- Poses are 4x4 float64 camera-to-world matrices of the *depth* camera. The world frame of a scan
  is the marker frame (paper §4.1, §4.3) once markers have been found.
- Extrinsics ``depth_to_ir`` and ``depth_to_rgb`` map points from the depth camera frame into the
  IR / RGB camera frames (4x4, metres).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .errors import AppFusionError

STREAMS = ("depth", "ir", "rgb")
RGB_ENCODINGS = ("srgb8", "linear")
#: Rec. 709 luminance weights of linear RGB (the one grey value of a colour everywhere it is needed)
REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of one camera stream.

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    fx, fy : float
        Focal lengths in pixels.
    cx, cy : float
        Principal point in pixels (OpenCV convention: pixel centres at integers).
    dist : tuple of float
        OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]); empty means none.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = ()

    def __post_init__(self):
        vals = (self.fx, self.fy, self.cx, self.cy)
        if self.width <= 0 or self.height <= 0:
            raise AppFusionError(f"intrinsics: image size must be positive, got {self.width}x{self.height}")
        if not all(np.isfinite(v) for v in vals) or self.fx <= 0 or self.fy <= 0:
            raise AppFusionError(f"intrinsics: focal lengths must be finite and positive, got fx={self.fx}, fy={self.fy}")

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width), the numpy shape of an image of this camera."""
        return (self.height, self.width)

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """Intrinsics of the same camera resampled to ``width`` x ``height`` pixels."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy,
                          (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, self.dist)

    def to_json(self) -> dict[str, Any]:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "dist": list(self.dist)}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "Intrinsics":
        try:
            return cls(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]),
                       float(d["cx"]), float(d["cy"]), tuple(float(x) for x in d.get("dist", ())))
        except KeyError as e:
            raise AppFusionError(f"intrinsics: missing field {e.args[0]!r}") from None

    def rays(self) -> np.ndarray:
        """Unit-z ray directions of every pixel, shape (H, W, 3), float32 (distortion ignored)."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float32), np.arange(self.height, dtype=np.float32))
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """Camera-frame 3-D points of a depth image (metres), shape (H, W, 3); NaN where depth is NaN."""
        if depth.shape != self.shape:
            raise AppFusionError(f"depth image of shape {depth.shape} does not match intrinsics {self.shape}")
        return self.rays() * depth[..., None]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project camera-frame points (N, 3) to pixel coordinates (N, 2); also returns z (N,)."""
        z = points[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * points[:, 0] / z + self.cx, self.fy * points[:, 1] / z + self.cy], axis=1)
        return uv, z


def make_pose(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """4x4 rigid transform from a rotation matrix and a translation (metres)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points of shape (..., 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def _srgb_decode(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.float32, copy=False)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


#: sRGB decoding of the 256 uint8 codes (the same float32 arithmetic as for float input)
_SRGB8_TO_LINEAR = _srgb_decode(np.arange(256, dtype=np.float32) / 255.0)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding; input uint8 or float in [0, 1], output float32 in [0, 1].

    uint8 input is decoded by a 256-entry table (one gather: ~10x faster than the power law on a
    640 x 480 frame, identical values)."""
    x = np.asarray(x)
    if x.dtype == np.uint8:
        return _SRGB8_TO_LINEAR[x]
    return _srgb_decode(x)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding of linear float values, clipped to [0, 1], float32."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


@dataclass
class Frame:
    """One time instant of a capture: any subset of depth, IR and RGB images.

    Attributes
    ----------
    index : int
        Position of the frame in its source, from 0.
    timestamp : float
        Seconds, monotonic within a session.
    depth : (H, W) float32 ndarray or None
        Metres, NaN = invalid.
    ir : (H, W) float32 ndarray or None
        Linear IR sensor units.
    rgb : (H, W, 3) ndarray or None
        uint8 sRGB or float32 linear, as ``rgb_encoding`` says.
    rgb_encoding : {"srgb8", "linear"}
    depth_intrinsics, ir_intrinsics, rgb_intrinsics : Intrinsics or None
    depth_to_ir, depth_to_rgb : (4, 4) ndarray
        Extrinsics from the depth camera to the IR / RGB cameras.
    pose : (4, 4) ndarray or None
        Ground-truth (or recorded) camera-to-world pose of the depth camera, if known.
    pass_name : str or None
        The scanning pass this frame belongs to ("environment", "geometry", "ir", "rgb", ...).
    emitter : bool or None
        IR emitter (projector) state when the IR image was taken, where known.
    """

    index: int
    timestamp: float
    depth: np.ndarray | None = None
    ir: np.ndarray | None = None
    rgb: np.ndarray | None = None
    rgb_encoding: str = "srgb8"
    depth_intrinsics: Intrinsics | None = None
    ir_intrinsics: Intrinsics | None = None
    rgb_intrinsics: Intrinsics | None = None
    depth_to_ir: np.ndarray = field(default_factory=lambda: np.eye(4))
    depth_to_rgb: np.ndarray = field(default_factory=lambda: np.eye(4))
    pose: np.ndarray | None = None
    pass_name: str | None = None
    emitter: bool | None = None

    def __post_init__(self):
        if self.rgb_encoding not in RGB_ENCODINGS:
            raise AppFusionError(f"frame {self.index}: unknown rgb_encoding {self.rgb_encoding!r}")

    @property
    def streams(self) -> tuple[str, ...]:
        """Names of the streams present in this frame."""
        return tuple(s for s in STREAMS if getattr(self, s) is not None)

    def rgb_linear(self) -> np.ndarray | None:
        """RGB as linear float32 in [0, 1] (decoding sRGB when needed), or None."""
        if self.rgb is None:
            return None
        if self.rgb_encoding == "srgb8":
            return srgb_to_linear(self.rgb)
        return self.rgb.astype(np.float32, copy=False)

    def replace(self, **changes) -> "Frame":
        """A copy with some fields changed (images are not copied)."""
        return replace(self, **changes)
