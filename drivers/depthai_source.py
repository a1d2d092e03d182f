"""Luxonis OAK-D / OAK-D Pro cameras through depthai v3, as an :class:`appfusion.source.Source`.

What an OAK gives the paper's pipeline (Wu & Zhou 2015):

- ``depth``: stereo depth of the two global-shutter mono cameras, aligned to the RGB camera by
  default (``StereoDepth.setDepthAlign(CAM_A)``), float32 metres with NaN where invalid (§4.1);
- ``ir``: the left mono camera (IR-sensitive on an OAK-D Pro), float32 counts (§5.1-5.2);
- ``rgb``: the colour camera, uint8 sRGB (§5.3);
- calibration read from the device's EEPROM (``Device.readCalibration()``): intrinsics,
  distortion and extrinsics of the three cameras.

The OAK-D Pro has an IR dot projector (for stereo on texture-less surfaces) and an IR flood LED.
The paper's BRDF fusion needs IR images lit by one compact source and no dot pattern; stereo needs
the dots. With ``illumination="alternate"`` a Script node on the device switches between the two on
every frame (Luxonis' "mono preview alternate" recipe), and the host labels each mono frame by its
content (:func:`dot_score`: dot frames have far more high-frequency energy than flood frames, which
is robust to the one-frame latency of the switch). Each output :class:`~appfusion.frame.Frame`
then pairs the depth of a dot frame with the IR image of the neighbouring flood frame
(``Frame.emitter = True``: the flood LED was on; ``meta["ir_illuminator"] = "flood"``).

The code is split so that everything except opening the device runs without hardware:

- :func:`build_device_graph` builds the on-device part of a pipeline (cameras, stereo, script);
- :class:`_Tap` host nodes turn ``ImgFrame`` messages into :class:`Packet` objects
  (:func:`depth_from_imgframe`, :func:`ir_from_imgframe`, :func:`rgb_from_imgframe`);
- :class:`FrameAssembler` (pure Python) groups packets by sequence number, matches RGB by time,
  classifies illumination and emits Frames;
- :func:`geometry_from_calibration` converts a ``dai.CalibrationHandler`` to intrinsics/extrinsics.

``DepthAISource(replay_dir=DIR)`` replays ``.mcap`` files written by ``record_dir=DIR`` (or any
graph of host nodes given as ``build_graph``) through the same host side with
``dai.Pipeline(False)``, which is how the tests exercise it.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import math
import os
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from appfusion.errors import DeviceError, SourceError
from appfusion.frame import Frame, Intrinsics, invert_pose
from appfusion.source import Control, Source, StreamCaps

__all__ = [
    "DepthAISource", "DepthAIConfig", "Packet", "FrameAssembler", "StreamGeometry", "dot_score",
    "depth_from_imgframe", "ir_from_imgframe", "rgb_from_imgframe", "packet_from_imgframe",
    "geometry_from_calibration", "nominal_geometry", "build_device_graph", "alternation_script",
    "list_devices", "ILLUMINATIONS", "TAP_STREAMS",
]

#: illumination modes of an OAK-D Pro ("auto": alternate when both depth and IR are wanted)
ILLUMINATIONS = ("auto", "alternate", "dots", "flood", "off")
#: names of the message streams the host side taps (the mono ``left`` camera is our IR stream)
TAP_STREAMS = ("depth", "left", "rgb")
#: nominal position of the OAK-D Pro IR illuminators in the RGB (= aligned depth) camera frame, metres:
#: the flood LED and the dot projector sit beside the colour camera between the mono pair. Pass a
#: measured ``emitter_position_m`` for better BRDF fits.
OAK_D_PRO_EMITTER_M = (0.0, -0.015, 0.0)


def _dai():
    try:
        import depthai as dai
    except ImportError as e:  # pragma: no cover - a dependency of appfusion
        raise DeviceError(f"depthai: the 'depthai' package is not installed ({e}); pip install 'depthai>=3.12,<4'") \
            from None
    return dai


def list_devices() -> list[dict[str, Any]]:
    """Attached OAK devices: ``[{"id", "name", "state", "protocol"}]`` (empty without hardware)."""
    dai = _dai()
    out = []
    for info in dai.Device.getAllAvailableDevices():
        out.append({"id": info.getDeviceId() if hasattr(info, "getDeviceId") else str(info.deviceId),
                    "name": str(getattr(info, "name", "")), "state": str(getattr(info, "state", "")),
                    "protocol": str(getattr(info, "protocol", ""))})
    return out


# ----------------------------------------------------------------------------------------------
# configuration and geometry
# ----------------------------------------------------------------------------------------------
@dataclass
class DepthAIConfig:
    """What the device pipeline streams.

    Attributes
    ----------
    streams : frozenset of str
        Output streams wanted: any of "depth", "ir", "rgb".
    fps : float
        Sensor frame rate (Hz). With alternation, depth and IR each come at ``fps / 2``.
    mono_size, rgb_size : (width, height)
        Mono (IR) and colour output sizes in pixels; aligned depth has ``rgb_size``.
    align : {"rgb", "ir"}
        Camera the stereo depth is aligned to: the colour camera (default), or the left mono
        camera, which makes the depth camera the IR camera as on a Kinect v1.
    illumination : {"auto", "alternate", "dots", "flood", "off"}
    dot_intensity, flood_intensity : float
        Projector / flood LED intensities in [0, 1] (OAK-D Pro).
    """

    streams: frozenset = frozenset({"depth", "ir", "rgb"})
    fps: float = 30.0
    mono_size: tuple[int, int] = (640, 400)
    rgb_size: tuple[int, int] = (640, 480)
    align: str = "rgb"
    illumination: str = "auto"
    dot_intensity: float = 0.7
    flood_intensity: float = 0.7

    def __post_init__(self):
        self.streams = frozenset(self.streams)
        bad = self.streams - {"depth", "ir", "rgb"}
        if bad or not self.streams:
            raise SourceError(f"depthai: streams must be a non-empty subset of depth, ir, rgb; got "
                              f"{', '.join(sorted(self.streams)) or 'none'}")
        if self.illumination not in ILLUMINATIONS:
            raise SourceError(f"depthai: illumination must be one of {', '.join(ILLUMINATIONS)}, "
                              f"got {self.illumination!r}")
        if self.align not in ("rgb", "ir"):
            raise SourceError(f"depthai: align must be 'rgb' or 'ir', got {self.align!r}")
        for name in ("dot_intensity", "flood_intensity"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise SourceError(f"depthai: {name} must be in [0, 1], got {v!r}")
        if not (isinstance(self.fps, (int, float)) and 0 < self.fps <= 120):
            raise SourceError(f"depthai: fps must be in (0, 120], got {self.fps!r}")
        self.mono_size = (int(self.mono_size[0]), int(self.mono_size[1]))
        self.rgb_size = (int(self.rgb_size[0]), int(self.rgb_size[1]))

    def resolved_illumination(self, has_projector: bool) -> str:
        """The illumination mode actually used on a device with / without IR projectors."""
        if not has_projector:
            if self.illumination not in ("auto", "off"):
                raise SourceError(f"depthai: illumination {self.illumination!r} needs an OAK-D Pro "
                                  f"(this device has no IR dot projector / flood LED)")
            return "off"
        if self.illumination == "auto":
            if {"depth", "ir"} <= self.streams:
                return "alternate"
            return "dots" if "depth" in self.streams else "flood"
        return self.illumination

    def to_json(self) -> dict[str, Any]:
        return {"streams": sorted(self.streams), "fps": self.fps, "mono_size": list(self.mono_size),
                "rgb_size": list(self.rgb_size), "align": self.align, "illumination": self.illumination,
                "dot_intensity": self.dot_intensity, "flood_intensity": self.flood_intensity}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "DepthAIConfig":
        return cls(streams=frozenset(d.get("streams", ("depth", "ir", "rgb"))), fps=float(d.get("fps", 30.0)),
                   mono_size=tuple(d.get("mono_size", (640, 400))), rgb_size=tuple(d.get("rgb_size", (640, 480))),
                   align=d.get("align", "rgb"), illumination=d.get("illumination", "auto"),
                   dot_intensity=float(d.get("dot_intensity", 0.7)),
                   flood_intensity=float(d.get("flood_intensity", 0.7)))


@dataclass
class StreamGeometry:
    """Intrinsics per output stream and extrinsics from the depth camera (metres)."""

    intrinsics: dict[str, Intrinsics]
    depth_to_ir: np.ndarray = field(default_factory=lambda: np.eye(4))
    depth_to_rgb: np.ndarray = field(default_factory=lambda: np.eye(4))
    source: str = "calibration"


def _dist(coeffs) -> tuple[float, ...]:
    c = tuple(float(x) for x in (coeffs or ()))
    return () if not any(c) else c


def geometry_from_calibration(calib, mono_size: tuple[int, int], rgb_size: tuple[int, int],
                              align: str = "rgb") -> StreamGeometry:
    """Intrinsics and extrinsics of our streams from a ``dai.CalibrationHandler``.

    The IR stream is the left mono camera (``CAM_B``), colour is ``CAM_A``. Aligned to RGB, the
    depth camera is the colour camera (``depth_to_rgb`` = identity, ``depth_to_ir`` = CAM_A->CAM_B);
    aligned to IR it is the left camera (``depth_to_ir`` = identity). depthai's
    ``getCameraExtrinsics(src, dst)`` maps points from ``src`` to ``dst`` coordinates with the
    translation in centimetres; it is converted to metres here.

    Parameters
    ----------
    calib : dai.CalibrationHandler
    mono_size, rgb_size : (width, height)
        Output sizes the intrinsics are scaled to.
    align : {"rgb", "ir"}
    """
    dai = _dai()
    A, B = dai.CameraBoardSocket.CAM_A, dai.CameraBoardSocket.CAM_B

    def intr(sock, size, what):
        try:
            K = np.asarray(calib.getCameraIntrinsics(sock, int(size[0]), int(size[1])), dtype=float)
            dist = calib.getDistortionCoefficients(sock)
        except Exception as e:
            raise SourceError(f"depthai: the calibration has no {what} camera intrinsics ({e})") from None
        return Intrinsics(int(size[0]), int(size[1]), K[0, 0], K[1, 1], K[0, 2], K[1, 2], _dist(dist))

    def extr(src, dst):
        try:
            T = np.asarray(calib.getCameraExtrinsics(src, dst), dtype=float)
        except Exception as e:
            raise SourceError(f"depthai: the calibration has no {src.name}->{dst.name} extrinsics ({e})") from None
        T = T.copy()
        T[:3, 3] /= 100.0  # centimetres -> metres
        return T

    ir = intr(B, mono_size, "left mono (IR)")
    rgb = intr(A, rgb_size, "colour")
    if align == "rgb":
        return StreamGeometry({"depth": rgb, "ir": ir, "rgb": rgb}, depth_to_ir=extr(A, B), depth_to_rgb=np.eye(4))
    return StreamGeometry({"depth": ir, "ir": ir, "rgb": rgb}, depth_to_ir=np.eye(4), depth_to_rgb=extr(B, A))


def nominal_geometry(mono_size: tuple[int, int], rgb_size: tuple[int, int], align: str = "rgb") -> StreamGeometry:
    """Nominal OAK-D geometry (no calibration): mono HFOV 80 deg / VFOV 55 deg, colour HFOV 66 / VFOV 54 deg
    (OAK-D Pro datasheet), left camera 3.75 cm left of the colour camera."""
    from drivers.openni2_source import fov_intrinsics

    ir = fov_intrinsics(*mono_size, math.radians(80.0), math.radians(55.0))
    rgb = fov_intrinsics(*rgb_size, math.radians(66.0), math.radians(54.0))
    a_to_b = np.eye(4)
    a_to_b[0, 3] = 0.0375  # the colour camera origin seen from the left camera
    if align == "rgb":
        return StreamGeometry({"depth": rgb, "ir": ir, "rgb": rgb}, a_to_b, np.eye(4), source="nominal")
    return StreamGeometry({"depth": ir, "ir": ir, "rgb": rgb}, np.eye(4), invert_pose(a_to_b), source="nominal")


# ----------------------------------------------------------------------------------------------
# message conversion
# ----------------------------------------------------------------------------------------------
@dataclass
class Packet:
    """One image message converted for the host side.

    Attributes
    ----------
    stream : {"depth", "left", "rgb"}
    seq : int
        Sequence number (mono cameras and the stereo depth made from them share it).
    t : float
        Host-synchronised capture time in seconds.
    image : ndarray
        depth: (H, W) float32 metres (NaN invalid); left: (H, W) float32 counts; rgb: (H, W, 3) uint8.
    """

    stream: str
    seq: int
    t: float
    image: np.ndarray


def _type_name(msg) -> str:
    return getattr(msg.getType(), "name", str(msg.getType())).split(".")[-1]


def depth_from_imgframe(msg) -> np.ndarray:
    """Depth (``RAW16``/``GRAY16``-like uint16 millimetres, StereoDepth's ``depth`` output) in metres.

    Returns (H, W) float32 with NaN where the depth is 0 (no stereo match).
    """
    arr = np.asarray(msg.getFrame())
    if arr.dtype != np.uint16:
        raise SourceError(f"depthai: depth message of type {_type_name(msg)} is {arr.dtype}, expected uint16 mm")
    arr = arr.reshape(int(msg.getHeight()), int(msg.getWidth()))
    out = arr.astype(np.float32) * np.float32(1e-3)
    out[arr == 0] = np.nan
    return out


def ir_from_imgframe(msg) -> np.ndarray:
    """Mono (IR) image as float32 linear counts, (H, W): GRAY8 / RAW8 as 0..255, RAW16 as is, NV12 / YUV the Y plane."""
    t = _type_name(msg)
    h, w = int(msg.getHeight()), int(msg.getWidth())
    if t in ("GRAY8", "RAW8", "RAW16", "GRAYF16"):
        arr = np.asarray(msg.getFrame())
        return arr.reshape(h, w).astype(np.float32)
    if t in ("NV12", "NV21", "YUV420p", "YUV400p"):
        data = np.asarray(msg.getData(), dtype=np.uint8)
        stride = int(msg.getStride()) or w
        if data.size < stride * (h - 1) + w:
            raise SourceError(f"depthai: {t} IR message of {data.size} bytes is too small for {w}x{h}")
        y = np.lib.stride_tricks.as_strided(data, shape=(h, w), strides=(stride, 1))
        return y.astype(np.float32)
    raise SourceError(f"depthai: IR message of type {t} is not supported (GRAY8, RAW8, RAW16, NV12)")


def rgb_from_imgframe(msg) -> np.ndarray:
    """Colour image as (H, W, 3) uint8 sRGB in RGB order (any colour type ``getCvFrame`` decodes)."""
    t = _type_name(msg)
    if t in ("GRAY8", "RAW8", "RAW16", "BITSTREAM", "NONE"):
        raise SourceError(f"depthai: colour message of type {t} is not a colour image")
    bgr = np.asarray(msg.getCvFrame())
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise SourceError(f"depthai: colour message of type {t} decoded to {bgr.shape} {bgr.dtype}")
    return np.ascontiguousarray(bgr[..., ::-1])


def packet_from_imgframe(stream: str, msg) -> Packet:
    """Convert an ``ImgFrame`` of tap ``stream`` ("depth", "left", "rgb") into a :class:`Packet`."""
    conv = {"depth": depth_from_imgframe, "left": ir_from_imgframe, "rgb": rgb_from_imgframe}.get(stream)
    if conv is None:
        raise SourceError(f"depthai: unknown tap stream {stream!r} ({', '.join(TAP_STREAMS)})")
    ts = msg.getTimestamp()
    t = ts.total_seconds() if isinstance(ts, datetime.timedelta) else float(ts)
    return Packet(stream, int(msg.getSequenceNum()), float(t), conv(msg))


# ----------------------------------------------------------------------------------------------
# illumination classification and frame assembly (pure Python)
# ----------------------------------------------------------------------------------------------
def dot_score(ir: np.ndarray, sigma: float = 2.0) -> float:
    """How much an IR image looks lit by a dot projector: high-pass energy over mean brightness.

    ``mean(|I - G_sigma * I|) / mean(G_sigma * I)`` with a Gaussian of ``sigma`` pixels. The dot
    pattern adds strong pixel-scale contrast; a flood-lit image of the same scene is smooth, so a
    dot frame scores several times higher than the flood frame next to it.

    Parameters
    ----------
    ir : (H, W) array
        IR image, any non-negative units.
    """
    import cv2

    x = np.asarray(ir, dtype=np.float32)
    if x.ndim != 2 or x.size == 0:
        raise SourceError(f"depthai: dot_score needs an (H, W) image, got {x.shape}")
    blur = cv2.GaussianBlur(x, (0, 0), sigma)
    return float(np.mean(np.abs(x - blur)) / (float(np.mean(blur)) + 1e-6))


@dataclass
class _Group:
    seq: int
    t: float
    parts: dict[str, Packet]


class FrameAssembler:
    """Turn a stream of :class:`Packet` objects into :class:`~appfusion.frame.Frame` objects.

    Packets of the mono streams (``depth``, ``left``) with the same sequence number form a group;
    a colour packet is attached by nearest timestamp (within half a frame period). In
    ``alternate`` mode consecutive groups are paired: the one with the higher :func:`dot_score`
    was lit by the dot projector and gives the depth, the other by the flood LED and gives the IR
    image (``emitter=True``, timestamp of the IR image). Groups that cannot be paired (a frame was
    dropped) are classified against the running scores of earlier pairs.

    Parameters
    ----------
    geometry : StreamGeometry
    want : set of str
        Output streams ("depth", "ir", "rgb").
    fps : float
        Nominal frame rate (Hz), for time matching.
    alternate : bool
        Dots / flood alternation (OAK-D Pro).
    emitter : bool or None
        ``Frame.emitter`` of frames outside alternate mode (None when the device has no projector).
    min_ratio : float
        Smallest dot-score ratio that tells a dot frame from a flood frame; closer pairs are
        emitted as two frames with ``emitter=None``.
    max_pending : int
        Complete groups held while waiting for a colour frame before giving up on it.
    """

    def __init__(self, geometry: StreamGeometry, want: Iterable[str], fps: float = 30.0, alternate: bool = False,
                 emitter: bool | None = None, min_ratio: float = 1.3, max_pending: int = 6):
        self.geometry = geometry
        self.want = frozenset(want)
        self.fps = float(fps)
        self.alternate = bool(alternate)
        self.emitter = emitter
        self.min_ratio = float(min_ratio)
        self.max_pending = int(max_pending)
        self.tol = 0.5 / self.fps
        mono = set()
        if "depth" in self.want or self.alternate:
            mono.add("depth")
        if "ir" in self.want or self.alternate:
            mono.add("left")
        self.mono = frozenset(mono)
        self._groups: dict[int, dict[str, Packet]] = {}
        self._ready: deque[_Group] = deque()
        self._rgb: deque[Packet] = deque(maxlen=64)
        self._held: _Group | None = None
        self._scores = {"dots": deque(maxlen=16), "flood": deque(maxlen=16)}
        self._index = 0
        self._last_t = -math.inf
        self._t_offset = 0.0
        self._max_complete = -1
        #: counters: frames emitted, groups dropped incomplete, ambiguous pairs, lone groups, rgb misses
        self.stats = {"frames": 0, "dropped": 0, "ambiguous": 0, "lone": 0, "no_rgb": 0, "pairs": 0}

    # -- input ---------------------------------------------------------------------------------
    def push(self, p: Packet) -> list[Frame]:
        """Add one packet; return the frames it completes (possibly none)."""
        if p.stream == "rgb":
            if "rgb" in self.want:
                self._rgb.append(p)
            return self._drain(False)
        if p.stream not in ("depth", "left"):
            raise SourceError(f"depthai: packet of unknown stream {p.stream!r}")
        if p.stream not in self.mono:
            return self._drain(False)
        if self.mono and p.seq <= self._max_complete - 8:
            self.stats["dropped"] += 1  # far too late: its group was given up
            return self._drain(False)
        g = self._groups.setdefault(p.seq, {})
        g[p.stream] = p
        if set(g) >= self.mono:
            del self._groups[p.seq]
            t = g["left"].t if "left" in g else g["depth"].t
            self._insert_ready(_Group(p.seq, t, g))
            self._max_complete = max(self._max_complete, p.seq)
            stale = [s for s in self._groups if s < self._max_complete - 4]
            for s in stale:
                del self._groups[s]
                self.stats["dropped"] += 1
        return self._drain(False)

    def flush(self) -> list[Frame]:
        """Emit everything still held (end of stream)."""
        out = self._drain(True)
        if self._held is not None:
            held, self._held = self._held, None
            out.extend(self._lone(held))
        self.stats["dropped"] += len(self._groups)
        self._groups.clear()
        return out

    def _insert_ready(self, g: _Group) -> None:
        if not self._ready or self._ready[-1].seq < g.seq:
            self._ready.append(g)
            return
        items = sorted([*self._ready, g], key=lambda x: x.seq)
        self._ready = deque(items)

    # -- colour matching -----------------------------------------------------------------------
    def _rgb_settled(self, t: float) -> bool:
        """True when no better colour match for time ``t`` can still arrive."""
        return bool(self._rgb) and self._rgb[-1].t >= t + self.tol

    def _rgb_for(self, t: float) -> Packet | None:
        best = None
        for p in self._rgb:
            if abs(p.t - t) <= self.tol and (best is None or abs(p.t - t) < abs(best.t - t)):
                best = p
        if best is None:
            self.stats["no_rgb"] += 1
        return best

    def _drain(self, final: bool) -> list[Frame]:
        out: list[Frame] = []
        if not self.mono:  # colour only: every colour packet is a frame
            while self._rgb:
                p = self._rgb.popleft()
                out.append(self._make(p.t, None, None, p, self.emitter))
            return out
        while self._ready:
            g = self._ready[0]
            if "rgb" in self.want and not final and not self._rgb_settled(g.t) and len(self._ready) <= self.max_pending:
                break
            self._ready.popleft()
            out.extend(self._process(g))
        return out

    # -- grouping ------------------------------------------------------------------------------
    def _process(self, g: _Group) -> list[Frame]:
        if not self.alternate:
            rgb = self._rgb_for(g.t) if "rgb" in self.want else None
            return [self._make(g.t, g.parts.get("depth"), g.parts.get("left"), rgb, self.emitter)]
        if self._held is None:
            self._held = g
            return []
        held = self._held
        if g.seq == held.seq + 1:
            self._held = None
            return self._pair(held, g)
        self._held = g
        return self._lone(held)

    def _pair(self, a: _Group, b: _Group) -> list[Frame]:
        sa, sb = dot_score(a.parts["left"].image), dot_score(b.parts["left"].image)
        hi, lo = max(sa, sb), min(sa, sb)
        if hi < self.min_ratio * lo:
            self.stats["ambiguous"] += 1
            return [self._plain(a), self._plain(b)]
        dots, flood = (a, b) if sa > sb else (b, a)
        self._scores["dots"].append(hi)
        self._scores["flood"].append(lo)
        self.stats["pairs"] += 1
        rgb = self._rgb_for(flood.t) if "rgb" in self.want else None
        return [self._make(flood.t, dots.parts["depth"], flood.parts["left"], rgb, True)]

    def _plain(self, g: _Group) -> Frame:
        rgb = self._rgb_for(g.t) if "rgb" in self.want else None
        return self._make(g.t, g.parts.get("depth"), g.parts.get("left"), rgb, None)

    def _lone(self, g: _Group) -> list[Frame]:
        """A group without a neighbour: classify it against earlier pairs' scores."""
        self.stats["lone"] += 1
        if not self._scores["dots"]:
            return [self._plain(g)]
        s = math.log(dot_score(g.parts["left"].image) + 1e-9)
        md = math.log(float(np.median(self._scores["dots"])) + 1e-9)
        mf = math.log(float(np.median(self._scores["flood"])) + 1e-9)
        rgb = self._rgb_for(g.t) if "rgb" in self.want else None
        if abs(s - md) < abs(s - mf):  # a dot frame: depth only
            return [self._make(g.t, g.parts["depth"], None, rgb, None)]
        return [self._make(g.t, None, g.parts["left"], rgb, True)]

    # -- frames --------------------------------------------------------------------------------
    def _make(self, t: float, depth: Packet | None, left: Packet | None, rgb: Packet | None,
              emitter: bool | None) -> Frame:
        t = t + self._t_offset
        if t <= self._last_t:  # never go back in time (clock reset, reordered packets)
            self._t_offset += self._last_t - t + 1e-6
            t = self._last_t + 1e-6
        self._last_t = t
        gi = self.geometry.intrinsics
        d = depth.image if (depth is not None and "depth" in self.want) else None
        ir = left.image if (left is not None and "ir" in self.want) else None
        c = rgb.image if (rgb is not None and "rgb" in self.want) else None
        for name, img in (("depth", d), ("ir", ir), ("rgb", c)):
            if img is not None and name in gi and img.shape[:2] != gi[name].shape:
                raise SourceError(f"depthai: {name} image is {img.shape[1]}x{img.shape[0]} but its intrinsics say "
                                  f"{gi[name].width}x{gi[name].height}; check mono_size / rgb_size")
        fr = Frame(index=self._index, timestamp=t, depth=d, ir=ir, rgb=c, rgb_encoding="srgb8",
                   depth_intrinsics=gi.get("depth") if d is not None else None,
                   ir_intrinsics=gi.get("ir") if ir is not None else None,
                   rgb_intrinsics=gi.get("rgb") if c is not None else None,
                   depth_to_ir=self.geometry.depth_to_ir.copy(), depth_to_rgb=self.geometry.depth_to_rgb.copy(),
                   emitter=emitter)
        self._index += 1
        self.stats["frames"] += 1
        return fr


# ----------------------------------------------------------------------------------------------
# device-side pipeline
# ----------------------------------------------------------------------------------------------
_SCRIPT = """
dots = {dots!r}
flood = {flood!r}
enabled = True
state = 0


def apply(s):
    if not enabled:
        Device.setIrLaserDotProjectorIntensity(0.0)
        Device.setIrFloodLightIntensity(0.0)
    elif s == 0:
        Device.setIrFloodLightIntensity(0.0)
        Device.setIrLaserDotProjectorIntensity(dots)
    else:
        Device.setIrLaserDotProjectorIntensity(0.0)
        Device.setIrFloodLightIntensity(flood)


apply(state)
while True:
    node.inputs['frame'].get()
    ctrl = node.inputs['ctrl'].tryGet()
    if ctrl is not None:
        parts = bytes(ctrl.getData()).decode().split()
        enabled = parts[0] == '1'
        dots = float(parts[1])
        flood = float(parts[2])
    state = 1 - state
    apply(state)
"""


def alternation_script(dot_intensity: float, flood_intensity: float) -> str:
    """Source of the on-device Script node that alternates dot projector and flood LED each frame.

    It waits for every left mono frame on input ``frame`` and then switches the illumination for
    the next exposure; a ``Buffer`` on input ``ctrl`` holding ``"ENABLED DOTS FLOOD"`` (e.g.
    ``"1 0.7 0.7"``, ``"0 0 0"``) changes the intensities or switches both off.
    """
    return _SCRIPT.format(dots=float(dot_intensity), flood=float(flood_intensity))


def build_device_graph(pipeline, dai, cfg: DepthAIConfig, illumination: str) -> dict[str, Any]:
    """Add the on-device nodes to ``pipeline``; return the outputs to tap, by tap stream name.

    Cameras: CAM_A colour, CAM_B / CAM_C left / right mono. Stereo depth (left-right check,
    subpixel) is aligned to CAM_A (or CAM_B with ``align="ir"``). The left mono output is the IR
    stream. In ``alternate`` illumination a Script node switching the projectors follows the left
    camera's frames; its ``ctrl`` input is returned under the key ``"_script_ctrl"``.
    """
    outs: dict[str, Any] = {}
    need_mono = bool({"depth", "ir"} & cfg.streams) or illumination == "alternate"
    if need_mono:
        left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B, sensorFps=cfg.fps)
        right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C, sensorFps=cfg.fps)
        lo = left.requestOutput(cfg.mono_size, type=dai.ImgFrame.Type.GRAY8, fps=cfg.fps)
        ro = right.requestOutput(cfg.mono_size, type=dai.ImgFrame.Type.GRAY8, fps=cfg.fps)
        if "depth" in cfg.streams or illumination == "alternate":
            stereo = pipeline.create(dai.node.StereoDepth)
            stereo.setLeftRightCheck(True)
            stereo.setSubpixel(True)
            lo.link(stereo.left)
            ro.link(stereo.right)
            if cfg.align == "rgb":
                stereo.setDepthAlign(dai.CameraBoardSocket.CAM_A)
                stereo.setOutputSize(*cfg.rgb_size)
            else:
                stereo.setDepthAlign(dai.CameraBoardSocket.CAM_B)
            outs["depth"] = stereo.depth
        if "ir" in cfg.streams or illumination == "alternate":
            outs["left"] = lo
        if illumination == "alternate":
            script = pipeline.create(dai.node.Script)
            script.setScript(alternation_script(cfg.dot_intensity, cfg.flood_intensity))
            lo.link(script.inputs["frame"])
            script.inputs["frame"].setBlocking(False)
            script.inputs["frame"].setMaxSize(1)
            script.inputs["ctrl"].setBlocking(False)
            outs["_script_ctrl"] = script.inputs["ctrl"]
    if "rgb" in cfg.streams:
        cam = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A, sensorFps=cfg.fps)
        outs["rgb"] = cam.requestOutput(cfg.rgb_size, type=dai.ImgFrame.Type.RGB888i, fps=cfg.fps)
    return outs


