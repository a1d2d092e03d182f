"""The appfusion session format: a crash-safe, lossless, TUM-compatible recording of a scan.

A session is a directory (full specification: ``docs/session-format.md``)::

    meta.json          device, per-stream intrinsics and encodings, extrinsics, emitter position
    depth/ ir/ rgb/    one lossless PNG per image, named by its timestamp
    depth.txt ir.txt rgb.txt   TUM-style index files: "timestamp path" lines
    events.txt         "timestamp key value" lines ("12.500000 pass geometry", "3.0 emitter off")
    groundtruth.txt    optional TUM trajectory "t tx ty tz qx qy qz qw" of the depth camera

The rgb/depth part opens as a TUM RGB-D sequence (depth at 5000 units per metre by default). The
scanning passes of the paper (§4.1 geometry, §4.3 environment, §5 IR reflectometry and RGB, §6 IR
calibration) are recorded one after another and marked by ``pass`` events.

Writing (:class:`SessionWriter`) is crash-safe: every PNG is written under a temporary name in its
stream folder, flushed, fsynced and renamed before its index line is appended, so an index line never
names a missing or half-written image; index files are flushed (handed to the OS) after every frame
and fsynced at most every ``fsync_interval_s`` (default 0.5 s). After ``kill -9`` every frame whose
``write`` returned replays; after a power cut, every frame up to the last index fsync (at most
~0.5 s lost). A half-written last index line is ignored.

Reading (:class:`SessionReader`) checks the whole index at open (existence, PNG signature, header
size/bit depth/colour type against ``meta.json``, PNG end chunk) and raises one
:class:`~appfusion.errors.SessionFormatError` naming the file and line of the first problem, or with
``skip_bad=True`` skips the frames concerned and lists them in :attr:`SessionReader.bad_frames`.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import posixpath
import threading
import time
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from appfusion.errors import AppFusionError, SessionFormatError
from appfusion.frame import STREAMS, Frame, Intrinsics, linear_to_srgb, srgb_to_linear
from appfusion.source import IndexedRecording, Source, StreamCaps

__all__ = [
    "FORMAT", "VERSION", "DEFAULT_UNITS_PER_M", "INDEX_FILES", "SessionWriter", "SessionReader",
    "copy_session", "parse_index", "parse_meta", "parse_events", "parse_groundtruth", "format_timestamp",
    "pose_to_tum", "tum_to_pose",
]

FORMAT = "appfusion-session"
VERSION = 1
#: depth PNG units per metre (TUM RGB-D convention: 5000, i.e. 0.2 mm per unit)
DEFAULT_UNITS_PER_M = 5000.0
#: index file of each stream
INDEX_FILES = {"depth": "depth.txt", "ir": "ir.txt", "rgb": "rgb.txt"}
EVENTS_FILE = "events.txt"
GROUNDTRUTH_FILE = "groundtruth.txt"
META_FILE = "meta.json"
#: PNG encoding names of the rgb stream in meta.json, and the Frame.rgb_encoding each reads back as
RGB_FILE_ENCODINGS = {"srgb8": "srgb8", "linear16": "linear"}
_FRAME_TO_FILE_RGB = {"srgb8": "srgb8", "linear": "linear16"}
#: tolerance when matching ground-truth poses to frames (seconds)
POSE_MATCH_S = 1e-3

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"
_PNG_COLOUR_TYPES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}
_INDEX_HEADERS = {
    "depth": "# depth maps (16-bit PNG, see meta.json streams.depth.units_per_m; 0 = invalid)\n",
    "ir": "# IR images (16-bit PNG, linear sensor counts)\n",
    "rgb": "# colour images (see meta.json streams.rgb.encoding)\n",
}


# ----------------------------------------------------------------------------------------------
# small helpers
# ----------------------------------------------------------------------------------------------
def format_timestamp(t: float) -> str:
    """The canonical text of a timestamp in seconds: fixed point with 6 decimals (microseconds)."""
    return f"{float(t):.6f}"


def _fsync_dir(path: Path) -> None:
    """Make renames/creations inside ``path`` durable (no-op where directories cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder: write, fsync, rename."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def pose_to_tum(pose: np.ndarray) -> tuple[float, ...]:
    """A 4x4 camera-to-world pose as TUM's ``tx ty tz qx qy qz qw`` (metres, unit quaternion)."""
    from scipy.spatial.transform import Rotation

    pose = np.asarray(pose, dtype=np.float64)
    q = Rotation.from_matrix(pose[:3, :3]).as_quat()  # scalar last: x y z w
    if q[3] < 0:
        q = -q
    return (*pose[:3, 3].tolist(), *q.tolist())


def tum_to_pose(values: Iterable[float]) -> np.ndarray:
    """Inverse of :func:`pose_to_tum`: ``tx ty tz qx qy qz qw`` to a 4x4 float64 pose."""
    from scipy.spatial.transform import Rotation

    v = np.asarray(list(values), dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(v[3:7]).as_matrix()
    T[:3, 3] = v[:3]
    return T


def _as_pose(m: Any, what: str) -> np.ndarray:
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise AppFusionError(f"{what}: not a 4x4 matrix of numbers") from None
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise AppFusionError(f"{what}: expected a finite 4x4 matrix, got shape {a.shape}")
    return a


def _read_text_lines(path: Path) -> tuple[list[tuple[int, str]], tuple[int, str] | None]:
    """Lines of a text file as (1-based number, text); a last line without newline returned apart."""
    data = path.read_bytes()
    return _split_lines(data)


def _split_lines(data: bytes | str) -> tuple[list[tuple[int, str]], tuple[int, str] | None]:
    if isinstance(data, str):
        data = data.encode("utf-8", "surrogatepass")
    parts = data.split(b"\n")
    tail = parts.pop()  # after the last newline: b"" when the file ends with one
    lines = [(i + 1, p.decode("utf-8", "replace").rstrip("\r")) for i, p in enumerate(parts)]
    partial = (len(parts) + 1, tail.decode("utf-8", "replace")) if tail.strip() else None
    return lines, partial


class _Problems:
    """Collects (path, line, reason) of bad lines/frames, or raises at the first one."""

    def __init__(self, skip_bad: bool):
        self.skip_bad = skip_bad
        self.items: list[tuple[str, int | None, str]] = []

    def __call__(self, path: str | os.PathLike, line: int | None, reason: str) -> None:
        if not self.skip_bad:
            raise SessionFormatError(path, reason, line)
        self.items.append((os.fspath(path), line, reason))


def _text_records(data: bytes | str, path, skip_bad: bool):
    """``(problems, records, dropped)`` of a line-based text file: ``records`` are the ``(line, text)``
    of its non-blank, non-comment lines (stripped); ``dropped`` the half-written last line, if any."""
    problems = _Problems(skip_bad)
    lines, partial = _split_lines(data)
    dropped = [(os.fspath(path), partial[0], partial[1])] if partial else []
    records = [(no, t.strip()) for no, t in lines if t.strip() and not t.strip().startswith("#")]
    return problems, records, dropped


def _timestamped(records, problems, path, n_fields: int, expected: str, keep_rest: bool = False):
    """``(line, fields, timestamp)`` of the records that split into ``n_fields`` fields (with
    ``keep_rest`` the last one keeps its spaces) and start with a finite timestamp; the others are
    reported to ``problems``."""
    for no, s in records:
        tok = s.split(None, n_fields - 1) if keep_rest else s.split()
        if len(tok) != n_fields:
            problems(path, no, f"expected {expected!r}, got {s[:60]!r}")
            continue
        try:
            t = float(tok[0])
        except ValueError:
            problems(path, no, f"timestamp {tok[0][:40]!r} is not a number")
            continue
        if not math.isfinite(t):
            problems(path, no, f"timestamp {tok[0][:40]!r} is not finite")
            continue
        yield no, tok, t


# ----------------------------------------------------------------------------------------------
# parsers of the text files (pure functions; fuzzed by the tests)
# ----------------------------------------------------------------------------------------------
def parse_index(data: bytes | str, path: str | os.PathLike = "index.txt", stream: str | None = None,
                skip_bad: bool = False):
    """Parse a TUM-style index file (``rgb.txt``, ``depth.txt``, ``ir.txt``).

    Parameters
    ----------
    data : bytes or str
        File contents. ``#`` lines and blank lines are skipped; others are ``timestamp path``.
    path : path-like
        The file's name, for messages.
    stream : str, optional
        When given, every path must lie in the folder of that name (``depth/...``); a path into
        another stream's folder (a swapped index) is an error.
    skip_bad : bool
        Collect bad lines instead of raising at the first.

    Returns
    -------
    entries : list of (line, timestamp_text, timestamp, relpath)
        Good lines, timestamps strictly increasing (seconds).
    bad : list of (path, line, reason)
        Bad lines (only with ``skip_bad``).
    dropped : list of (path, line, text)
        A half-written last line (no newline), which is never an error.

    Raises
    ------
    SessionFormatError
        Naming the file and line of the first bad line (unless ``skip_bad``).
    """
    problems, records, dropped = _text_records(data, path, skip_bad)
    entries: list[tuple[int, str, float, str]] = []
    last_t, last_line = -math.inf, 0
    for no, tok, t in _timestamped(records, problems, path, 2, "timestamp path"):
        rel = tok[1]
        norm = posixpath.normpath(rel)
        if "\\" in rel or posixpath.isabs(rel) or norm == ".." or norm.startswith("../") or norm == ".":
            problems(path, no, f"path {rel[:60]!r} does not lie inside the recording")
            continue
        if stream is not None and not norm.startswith(stream + "/"):
            problems(path, no, f"path {rel[:60]!r} is not in the {stream}/ folder (swapped index files?)")
            continue
        if t <= last_t:
            problems(path, no, f"timestamp {tok[0]} is not after the previous one ({last_t:.6f} on line "
                               f"{last_line}): timestamps must increase")
            continue
        entries.append((no, tok[0], t, norm))
        last_t, last_line = t, no
    return entries, problems.items, dropped


def parse_events(data: bytes | str, path: str | os.PathLike = EVENTS_FILE, skip_bad: bool = False):
    """Parse ``events.txt``: ``timestamp key value`` lines, time non-decreasing.

    Returns ``(events, bad, dropped)`` with ``events`` a list of ``(t, key, value)``; see
    :func:`parse_index` for ``bad`` and ``dropped``.
    """
    problems, records, dropped = _text_records(data, path, skip_bad)
    events: list[tuple[float, str, str]] = []
    last_t = -math.inf
    for no, tok, t in _timestamped(records, problems, path, 3, "timestamp key value", keep_rest=True):
        if t < last_t:
            problems(path, no, f"event time {tok[0]} is before the previous event ({last_t:.6f})")
            continue
        if tok[1] == "emitter" and tok[2].strip().lower() not in _EMITTER_VALUES:
            problems(path, no, f"emitter event value {tok[2][:20]!r} is not on/off")
            continue
        events.append((t, tok[1], tok[2].strip()))
        last_t = t
    return events, problems.items, dropped


_EMITTER_VALUES = {"on": True, "off": False, "1": True, "0": False, "true": True, "false": False}


def parse_groundtruth(data: bytes | str, path: str | os.PathLike = GROUNDTRUTH_FILE, skip_bad: bool = False):
    """Parse a TUM trajectory: ``timestamp tx ty tz qx qy qz qw`` lines (metres, unit quaternion).

    Returns
    -------
    times : (N,) float64 ndarray
        Seconds, strictly increasing.
    poses : (N, 4, 4) float64 ndarray
        Camera-to-world poses.
    bad, dropped : list
        As in :func:`parse_index`.
    """
    problems, records, dropped = _text_records(data, path, skip_bad)
    times: list[float] = []
    vals: list[list[float]] = []
    for no, s in records:
        tok = s.split()
        if len(tok) != 8:
            problems(path, no, f"expected 8 numbers 'timestamp tx ty tz qx qy qz qw', got {len(tok)} fields")
            continue
        try:
            v = [float(x) for x in tok]
        except ValueError:
            problems(path, no, "a field is not a number")
            continue
        if not all(math.isfinite(x) for x in v):
            problems(path, no, "a field is not finite")
            continue
        qn = math.sqrt(sum(x * x for x in v[4:8]))
        if not 0.5 < qn < 2.0:
            problems(path, no, f"quaternion norm {qn:.3g} is far from 1")
            continue
        if times and v[0] <= times[-1]:
            problems(path, no, f"timestamp {tok[0]} is not after the previous one")
            continue
        times.append(v[0])
        vals.append(v[1:])
    poses = np.zeros((len(vals), 4, 4))
    if vals:
        from scipy.spatial.transform import Rotation

        a = np.asarray(vals)
        poses[:, :3, :3] = Rotation.from_quat(a[:, 3:7]).as_matrix()
        poses[:, :3, 3] = a[:, :3]
        poses[:, 3, 3] = 1.0
    return np.asarray(times, dtype=np.float64), poses, problems.items, dropped


def _field(d: dict, key: str, path, where: str):
    if not isinstance(d, dict) or key not in d:
        raise SessionFormatError(path, f"missing field {where + key!r}")
    return d[key]


def _matrix_field(d: dict, key: str, path) -> np.ndarray:
    v = _field(d, key, path, "extrinsics.")
    try:
        return _as_pose(v, f"extrinsics.{key}")
    except AppFusionError as e:
        raise SessionFormatError(path, str(e)) from None


def parse_meta(data: bytes | str, path: str | os.PathLike = META_FILE) -> dict[str, Any]:
    """Parse and validate ``meta.json``.

    Returns
    -------
    dict
        The JSON object, plus parsed values under ``"_intrinsics"`` (stream -> Intrinsics) and
        ``"_extrinsics"`` (name -> (4, 4) ndarray).

    Raises
    ------
    SessionFormatError
        Bad JSON (with its line), wrong format or version, a missing or malformed field.
    """
    try:
        text = data.decode("utf-8") if isinstance(data, bytes) else data
        meta = json.loads(text)
    except UnicodeDecodeError as e:
        raise SessionFormatError(path, f"not UTF-8 text ({e.reason} at byte {e.start})") from None
    except json.JSONDecodeError as e:
        raise SessionFormatError(path, f"not valid JSON: {e.msg} (column {e.colno})", e.lineno) from None
    except RecursionError:
        raise SessionFormatError(path, "not valid JSON: nested too deeply") from None
    if not isinstance(meta, dict):
        raise SessionFormatError(path, f"expected a JSON object, got {type(meta).__name__}")
    fmt = _field(meta, "format", path, "")
    if fmt != FORMAT:
        raise SessionFormatError(path, f"format is {str(fmt)[:40]!r}, expected {FORMAT!r}")
    ver = _field(meta, "version", path, "")
    if not isinstance(ver, int) or isinstance(ver, bool) or ver < 1:
        raise SessionFormatError(path, f"version {ver!r} is not a positive integer")
    if ver > VERSION:
        raise SessionFormatError(path, f"version {ver} is newer than this reader understands ({VERSION})")
    dev = _field(meta, "device", path, "")
    if not isinstance(dev, str):
        raise SessionFormatError(path, "field 'device' must be a string")
    streams = _field(meta, "streams", path, "")
    if not isinstance(streams, dict):
        raise SessionFormatError(path, "field 'streams' must be an object")
    intr: dict[str, Intrinsics] = {}
    for name, s in streams.items():
        if name not in STREAMS:
            raise SessionFormatError(path, f"unknown stream {str(name)[:20]!r} (known: {', '.join(STREAMS)})")
        if not isinstance(s, dict):
            raise SessionFormatError(path, f"streams.{name} must be an object")
        ij = _field(s, "intrinsics", path, f"streams.{name}.")
        try:
            if not isinstance(ij, dict):
                raise AppFusionError("not an object")
            intr[name] = Intrinsics.from_json(ij)
        except (AppFusionError, TypeError, ValueError, OverflowError) as e:
            raise SessionFormatError(path, f"streams.{name}.intrinsics: {e}") from None
        enc = _field(s, "encoding", path, f"streams.{name}.")
        want = ("png16",) if name in ("depth", "ir") else tuple(RGB_FILE_ENCODINGS)
        if enc not in want:
            raise SessionFormatError(path, f"streams.{name}.encoding is {str(enc)[:20]!r}, expected one of {want}")
        if name == "depth":
            u = _field(s, "units_per_m", path, "streams.depth.")
            if isinstance(u, bool) or not isinstance(u, (int, float)) or not math.isfinite(u) or u <= 0:
                raise SessionFormatError(path, f"streams.depth.units_per_m must be a positive number, got {u!r}")
        if name == "ir":
            b = s.get("bits", 16)
            if isinstance(b, bool) or not isinstance(b, int) or not 1 <= b <= 16:
                raise SessionFormatError(path, f"streams.ir.bits must be an integer 1..16, got {b!r}")
    ext = _field(meta, "extrinsics", path, "")
    if not isinstance(ext, dict):
        raise SessionFormatError(path, "field 'extrinsics' must be an object")
    extr = {k: _matrix_field(ext, k, path) for k in ("depth_to_ir", "depth_to_rgb")}
    em = meta.get("emitter_position_m", [0.075, 0.0, 0.0])
    if (not isinstance(em, list) or len(em) != 3
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in em)):
        raise SessionFormatError(path, f"emitter_position_m must be 3 numbers, got {str(em)[:40]}")
    for key, typ in (("notes", str), ("extra", dict), ("created", str)):
        if key in meta and not isinstance(meta[key], typ):
            raise SessionFormatError(path, f"field {key!r} must be a {typ.__name__}")
    meta["_intrinsics"] = intr
    meta["_extrinsics"] = extr
    return meta


# ----------------------------------------------------------------------------------------------
# PNG checks and decoding
# ----------------------------------------------------------------------------------------------
def _expected_png(stream: str, rgb_file_encoding: str) -> tuple[int, int]:
    """(bit depth, colour type) a stream's PNGs must have."""
    if stream in ("depth", "ir"):
        return 16, 0
    return (8, 2) if rgb_file_encoding == "srgb8" else (16, 2)


def check_png(path: Path, shape: tuple[int, int] | None, bits: int | None, colour: int | None) -> str | None:
    """Cheap structural check of a PNG file without decoding it.

    Reads the signature and IHDR chunk (first 33 bytes) and the IEND chunk (last 12 bytes).

    Returns
    -------
    str or None
        What is wrong (missing, truncated, wrong size or pixel format), or None if it looks right.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(33)
            size = f.seek(0, os.SEEK_END)
            if size >= 45:
                f.seek(size - 12)
            tail = f.read(12)
    except FileNotFoundError:
        return "file is missing"
    except IsADirectoryError:
        return "is a directory, not a PNG file"
    except OSError as e:
        return f"cannot be read ({e.strerror})"
    if len(head) < 33 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return f"not a PNG file ({size} bytes)" if size else "empty file (0 bytes)"
    if tail != _PNG_IEND:
        return f"truncated PNG ({size} bytes, no IEND chunk at the end)"
    w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    b, c = head[24], head[25]
    if shape is not None and (h, w) != tuple(shape):
        return f"image is {w}x{h}, meta.json says {shape[1]}x{shape[0]}"
    if (bits is not None and b != bits) or (colour is not None and c != colour):
        return (f"image is {b}-bit {_PNG_COLOUR_TYPES.get(c, c)}, expected {bits}-bit "
                f"{_PNG_COLOUR_TYPES.get(colour, colour)} (swapped or foreign file?)")
    return None


def read_image(path: Path, line: int | None = None, index: str | os.PathLike | None = None) -> np.ndarray:
    """Decode an image file unchanged (PNG/JPG; channels converted from OpenCV's BGR to RGB).

    Raises
    ------
    SessionFormatError
        Naming the image (and the index file and line that point to it) if it cannot be decoded.
    """
    import cv2

    where = f" (from {os.fspath(index)}:{line})" if index is not None else ""
    try:
        buf = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise SessionFormatError(path, f"file is missing{where}") from None
    except OSError as e:
        raise SessionFormatError(path, f"cannot be read: {e.strerror}{where}") from None
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if img is None:
        raise SessionFormatError(path, f"cannot decode image ({buf.size} bytes){where}")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[..., :3]
        img = np.ascontiguousarray(img[..., ::-1])
    return img


# ----------------------------------------------------------------------------------------------
# writer
# ----------------------------------------------------------------------------------------------
class SessionWriter:
    """Record frames into a session directory, crash-safely.

    Parameters
    ----------
    path : path-like
        Directory to create (it may exist if empty).
    device : str
        Device model / name.
    intrinsics : dict of str -> Intrinsics, optional
        Intrinsics of the streams that will be recorded. A stream first seen in a frame is added
        to ``meta.json`` (rewritten atomically) from the frame's own intrinsics.
    depth_to_ir, depth_to_rgb : (4, 4) array, optional
        Extrinsics in metres (identity by default; a Kinect v1's ``depth_to_ir`` is the identity).
    depth_units_per_m : float
        Depth PNG units per metre (TUM: 5000). Depths beyond ``65535 / depth_units_per_m`` metres
        are stored as invalid (0) and counted in :attr:`clipped_depth_pixels`.
    rgb_encoding : {"srgb8", "linear"}
        ``"srgb8"``: 8-bit sRGB PNG; ``"linear"``: 16-bit linear PNG (``"linear16"`` in meta).
        Frames in the other encoding are converted.
    emitter_position_m : 3 floats
        IR emitter position in the depth camera frame (metres).
    notes : str
    extra : dict
        Any JSON-serialisable extra metadata.
    ir_bits : int
        Significant bits of IR counts (Kinect v1: 10).
    png_compression : int
        zlib level 0..9 for the PNGs (1: fast, lossless in every case).
    fsync_interval_s : float
        Index files are flushed after every frame and fsynced (with the folders that gained images)
        when this much time has passed since their last fsync; 0 fsyncs every frame. PNGs are always
        fsynced before they are indexed. Default 0.5 s: measured on the 2-core build machine,
        fsyncing indices and folders every frame cost ~15 ms per 640x480 depth+IR frame against
        ~2 ms at 0.5 s.
    threads : int
        Encode and write the images of one frame in up to this many parallel threads (OpenCV
        releases the GIL); 1 (default) writes them one after another. On the shared 2-core build
        machine no gain was measurable; a recorder on a multi-core machine may ask for 2 or 3.

    Notes
    -----
    ``write`` appends one frame: every image of it is written and renamed into place, then its
    index lines are appended. Frame timestamps must increase (after rounding to microseconds). A
    change of ``frame.pass_name`` or ``frame.emitter`` is recorded as an event automatically.
    """

    def __init__(self, path: str | os.PathLike, device: str = "unknown",
                 intrinsics: dict[str, Intrinsics] | None = None, depth_to_ir: Any = None, depth_to_rgb: Any = None,
                 depth_units_per_m: float = DEFAULT_UNITS_PER_M, rgb_encoding: str = "srgb8",
                 emitter_position_m: Iterable[float] = (0.075, 0.0, 0.0), notes: str = "",
                 extra: dict | None = None, ir_bits: int = 10, png_compression: int = 1,
                 fsync_interval_s: float = 0.5, threads: int = 1):
        self.path = Path(path)
        if rgb_encoding not in _FRAME_TO_FILE_RGB:
            raise AppFusionError(f"session writer: rgb_encoding must be 'srgb8' or 'linear', got {rgb_encoding!r}")
        if not (isinstance(depth_units_per_m, (int, float)) and math.isfinite(depth_units_per_m)
                and depth_units_per_m > 0):
            raise AppFusionError(f"session writer: depth_units_per_m must be positive, got {depth_units_per_m!r}")
        if not isinstance(ir_bits, int) or not 1 <= ir_bits <= 16:
            raise AppFusionError(f"session writer: ir_bits must be 1..16, got {ir_bits!r}")
        em = [float(x) for x in emitter_position_m]
        if len(em) != 3 or not all(math.isfinite(x) for x in em):
            raise AppFusionError(f"session writer: emitter_position_m must be 3 finite numbers, got {em}")
        extra = dict(extra or {})
        try:
            json.dumps(extra)
        except (TypeError, ValueError) as e:
            raise AppFusionError(f"session writer: 'extra' is not JSON-serialisable: {e}") from None
        self.device = str(device)
        self.rgb_encoding = rgb_encoding
        self.units_per_m = float(depth_units_per_m)
        self.ir_bits = ir_bits
        self.png_compression = int(png_compression)
        self.fsync_interval_s = float(fsync_interval_s)
        self.depth_to_ir = _as_pose(np.eye(4) if depth_to_ir is None else depth_to_ir, "depth_to_ir")
        self.depth_to_rgb = _as_pose(np.eye(4) if depth_to_rgb is None else depth_to_rgb, "depth_to_rgb")
        self._intr: dict[str, Intrinsics] = {}
        for k, v in (intrinsics or {}).items():
            if k not in STREAMS:
                raise AppFusionError(f"session writer: unknown stream {k!r} in intrinsics (known: {', '.join(STREAMS)})")
            self._intr[k] = v if isinstance(v, Intrinsics) else Intrinsics.from_json(v)
        self._emitter_position = em
        self._notes = str(notes)
        self._extra = extra
        self._created = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")

        if self.path.exists():
            if not self.path.is_dir():
                raise AppFusionError(f"session writer: {self.path} exists and is not a directory")
            if any(self.path.iterdir()):
                raise AppFusionError(f"session writer: {self.path} is not empty; refusing to overwrite a recording")
        self.path.mkdir(parents=True, exist_ok=True)

        self.threads = int(threads)
        self._pool = None
        self._lock = threading.Lock()
        self._files: dict[str, Any] = {}
        self._dirty_files: set[str] = set()
        self._dirty_dirs: set[Path] = set()
        self._last_fsync = time.monotonic()
        self._closed = False
        self._last_t: float | None = None
        self._last_event_t = -math.inf
        self._pass: str | None = None
        self._emitter: bool | None = None
        #: frames written, per stream
        self.counts = {s: 0 for s in STREAMS}
        #: number of frames written
        self.n_frames = 0
        #: depth pixels that did not fit the 16-bit range and were stored as invalid
        self.clipped_depth_pixels = 0
        #: seconds spent fsyncing index/event files and folders (the periodic part of crash safety)
        self.fsync_seconds = 0.0
        #: seconds spent writing + fsyncing + renaming image files
        self.image_write_seconds = 0.0
        #: seconds spent encoding PNGs
        self.encode_seconds = 0.0

        self._write_meta()
        for s in self._intr:
            self._open_stream(s)
        self._open_text(EVENTS_FILE, "# events: timestamp key value\n")
        self._sync(force=True)

    # -- meta ----------------------------------------------------------------------------------
    def meta_dict(self) -> dict[str, Any]:
        """The contents of ``meta.json`` as written."""
        streams: dict[str, Any] = {}
        for s in STREAMS:
            if s not in self._intr:
                continue
            d: dict[str, Any] = {"intrinsics": self._intr[s].to_json()}
            if s == "depth":
                d.update(encoding="png16", units_per_m=self.units_per_m)
            elif s == "ir":
                d.update(encoding="png16", bits=self.ir_bits)
            else:
                d.update(encoding=_FRAME_TO_FILE_RGB[self.rgb_encoding])
            streams[s] = d
        return {"format": FORMAT, "version": VERSION, "device": self.device, "created": self._created,
                "streams": streams,
                "extrinsics": {"depth_to_ir": self.depth_to_ir.tolist(), "depth_to_rgb": self.depth_to_rgb.tolist()},
                "emitter_position_m": self._emitter_position, "notes": self._notes, "extra": self._extra}

    def _write_meta(self) -> None:
        data = json.dumps(self.meta_dict(), indent=2).encode("utf-8") + b"\n"
        _atomic_write(self.path / META_FILE, data)
        _fsync_dir(self.path)

    def _open_text(self, name: str, header: str):
        f = open(self.path / name, "a", encoding="utf-8", newline="\n")
        if f.tell() == 0:
            f.write(header)
            f.flush()
        self._files[name] = f
        self._dirty_files.add(name)
        self._dirty_dirs.add(self.path)
        return f

    def _append(self, name: str, text: str) -> None:
        """Append whole lines to a text file with one write, and hand them to the OS (flush)."""
        f = self._files[name]
        f.write(text)
        f.flush()
        self._dirty_files.add(name)

    def _open_stream(self, s: str) -> None:
        (self.path / s).mkdir(exist_ok=True)
        self._dirty_dirs.add(self.path)
        self._open_text(INDEX_FILES[s], _INDEX_HEADERS[s] + "# timestamp filename\n")

    def _sync(self, force: bool = False) -> None:
        """fsync the folders that gained files, then the text files that grew, since the last sync."""
        now = time.monotonic()
        if not force and now - self._last_fsync < self.fsync_interval_s:
            return
        if not (self._dirty_dirs or self._dirty_files):
            return
        t0 = time.perf_counter()
        # folders first: an index line made durable must not name an image whose rename is not
        for d in sorted(self._dirty_dirs, key=lambda p: -len(p.parts)):
            _fsync_dir(d)
        for name in sorted(self._dirty_files):
            os.fsync(self._files[name].fileno())
        self._dirty_dirs.clear()
        self._dirty_files.clear()
        self.fsync_seconds += time.perf_counter() - t0
        self._last_fsync = now

    # -- writing -------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise AppFusionError(f"session writer: {self.path} is closed")

    def event(self, timestamp: float, key: str, value: Any) -> None:
        """Append ``timestamp key value`` to ``events.txt`` (e.g. ``event(t, "pass", "geometry")``).

        Event times must not decrease. ``emitter`` values may be bools or on/off.
        """
        self._check_open()
        key = str(key)
        if not key or any(c.isspace() for c in key):
            raise AppFusionError(f"session writer: event key {key!r} must be one word")
        if isinstance(value, bool):
            value = "on" if value else "off"
        value = str(value).strip()
        if not value or "\n" in value or "\r" in value:
            raise AppFusionError(f"session writer: event value {value!r} must be non-empty and on one line")
        if key == "emitter" and value.lower() not in _EMITTER_VALUES:
            raise AppFusionError(f"session writer: emitter event value must be on/off, got {value!r}")
        t = float(timestamp)
        if not math.isfinite(t) or t < self._last_event_t:
            raise AppFusionError(f"session writer: event time {t} is before the previous event "
                                 f"({self._last_event_t}); events must be in time order")
        self._append(EVENTS_FILE, f"{format_timestamp(t)} {key} {value}\n")
        self._last_event_t = t
        if key == "pass":
            self._pass = value
        elif key == "emitter":
            self._emitter = _EMITTER_VALUES[value.lower()]
        self._sync()

    def _encode(self, stream: str, img: np.ndarray, frame: Frame, intr: Intrinsics) -> np.ndarray:
        """Convert a frame image to the PNG array of its stream (uint16 or uint8; RGB order)."""
        shape = intr.shape
        if img.shape[:2] != shape:
            raise AppFusionError(f"session writer: frame {frame.index} {stream} image is "
                                 f"{img.shape[1]}x{img.shape[0]}, the session's {stream} intrinsics say "
                                 f"{shape[1]}x{shape[0]}")
        if stream == "depth":
            if img.ndim != 2:
                raise AppFusionError(f"session writer: frame {frame.index} depth must be (H, W), got {img.shape}")
            d = np.asarray(img, dtype=np.float64) * self.units_per_m
            with np.errstate(invalid="ignore"):
                u = np.rint(d)
                bad = ~(u <= 65535.0)  # NaN or too far
                bad &= np.isfinite(img) & (img > 0)  # count only real depths that do not fit
                u[~(u >= 1.0) | ~(u <= 65535.0)] = 0
            self.clipped_depth_pixels += int(np.count_nonzero(bad))
            return u.astype(np.uint16)
        if stream == "ir":
            if img.ndim != 2:
                raise AppFusionError(f"session writer: frame {frame.index} IR must be (H, W), got {img.shape}")
            a = np.asarray(img, dtype=np.float64)
            if not np.all(np.isfinite(a)):
                raise AppFusionError(f"session writer: frame {frame.index} IR image has NaN or infinite counts")
            return np.clip(np.rint(a), 0, 65535).astype(np.uint16)
        if img.ndim != 3 or img.shape[2] != 3:
            raise AppFusionError(f"session writer: frame {frame.index} RGB must be (H, W, 3), got {img.shape}")
        if frame.rgb_encoding == "srgb8" and img.dtype != np.uint8:
            raise AppFusionError(f"session writer: frame {frame.index} says srgb8 but RGB is {img.dtype}")
        if self.rgb_encoding == "srgb8":
            if frame.rgb_encoding == "srgb8":
                return img
            return np.rint(linear_to_srgb(img) * 255.0).astype(np.uint8)
        lin = srgb_to_linear(img) if frame.rgb_encoding == "srgb8" else np.asarray(img, dtype=np.float64)
        if not np.all(np.isfinite(lin)):
            raise AppFusionError(f"session writer: frame {frame.index} linear RGB has NaN or infinite values")
        return np.rint(np.clip(lin, 0.0, 1.0) * 65535.0).astype(np.uint16)

    def _write_png(self, stream: str, name: str, arr: np.ndarray) -> None:
        import cv2

        if arr.ndim == 3:
            arr = arr[..., ::-1]
        t0 = time.perf_counter()
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr), [cv2.IMWRITE_PNG_COMPRESSION, self.png_compression])
        if not ok:  # pragma: no cover - OpenCV encodes every uint8/uint16 array
            raise AppFusionError(f"session writer: cannot encode {stream} image as PNG")
        t1 = time.perf_counter()
        _atomic_write(self.path / stream / name, buf.tobytes())
        t2 = time.perf_counter()
        with self._lock:
            self._dirty_dirs.add(self.path / stream)
            self.encode_seconds += t1 - t0
            self.image_write_seconds += t2 - t1

    def write(self, frame: Frame) -> None:
        """Append one frame (all its streams, its pose, and pass/emitter changes as events)."""
        self._check_open()
        t = float(frame.timestamp)
        if not math.isfinite(t):
            raise AppFusionError(f"session writer: frame {frame.index} has timestamp {t}")
        ts = format_timestamp(t)
        if self._last_t is not None and float(ts) <= self._last_t:
            raise AppFusionError(f"session writer: frame {frame.index} timestamp {ts} is not after the previous "
                                 f"frame's ({format_timestamp(self._last_t)}); timestamps must increase by >= 1 us")
        streams = frame.streams
        if not streams:
            raise AppFusionError(f"session writer: frame {frame.index} at {ts} has no images")
        new = [s for s in streams if s not in self._intr]
        intr = dict(self._intr)
        for s in new:
            fi = getattr(frame, f"{s}_intrinsics")
            if fi is None:
                raise AppFusionError(f"session writer: frame {frame.index} has a {s} image but the session was "
                                     f"opened without {s} intrinsics and the frame carries none")
            intr[s] = fi
        encoded = {s: self._encode(s, getattr(frame, s), frame, intr[s]) for s in streams}
        if new:
            self._intr = intr
            self._write_meta()
            for s in new:
                self._open_stream(s)
        if frame.pass_name is not None and frame.pass_name != self._pass:
            self.event(max(t, self._last_event_t), "pass", frame.pass_name)
        if frame.emitter is not None and frame.emitter != self._emitter:
            self.event(max(t, self._last_event_t), "emitter", frame.emitter)
        name = f"{ts}.png"
        if len(streams) > 1 and self.threads > 1:
            if self._pool is None:
                from concurrent.futures import ThreadPoolExecutor

                self._pool = ThreadPoolExecutor(max_workers=min(self.threads, len(STREAMS)),
                                                thread_name_prefix="session-png")
            for fut in [self._pool.submit(self._write_png, s, name, encoded[s]) for s in streams]:
                fut.result()  # re-raises an error of any image (then nothing of this frame is indexed)
        else:
            for s in streams:
                self._write_png(s, name, encoded[s])
        # all images are in place: now index them (one short write per file)
        for s in streams:
            self._append(INDEX_FILES[s], f"{ts} {s}/{name}\n")
            self.counts[s] += 1
        if frame.pose is not None:
            pose = _as_pose(frame.pose, f"frame {frame.index} pose")
            if GROUNDTRUTH_FILE not in self._files:
                self._open_text(GROUNDTRUTH_FILE, "# ground truth trajectory of the depth camera (camera to world)\n"
                                                  "# timestamp tx ty tz qx qy qz qw\n")
            self._append(GROUNDTRUTH_FILE, ts + "".join(f" {v:.10g}" for v in pose_to_tum(pose)) + "\n")
        self._last_t = float(ts)
        self.n_frames += 1
        self._sync()

    def close(self) -> None:
        """Flush and fsync everything; the writer cannot be used afterwards."""
        if self._closed:
            return
        try:
            self._sync(force=True)
        finally:
            for f in self._files.values():
                f.close()
            if self._pool is not None:
                self._pool.shutdown()
            self._closed = True

    def __enter__(self) -> "SessionWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ----------------------------------------------------------------------------------------------
# reader
# ----------------------------------------------------------------------------------------------
def _caps_from_groups(streams: Iterable[str], combos: Iterable[frozenset], rates: dict[str, float]) -> StreamCaps:
    """Stream caps from the stream combinations frames actually have (maximal sets only)."""
    combos = set(combos)
    maximal = sorted((c for c in combos if not any(c < o for o in combos)), key=lambda c: sorted(c))
    s = frozenset(streams)
    return StreamCaps(s, tuple(maximal) if maximal else (s,), rates)


def _rates(times: dict[str, np.ndarray]) -> dict[str, float]:
    """Median frame rate (Hz) per stream from its timestamps."""
    out = {}
    for s, t in times.items():
        dt = np.diff(np.asarray(t, dtype=np.float64))
        dt = dt[dt > 0]
        if dt.size:
            out[s] = float(1.0 / np.median(dt))
    return out


class SessionReader(IndexedRecording):
    """Replay a session directory as a :class:`~appfusion.source.Source`.

    Parameters
    ----------
    path : path-like
        The session directory.
    skip_bad : bool
        False: any damage raises one :class:`SessionFormatError` naming the file and line. True:
        frames with a bad index line or image are skipped and listed in :attr:`bad_frames`.
    check_images : bool
        Check every indexed PNG's header and end chunk at open (default; ~0.3 ms per image on the
        loaded build machine). False only checks that the files exist; damaged images are then
        found when their frame is read.

    Attributes
    ----------
    bad_frames : list of (path, line, reason)
        Problems skipped (``skip_bad=True``); images that fail to decode during iteration are
        appended when met (such frames are skipped, so iteration may yield fewer than ``len``).
    dropped_lines : list of (path, line, text)
        Half-written last lines of index/event files (after a crash); never an error.
    events : list of (t, key, value)
        From ``events.txt``, in time order.
    """

    def __init__(self, path: str | os.PathLike, skip_bad: bool = False, check_images: bool = True):
        super().__init__()
        self.path = Path(path)
        self.name = f"session {self.path}"
        self.skip_bad = bool(skip_bad)
        if not self.path.is_dir():
            raise SessionFormatError(self.path, "not a directory (a session is a directory with meta.json)")
        mp = self.path / META_FILE
        try:
            raw = mp.read_bytes()
        except FileNotFoundError:
            raise SessionFormatError(mp, "missing: not an appfusion session") from None
        except OSError as e:
            raise SessionFormatError(mp, f"cannot be read: {e.strerror}") from None
        m = parse_meta(raw, mp)
        self._intr: dict[str, Intrinsics] = m.pop("_intrinsics")
        ext = m.pop("_extrinsics")
        self.depth_to_ir, self.depth_to_rgb = ext["depth_to_ir"], ext["depth_to_rgb"]
        self._meta = m
        streams = m["streams"]
        self.units_per_m = float(streams["depth"]["units_per_m"]) if "depth" in streams else DEFAULT_UNITS_PER_M
        self.rgb_file_encoding = streams["rgb"]["encoding"] if "rgb" in streams else "srgb8"
        self.rgb_encoding = RGB_FILE_ENCODINGS[self.rgb_file_encoding]
        self.bad_frames: list[tuple[str, int | None, str]] = []
        self.dropped_lines: list[tuple[str, int, str]] = []
        problems = _Problems(self.skip_bad)

        # index files
        groups: dict[str, dict[str, tuple[int, str]]] = {}
        gtime: dict[str, float] = {}
        bad_ts: set[str] = set()
        for s in STREAMS:
            if s not in streams:
                continue
            ip = self.path / INDEX_FILES[s]
            try:
                data = ip.read_bytes()
            except FileNotFoundError:
                raise SessionFormatError(ip, f"missing: meta.json declares a {s} stream") from None
            entries, bad, dropped = parse_index(data, ip, stream=s, skip_bad=self.skip_bad)
            problems.items.extend(bad)
            if bad:  # a bad line with a readable timestamp makes that whole frame bad
                text = dict(_split_lines(data)[0])
                bad_ts.update(tok[0] for tok in (text[b[1]].split() for b in bad) if tok)
            self.dropped_lines.extend(dropped)
            folder = self.path / s
            try:
                present = set(os.listdir(folder))
            except FileNotFoundError:
                present = set()
            bits, colour = _expected_png(s, self.rgb_file_encoding)
            for no, ts, t, rel in entries:
                fp = self.path / rel
                if rel.count("/") == 1 and rel.split("/")[1] not in present:
                    reason = f"points to {rel}, which does not exist"
                elif not check_images and rel.count("/") == 1:
                    reason = None
                else:
                    why = check_png(fp, self._intr[s].shape, bits, colour)
                    reason = None if why is None else f"{rel}: {why}"
                if reason is not None:
                    problems(ip, no, reason)
                    bad_ts.add(ts)
                    continue
                groups.setdefault(ts, {})[s] = (no, rel)
                gtime[ts] = t
        for ts in bad_ts:
            groups.pop(ts, None)
        order = sorted(groups, key=lambda k: (gtime[k], k))
        self._groups = [groups[k] for k in order]
        self._times = np.array([gtime[k] for k in order], dtype=np.float64)

        # events
        ep = self.path / EVENTS_FILE
        self.events: list[tuple[float, str, str]] = []
        if ep.exists():
            self.events, bad, dropped = parse_events(ep.read_bytes(), ep, skip_bad=self.skip_bad)
            problems.items.extend(bad)
            self.dropped_lines.extend(dropped)
        self._pass = self._event_lookup("pass", lambda v: v)
        self._emit = self._event_lookup("emitter", lambda v: _EMITTER_VALUES[v.lower()])

        # ground truth
        self._poses: list[np.ndarray | None] = [None] * len(self._times)
        gp = self.path / GROUNDTRUTH_FILE
        if gp.exists():
            gt_t, gt_p, bad, dropped = parse_groundtruth(gp.read_bytes(), gp, skip_bad=self.skip_bad)
            problems.items.extend(bad)
            self.dropped_lines.extend(dropped)
            self._poses = _match_poses(self._times, gt_t, gt_p, POSE_MATCH_S)
        self.bad_frames.extend(problems.items)

        combos = [frozenset(g) for g in self._groups]
        st = self.stream_timestamps()
        self._caps = _caps_from_groups(streams, combos, _rates(st))
        self._pos = 0

    def _event_lookup(self, key: str, conv):
        ev = [(t, conv(v)) for t, k, v in self.events if k == key]
        if not ev:
            return [None] * len(self._times)
        et = np.array([e[0] for e in ev])
        idx = np.searchsorted(et, self._times, side="right") - 1
        return [ev[i][1] if i >= 0 else None for i in idx]

    # -- Source API ----------------------------------------------------------------------------
    @property
    def caps(self) -> StreamCaps:
        return self._caps

    @property
    def intrinsics(self) -> dict[str, Intrinsics]:
        return dict(self._intr)

    @property
    def meta(self) -> dict[str, Any]:
        """meta.json as a dict, plus ``format_name`` ("session") and ``depth_units_per_m``."""
        return {**self._meta, "format_name": "session", "depth_units_per_m": self.units_per_m}

    def __len__(self) -> int:
        return len(self._groups)


    def stream_timestamps(self) -> dict[str, np.ndarray]:
        """Timestamps (seconds) of the frames that have each stream, without decoding images."""
        out = {}
        for s in self._intr:
            sel = [k for k, g in enumerate(self._groups) if s in g]
            out[s] = self._times[sel]
        return out

    @property
    def timestamps(self) -> np.ndarray:
        """(N,) frame timestamps in seconds."""
        return self._times.copy()

    @property
    def poses(self) -> list[np.ndarray | None]:
        """Ground-truth pose of each frame (from groundtruth.txt) or None, without decoding images."""
        return [None if p is None else p.copy() for p in self._poses]

    def __getitem__(self, index: int) -> Frame:
        return self.frame(index)

    def frame(self, index: int) -> Frame:
        """Decode frame ``index`` (0-based); raises SessionFormatError naming file and line if damaged."""
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"{self.name}: frame {index} out of range (0..{n - 1})")
        index %= n
        g = self._groups[index]
        imgs: dict[str, np.ndarray] = {}
        for s, (no, rel) in g.items():
            ip = self.path / INDEX_FILES[s]
            img = read_image(self.path / rel, no, ip)
            bits, colour = _expected_png(s, self.rgb_file_encoding)
            want_dtype = np.uint16 if bits == 16 else np.uint8
            want_shape = self._intr[s].shape + ((3,) if colour == 2 else ())
            if img.dtype != want_dtype or img.shape != want_shape:
                raise SessionFormatError(self.path / rel, f"decoded {img.dtype} image of shape {img.shape}, "
                                                          f"expected {np.dtype(want_dtype)} {want_shape} "
                                                          f"(from {ip}:{no})")
            if s == "depth":
                d = img.astype(np.float32) / np.float32(self.units_per_m)
                d[img == 0] = np.nan
                imgs[s] = d
            elif s == "ir":
                imgs[s] = img.astype(np.float32)
            elif self.rgb_file_encoding == "linear16":
                imgs[s] = img.astype(np.float32) / np.float32(65535.0)
            else:
                imgs[s] = img
        pose = self._poses[index]
        return Frame(index=index, timestamp=float(self._times[index]), depth=imgs.get("depth"), ir=imgs.get("ir"),
                     rgb=imgs.get("rgb"), rgb_encoding=self.rgb_encoding,
                     depth_intrinsics=self._intr.get("depth"), ir_intrinsics=self._intr.get("ir"),
                     rgb_intrinsics=self._intr.get("rgb"), depth_to_ir=self.depth_to_ir.copy(),
                     depth_to_rgb=self.depth_to_rgb.copy(), pose=None if pose is None else pose.copy(),
                     pass_name=self._pass[index], emitter=self._emit[index])


def _match_poses(times: np.ndarray, gt_t: np.ndarray, gt_p: np.ndarray, tol: float) -> list[np.ndarray | None]:
    """Pose of the nearest ground-truth sample within ``tol`` seconds of each time, else None."""
    if len(gt_t) == 0 or len(times) == 0:
        return [None] * len(times)
    j = np.clip(np.searchsorted(gt_t, times), 1, max(len(gt_t) - 1, 1))
    j0 = np.clip(j - 1, 0, len(gt_t) - 1)
    j1 = np.clip(j, 0, len(gt_t) - 1)
    pick = np.where(np.abs(gt_t[j0] - times) <= np.abs(gt_t[j1] - times), j0, j1)
    ok = np.abs(gt_t[pick] - times) <= tol + 1e-9
    return [gt_p[k] if o else None for k, o in zip(pick, ok)]


# ----------------------------------------------------------------------------------------------
# conversion
# ----------------------------------------------------------------------------------------------
def copy_session(src: Source, dst_path: str | os.PathLike, depth_units_per_m: float | None = None,
                 device: str | None = None, notes: str | None = None, show_progress: bool = False,
                 fsync_interval_s: float = 0.5) -> dict[str, Any]:
    """Write every frame (and event) of any recording into a new session directory.

    Parameters
    ----------
    src : Source
        A recording (anything :func:`replay.open.open_recording` returns); opened and closed here.
    dst_path : path-like
        New, empty session directory.
    depth_units_per_m : float, optional
        Depth PNG scale; default: the source's ``meta["depth_units_per_m"]`` if it is a session,
        else 5000 (TUM).
    device, notes : str, optional
        Default: from the source's meta.
    show_progress : bool
        Show a progress bar (:func:`appfusion.progress.progress`).
    fsync_interval_s : float
        As in :class:`SessionWriter` (conversion is not a live capture, so fsync less often).

    Returns
    -------
    dict
        ``frames`` written, ``counts`` per stream, ``clipped_depth_pixels``, ``bad_frames`` of the
        source (with ``skip_bad``), ``seconds``.
    """
    from appfusion.progress import progress

    t0 = time.perf_counter()
    with src:
        smeta = dict(src.meta)
        n = len(src) if src.is_recording else None
        it = iter(src)
        first = next(it, None)
        if first is None:
            raise AppFusionError(f"convert: {getattr(src, 'name', src)} has no frames to convert")
        intr = dict(src.intrinsics)
        for s in first.streams:
            fi = getattr(first, f"{s}_intrinsics")
            if fi is not None:
                intr.setdefault(s, fi)
        units = depth_units_per_m
        if units is None:
            units = float(smeta["depth_units_per_m"]) if smeta.get("format_name") == "session" else DEFAULT_UNITS_PER_M
        extra = dict(smeta.get("extra") or {}) if smeta.get("format_name") == "session" else {}
        extra.setdefault("converted_from", {"path": str(getattr(src, "path", "")),
                                            "format": smeta.get("format_name", type(src).__name__)})
        # IR significant bits: the session's, else what the source says (Kinect v1 drivers: 10), else 16
        ir_bits = smeta.get("streams", {}).get("ir", {}).get("bits", smeta.get("ir_bits", 16))
        em = smeta.get("emitter_position_m", (0.075, 0.0, 0.0))
        events = sorted(getattr(src, "events", []) or [], key=lambda e: e[0])
        with SessionWriter(dst_path, device=device or str(smeta.get("device", getattr(src, "name", "unknown"))),
                           intrinsics=intr, depth_to_ir=first.depth_to_ir, depth_to_rgb=first.depth_to_rgb,
                           depth_units_per_m=units, rgb_encoding=first.rgb_encoding, emitter_position_m=em,
                           notes=smeta.get("notes", "") if notes is None else notes, extra=extra,
                           ir_bits=int(ir_bits), fsync_interval_s=fsync_interval_s) as w:
            ev = 0

            def frames():
                yield first
                yield from it

            for fr in progress(frames(), total=n, desc="convert", enable=show_progress):
                while ev < len(events) and events[ev][0] <= fr.timestamp:
                    w.event(*events[ev])
                    ev += 1
                w.write(fr)
            for e in events[ev:]:
                w.event(*e)
        bad = list(getattr(src, "bad_frames", []))
    return {"frames": w.n_frames, "counts": dict(w.counts), "clipped_depth_pixels": w.clipped_depth_pixels,
            "bad_frames": bad, "seconds": time.perf_counter() - t0}
