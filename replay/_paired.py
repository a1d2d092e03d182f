"""Shared machinery of the folder readers of foreign RGB-D recordings (TUM, Redwood/Open3D).

Both formats are lists of (timestamp, depth image, colour image) with optional poses: a
:class:`PairedReader` holds such a list and decodes frames on demand, with the same error and
``skip_bad`` behaviour as :class:`replay.session.SessionReader`.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from appfusion.errors import AppFusionError, SessionFormatError
from appfusion.frame import Frame, Intrinsics
from appfusion.source import IndexedRecording, StreamCaps

from .session import _rates, read_image

#: PrimeSense / Kinect v1 default intrinsics at 640x480 (TUM's "ROS default", Open3D's
#: PrimeSenseDefault): fx = fy = 525, cx = 319.5, cy = 239.5 pixels
PRIMESENSE_DEFAULT = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)


@dataclass
class Item:
    """One frame of a paired recording: where its images are and which index line named them."""

    timestamp: float
    depth: Path | None
    rgb: Path | None
    depth_index: Path | None = None
    depth_line: int | None = None
    rgb_index: Path | None = None
    rgb_line: int | None = None
    rgb_timestamp: float | None = None


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk without decoding, or None if not a readable PNG."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of a PNG (header only) or any other image OpenCV reads (decoded)."""
    s = png_size(path)
    if s is not None:
        return s
    try:
        img = read_image(path)
    except SessionFormatError:
        return None
    return img.shape[1], img.shape[0]


def read_camera_json(path: Path) -> Intrinsics:
    """Intrinsics from a camera JSON file.

    Accepted layouts: Open3D's ``PinholeCameraIntrinsic`` JSON (``width``, ``height`` and a 9-element
    ``intrinsic_matrix`` in column-major order), or ``width``, ``height``, ``fx``, ``fy``, ``cx``,
    ``cy`` (optionally ``dist``) as :meth:`Intrinsics.to_json` writes, optionally nested under a
    ``"depth"`` key.

    Raises
    ------
    SessionFormatError
        Naming the file, if it is not JSON or lacks a field.
    """
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SessionFormatError(path, "camera file is missing") from None
    except UnicodeDecodeError:
        raise SessionFormatError(path, "camera file is not UTF-8 text") from None
    except json.JSONDecodeError as e:
        raise SessionFormatError(path, f"not valid JSON: {e.msg}", e.lineno) from None
    if isinstance(d, dict) and isinstance(d.get("depth"), dict):
        d = d["depth"]
    if not isinstance(d, dict):
        raise SessionFormatError(path, "expected a JSON object with camera intrinsics")
    try:
        if "intrinsic_matrix" in d:
            m = np.asarray(d["intrinsic_matrix"], dtype=np.float64)
            if m.size != 9:
                raise SessionFormatError(path, f"intrinsic_matrix has {m.size} numbers, expected 9")
            K = m.reshape(3, 3).T  # column-major in Open3D's JSON
            return Intrinsics(int(d["width"]), int(d["height"]), float(K[0, 0]), float(K[1, 1]),
                              float(K[0, 2]), float(K[1, 2]))
        return Intrinsics.from_json(d)
    except KeyError as e:
        raise SessionFormatError(path, f"missing field {e.args[0]!r}") from None
    except (AppFusionError, TypeError, ValueError, OverflowError) as e:
        if isinstance(e, SessionFormatError):
            raise
        raise SessionFormatError(path, f"bad camera intrinsics: {e}") from None