# ----------------------------------------------------------------------------------------------
# host side
# ----------------------------------------------------------------------------------------------
_END = "__end__"


_TAP_CLASS = None


def _tap_class():
    """The host node class (created lazily so that importing this module needs no depthai)."""
    global _TAP_CLASS
    if _TAP_CLASS is not None:
        return _TAP_CLASS
    dai = _dai()

    class _Tap(dai.node.ThreadedHostNode):
        """Host node: converts each ``ImgFrame`` of one stream to a :class:`Packet` on a Python queue.

        The queue is bounded (back-pressure on the device when the consumer is slow); a put waits
        until there is room or the source is closed (``abandon`` set), so that the last packets of
        a replay are not lost and a closed source never leaves the node blocked.
        """

        def __init__(self):
            super().__init__()
            self.inp = self.createInput()
            self.stream = ""
            self.sink: queue.Queue | None = None
            self.abandon: threading.Event | None = None

        def _put(self, item) -> bool:
            while True:
                try:
                    self.sink.put(item, timeout=0.1)
                    return True
                except queue.Full:
                    if self.abandon.is_set():
                        return False

        def run(self):
            stream, error = self.stream, None
            try:
                while self.isRunning():
                    try:
                        msg = self.inp.get()
                    except Exception:  # the queue closes when the pipeline stops
                        break
                    if msg is None:
                        continue
                    try:
                        pkt = packet_from_imgframe(stream, msg)
                    except Exception as e:  # a bad message: report it to the consumer and stop
                        error = e
                        break
                    if not self._put(pkt):
                        break
            finally:
                self._put((_END, stream, error))

    _TAP_CLASS = _Tap
    return _Tap


