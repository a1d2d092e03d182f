"""Azure Kinect DK recordings (``k4arecorder`` Matroska files) as a :class:`~appfusion.source.Source`.

An Azure Kinect streams depth, IR and colour at the same time, so one recording is one ``scan`` pass
in the sense of ``docs/conventions.md``: geometry (paper §4.1), IR BRDF fusion (§5.1–5.2) and the RGB
pass (§5.3) can all be fed from it. Its time-of-flight illuminator sits beside the depth lens, so the
IR light and view directions of §5.1 (Fig. 3) coincide far more closely than on a Kinect v1.

File layout (Azure Kinect "record file format")
-----------------------------------------------
- Segment ``Info`` with ``TimecodeScale`` (1000 ns in k4arecorder files, i.e. block times in µs).
- Video tracks named ``COLOR``, ``DEPTH`` and ``IR`` (codec ``V_MS/VFW/FOURCC``; the FOURCC sits in
  the BITMAPINFOHEADER stored as ``CodecPrivate``). Colour is ``MJPG`` (or ``NV12``, ``YUY2``, raw
  BGRA); depth and IR are ``b16g``: 16-bit grey, **big-endian** as the FOURCC says. (This was checked
  on the shared recording: read big-endian the depth of a valid pixel differs from its neighbour's by a
  median of 1 mm and ranges 0.18–2.19 m; read little-endian the same statistics are 256 "mm" and
  0.26–64.8 "m". k4arecorder byte-swaps on write and k4a playback swaps back.) Depth is in
  millimetres, 0 = invalid; IR in sensor counts.
- An ``IMU`` track (``S_K4A/IMU``), ignored here.
- An attachment ``calibration.json`` (tag ``K4A_CALIBRATION_FILE``): the device's factory calibration.
- Tags: ``K4A_START_OFFSET_NS`` (device time of the recording's time 0), ``K4A_DEPTH_MODE``,
  ``K4A_COLOR_MODE``, ``K4A_IR_MODE``, ``K4A_DEVICE_SERIAL_NUMBER``, ``K4A_DEPTH_DELAY_NS``, ...

Block headers are indexed with a small EBML walker that reads element headers only (so opening a
multi-gigabyte recording does not read its images, a truncated file is detected exactly, and seeking
is a file offset); PyAV reads the tags and the calibration attachment. The walker also checks every
element against the file size, because FFmpeg's demuxer silently drops a cut-off last packet.

Calibration maths (k4a ``mode_specific_calibration.c``)
-------------------------------------------------------
``calibration.json`` stores, per camera, 14 Brown–Conrady ``ModelParameters``
``[cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1]`` where ``cx, cy, fx, fy`` are
*normalised* by the full sensor size (``SensorWidth x SensorHeight``: 1024 x 1024 depth, 4096 x 3072
colour) and *0-cornered* (0 = the top-left corner of the top-left pixel). A capture mode reads the
sensor binned to ``(Wb, Hb)`` and then cropped at offset ``(ox, oy)`` to the output size, so in that
mode's pixels (OpenCV convention, pixel centres at integers)::

    fx = fx_n * Wb          fy = fy_n * Hb
    cx = cx_n * Wb - ox - 0.5
    cy = cy_n * Hb - oy - 0.5

with, e.g., NFOV unbinned depth: ``(Wb, Hb) = (1024, 1024)``, ``(ox, oy) = (192, 180)``, output
640 x 576; NFOV 2x2 binned: ``(512, 512)``, ``(96, 90)``, 320 x 288; WFOV: no crop; 720p colour:
``(1280, 960)``, ``(0, 120)``, 1280 x 720 (the 4:3 sensor image scaled, 120 rows cropped top and
bottom). The distortion becomes OpenCV's rational model ``(k1, k2, p1, p2, k3, k4, k5, k6)`` (exact
when ``codx = cody = 0``, as on shipped devices). Each camera's ``Rt`` is the world-to-camera
transform with the depth camera as world (row-major rotation, translation in metres), so
``depth_to_rgb = Rt_color @ inv(Rt_depth)``. IR is the depth sensor itself: ``depth_to_ir = I`` and
IR intrinsics equal depth intrinsics.

Timestamps are k4a *device* timestamps, as ``k4a_playback`` reports them: block time plus
``K4A_START_OFFSET_NS``, in seconds (the shared recording's one capture is at 0.800222 s = 463 945 µs
block time + 336 277 µs offset, the value pyk4a's own tests expect). A frame's timestamp is its depth
image's (else IR's, else colour's).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from appfusion.errors import SessionFormatError
from appfusion.frame import Frame, Intrinsics, invert_pose, make_pose
from appfusion.source import Source, StreamCaps

__all__ = ["AzureKinectReader", "DEPTH_MODES", "COLOR_RESOLUTIONS", "parse_calibration",
           "mode_intrinsics"]

#: depth mode -> (binned calibration resolution (W, H), crop offset (x, y), output size (W, H))
DEPTH_MODES: dict[str, tuple[tuple[int, int], tuple[int, int], tuple[int, int]]] = {
    "NFOV_2X2BINNED": ((512, 512), (96, 90), (320, 288)),
    "NFOV_UNBINNED": ((1024, 1024), (192, 180), (640, 576)),
    "WFOV_2X2BINNED": ((512, 512), (0, 0), (512, 512)),
    "WFOV_UNBINNED": ((1024, 1024), (0, 0), (1024, 1024)),
    "PASSIVE_IR": ((1024, 1024), (0, 0), (1024, 1024)),
}

#: colour resolution -> (binned 4:3 calibration resolution, crop offset, output size)
COLOR_RESOLUTIONS: dict[str, tuple[tuple[int, int], tuple[int, int], tuple[int, int]]] = {
    "720P": ((1280, 960), (0, 120), (1280, 720)),
    "1080P": ((1920, 1440), (0, 180), (1920, 1080)),
    "1440P": ((2560, 1920), (0, 240), (2560, 1440)),
    "1536P": ((2048, 1536), (0, 0), (2048, 1536)),
    "2160P": ((3840, 2880), (0, 360), (3840, 2160)),
    "3072P": ((4096, 3072), (0, 0), (4096, 3072)),
}

_COLOR_FORMATS = ("MJPG", "NV12", "YUY2", "BGRA")
_SUPPORTED_LENS_MODELS = ("CALIBRATION_LensDistortionModelBrownConrady",
                          "CALIBRATION_LensDistortionModelRational6KT",
                          "CALIBRATION_LensDistortionModelPolynomial3K")

# EBML / Matroska element ids (with their length-marker bits, as written in files)
_EBML, _DOCTYPE = 0x1A45DFA3, 0x4282
_SEGMENT, _INFO, _TRACKS, _CLUSTER = 0x18538067, 0x1549A966, 0x1654AE6B, 0x1F43B675
_LEVEL1 = {0x114D9B74, _INFO, _TRACKS, 0x1C53BB6B, 0x1941A469, 0x1254C367, _CLUSTER, 0x1043A770}
_TIMECODE_SCALE = 0x2AD7B1
_TRACK_ENTRY, _TRACK_NUMBER, _TRACK_UID, _TRACK_TYPE = 0xAE, 0xD7, 0x73C5, 0x83
_CODEC_ID, _CODEC_PRIVATE, _NAME, _DEFAULT_DURATION = 0x86, 0x63A2, 0x536E, 0x23E383
_VIDEO, _PIXEL_WIDTH, _PIXEL_HEIGHT = 0xE0, 0xB0, 0xBA
_CLUSTER_TIMECODE, _SIMPLE_BLOCK, _BLOCK_GROUP, _BLOCK = 0xE7, 0xA3, 0xA0, 0xA1
_ROLE_OF_NAME = {"COLOR": "rgb", "DEPTH": "depth", "IR": "ir", "DEPTH_IR": "ir"}


# ---------------------------------------------------------------------------------------------
# calibration
# ---------------------------------------------------------------------------------------------
def mode_intrinsics(params: list[float] | np.ndarray, binned: tuple[int, int], crop: tuple[int, int],
                    out: tuple[int, int]) -> Intrinsics:
    """Pixel intrinsics of one Azure Kinect capture mode from normalised calibration parameters.

    Implements k4a's ``transformation_get_mode_specific_camera_calibration`` (see the module
    docstring): ``fx = fx_n Wb``, ``fy = fy_n Hb``, ``cx = cx_n Wb - ox - 0.5``,
    ``cy = cy_n Hb - oy - 0.5``.

    Parameters
    ----------
    params : sequence of 14 float
        ``[cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1]``; the first four normalised
        by the calibration image size and 0-cornered, the rest dimensionless.
    binned : (int, int)
        ``(Wb, Hb)``: the sensor image size (pixels) the mode reads before cropping.
    crop : (int, int)
        ``(ox, oy)``: offset (pixels) of the output window inside the binned image.
    out : (int, int)
        ``(W, H)``: output image size in pixels.

    Returns
    -------
    Intrinsics
        fx, fy, cx, cy in output pixels (pixel centres at integers), distortion as OpenCV's rational
        model ``(k1, k2, p1, p2, k3, k4, k5, k6)``.
    """
    p = [float(v) for v in params]
    cx_n, cy_n, fx_n, fy_n, k1, k2, k3, k4, k5, k6 = p[:10]
    p2, p1 = p[12], p[13]
    (wb, hb), (ox, oy), (w, h) = binned, crop, out
    return Intrinsics(int(w), int(h), fx_n * wb, fy_n * hb, cx_n * wb - ox - 0.5, cy_n * hb - oy - 0.5,
                      (k1, k2, p1, p2, k3, k4, k5, k6))


def _rt_matrix(rt: dict, where: str, path) -> np.ndarray:
    try:
        R = np.asarray(rt["Rotation"], dtype=float).reshape(3, 3)
        t = np.asarray(rt["Translation"], dtype=float).reshape(3)
    except (KeyError, TypeError, ValueError) as e:
        raise SessionFormatError(path, f"calibration.json: {where} has no valid Rt "
                                       f"(Rotation 3x3, Translation 3): {e}") from None
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise SessionFormatError(path, f"calibration.json: {where} Rt is not finite")
    return make_pose(R, t)


def parse_calibration(blob: bytes | str, depth_mode: str, color_resolution: str | None,
                      path: str | os.PathLike = "calibration.json") -> dict[str, Any]:
    """Parse an Azure Kinect ``calibration.json`` into this package's intrinsics and extrinsics.

    Parameters
    ----------
    blob : bytes or str
        The JSON text (the recording's attachment).
    depth_mode : str
        A key of :data:`DEPTH_MODES` (the depth/IR mode the images were taken in).
    color_resolution : str or None
        A key of :data:`COLOR_RESOLUTIONS`, or None for no colour camera.
    path : path-like
        Named in error messages.

    Returns
    -------
    dict
        ``intrinsics`` ({"depth", "ir"[, "rgb"]}: Intrinsics), ``depth_to_rgb`` ((4, 4) float64,
        metres), ``serial`` (str or None), ``metric_radius`` ({"depth", "rgb"}: float, the radius in
        normalised image coordinates inside which the distortion model is valid).

    Raises
    ------
    SessionFormatError
        Not JSON, a camera missing, or parameters malformed.
    """
    try:
        doc = json.loads(blob)
        info = doc["CalibrationInformation"]
        cameras = info["Cameras"]
    except (ValueError, KeyError, TypeError) as e:
        raise SessionFormatError(path, f"calibration.json is not an Azure Kinect calibration: {e}") from None
    by_loc = {c.get("Location"): c for c in cameras if isinstance(c, dict)}

    def camera(location: str, what: str) -> tuple[list[float], dict, tuple[int, int], float]:
        cam = by_loc.get(location)
        if cam is None:
            raise SessionFormatError(path, f"calibration.json has no {what} camera ({location})")
        try:
            intr = cam["Intrinsics"]
            model = intr["ModelType"]
            params = [float(v) for v in intr["ModelParameters"]]
            size = (int(cam["SensorWidth"]), int(cam["SensorHeight"]))
            radius = float(cam.get("MetricRadius", 0.0))
        except (KeyError, TypeError, ValueError) as e:
            raise SessionFormatError(path, f"calibration.json: {what} camera is malformed: {e}") from None
        if model not in _SUPPORTED_LENS_MODELS:
            raise SessionFormatError(path, f"calibration.json: {what} camera uses lens model {model!r}; "
                                           f"supported: {', '.join(_SUPPORTED_LENS_MODELS)}")
        if len(params) < 14 or not all(np.isfinite(params[:14])):
            raise SessionFormatError(path, f"calibration.json: {what} camera needs 14 finite "
                                           f"ModelParameters, got {len(params)}")
        return params, cam, size, (radius if radius > 1e-4 else 1.7)  # k4a's default when unset

    if depth_mode not in DEPTH_MODES:
        raise SessionFormatError(path, f"unknown depth mode {depth_mode!r} (known: {', '.join(DEPTH_MODES)})")
    d_params, d_cam, d_size, d_radius = camera("CALIBRATION_CameraLocationD0", "depth")
    if d_size != (1024, 1024):
        raise SessionFormatError(path, f"calibration.json: depth sensor is {d_size[0]}x{d_size[1]}, "
                                       "expected 1024x1024")
    depth = mode_intrinsics(d_params, *DEPTH_MODES[depth_mode])
    world_to_depth = _rt_matrix(d_cam.get("Rt", {}), "depth camera", path)
    out: dict[str, Any] = {"intrinsics": {"depth": depth, "ir": depth},
                           "depth_to_rgb": np.eye(4), "metric_radius": {"depth": d_radius},
                           "serial": info.get("Metadata", {}).get("SerialId")}
    if color_resolution is not None:
        if color_resolution not in COLOR_RESOLUTIONS:
            raise SessionFormatError(path, f"unknown colour resolution {color_resolution!r} "
                                           f"(known: {', '.join(COLOR_RESOLUTIONS)})")
        c_params, c_cam, c_size, c_radius = camera("CALIBRATION_CameraLocationPV0", "colour")
        w, h = c_size
        if w * 9 // 16 == h:
            # legacy 16:9 calibration: re-normalise to the 4:3 sensor (k4a: {4096, 2304}, {0, -384}, {4096, 3072})
            c_params = list(c_params)
            c_params[1] = c_params[1] * 2304 / 3072 + 384 / 3072
            c_params[3] = c_params[3] * 2304 / 3072
        elif w * 3 // 4 != h:
            raise SessionFormatError(path, f"calibration.json: colour sensor size {w}x{h} is neither 4:3 nor 16:9")
        out["intrinsics"]["rgb"] = mode_intrinsics(c_params, *COLOR_RESOLUTIONS[color_resolution])
        world_to_color = _rt_matrix(c_cam.get("Rt", {}), "colour camera", path)
        out["depth_to_rgb"] = world_to_color @ invert_pose(world_to_depth)
        out["metric_radius"]["rgb"] = c_radius
    return out


# ---------------------------------------------------------------------------------------------
# Matroska structure (element headers only)
# ---------------------------------------------------------------------------------------------
class _Truncated(Exception):
    pass


@dataclass
class _Track:
    number: int
    uid: int = 0
    type: int = 0
    codec_id: str = ""
    fourcc: str = ""
    name: str = ""
    default_duration_ns: int = 0
    width: int = 0
    height: int = 0


@dataclass(frozen=True)
class _Block:
    track: int
    ticks: int          # block time in TimecodeScale units
    offset: int         # file offset of the payload
    size: int           # payload bytes


@dataclass
class _Layout:
    timecode_scale: int = 1_000_000
    tracks: dict[int, _Track] = field(default_factory=dict)
    blocks: list[_Block] = field(default_factory=list)
    truncated_at: int | None = None


def _vint(buf: bytes, i: int, keep_marker: bool) -> tuple[int, int, bool]:
    """Decode an EBML variable-length integer at ``buf[i]``: (value, length in bytes, all-ones)."""
    if i >= len(buf):
        raise _Truncated
    first = buf[i]
    if first == 0:
        raise ValueError(f"invalid EBML variable-length integer 0x00 at +{i}")
    n = 9 - first.bit_length()
    if i + n > len(buf):
        raise _Truncated
    v = first if keep_marker else first & ((1 << (8 - n)) - 1)
    for k in range(1, n):
        v = (v << 8) | buf[i + k]
    return v, n, (not keep_marker) and v == (1 << (7 * n)) - 1


def _children(buf: bytes) -> Iterator[tuple[int, bytes]]:
    """(id, payload) of the elements inside an in-memory master element's payload."""
    i = 0
    while i < len(buf):
        eid, n, _ = _vint(buf, i, True)
        size, m, _ = _vint(buf, i + n, False)
        start = i + n + m
        if start + size > len(buf):
            raise _Truncated
        yield eid, buf[start:start + size]
        i = start + size


def _uint(b: bytes) -> int:
    return int.from_bytes(b, "big") if b else 0


def _parse_tracks(payload: bytes) -> dict[int, _Track]:
    tracks = {}
    for eid, entry in _children(payload):
        if eid != _TRACK_ENTRY:
            continue
        t = _Track(number=0)
        for cid, val in _children(entry):
            if cid == _TRACK_NUMBER:
                t.number = _uint(val)
            elif cid == _TRACK_UID:
                t.uid = _uint(val)
            elif cid == _TRACK_TYPE:
                t.type = _uint(val)
            elif cid == _CODEC_ID:
                t.codec_id = val.rstrip(b"\0").decode("ascii", "replace")
            elif cid == _CODEC_PRIVATE and len(val) >= 20:
                t.fourcc = val[16:20].rstrip(b"\0").decode("ascii", "replace")  # BITMAPINFOHEADER.biCompression
            elif cid == _NAME:
                t.name = val.rstrip(b"\0").decode("utf-8", "replace")
            elif cid == _DEFAULT_DURATION:
                t.default_duration_ns = _uint(val)
            elif cid == _VIDEO:
                for vid, vv in _children(val):
                    if vid == _PIXEL_WIDTH:
                        t.width = _uint(vv)
                    elif vid == _PIXEL_HEIGHT:
                        t.height = _uint(vv)
        tracks[t.number] = t
    return tracks


class _Walker:
    """Reads Matroska element headers from a file and lists its blocks (no image data is read)."""

    def __init__(self, f, file_size: int):
        self.f, self.file_size = f, file_size

    def header(self, pos: int) -> tuple[int, int, int, bool]:
        """(id, payload size, payload start, size unknown) of the element at ``pos``."""
        self.f.seek(pos)
        buf = self.f.read(12)
        eid, n, _ = _vint(buf, 0, True)
        size, m, unknown = _vint(buf, n, False)
        return eid, size, pos + n + m, unknown

    def read(self, pos: int, size: int) -> bytes:
        self.f.seek(pos)
        data = self.f.read(size)
        if len(data) < size:
            raise _Truncated
        return data

    def cluster(self, start: int, end: int, unknown: bool, layout: _Layout) -> int:
        """Index the blocks of one cluster; returns where the next level-1 element starts."""
        base = None
        pos = start
        while pos < end:
            eid, size, data, unk = self.header(pos)
            if unknown and eid in _LEVEL1:
                return pos
            if unk:
                raise ValueError(f"element 0x{eid:X} at byte {pos} inside a cluster has unknown size")
            if data + size > self.file_size:
                raise _Truncated
            if eid == _CLUSTER_TIMECODE:
                base = _uint(self.read(data, size))
            elif eid == _SIMPLE_BLOCK:
                self.block(data, size, base, pos, layout)
            elif eid == _BLOCK_GROUP:
                gpos = data
                while gpos < data + size:
                    bid, bsize, bdata, _ = self.header(gpos)
                    if bid == _BLOCK:
                        self.block(bdata, bsize, base, gpos, layout)
                    gpos = bdata + bsize
            pos = data + size
        return pos

    def block(self, data: int, size: int, base: int | None, pos: int, layout: _Layout) -> None:
        if base is None:
            raise ValueError(f"block at byte {pos} comes before its cluster's timecode")
        head = self.read(data, min(size, 11))
        track, n, _ = _vint(head, 0, False)
        if len(head) < n + 3:
            raise ValueError(f"block at byte {pos} is too short ({size} bytes)")
        rel = int.from_bytes(head[n:n + 2], "big", signed=True)
        flags = head[n + 2]
        t = layout.tracks.get(track)
        if t is not None and t.name in _ROLE_OF_NAME and flags & 0x06:
            raise ValueError(f"block at byte {pos} of track {t.name} uses lacing, which k4arecorder never writes")
        layout.blocks.append(_Block(track, base + rel, data + n + 3, size - n - 3))


def _scan(path: Path, skip_bad: bool) -> _Layout:
    """Validate the Matroska structure of ``path`` and index its blocks (see module docstring)."""
    file_size = path.stat().st_size
    layout = _Layout()
    with open(path, "rb") as f:
        if f.read(4) != b"\x1a\x45\xdf\xa3":
            raise SessionFormatError(path, "not a Matroska (MKV) file: it does not start with an EBML header")
        w = _Walker(f, file_size)
        pos = 0
        try:
            eid, size, data, _ = w.header(0)
            doctype = dict(_children(w.read(data, size))).get(_DOCTYPE, b"").rstrip(b"\0")
            if doctype != b"matroska":
                raise SessionFormatError(path, f"not a Matroska file (EBML DocType {doctype.decode('ascii', 'replace')!r})")
            pos = data + size
            eid, size, data, unknown = w.header(pos)
            if eid != _SEGMENT:
                raise SessionFormatError(path, f"no Matroska Segment after the EBML header (element 0x{eid:X} at byte {pos})")
            end = file_size if unknown else data + size
            if end > file_size:
                if not skip_bad:
                    raise _Truncated(f"its Matroska Segment declares {end} bytes but the file has {file_size}")
                layout.truncated_at, end = file_size, file_size
            pos = data
            while pos < end:
                eid, size, data, unknown = w.header(pos)
                if eid == _CLUSTER:
                    cend = end if unknown else data + size
                    if cend > file_size:
                        raise _Truncated
                    pos = w.cluster(data, cend, unknown, layout)
                    continue
                if unknown:
                    raise SessionFormatError(path, f"element 0x{eid:X} at byte {pos} has unknown size")
                if data + size > file_size:
                    raise _Truncated
                if eid == _INFO:
                    scale = dict(_children(w.read(data, size))).get(_TIMECODE_SCALE)
                    if scale is not None:
                        layout.timecode_scale = _uint(scale)
                elif eid == _TRACKS:
                    layout.tracks = _parse_tracks(w.read(data, size))
                pos = data + size
        except _Truncated as e:
            if not skip_bad:
                what = e.args[0] if e.args else (f"the Matroska element at byte {pos} ends past the end of "
                                                 f"the file ({file_size} bytes)")
                raise SessionFormatError(
                    path, f"file is truncated: {what}; the copy is incomplete or the recording was "
                          "interrupted (AzureKinectReader(..., skip_bad=True) reads the frames before the cut)"
                ) from None
            layout.truncated_at = pos
            layout.blocks = [b for b in layout.blocks if b.offset + b.size <= file_size]
        except ValueError as e:
            raise SessionFormatError(path, f"damaged Matroska structure: {e}") from None
    return layout


# ---------------------------------------------------------------------------------------------
# the reader
# ---------------------------------------------------------------------------------------------
class AzureKinectReader(Source):
    """A k4arecorder MKV recording as a seekable :class:`~appfusion.source.Source`.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.mkv`` file.
    skip_bad : bool, default False
        If False, a truncated or damaged file raises :class:`SessionFormatError` on construction and
        an undecodable image raises on reading. If True, a truncated file yields the complete frames
        before the cut, and frames whose colour cannot be decoded get ``rgb=None``.
    pass_name : str or None, default "scan"
        Scanning pass of every frame (an Azure Kinect delivers depth, IR and RGB at once).

    Attributes
    ----------
    caps : StreamCaps
        All streams the recording has, together, at the recording's frame rate.
    intrinsics : dict
        ``"depth"``, ``"ir"`` (equal: same sensor) and ``"rgb"`` :class:`Intrinsics` for the
        recording's modes, from the ``calibration.json`` attachment.
    meta : dict
        ``device``, ``serial``, ``depth_mode``, ``ir_mode``, ``color_format``, ``color_resolution``,
        ``fps``, ``start_offset_s``, ``depth_delay_s``, ``depth_units_per_m`` (1000),
        ``emitter_position_m``, ``depth_to_ir``/``depth_to_rgb`` (nested lists), ``metric_radius``,
        firmware versions and the raw ``calibration_json``.

    Frames carry depth (float32 metres, NaN invalid), IR (float32 counts), RGB (uint8 sRGB, RGB
    order) and timestamps in seconds of device time (see the module docstring).

    Raises
    ------
    SessionFormatError
        The file is missing, not Matroska, truncated, lacks the calibration attachment or the
        DEPTH/IR/COLOR tracks, or has an unsupported mode; the message names the file.
    """

    is_recording = True

    def __init__(self, path: str | os.PathLike, skip_bad: bool = False, pass_name: str | None = "scan"):
        super().__init__()
        self.path = Path(path)
        self.name = f"azure-kinect:{self.path.name}"
        self.skip_bad = skip_bad
        self.pass_name = pass_name
        self._fh = None
        self._pos = 0
        if not self.path.is_file():
            raise SessionFormatError(self.path, "no such file")
        self._layout = _scan(self.path, skip_bad)
        self._read_container()
        self._roles = self._find_tracks()
        self._groups = self._group_blocks()
        if not self._groups:
            raise SessionFormatError(self.path, "the recording contains no depth, IR or colour frames")
        self._configure()

    # -- container metadata (PyAV) -------------------------------------------------------------
    def _read_container(self) -> None:
        import av

        try:
            with av.open(str(self.path)) as c:
                self._tags = {k.upper(): v for k, v in c.metadata.items()}
                self._track_tags: dict[str, dict[str, str]] = {}
                calib = None
                for s in c.streams:
                    md = dict(s.metadata)
                    if s.type == "attachment":
                        if ("K4A_CALIBRATION_FILE" in md or md.get("filename") == "calibration.json") and calib is None:
                            calib = bytes(s.data)
                    elif md.get("title"):
                        self._track_tags[md["title"]] = md
        except av.FFmpegError as e:
            raise SessionFormatError(self.path, f"FFmpeg cannot read the Matroska container: {e}") from None
        if calib is None:
            raise SessionFormatError(self.path, "no calibration.json attachment: not an Azure Kinect "
                                                "(k4arecorder) recording, or its calibration was stripped")
        self._calibration_json = calib

    def _find_tracks(self) -> dict[str, _Track]:
        roles: dict[str, _Track] = {}
        for t in self._layout.tracks.values():
            role = _ROLE_OF_NAME.get(t.name)
            if role is not None and role not in roles:
                roles[role] = t
        if not ({"depth", "ir"} & set(roles)):
            names = ", ".join(repr(t.name) for t in self._layout.tracks.values()) or "none"
            raise SessionFormatError(self.path, f"no DEPTH or IR track (tracks: {names}); not a k4arecorder file")
        for role in ("depth", "ir"):
            t = roles.get(role)
            if t is not None and t.fourcc != "b16g":
                raise SessionFormatError(self.path, f"{t.name} track has FOURCC {t.fourcc!r}, expected 'b16g'")
        return roles

    def _group_blocks(self) -> list[dict[str, _Block]]:
        """Group the tracks' blocks into captures: one block per track, times within half a period."""
        role_of = {t.number: r for r, t in self._roles.items()}
        scale = self._layout.timecode_scale
        events = sorted(((b.ticks * scale, r, b) for b in self._layout.blocks
                         if (r := role_of.get(b.track)) is not None), key=lambda e: (e[0], e[1]))
        durations = [t.default_duration_ns for t in self._roles.values() if t.default_duration_ns > 0]
        if durations:
            period = min(durations)
        else:
            ts = np.unique([e[0] for e in events])
            period = int(np.median(np.diff(ts))) if len(ts) > 1 else 33_333_333
        self._period_ns = period
        groups: list[dict[str, Any]] = []
        t0 = None
        for t, role, blk in events:
            if not groups or role in groups[-1] or t - t0 >= period / 2:
                groups.append({})
                t0 = t
            groups[-1][role] = blk
        if self._layout.truncated_at is not None and groups and set(groups[-1]) != set(self._roles):
            groups.pop()  # the capture the cut went through
        return groups

    def _configure(self) -> None:
        tags, tt = self._tags, self._track_tags
        depth_t = self._roles.get("depth") or self._roles["ir"]
        depth_name = depth_t.name
        depth_mode = tt.get("DEPTH", {}).get("K4A_DEPTH_MODE")
        if depth_mode is None:
            size = (depth_t.width, depth_t.height)
            by_size = {v[2]: k for k, v in DEPTH_MODES.items() if k != "PASSIVE_IR"}
            depth_mode = by_size.get(size) if "depth" in self._roles else "PASSIVE_IR"
            if depth_mode is None:
                raise SessionFormatError(self.path, f"{depth_name} track is {size[0]}x{size[1]}, not an Azure Kinect depth mode")
        if depth_mode not in DEPTH_MODES:
            raise SessionFormatError(self.path, f"unknown K4A_DEPTH_MODE {depth_mode!r}")
        out_w, out_h = DEPTH_MODES[depth_mode][2]
        for role in ("depth", "ir"):
            t = self._roles.get(role)
            if t is not None and (t.width, t.height) != (out_w, out_h):
                raise SessionFormatError(self.path, f"{t.name} track is {t.width}x{t.height} but depth mode "
                                                    f"{depth_mode} gives {out_w}x{out_h}")
        color_res = color_fmt = None
        ct = self._roles.get("rgb")
        if ct is not None:
            mode = tt.get(ct.name, {}).get("K4A_COLOR_MODE", "")
            color_fmt = mode.split("_")[0] if "_" in mode else (ct.fourcc or "BGRA")
            if color_fmt not in _COLOR_FORMATS:
                raise SessionFormatError(self.path, f"COLOR track format {color_fmt!r} is not supported "
                                                    f"({', '.join(_COLOR_FORMATS)})")
            by_size = {v[2]: k for k, v in COLOR_RESOLUTIONS.items()}
            color_res = by_size.get((ct.width, ct.height))
            if color_res is None:
                raise SessionFormatError(self.path, f"COLOR track is {ct.width}x{ct.height}, not an Azure Kinect colour resolution")
        self._color_format = color_fmt
        cal = parse_calibration(self._calibration_json, depth_mode, color_res, self.path)
        self._intrinsics = cal["intrinsics"]
        self._depth_to_rgb = cal["depth_to_rgb"]
        self._depth_mode = depth_mode
        ir_mode = tt.get(self._roles["ir"].name, {}).get("K4A_IR_MODE") if "ir" in self._roles else None
        self._emitter = None if ir_mode is None else ir_mode.upper() != "PASSIVE"
        self._start_offset_ns = int(tags.get("K4A_START_OFFSET_NS", 0) or 0)
        fps = 1e9 / self._period_ns
        streams = set(self._roles)
        self._caps = StreamCaps.all_together(streams, {s: fps for s in streams})
        self._meta = {
            "device": "azure-kinect",
            "model": "Azure Kinect DK",
            "serial": tags.get("K4A_DEVICE_SERIAL_NUMBER") or cal["serial"],
            "depth_mode": depth_mode,
            "ir_mode": ir_mode,
            "color_format": color_fmt,
            "color_resolution": color_res,
            "fps": round(fps, 6),
            "start_offset_s": self._start_offset_ns * 1e-9,
            "depth_delay_s": int(tags.get("K4A_DEPTH_DELAY_NS", 0) or 0) * 1e-9,
            "wired_sync_mode": tags.get("K4A_WIRED_SYNC_MODE"),
            "color_firmware": tags.get("K4A_COLOR_FIRMWARE_VERSION"),
            "depth_firmware": tags.get("K4A_DEPTH_FIRMWARE_VERSION"),
            "depth_units_per_m": 1000.0,
            "rgb_encoding": "srgb8",
            # time-of-flight: the illuminator sits beside the depth lens; k4a does not calibrate its offset
            "emitter_position_m": [0.0, 0.0, 0.0],
            "depth_to_ir": np.eye(4).tolist(),
            "depth_to_rgb": self._depth_to_rgb.tolist(),
            "metric_radius": cal["metric_radius"],
            "truncated": self._layout.truncated_at is not None,
            "calibration_json": self._calibration_json.decode("utf-8", "replace"),
            "path": str(self.path),
        }

    # -- Source API ----------------------------------------------------------------------------
    @property
    def caps(self) -> StreamCaps:
        return self._caps

    @property
    def intrinsics(self) -> dict[str, Intrinsics]:
        return dict(self._intrinsics)

    @property
    def meta(self) -> dict[str, Any]:
        return dict(self._meta)

    @property
    def depth_to_rgb(self) -> np.ndarray:
        """(4, 4) float64 transform from the depth to the colour camera frame (metres)."""
        return self._depth_to_rgb.copy()

    @property
    def timestamps(self) -> np.ndarray:
        """Device timestamps (seconds) of all frames, shape (N,), without reading any image."""
        return np.array([self._timestamp(g) for g in self._groups])

    def __len__(self) -> int:
        return len(self._groups)

    def seek(self, index: int) -> None:
        n = len(self._groups)
        if not -n <= index < n:
            raise IndexError(f"{self.name}: frame {index} out of range (0..{n - 1})")
        self._pos = index % n

    def _open(self) -> None:
        self._fh = open(self.path, "rb")

    def __del__(self):
        fh = getattr(self, "_fh", None)
        if fh is not None:
            fh.close()

    def _close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def _frames(self) -> Iterator[Frame]:
        while self._pos < len(self._groups):
            i = self._pos
            self._pos += 1
            yield self.read_frame(i)

    # -- decoding ------------------------------------------------------------------------------
    def _timestamp(self, group: dict[str, _Block]) -> float:
        blk = group.get("depth") or group.get("ir") or group["rgb"]
        return (blk.ticks * self._layout.timecode_scale + self._start_offset_ns) * 1e-9

    def _payload(self, blk: _Block) -> bytes:
        fh = self._fh
        if fh is None:
            raise SessionFormatError(self.path, "reader is closed; open it (or use it as a context manager) first")
        fh.seek(blk.offset)
        data = fh.read(blk.size)
        if len(data) != blk.size:
            raise SessionFormatError(self.path, f"block at byte {blk.offset} is cut short (file changed while open?)")
        return data

    def _gray16(self, blk: _Block, role: str, index: int) -> np.ndarray:
        t = self._roles[role]
        if blk.size != t.width * t.height * 2:
            raise SessionFormatError(self.path, f"frame {index}: {t.name} image has {blk.size} bytes, expected "
                                                f"{t.width}x{t.height}x2 = {t.width * t.height * 2}")
        return np.frombuffer(self._payload(blk), dtype=">u2").reshape(t.height, t.width)

    def _color(self, blk: _Block, index: int) -> np.ndarray | None:
        import cv2

        t = self._roles["rgb"]
        data = np.frombuffer(self._payload(blk), dtype=np.uint8)
        w, h, fmt = t.width, t.height, self._color_format
        rgb = None
        expected = {"NV12": w * h * 3 // 2, "YUY2": w * h * 2, "BGRA": w * h * 4}.get(fmt)
        if fmt == "MJPG":
            bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
            if bgr is not None and bgr.shape[:2] == (h, w):
                rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        elif data.size == expected:
            if fmt == "NV12":
                rgb = cv2.cvtColor(data.reshape(h * 3 // 2, w), cv2.COLOR_YUV2RGB_NV12)
            elif fmt == "YUY2":
                rgb = cv2.cvtColor(data.reshape(h, w, 2), cv2.COLOR_YUV2RGB_YUY2)
            else:
                rgb = cv2.cvtColor(data.reshape(h, w, 4), cv2.COLOR_BGRA2RGB)
        if rgb is None and not self.skip_bad:
            raise SessionFormatError(self.path, f"frame {index}: the {fmt} colour image at byte {blk.offset} "
                                                f"({blk.size} bytes) cannot be decoded to {w}x{h}")
        return rgb

    def read_frame(self, index: int) -> Frame:
        """Decode frame ``index`` (0-based; negative counts from the end) without moving the cursor.

        Returns
        -------
        Frame
            depth (H, W) float32 metres (NaN where the sensor gave 0), ir (H, W) float32 counts,
            rgb (Hc, Wc, 3) uint8 sRGB; a stream the capture lacks is None.
        """
        n = len(self._groups)
        if not -n <= index < n:
            raise IndexError(f"{self.name}: frame {index} out of range (0..{n - 1})")
        index %= n
        if self._fh is None:
            self.open()
        g = self._groups[index]
        depth = ir = rgb = None
        if "depth" in g:
            raw = self._gray16(g["depth"], "depth", index)
            depth = np.where(raw == 0, np.float32(np.nan), raw.astype(np.float32) * np.float32(1e-3))
        if "ir" in g:
            ir = self._gray16(g["ir"], "ir", index).astype(np.float32)
        if "rgb" in g:
            rgb = self._color(g["rgb"], index)
        return Frame(index=index, timestamp=self._timestamp(g), depth=depth, ir=ir, rgb=rgb,
                     rgb_encoding="srgb8",
                     depth_intrinsics=self._intrinsics.get("depth"), ir_intrinsics=self._intrinsics.get("ir"),
                     rgb_intrinsics=self._intrinsics.get("rgb"),
                     depth_to_ir=np.eye(4), depth_to_rgb=self._depth_to_rgb.copy(),
                     pass_name=self.pass_name, emitter=self._emitter)