class PairedReader(IndexedRecording):
    """A recording of depth + colour image pairs (TUM, Redwood) as a seekable Source.

    Subclasses fill :attr:`items`, :attr:`poses`, :attr:`_intrinsics`, :attr:`units_per_m` and
    :attr:`_meta` in their constructor, then call :meth:`_finish`.
    """

    format_name = "paired"

    def __init__(self, path: str | os.PathLike, skip_bad: bool = False):
        super().__init__()
        self.path = Path(path)
        self.skip_bad = bool(skip_bad)
        self.bad_frames: list[tuple[str, int | None, str]] = []
        self.items: list[Item] = []
        self.poses: list[np.ndarray | None] = []
        self.units_per_m = 5000.0
        self._intrinsics: dict[str, Intrinsics] = {}
        self._meta: dict[str, Any] = {}
        self.depth_to_rgb = np.eye(4)
        self._pos = 0

    def _problem(self, path, line, reason) -> None:
        if not self.skip_bad:
            raise SessionFormatError(path, reason, line)
        self.bad_frames.append((os.fspath(path), line, reason))

    def _finish(self) -> None:
        """Drop items whose files are missing (or raise), set caps."""
        keep, poses = [], []
        for k, it in enumerate(self.items):
            ok = True
            for s, p, index, line in (("depth", it.depth, it.depth_index, it.depth_line),
                                      ("rgb", it.rgb, it.rgb_index, it.rgb_line)):
                if p is not None and not p.is_file():
                    if index is None:
                        self._problem(p, None, f"{s} image does not exist")
                    else:
                        self._problem(index, line, f"{s} image {p} does not exist")
                    ok = False
                    break
            if ok:
                keep.append(it)
                poses.append(self.poses[k] if k < len(self.poses) else None)
        self.items, self.poses = keep, poses
        streams = [s for s in ("depth", "rgb") if any(getattr(i, s) is not None for i in self.items)]
        self._caps = StreamCaps.all_together(streams, _rates(self.stream_timestamps()))

    # -- Source API ----------------------------------------------------------------------------
    @property
    def caps(self) -> StreamCaps:
        return self._caps

    @property
    def intrinsics(self) -> dict[str, Intrinsics]:
        return dict(self._intrinsics)

    @property
    def meta(self) -> dict[str, Any]:
        return {**self._meta, "format_name": self.format_name, "depth_units_per_m": self.units_per_m,
                "path": str(self.path)}

    def __len__(self) -> int:
        return len(self.items)


    @property
    def timestamps(self) -> np.ndarray:
        """(N,) frame timestamps in seconds."""
        return np.array([it.timestamp for it in self.items], dtype=np.float64)

    def stream_timestamps(self) -> dict[str, np.ndarray]:
        """Timestamps of the images of each stream (seconds), without decoding."""
        out = {}
        for s in ("depth", "rgb"):
            ts = [(it.rgb_timestamp if s == "rgb" and it.rgb_timestamp is not None else it.timestamp)
                  for it in self.items if getattr(it, s) is not None]
            if ts:
                out[s] = np.asarray(ts, dtype=np.float64)
        return out

    def __getitem__(self, index: int) -> Frame:
        return self.frame(index)

    def _load(self, it: Item, stream: str) -> np.ndarray:
        p = getattr(it, stream)
        line, index = (it.depth_line, it.depth_index) if stream == "depth" else (it.rgb_line, it.rgb_index)
        img = read_image(p, line, index) if index is not None else read_image(p)
        want = self._intrinsics.get(stream)
        if want is not None and img.shape[:2] != want.shape:
            raise SessionFormatError(p, f"image is {img.shape[1]}x{img.shape[0]}, the camera intrinsics are "
                                        f"{want.width}x{want.height}")
        return img

    def frame(self, index: int) -> Frame:
        """Decode frame ``index``: depth float32 metres (NaN invalid), RGB uint8 sRGB (or linear float32
        for 16-bit colour PNGs), pose if known."""
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"{self.name}: frame {index} out of range (0..{n - 1})")
        index %= n
        it = self.items[index]
        depth = rgb = None
        enc = "srgb8"
        if it.depth is not None:
            raw = self._load(it, "depth")
            if raw.ndim != 2 or raw.dtype != np.uint16:
                raise SessionFormatError(it.depth, f"depth image is {raw.dtype} with shape {raw.shape}, expected a "
                                                   f"16-bit single-channel PNG (colour and depth swapped?)")
            depth = raw.astype(np.float32) / np.float32(self.units_per_m)
            depth[raw == 0] = np.nan
        if it.rgb is not None:
            raw = self._load(it, "rgb")
            if raw.ndim == 2:
                raw = np.repeat(raw[..., None], 3, axis=2)
            if raw.dtype == np.uint8:
                rgb = raw
            elif raw.dtype == np.uint16:
                rgb, enc = raw.astype(np.float32) / np.float32(65535.0), "linear"
            else:
                raise SessionFormatError(it.rgb, f"colour image has unsupported type {raw.dtype}")
        pose = self.poses[index] if index < len(self.poses) else None
        return Frame(index=index, timestamp=float(it.timestamp), depth=depth, rgb=rgb, rgb_encoding=enc,
                     depth_intrinsics=self._intrinsics.get("depth"), rgb_intrinsics=self._intrinsics.get("rgb"),
                     depth_to_rgb=self.depth_to_rgb.copy(), pose=None if pose is None else pose.copy())


def default_intrinsics(sample: Path | None) -> Intrinsics:
    """PrimeSense default intrinsics, rescaled to the size of ``sample`` if it is not 640x480."""
    size = image_size(sample) if sample is not None else None
    if size is None or size == (640, 480):
        return PRIMESENSE_DEFAULT
    return PRIMESENSE_DEFAULT.scaled(*size)