class DepthAISource(Source):
    """An OAK-D / OAK-D Pro (depthai v3), or a replay of its recorded messages.

    Parameters
    ----------
    device_id : str, optional
        MX id, name or IP of the device; default the first one available.
    streams : iterable of str
        Output streams ("depth", "ir", "rgb"); all three by default.
    config : DepthAIConfig, optional
        Full configuration (``streams`` and ``**options`` override its fields).
    replay_dir : path-like, optional
        Replay ``depth.mcap`` / ``left.mcap`` / ``rgb.mcap`` with ``calibration.json`` and
        ``config.json`` from a folder written with ``record_dir``; no device is opened.
    record_dir : path-like, optional
        While streaming, also record the tapped messages there (``.mcap``, depthai's
        RecordMessage) with the calibration and configuration.
    build_graph : callable, optional
        ``build_graph(pipeline) -> {"depth": Output, "left": Output, "rgb": Output}`` building a
        host-only graph (``dai.Pipeline(False)``); for tests and custom inputs. Needs ``calibration``
        or runs with nominal geometry.
    calibration : dai.CalibrationHandler or path-like, optional
        Calibration to use instead of the device's (``eepromToJsonFile`` format for paths).
    emitter_position_m : 3 floats, optional
        IR illuminator position in the depth camera frame (default: nominal OAK-D Pro).
    timeout_s, first_frame_timeout_s : float
        Longest silence while streaming / before the first frame before
        :class:`~appfusion.errors.DeviceError` (live sources only).
    live : bool, optional
        Treat silence and the end of the pipeline as a lost device (default: True for a device,
        False for replays and host graphs, which simply end).
    **options
        Fields of :class:`DepthAIConfig` (``fps``, ``illumination``, ``mono_size``, ...).
    """

    def __init__(self, device_id: str | None = None, *, streams: Iterable[str] | None = None,
                 config: DepthAIConfig | None = None, replay_dir: str | os.PathLike | None = None,
                 record_dir: str | os.PathLike | None = None,
                 build_graph: Callable[[Any], dict[str, Any]] | None = None, calibration: Any = None,
                 emitter_position_m: Iterable[float] | None = None, timeout_s: float = 3.0,
                 first_frame_timeout_s: float = 10.0, live: bool | None = None, **options: Any):
        super().__init__()
        base = config.to_json() if config is not None else {}
        if replay_dir is not None and config is None:
            cfg_file = Path(replay_dir) / "config.json"
            if cfg_file.is_file():
                try:
                    base = json.loads(cfg_file.read_text())
                except (OSError, ValueError) as e:
                    raise SourceError(f"{cfg_file}: cannot read the replay configuration: {e}") from None
        if streams is not None:
            base["streams"] = sorted(streams)
        base.update({k: (sorted(v) if k == "streams" else v) for k, v in options.items()})
        unknown = set(options) - set(DepthAIConfig.__dataclass_fields__)
        if unknown:
            raise SourceError(f"depthai: unknown option(s) {', '.join(sorted(unknown))}")
        self.config = DepthAIConfig.from_json(base)
        self.device_id = device_id
        self.replay_dir = None if replay_dir is None else Path(replay_dir)
        self.record_dir = None if record_dir is None else Path(record_dir)
        self._build_graph = build_graph
        self._calibration_arg = calibration
        self._emitter_arg = None if emitter_position_m is None else tuple(float(x) for x in emitter_position_m)
        self.timeout_s = float(timeout_s)
        self.first_frame_timeout_s = float(first_frame_timeout_s)
        self.host_only = build_graph is not None or replay_dir is not None
        #: silence longer than ``timeout_s``, or the pipeline ending, means the device was lost
        self.live = (not self.host_only) if live is None else bool(live)
        self.name = ("depthai-replay:" + str(replay_dir)) if replay_dir is not None else \
            ("depthai:host-graph" if build_graph is not None else f"depthai:{device_id or 'any'}")
        if self.replay_dir is not None and not self.replay_dir.is_dir():
            raise SourceError(f"{self.replay_dir}: no such depthai recording folder")
        self._pipeline = None
        self._device = None
        self._queue: queue.Queue | None = None
        self._taps: list[str] = []
        self._ctrl_queue = None
        self._geometry: StreamGeometry | None = None
        self._illumination = "off"
        self._has_projector = False
        self._meta: dict[str, Any] = {}
        self._controls: dict[str, Control] = {}
        self._assembler: FrameAssembler | None = None
        self._stopping = False
        self.pass_name: str | None = None

    # -- description ---------------------------------------------------------------------------
    @property
    def caps(self) -> StreamCaps:
        s = self.config.streams
        rate = self.config.fps / 2 if self._illumination == "alternate" else self.config.fps
        return StreamCaps.all_together(s, {k: rate for k in s})

    @property
    def intrinsics(self) -> dict[str, Intrinsics]:
        if self._geometry is None:
            return {}
        return {k: v for k, v in self._geometry.intrinsics.items() if k in self.config.streams}

    @property
    def meta(self) -> dict[str, Any]:
        return dict(self._meta)

    @property
    def controls(self) -> dict[str, Control]:
        return dict(self._controls)

    @property
    def illumination(self) -> str:
        """The illumination mode in use ("alternate", "dots", "flood" or "off")."""
        return self._illumination

    # -- opening -------------------------------------------------------------------------------
    def _load_calibration(self, dai):
        c = self._calibration_arg
        if c is None and self.replay_dir is not None and (self.replay_dir / "calibration.json").is_file():
            c = self.replay_dir / "calibration.json"
        if c is None or isinstance(c, StreamGeometry):
            return c
        if isinstance(c, (str, os.PathLike)):
            try:
                return dai.CalibrationHandler(os.fspath(c))
            except Exception as e:
                raise SourceError(f"{c}: not a depthai calibration file ({e})") from None
        return c

    def _open(self) -> None:
        dai = _dai()
        cfg = self.config
        self._queue = queue.Queue(maxsize=64)
        self._abandon = threading.Event()
        self._stopping = False
        calib = self._load_calibration(dai)
        device_name = "OAK (host graph)"
        try:
            if self.host_only:
                self._pipeline = dai.Pipeline(False)
                if self.replay_dir is not None:
                    outs = self._replay_outputs(dai)
                    info = {}
                    if (self.replay_dir / "device.json").is_file():
                        with contextlib.suppress(Exception):
                            info = json.loads((self.replay_dir / "device.json").read_text())
                    device_name = info.get("device", "OAK (replay)")
                    self._has_projector = bool(info.get("has_projector", False))
                    self._illumination = info.get("illumination", "off")
                else:
                    outs = self._build_graph(self._pipeline)
                    self._has_projector = cfg.illumination not in ("auto", "off")
                    self._illumination = cfg.illumination if cfg.illumination != "auto" else "off"
            else:
                self._open_device(dai)
                device_name = self._meta["device"]
                calib = calib if calib is not None else self._device_calibration()
                outs = build_device_graph(self._pipeline, dai, cfg, self._illumination)
            if isinstance(calib, StreamGeometry):
                self._geometry = calib
            elif calib is not None:
                self._geometry = geometry_from_calibration(calib, cfg.mono_size, cfg.rgb_size, cfg.align)
            else:
                self._geometry = nominal_geometry(cfg.mono_size, cfg.rgb_size, cfg.align)
            self._ctrl_queue = None
            ctrl = outs.pop("_script_ctrl", None)
            if ctrl is not None:
                self._ctrl_queue = ctrl.createInputQueue()
            Tap = _tap_class()
            self._taps = []
            for stream in TAP_STREAMS:
                if stream not in outs:
                    continue
                tap = self._pipeline.create(Tap)
                tap.stream, tap.sink, tap.abandon = stream, self._queue, self._abandon
                outs[stream].link(tap.inp)
                self._taps.append(stream)
                if self.record_dir is not None:
                    self.record_dir.mkdir(parents=True, exist_ok=True)
                    rec = self._pipeline.create(dai.node.RecordMessage)
                    rec.setRecordFile(str(self.record_dir / f"{stream}.mcap"))
                    outs[stream].link(rec.input)
            if not self._taps:
                raise SourceError(f"{self.name}: the graph has none of the outputs {', '.join(TAP_STREAMS)}")
            want = set(cfg.streams)
            missing = [s for s in want if {"depth": "depth", "ir": "left", "rgb": "rgb"}[s] not in self._taps]
            if missing:
                raise SourceError(f"{self.name}: no {', '.join(sorted(missing))} messages in "
                                  + (str(self.replay_dir) if self.replay_dir else "the graph"))
            alternate = self._illumination == "alternate"
            emitter = None
            if self._has_projector and not alternate:
                emitter = self._illumination != "off"
            self._assembler = FrameAssembler(self._geometry, want, cfg.fps, alternate=alternate, emitter=emitter)
            em = self._emitter_arg or (OAK_D_PRO_EMITTER_M if self._has_projector else (0.0, 0.0, 0.0))
            self._meta.update({"device": device_name, "driver": "depthai", "depthai_version": dai.__version__,
                               "config": cfg.to_json(), "illumination": self._illumination,
                               "ir_illuminator": {"alternate": "flood", "flood": "flood", "dots": "dots"}.get(
                                   self._illumination, "none"),
                               "emitter_position_m": list(em), "emitter_position_nominal": self._emitter_arg is None,
                               "ir_bits": 8, "geometry_from": self._geometry.source,
                               "depth_to_ir": self._geometry.depth_to_ir.tolist(),
                               "depth_to_rgb": self._geometry.depth_to_rgb.tolist()})
            if self.record_dir is not None:
                self._write_record_side_files(calib)
            self._pipeline.start()
            if self._device is not None and not alternate:
                self._apply_illumination()
        except BaseException:
            self._teardown()
            raise

    def _replay_outputs(self, dai) -> dict[str, Any]:
        outs = {}
        for stream in TAP_STREAMS:
            f = self.replay_dir / f"{stream}.mcap"
            if f.is_file():
                node = self._pipeline.create(dai.node.ReplayMessage)
                node.setReplayFile(str(f))
                node.setLoop(False)
                outs[stream] = node.out
        if not outs:
            raise SourceError(f"{self.replay_dir}: no depth.mcap, left.mcap or rgb.mcap to replay")
        return outs

    def _open_device(self, dai) -> None:
        try:
            available = dai.Device.getAllAvailableDevices()
        except Exception as e:
            raise DeviceError(f"depthai: cannot list devices: {e}") from None
        if not available:
            raise DeviceError("depthai: no OAK device found (is it plugged in, and are the udev rules from "
                              "drivers/udev/ installed? see docs/hardware.md)")
        try:
            dev = dai.Device(self.device_id) if self.device_id else dai.Device()
        except Exception as e:
            raise DeviceError(f"depthai: cannot open device {self.device_id or '(first available)'}: {e}") from None
        self._device = dev
        with contextlib.suppress(Exception):
            dev.setMaxReconnectionAttempts(0)
        self._pipeline = dai.Pipeline(dev)
        with contextlib.suppress(Exception):
            self._pipeline.setStopOnDeviceLoss(True)
        try:
            self._has_projector = bool(dev.getIrDrivers())
        except Exception:
            self._has_projector = False
        self._illumination = self.config.resolved_illumination(self._has_projector)
        name = "OAK"
        with contextlib.suppress(Exception):
            name = dev.getDeviceName()
        dev_id = self.device_id or ""
        with contextlib.suppress(Exception):
            dev_id = dev.getDeviceId()
        self.name = f"depthai:{dev_id} ({name})"
        self._meta.update(device=name, device_id=dev_id, has_projector=self._has_projector)
        if self._has_projector:
            self._controls = {
                "emitter": Control("emitter", "bool", self._illumination != "off"),
                "dot_intensity": Control("dot_intensity", "float", self.config.dot_intensity, (0.0, 1.0)),
                "flood_intensity": Control("flood_intensity", "float", self.config.flood_intensity, (0.0, 1.0)),
            }

    def _device_calibration(self):
        try:
            return self._device.readCalibration()
        except Exception as e:
            raise DeviceError(f"{self.name}: cannot read the calibration from the device EEPROM: {e}") from None

    def _write_record_side_files(self, calib) -> None:
        d = self.record_dir
        (d / "config.json").write_text(json.dumps(self.config.to_json(), indent=2) + "\n")
        (d / "device.json").write_text(json.dumps({"device": self._meta.get("device"),
                                                   "has_projector": self._has_projector,
                                                   "illumination": self._illumination}, indent=2) + "\n")
        if calib is not None and hasattr(calib, "eepromToJsonFile"):
            with contextlib.suppress(Exception):
                calib.eepromToJsonFile(str(d / "calibration.json"))

    # -- controls ------------------------------------------------------------------------------
    def _apply_illumination(self) -> None:
        """Set projector intensities from the controls (non-alternating modes, live device)."""
        dev = self._device
        on = self._controls["emitter"].value if "emitter" in self._controls else False
        dots = self._controls["dot_intensity"].value if "dot_intensity" in self._controls else 0.0
        flood = self._controls["flood_intensity"].value if "flood_intensity" in self._controls else 0.0
        mode = self._illumination
        try:
            dev.setIrLaserDotProjectorIntensity(float(dots) if on and mode == "dots" else 0.0)
            dev.setIrFloodLightIntensity(float(flood) if on and mode == "flood" else 0.0)
        except Exception as e:
            raise DeviceError(f"{self.name}: cannot set the IR projectors: {e}") from None

    def set_control(self, name: str, value: Any) -> None:
        if name in ("emitter", "dot_intensity", "flood_intensity") and name not in self._controls:
            raise SourceError(f"{self.name}: no IR projector control (only an OAK-D Pro has a dot projector "
                              f"and a flood LED" + ("" if self.is_open else "; open the device first") + ")")
        super().set_control(name, value)

    def _set_control(self, name: str, value: Any) -> None:
        c = self._controls[name]
        if c.kind == "bool":
            value = bool(value)
        else:
            value = float(value)
            if not 0.0 <= value <= 1.0:
                raise SourceError(f"{self.name}: {name} must be in [0, 1], got {value}")
        self._controls[name] = Control(name, c.kind, value, c.limits, c.unit)
        if self._device is None:
            return
        if self._illumination == "alternate":
            if self._ctrl_queue is None:  # pragma: no cover - the graph always has the script input
                raise SourceError(f"{self.name}: the alternation script has no control input")
            dai = _dai()
            buf = dai.Buffer()
            text = (f"{int(bool(self._controls['emitter'].value))} {self._controls['dot_intensity'].value:.4f} "
                    f"{self._controls['flood_intensity'].value:.4f}")
            buf.setData(list(text.encode()))
            self._ctrl_queue.send(buf)
            self._assembler.alternate = bool(self._controls["emitter"].value)
            self._assembler.emitter = False if not self._controls["emitter"].value else None
        else:
            self._apply_illumination()
            if self._assembler is not None:
                self._assembler.emitter = bool(self._controls["emitter"].value) and self._illumination != "off"

    # -- reading -------------------------------------------------------------------------------
    def _frames(self) -> Iterator[Frame]:
        asm, q = self._assembler, self._queue
        ended: set[str] = set()
        error: BaseException | None = None
        last = time.monotonic()
        got_any = False
        while True:
            try:
                item = q.get(timeout=0.1)
            except queue.Empty:
                limit = self.timeout_s if got_any else self.first_frame_timeout_s
                if self.live and time.monotonic() - last > limit:
                    for fr in asm.flush():
                        yield self._tag(fr)
                    raise DeviceError(f"{self.name}: no frame for {limit:g} s after {asm.stats['frames']} frames "
                                      f"(device unplugged or stalled)")
                if self._pipeline is not None and not self._pipeline.isRunning() and q.empty() \
                        and len(ended) < len(self._taps):
                    # the pipeline ended without every tap saying so: give them a moment
                    if time.monotonic() - last > 1.0:
                        break
                continue
            last = time.monotonic()
            if isinstance(item, tuple) and item and item[0] == _END:
                ended.add(item[1])
                if item[2] is not None and error is None:
                    error = item[2]
                if len(ended) >= len(self._taps):
                    break
                continue
            got_any = True
            for fr in asm.push(item):
                yield self._tag(fr)
        for fr in asm.flush():
            yield self._tag(fr)
        if error is not None:
            raise SourceError(f"{self.name}: bad message after {asm.stats['frames']} frames: {error}")
        if self.live and not self._stopping:
            raise DeviceError(f"{self.name}: the device stopped streaming after {asm.stats['frames']} frames "
                              f"(unplugged?)")

    def _tag(self, fr: Frame) -> Frame:
        if self.pass_name is not None:
            fr.pass_name = self.pass_name
        return fr

    def select_pass(self, name: str) -> frozenset[str]:
        """Tag frames with scanning pass ``name``; an OAK streams all its streams in every pass."""
        from drivers import streams_for_pass

        want = streams_for_pass(name, self.caps)
        self.pass_name = name
        return want

    def select_streams(self, streams: Iterable[str]) -> None:
        """Accept any subset of the configured streams (an OAK streams them all together)."""
        want = frozenset(streams)
        if not want <= self.config.streams:
            raise SourceError(f"{self.name}: streams {', '.join(sorted(want - self.config.streams))} are not "
                              f"configured (configured: {', '.join(sorted(self.config.streams))})")

    # -- closing -------------------------------------------------------------------------------
    def _teardown(self) -> None:
        self._stopping = True
        if getattr(self, "_abandon", None) is not None:
            self._abandon.set()
        p, self._pipeline = self._pipeline, None
        if p is not None:
            if self._device is not None:
                with contextlib.suppress(Exception):
                    self._device.setIrLaserDotProjectorIntensity(0.0)
                    self._device.setIrFloodLightIntensity(0.0)
            with contextlib.suppress(Exception):
                p.stop()
            with contextlib.suppress(Exception):
                p.wait()
        d, self._device = self._device, None
        if d is not None:
            with contextlib.suppress(Exception):
                d.close()

    def _close(self) -> None:
        self._teardown()
