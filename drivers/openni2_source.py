"""Live OpenNI2 devices (Kinect v1 via libfreenect's driver, PrimeSense / Asus Xtion, the DummyDevice).

The paper captures with a Kinect v1 (Wu & Zhou 2015, §3, §4.1): depth for geometry, the IR camera
with the structured-light emitter as an active reflectometer (§5.1-5.2), the RGB camera for the
diffuse albedo (§5.3), and emitter-off IR frames for the background-noise calibration (§6). The
Kinect v1 cannot stream IR and colour at the same time (§8, "device limitation"), so its
:class:`~appfusion.source.StreamCaps` say ``together = ({depth, ir}, {depth, rgb})`` and a scan
switches streams between passes with :meth:`OpenNI2Source.select_streams` /
:meth:`OpenNI2Source.select_pass`.

Units delivered (``docs/conventions.md``):

- depth: float32 metres, NaN where the device reports 0 (``DEPTH_1_MM`` / ``DEPTH_100_UM``);
- IR: float32 linear sensor counts (``GRAY16``: 10-bit on a Kinect v1 / PS1080; ``GRAY8``);
- colour: uint8 sRGB, (H, W, 3) RGB order (``RGB888``, ``YUV422``/``YUYV`` and ``JPEG`` decoded);
- timestamps: the device's microsecond clock in seconds, forced monotonic across stream restarts.

Intrinsics come from the caller's calibration when given, else from the stream's field of view
(``fx = (W / 2) / tan(hfov / 2)``), else from the nominal Kinect v1 / PS1080 field of view (the
DummyDevice reports none); ``meta["intrinsics_from"]`` says which.

Debian's ``libopenni2-0`` has two quirks handled here: it ships ``libOpenNI2.so.0`` only (the
``openni`` binding looks for ``libOpenNI2.so``), and its drivers' stream threads outlive
``oniStreamStop`` by up to one frame period, so destroying a stream straight after stopping it
crashes the process later; every stop here waits a few frame periods before destroying. Playback
of ``.oni`` files hangs or crashes in that build, so :class:`OpenNI2Source` probes playback in a
subprocess with a timeout before it plays a file in-process (:func:`probe_oni_playback`).
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from appfusion.errors import DeviceError, SourceError
from appfusion.frame import Frame, Intrinsics, invert_pose, make_pose
from appfusion.source import Control, Source, StreamCaps

__all__ = [
    "OpenNI2Source", "load_openni2", "openni2_drivers", "driver_dirs", "has_kinect_v1_driver", "fov_intrinsics",
    "depth_to_metres", "ir_to_counts", "colour_to_rgb8", "probe_oni_playback", "list_devices",
    "NOMINAL_FOV_RAD", "KINECT_V1_DEPTH_TO_RGB", "EMITTER_PROPERTY_IDS",
]

# ----------------------------------------------------------------------------------------------
# constants
# ----------------------------------------------------------------------------------------------
#: nominal fields of view (horizontal, vertical) in radians of a Kinect v1 / PS1080, as the PS1080
#: driver reports them; used when a driver reports none (the DummyDevice)
NOMINAL_FOV_RAD = {
    "depth": (1.0144686707507438, 0.78980943449644714),
    "ir": (1.0144686707507438, 0.78980943449644714),
    "rgb": (1.0225999928, 0.7966156602),
}
#: nominal depth(= IR)-camera to RGB-camera transform of a Kinect v1: the RGB camera sits 2.5 cm
#: beside the IR camera, towards the emitter (+x of the depth camera, docs/conventions.md)
KINECT_V1_DEPTH_TO_RGB = make_pose(t=(-0.025, 0.0, 0.0))
#: emitter (structured-light projector) position of a Kinect v1 in the depth camera frame, metres
KINECT_V1_EMITTER_M = (0.075, 0.0, 0.0)

#: PS1080 module property ids (OpenNI2 ``PS1080.h``): emitter on/off (XnUInt64 boolean) and the
#: emitter-to-depth-CMOS distance in cm (double, "LDDIS"), zero-plane distance (mm) and pixel size
XN_MODULE_PROPERTY_EMITTER_STATE = 0x1080E007
XN_STREAM_PROPERTY_EMITTER_DCMOS_DISTANCE = 0x1080100E
XN_STREAM_PROPERTY_ZERO_PLANE_DISTANCE = 0x1080100C
XN_STREAM_PROPERTY_ZERO_PLANE_PIXEL_SIZE = 0x1080100D
#: device properties that switch the IR emitter, tried in order
EMITTER_PROPERTY_IDS = (XN_MODULE_PROPERTY_EMITTER_STATE,)

# OpenNI2 enums (OniCEnums.h); duplicated so that the pure conversion helpers need no library
PF_DEPTH_1_MM, PF_DEPTH_100_UM, PF_SHIFT_9_2, PF_SHIFT_9_3 = 100, 101, 102, 103
PF_RGB888, PF_YUV422, PF_GRAY8, PF_GRAY16, PF_JPEG, PF_YUYV = 200, 201, 202, 203, 204, 205
PIXEL_FORMAT_NAMES = {PF_DEPTH_1_MM: "DEPTH_1_MM", PF_DEPTH_100_UM: "DEPTH_100_UM", PF_SHIFT_9_2: "SHIFT_9_2",
                      PF_SHIFT_9_3: "SHIFT_9_3", PF_RGB888: "RGB888", PF_YUV422: "YUV422", PF_GRAY8: "GRAY8",
                      PF_GRAY16: "GRAY16", PF_JPEG: "JPEG", PF_YUYV: "YUYV"}
_FORMAT_BY_NAME = {v: k for k, v in PIXEL_FORMAT_NAMES.items()}
#: formats each of our streams can deliver, in order of preference
STREAM_FORMATS = {
    "depth": (PF_DEPTH_1_MM, PF_DEPTH_100_UM),
    "ir": (PF_GRAY16, PF_GRAY8, PF_RGB888),
    "rgb": (PF_RGB888, PF_YUV422, PF_YUYV, PF_JPEG),
}
SENSOR_OF_STREAM = {"depth": 3, "ir": 1, "rgb": 2}  # ONI_SENSOR_DEPTH / IR / COLOR
ONI_STATUS_TIME_OUT = 102

#: library directories searched for ``libOpenNI2.so*`` (besides $OPENNI2_REDIST64 / $OPENNI2_REDIST)
_LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib/arm-linux-gnueabihf",
             "/usr/local/lib", "/usr/lib", "/usr/lib64", "/lib")
_LIB_NAMES = ("libOpenNI2.so", "libOpenNI2.so.0")

#: usb vendor ids -> maker
_VENDORS = {0x045E: "Microsoft", 0x1D27: "PrimeSense", 0x2BC5: "Orbbec"}

_lock = threading.Lock()
_openni = None
_lib_dir: str | None = None


# ----------------------------------------------------------------------------------------------
# library loading and driver discovery
# ----------------------------------------------------------------------------------------------
def _candidate_dirs(library_dir: str | os.PathLike | None) -> list[str]:
    dirs = []
    if library_dir:
        dirs.append(os.fspath(library_dir))
    for var in ("OPENNI2_REDIST64", "OPENNI2_REDIST"):
        if os.environ.get(var):
            dirs.append(os.environ[var])
    dirs.extend(_LIB_DIRS)
    return list(dict.fromkeys(dirs))


def load_openni2(library_dir: str | os.PathLike | None = None):
    """Load and initialise the OpenNI2 runtime once per process; return the ``openni.openni2`` module.

    Parameters
    ----------
    library_dir : path-like, optional
        Directory holding ``libOpenNI2.so`` or ``libOpenNI2.so.0`` (Debian ships only the latter);
        default: ``$OPENNI2_REDIST64``, ``$OPENNI2_REDIST``, then the usual library directories.

    Raises
    ------
    DeviceError
        The ``openni`` Python package or the OpenNI2 library is missing or fails to initialise.
    """
    global _openni, _lib_dir
    with _lock:
        if _openni is not None and _openni.is_initialized():
            return _openni
        try:
            from openni import openni2
        except ImportError as e:  # pragma: no cover - a dependency of appfusion
            raise DeviceError(f"openni2: the 'openni' Python package is not installed ({e}); "
                              f"pip install openni") from None
        if openni2.is_initialized():
            _openni, _lib_dir = openni2, openni2.loaded_dll_directory
            return openni2
        tried = []
        for d in _candidate_dirs(library_dir):
            for name in _LIB_NAMES:
                if not os.path.isfile(os.path.join(d, name)):
                    continue
                tried.append(os.path.join(d, name))
                openni2._dll_name = name
                try:
                    openni2.initialize(d)
                except Exception as e:  # the binding raises InitializationError / OpenNIError / OSError
                    tried[-1] += f" ({e.__class__.__name__}: {str(e).strip().splitlines()[-1]})"
                    continue
                _openni, _lib_dir = openni2, d
                return openni2
        if tried:
            raise DeviceError("openni2: the OpenNI2 library failed to initialise: " + "; ".join(tried))
        raise DeviceError("openni2: libOpenNI2.so not found (searched "
                          + ", ".join(_candidate_dirs(library_dir))
                          + "); install it with `sudo apt-get install libopenni2-0` or set OPENNI2_REDIST64")


def driver_dirs(library_dir: str | os.PathLike | None = None) -> list[Path]:
    """Existing ``OpenNI2/Drivers`` directories next to the OpenNI2 libraries that may be loaded."""
    base = [library_dir] if library_dir else ([_lib_dir] if _lib_dir else _candidate_dirs(None))
    out = []
    for d in base:
        p = Path(d) / "OpenNI2" / "Drivers"
        if p.is_dir():
            out.append(p)
    return out


def openni2_drivers(library_dir: str | os.PathLike | None = None) -> list[str]:
    """File names of the OpenNI2 driver libraries installed (``libPS1080.so.0``, ``libFreenectDriver.so``, ...)."""
    names = []
    for d in driver_dirs(library_dir):
        names.extend(sorted(p.name for p in d.iterdir() if ".so" in p.name))
    return list(dict.fromkeys(names))


def has_kinect_v1_driver(library_dir: str | os.PathLike | None = None) -> bool:
    """True if libfreenect's OpenNI2 driver (``libFreenectDriver.so``) is in an OpenNI2 drivers directory.

    Debian's ``libfreenect0.5`` does not ship it; build libfreenect with ``-DBUILD_OPENNI2_DRIVER=ON``
    and copy ``libFreenectDriver.so`` into ``/usr/lib/x86_64-linux-gnu/OpenNI2/Drivers`` (docs/hardware.md).
    """
    return any(n.lower().startswith("libfreenectdriver") for n in openni2_drivers(library_dir))


def list_devices(library_dir: str | os.PathLike | None = None) -> list[dict[str, Any]]:
    """Enumerate attached OpenNI2 devices: ``[{"uri", "name", "vendor", "usb_vendor_id", "usb_product_id"}]``.

    The DummyDevice is never enumerated; open it as ``OpenNI2Source("Dummy")``.
    """
    load_openni2(library_dir)
    from openni import _openni2 as c_api

    pdevs = ctypes.POINTER(c_api.OniDeviceInfo)()
    count = ctypes.c_int()
    c_api.oniGetDeviceList(ctypes.byref(pdevs), ctypes.byref(count))
    try:
        return [{"uri": pdevs[i].uri.decode(errors="replace"), "name": pdevs[i].name.decode(errors="replace"),
                 "vendor": pdevs[i].vendor.decode(errors="replace"), "usb_vendor_id": int(pdevs[i].usbVendorId),
                 "usb_product_id": int(pdevs[i].usbProductId)} for i in range(count.value)]
    finally:
        c_api.oniReleaseDeviceList(pdevs)


# ----------------------------------------------------------------------------------------------
# pure conversions (no library needed)
# ----------------------------------------------------------------------------------------------
def fov_intrinsics(width: int, height: int, hfov_rad: float, vfov_rad: float) -> Intrinsics:
    """Pinhole intrinsics of an undistorted camera from its fields of view.

    ``fx = (W / 2) / tan(hfov / 2)``, ``fy = (H / 2) / tan(vfov / 2)``, principal point at the image
    centre ``((W - 1) / 2, (H - 1) / 2)`` (pixel centres at integers, docs/conventions.md).

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    hfov_rad, vfov_rad : float
        Full horizontal and vertical fields of view in radians, in (0, pi).
    """
    for name, v in (("horizontal", hfov_rad), ("vertical", vfov_rad)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.0 < v < math.pi):
            raise SourceError(f"openni2: {name} field of view {v!r} rad is not in (0, pi)")
    fx = (width / 2.0) / math.tan(hfov_rad / 2.0)
    fy = (height / 2.0) / math.tan(vfov_rad / 2.0)
    return Intrinsics(int(width), int(height), fx, fy, (width - 1) / 2.0, (height - 1) / 2.0)


def depth_to_metres(raw: np.ndarray, pixel_format: int) -> np.ndarray:
    """Depth pixels of an OpenNI2 depth frame in metres.

    Parameters
    ----------
    raw : (H, W) uint16 ndarray
        Depth values as the device sends them.
    pixel_format : int
        ``DEPTH_1_MM`` (100: millimetres) or ``DEPTH_100_UM`` (101: 0.1 mm).

    Returns
    -------
    (H, W) float32 ndarray
        Metres; NaN where the device reports 0 (no measurement).
    """
    scale = {PF_DEPTH_1_MM: 1e-3, PF_DEPTH_100_UM: 1e-4}.get(int(pixel_format))
    if scale is None:
        raise SourceError(f"openni2: depth pixel format {PIXEL_FORMAT_NAMES.get(pixel_format, pixel_format)} "
                          f"is not metric; choose DEPTH_1_MM or DEPTH_100_UM")
    raw = np.asarray(raw)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise SourceError(f"openni2: depth frame must be (H, W) uint16, got {raw.shape} {raw.dtype}")
    out = raw.astype(np.float32) * np.float32(scale)
    out[raw == 0] = np.nan
    return out


def ir_to_counts(raw: np.ndarray, pixel_format: int) -> np.ndarray:
    """IR pixels of an OpenNI2 IR frame as float32 linear sensor counts, shape (H, W).

    ``GRAY16`` (Kinect v1 / PS1080: 10 significant bits, 0..1023) and ``GRAY8`` are taken as they are;
    ``RGB888`` IR (some drivers send grey as three equal channels) keeps its first channel.
    """
    raw = np.asarray(raw)
    pf = int(pixel_format)
    if pf == PF_RGB888:
        if raw.ndim != 3 or raw.shape[2] != 3:
            raise SourceError(f"openni2: RGB888 IR frame must be (H, W, 3), got {raw.shape}")
        raw = raw[..., 0]
    elif pf not in (PF_GRAY16, PF_GRAY8):
        raise SourceError(f"openni2: IR pixel format {PIXEL_FORMAT_NAMES.get(pf, pf)} is not supported "
                          f"(GRAY16, GRAY8, RGB888)")
    if raw.ndim != 2:
        raise SourceError(f"openni2: IR frame must be (H, W), got {raw.shape}")
    return raw.astype(np.float32)


def colour_to_rgb8(data: np.ndarray, pixel_format: int, width: int, height: int) -> np.ndarray:
    """Colour pixels of an OpenNI2 colour frame as (H, W, 3) uint8 sRGB in RGB order.

    Parameters
    ----------
    data : ndarray
        ``RGB888``: (H, W, 3) uint8. ``YUV422`` (UYVY byte order in OpenNI2) / ``YUYV``: (H, W, 2) uint8.
        ``JPEG``: 1-D uint8 bytes of the compressed image.
    pixel_format : int
    width, height : int
        Image size in pixels (checked).
    """
    import cv2

    pf = int(pixel_format)
    data = np.asarray(data)
    if pf == PF_RGB888:
        out = data
    elif pf in (PF_YUV422, PF_YUYV):
        if data.shape != (height, width, 2):
            raise SourceError(f"openni2: {PIXEL_FORMAT_NAMES[pf]} frame must be ({height}, {width}, 2), got {data.shape}")
        code = cv2.COLOR_YUV2RGB_UYVY if pf == PF_YUV422 else cv2.COLOR_YUV2RGB_YUYV
        out = cv2.cvtColor(np.ascontiguousarray(data), code)
    elif pf == PF_JPEG:
        bgr = cv2.imdecode(np.ascontiguousarray(data.reshape(-1), dtype=np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise SourceError("openni2: a JPEG colour frame could not be decoded")
        out = bgr[..., ::-1]
    else:
        raise SourceError(f"openni2: colour pixel format {PIXEL_FORMAT_NAMES.get(pf, pf)} is not supported "
                          f"(RGB888, YUV422, YUYV, JPEG)")
    if out.shape != (height, width, 3) or out.dtype != np.uint8:
        raise SourceError(f"openni2: colour frame is {out.shape} {out.dtype}, expected ({height}, {width}, 3) uint8")
    return np.ascontiguousarray(out)


def _frame_pixels(vframe) -> tuple[np.ndarray, int, int, int]:
    """Copy the pixels of an OpenNI2 ``VideoFrame`` into an ndarray, honouring the row stride.

    Returns (array, pixel_format, width, height); the array is (H, W) uint16 for 16-bit formats,
    (H, W, 3) / (H, W, 2) uint8 for RGB888 / YUV, (H, W) uint8 for GRAY8, 1-D bytes for JPEG.
    """
    w, h, stride, size = int(vframe.width), int(vframe.height), int(vframe.stride), int(vframe.dataSize)
    pf = int(vframe.videoMode.pixelFormat)
    buf = np.ctypeslib.as_array((ctypes.c_uint8 * size).from_address(vframe.data)).copy()
    if pf == PF_JPEG:
        return buf, pf, w, h
    bpp = {PF_DEPTH_1_MM: 2, PF_DEPTH_100_UM: 2, PF_SHIFT_9_2: 2, PF_SHIFT_9_3: 2, PF_GRAY16: 2,
           PF_GRAY8: 1, PF_RGB888: 3, PF_YUV422: 2, PF_YUYV: 2}.get(pf)
    if bpp is None:
        raise SourceError(f"openni2: unknown pixel format {pf}")
    stride = stride or w * bpp
    if stride < w * bpp or size < stride * (h - 1) + w * bpp:
        raise SourceError(f"openni2: frame of {size} bytes is too small for {w}x{h} {PIXEL_FORMAT_NAMES[pf]} "
                          f"(stride {stride})")
    rows = np.lib.stride_tricks.as_strided(buf, shape=(h, w * bpp), strides=(stride, 1))
    rows = np.ascontiguousarray(rows)
    if bpp == 2 and pf not in (PF_YUV422, PF_YUYV):
        return rows.view("<u2").reshape(h, w), pf, w, h
    if pf == PF_GRAY8:
        return rows.reshape(h, w), pf, w, h
    return rows.reshape(h, w, bpp), pf, w, h


# ----------------------------------------------------------------------------------------------
# .oni playback probe
# ----------------------------------------------------------------------------------------------
_PROBE_CODE = r"""
import os, sys
from openni import openni2
lib, name, path, wait_s = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
openni2._dll_name = name
openni2.initialize(lib)
d = openni2.Device(path.encode())
if not d.is_file():
    print("not a playback device"); sys.stdout.flush(); os._exit(3)
s = None
for sensor in (openni2.SENSOR_DEPTH, openni2.SENSOR_IR, openni2.SENSOR_COLOR):
    if d.has_sensor(sensor):
        s = d.create_stream(sensor)
        break
if s is None:
    print("no stream in the file"); sys.stdout.flush(); os._exit(4)
s.start()
if openni2.wait_for_any_stream([s], wait_s) is None:
    print("no frame within %g s" % wait_s); sys.stdout.flush(); os._exit(5)
f = s.read_frame()
print("ok", f.width, f.height); sys.stdout.flush()
os._exit(0)
"""


def probe_oni_playback(path: str | os.PathLike, timeout_s: float = 10.0,
                       library_dir: str | os.PathLike | None = None) -> tuple[bool, str]:
    """Check in a subprocess that this machine's OpenNI2 can play ``path`` (open, start, read one frame).

    Debian's OpenNI2 build hangs or segfaults playing ``.oni`` files; probing in a child process keeps
    the caller alive. Returns ``(ok, detail)`` where ``detail`` says what happened ("hung for 10 s",
    "crashed with SIGSEGV", the child's last output line).
    """
    load_openni2(library_dir)  # finds the library (raises DeviceError if there is none)
    from openni import openni2

    wait_s = max(0.5, min(3.0, timeout_s / 2.0))
    cmd = [sys.executable, "-c", _PROBE_CODE, _lib_dir or "", openni2._dll_name, os.fspath(path), f"{wait_s:g}"]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return False, f"OpenNI2 playback hung for {timeout_s:g} s"
    out = (r.stdout.strip().splitlines() or [""])[-1]
    if r.returncode == 0 and out.startswith("ok"):
        return True, out
    if r.returncode < 0:
        import signal

        try:
            sig = signal.Signals(-r.returncode).name
        except ValueError:
            sig = f"signal {-r.returncode}"
        return False, f"OpenNI2 playback crashed with {sig}"
    err = (r.stderr.strip().splitlines() or [out or f"exit status {r.returncode}"])[-1]
    return False, f"OpenNI2 playback failed: {out or err}"


# ----------------------------------------------------------------------------------------------
# the source
# ----------------------------------------------------------------------------------------------
def _parse_mode(stream: str, spec) -> tuple[int, int, float | None, int | None]:
    """(width, height[, fps[, pixel format name or id]]) -> (w, h, fps or None, format id or None)."""
    if isinstance(spec, str):
        parts = spec.lower().replace("@", "x").split("x")
        spec = [int(parts[0]), int(parts[1])] + ([float(parts[2])] if len(parts) > 2 else [])
    spec = list(spec)
    if len(spec) < 2 or len(spec) > 4:
        raise SourceError(f"openni2: video mode for {stream} must be (width, height[, fps[, format]]), got {spec!r}")
    fmt = None
    if len(spec) == 4:
        fmt = spec[3]
        if isinstance(fmt, str):
            if fmt.upper() not in _FORMAT_BY_NAME:
                raise SourceError(f"openni2: unknown pixel format {fmt!r} for {stream} "
                                  f"(known: {', '.join(_FORMAT_BY_NAME)})")
            fmt = _FORMAT_BY_NAME[fmt.upper()]
        fmt = int(fmt)
    return int(spec[0]), int(spec[1]), (float(spec[2]) if len(spec) > 2 else None), fmt


def _mode_text(m) -> str:
    return f"{m.resolutionX}x{m.resolutionY}@{m.fps} {PIXEL_FORMAT_NAMES.get(int(m.pixelFormat), m.pixelFormat)}"


class OpenNI2Source(Source):
    """A live OpenNI2 device (or an ``.oni`` file where this machine's OpenNI2 can play it).

    Parameters
    ----------
    uri : str, optional
        Device URI as OpenNI2 enumerates it (``list_devices()``), ``"Dummy"`` for the DummyDevice,
        a path to an ``.oni`` file, or None / ``""`` for the first device attached.
    streams : iterable of str, optional
        Streams to run at first (``{"depth", "ir"}``...). Default: depth and IR if the device has IR,
        else every stream that can run together.
    modes : dict, optional
        Video mode per stream: ``(width, height[, fps[, pixel format]])`` or ``"640x480@30"``.
        Default: the mode closest to 640x480 at 30 fps in the preferred pixel format
        (depth ``DEPTH_1_MM``, IR ``GRAY16``, colour ``RGB888``).
    register : bool
        Use the device's depth-to-colour registration where it has it: depth is then warped into
        the RGB camera, whose intrinsics it takes, ``depth_to_rgb`` becomes the identity and
        ``depth_to_ir`` the RGB-to-IR transform. Off by default so that the depth camera (the IR
        camera of a Kinect v1) stays the same through every pass of a session.
    intrinsics : dict of str -> Intrinsics, optional
        Calibrated intrinsics per stream (rescaled when a stream runs at another size).
    depth_to_rgb : (4, 4) array, optional
        Calibrated depth-to-RGB extrinsics (metres); default: the Kinect v1 nominal 2.5 cm offset.
    ir_rgb_together : bool, optional
        Override the capability model: a Kinect v1 / PrimeSense cannot stream IR and colour at
        once (the default for any device with both sensors).
    timeout_s, first_frame_timeout_s : float
        Longest wait for a frame while streaming / after (re)starting streams; a longer silence
        raises :class:`~appfusion.errors.DeviceError` (device unplugged).
    library_dir : path-like, optional
        Where ``libOpenNI2.so*`` lives (see :func:`load_openni2`).
    oni_probe_timeout_s : float
        Time allowed to the playback probe of an ``.oni`` file.
    """

    def __init__(self, uri: str | None = None, streams: Iterable[str] | None = None,
                 modes: dict[str, Any] | None = None, register: bool = False,
                 intrinsics: dict[str, Intrinsics] | None = None, depth_to_rgb: np.ndarray | None = None,
                 ir_rgb_together: bool | None = None, timeout_s: float = 2.0, first_frame_timeout_s: float = 5.0,
                 library_dir: str | os.PathLike | None = None, oni_probe_timeout_s: float = 10.0):
        super().__init__()
        self.uri = "" if uri is None else str(uri)
        self._want_streams = None if streams is None else frozenset(streams)
        self._modes_req = {k: _parse_mode(k, v) for k, v in (modes or {}).items()}
        for k in self._modes_req:
            if k not in SENSOR_OF_STREAM:
                raise SourceError(f"openni2: video mode given for unknown stream {k!r} (depth, ir, rgb)")
        self.register = bool(register)
        self._calib = dict(intrinsics or {})
        self._depth_to_rgb_cal = None if depth_to_rgb is None else np.asarray(depth_to_rgb, dtype=float)
        self._ir_rgb_together = ir_rgb_together
        self.timeout_s = float(timeout_s)
        self.first_frame_timeout_s = float(first_frame_timeout_s)
        self.library_dir = library_dir
        self.oni_probe_timeout_s = float(oni_probe_timeout_s)
        self.is_recording = self._looks_like_file(self.uri)
        self.name = f"openni2:{self.uri or 'any'}"
        self._dev = None
        self._streams: dict[str, Any] = {}
        self._started: set[str] = set()
        self._modes: dict[str, Any] = {}
        self._caps: StreamCaps | None = None
        self._intr: dict[str, Intrinsics] = {}
        self._intr_from: dict[str, str] = {}
        self._meta: dict[str, Any] = {}
        self._controls: dict[str, Control] = {}
        self._emitter_pid: int | None = None
        self._registered = False
        self._recorder = None
        self._index = 0
        self._t_offset = 0.0
        self._last_t = -math.inf
        self._restarted = True
        self.pass_name: str | None = None

    @staticmethod
    def _looks_like_file(uri: str) -> bool:
        return uri.lower().endswith(".oni") or (bool(uri) and os.path.isfile(uri))

    # -- opening -------------------------------------------------------------------------------
    def _open(self) -> None:
        ni = load_openni2(self.library_dir)
        if self.is_recording:
            if not os.path.isfile(self.uri):
                raise SourceError(f"{self.uri}: no such .oni file")
            ok, detail = probe_oni_playback(self.uri, self.oni_probe_timeout_s, self.library_dir)
            if not ok:
                raise SourceError(f"{self.uri}: {detail} (this OpenNI2 build cannot play .oni files; use "
                                  f"`appfusion convert` on a machine where OpenNI2 playback works, or record "
                                  f"with `appfusion record openni2:... OUT` into a session instead)")
        try:
            self._dev = ni.Device(self.uri.encode() if self.uri else None)
        except Exception as e:
            what = f"device {self.uri!r}" if self.uri else "any device"
            hint = ""
            if not self.uri or self.uri != "Dummy":
                hint = (" (is it plugged in and are the udev rules installed? see docs/hardware.md; a Kinect v1 "
                        "needs libfreenect's OpenNI2 driver" + ("" if has_kinect_v1_driver(self.library_dir)
                                                                 else ", which is not installed") + ")")
            raise DeviceError(f"openni2: cannot open {what}: {_oni_error_text(e)}{hint}") from None
        try:
            self._describe()
            if self.is_recording and self._dev.playback is not None:
                with contextlib.suppress(Exception):
                    self._dev.playback.set_repeat_enabled(False)
                    self._dev.playback.set_speed(-1.0)  # as fast as frames are read
            want = self._want_streams if self._want_streams is not None else self._default_streams()
            self._start(want)
        except BaseException:
            self._teardown()
            raise

    def _describe(self) -> None:
        """Device info, capability model, controls and meta (no stream started)."""
        ni = load_openni2(self.library_dir)
        info = self._dev.get_device_info()
        name = info.name.decode(errors="replace")
        vendor = info.vendor.decode(errors="replace") or _VENDORS.get(int(info.usbVendorId), "")
        uri = info.uri.decode(errors="replace")
        have = set()
        self._sensor_modes = {}
        for s, sensor in SENSOR_OF_STREAM.items():
            si = self._dev.get_sensor_info(sensor)
            if si is not None and len(si.videoModes):
                have.add(s)
                self._sensor_modes[s] = list(si.videoModes)
        if not have:
            raise DeviceError(f"openni2: device {uri!r} has no depth, IR or colour sensor")
        together = self._ir_rgb_together
        if together is None:
            together = False  # Kinect v1, PrimeSense/Asus, Orbbec Astra: not both over one USB interface
        if {"ir", "rgb"} <= have and not together:
            groups = tuple(frozenset(have - {x}) for x in ("rgb", "ir"))
        else:
            groups = (frozenset(have),)
        self.model = f"{vendor} {name}".strip() or uri
        self.name = f"openni2:{uri} ({self.model})"
        self._caps = StreamCaps(frozenset(have), groups,
                                {s: float(max(m.fps for m in self._sensor_modes[s])) for s in have})
        # the emitter control: PS1080 property (PrimeSense, Asus Xtion, Orbbec)
        self._emitter_pid = None
        for pid in EMITTER_PROPERTY_IDS:
            try:
                if self._dev.is_property_supported(pid):
                    self._emitter_pid = pid
                    break
            except Exception:
                continue
        self._controls = {}
        if self._emitter_pid is not None:
            state = None
            with contextlib.suppress(Exception):
                state = bool(self._dev.get_property(self._emitter_pid, ctypes.c_uint64).value)
            self._controls["emitter"] = Control("emitter", "bool", state if state is not None else True)
        self._emitter_position = KINECT_V1_EMITTER_M
        self._meta = {"device": self.model, "uri": uri, "vendor": vendor, "name": name,
                      "usb_vendor_id": int(info.usbVendorId), "usb_product_id": int(info.usbProductId),
                      "driver": "openni2", "openni2_version": _version_text(ni),
                      "openni2_drivers": openni2_drivers(self.library_dir),
                      "kinect_v1_driver": has_kinect_v1_driver(self.library_dir),
                      "emitter_position_m": list(self._emitter_position), "ir_bits": 10,
                      "depth_units_per_m": 1000.0, "is_file": bool(self.is_recording)}
        for prop, key in ((ni.c_api.ONI_DEVICE_PROPERTY_SERIAL_NUMBER, "serial"),
                          (ni.c_api.ONI_DEVICE_PROPERTY_FIRMWARE_VERSION, "firmware")):
            with contextlib.suppress(Exception):
                self._meta[key] = self._dev.get_property(prop, ctypes.c_char * 64).value.decode(errors="replace")

    def _default_streams(self) -> frozenset[str]:
        caps = self._caps
        for g in caps.together:
            if "ir" in g and "depth" in g:
                return frozenset({"depth", "ir"})
        return max(caps.together, key=len)

    def _choose_mode(self, stream: str):
        modes = self._sensor_modes[stream]
        req = self._modes_req.get(stream)
        fmts = STREAM_FORMATS[stream]
        usable = [m for m in modes if int(m.pixelFormat) in fmts]
        if req is not None:
            w, h, fps, fmt = req
            cands = [m for m in usable if m.resolutionX == w and m.resolutionY == h
                     and (fps is None or abs(m.fps - fps) < 0.5) and (fmt is None or int(m.pixelFormat) == fmt)]
            if not cands:
                raise SourceError(f"{self.name}: no {stream} video mode {w}x{h}"
                                  + (f"@{fps:g}" if fps else "")
                                  + (f" {PIXEL_FORMAT_NAMES.get(fmt, fmt)}" if fmt is not None else "")
                                  + "; the device has: " + ", ".join(_mode_text(m) for m in modes))
        else:
            cands = usable
            if not cands:
                raise SourceError(f"{self.name}: none of the {stream} video modes is usable "
                                  f"({', '.join(_mode_text(m) for m in modes)}); supported pixel formats: "
                                  + ", ".join(PIXEL_FORMAT_NAMES[f] for f in fmts))
        return min(cands, key=lambda m: (fmts.index(int(m.pixelFormat)), abs(m.fps - 30),
                                         abs(m.resolutionX * m.resolutionY - 640 * 480)))

    # -- stream management ---------------------------------------------------------------------
    def _stop_all(self) -> None:
        """Stop every stream, wait until the driver threads have let go, then destroy them."""
        self._halt_streams()
        self._destroy_streams()

    def _halt_streams(self) -> None:
        """Stop every running stream and wait until no driver thread touches it any more."""
        if not self._started:
            return
        fps = min((float(m.fps) for m in self._modes.values()), default=30.0) or 30.0
        ni = load_openni2(self.library_dir)
        for name in self._started:
            # stopping a stream whose driver thread has not produced its first frame yet
            # crashes Debian's DummyDevice later: let every started stream deliver one frame
            with contextlib.suppress(Exception):
                ni.wait_for_any_stream([self._streams[name]], 1.0)
        for name in self._started:
            with contextlib.suppress(Exception):
                self._streams[name].stop()
        self._started = set()
        # Debian's drivers keep a stream thread alive for up to a frame period after stop
        time.sleep(max(0.1, 3.0 / fps))

    def _destroy_streams(self) -> None:
        """Destroy the (stopped) streams."""
        self._halt_streams()
        for s in self._streams.values():
            with contextlib.suppress(Exception):
                s.close()
        self._streams = {}
        self._modes = {}

    def _start(self, streams: frozenset[str]) -> None:
        ni = load_openni2(self.library_dir)
        streams = frozenset(streams)
        self._check_combination(streams)
        created = {}
        try:
            for st in ("depth", "ir", "rgb"):
                if st not in streams:
                    continue
                vs = self._dev.create_stream(SENSOR_OF_STREAM[st])
                created[st] = vs
                mode = self._choose_mode(st)
                try:
                    cur = vs.get_video_mode()
                    if (cur.resolutionX, cur.resolutionY, cur.fps, int(cur.pixelFormat)) != \
                            (mode.resolutionX, mode.resolutionY, mode.fps, int(mode.pixelFormat)):
                        vs.set_video_mode(mode)
                except Exception as e:
                    raise SourceError(f"{self.name}: cannot set {st} video mode {_mode_text(mode)}: "
                                      f"{_oni_error_text(e)}") from None
                with contextlib.suppress(Exception):
                    if vs.is_property_supported(ni.c_api.ONI_STREAM_PROPERTY_MIRRORING):
                        vs.set_mirroring_enabled(False)
                self._modes[st] = vs.get_video_mode()
            self._registered = False
            if self.register and "depth" in streams:
                mode_reg = ni.IMAGE_REGISTRATION_DEPTH_TO_COLOR
                with contextlib.suppress(Exception):
                    if self._dev.is_image_registration_mode_supported(mode_reg):
                        self._dev.set_image_registration_mode(mode_reg)
                        self._registered = True
            if {"depth", "rgb"} <= streams:
                with contextlib.suppress(Exception):
                    self._dev.set_depth_color_sync_enabled(True)
            for st, vs in created.items():
                try:
                    vs.start()
                    self._started.add(st)
                except Exception as e:
                    raise DeviceError(f"{self.name}: cannot start the {st} stream: {_oni_error_text(e)}") from None
            self._streams = created
        except BaseException:
            self._streams = created
            self._stop_all()
            raise
        self._restarted = True
        self._update_geometry()

    def _check_combination(self, streams: frozenset[str]) -> None:
        caps = self._caps
        unknown = set(streams) - {"depth", "ir", "rgb"}
        if unknown:
            raise SourceError(f"{self.name}: unknown stream(s) {', '.join(sorted(unknown))} (depth, ir, rgb)")
        missing = set(streams) - set(caps.streams)
        if missing:
            raise SourceError(f"{self.name}: the device has no {', '.join(sorted(missing))} stream "
                              f"(it has {', '.join(sorted(caps.streams))})")
        if not streams:
            raise SourceError(f"{self.name}: select at least one stream")
        if not caps.can_stream(streams):
            groups = " or ".join("{" + ", ".join(sorted(g)) + "}" for g in caps.together)
            raise SourceError(f"{self.name}: cannot stream {', '.join(sorted(streams))} at the same time "
                              f"(a Kinect v1 / PrimeSense sends IR and colour over one channel); it can stream "
                              f"{groups}: record IR and RGB in separate passes")

    def _update_geometry(self) -> None:
        """Intrinsics of the running streams and the extrinsics (calibration, FOV, or nominal)."""
        intr, src = {}, {}
        for st, vs in self._streams.items():
            m = self._modes[st]
            w, h = int(m.resolutionX), int(m.resolutionY)
            if st in self._calib:
                c = self._calib[st]
                intr[st] = c if (c.width, c.height) == (w, h) else c.scaled(w, h)
                src[st] = "calibration"
                continue
            try:
                hf, vf = vs.get_horizontal_fov(), vs.get_vertical_fov()
                intr[st] = fov_intrinsics(w, h, hf, vf)
                src[st] = "device-fov"
            except Exception:
                intr[st] = fov_intrinsics(w, h, *NOMINAL_FOV_RAD[st])
                src[st] = "nominal-fov"
        # the IR camera is the depth camera of a Kinect v1 / PS1080 (same optics)
        if "depth" in intr and "ir" not in intr and "ir" in self._caps.streams:
            d = intr["depth"]
            intr["ir"] = self._calib["ir"] if "ir" in self._calib else d
            src.setdefault("ir", src["depth"])
        if "ir" in intr and "depth" not in intr and "depth" in self._caps.streams:
            intr["depth"] = intr["ir"]
            src["depth"] = src["ir"]
        for st in ("depth", "ir", "rgb"):
            if st not in intr and st in self._caps.streams:
                # a stream not running now keeps its last (or nominal) intrinsics for the session
                if st in self._intr:
                    intr[st], src[st] = self._intr[st], self._intr_from.get(st, "nominal-fov")
                elif st in self._calib:
                    intr[st], src[st] = self._calib[st], "calibration"
                else:
                    ref = intr.get("depth") or next(iter(intr.values()))
                    intr[st] = fov_intrinsics(ref.width, ref.height, *NOMINAL_FOV_RAD[st])
                    src[st] = "nominal-fov"
        d2rgb = self._depth_to_rgb_cal if self._depth_to_rgb_cal is not None else KINECT_V1_DEPTH_TO_RGB
        d2ir = np.eye(4)
        if self._registered and "rgb" in intr and "depth" in intr:
            d = intr["depth"]
            intr["depth"] = intr["rgb"].scaled(d.width, d.height)
            src["depth"] = src["rgb"] + "+registered"
            d2ir = invert_pose(d2rgb)
            d2rgb = np.eye(4)
        # emitter distance from the PS1080 depth stream where the device reports it
        if "depth" in self._streams:
            with contextlib.suppress(Exception):
                dist_cm = self._streams["depth"].get_property(XN_STREAM_PROPERTY_EMITTER_DCMOS_DISTANCE,
                                                              ctypes.c_double).value
                if 1.0 < dist_cm < 30.0:
                    self._emitter_position = (dist_cm / 100.0, 0.0, 0.0)
                    self._meta["emitter_position_m"] = list(self._emitter_position)
        self._intr, self._intr_from = intr, src
        self._depth_to_ir, self._depth_to_rgb = d2ir, np.asarray(d2rgb, dtype=float)
        self._meta.update(intrinsics_from=dict(src), registered=self._registered,
                          streams_running=sorted(self._streams),
                          video_modes={k: _mode_text(m) for k, m in self._modes.items()},
                          depth_to_rgb_from="calibration" if self._depth_to_rgb_cal is not None
                          else "kinect-v1-nominal", emitter_position_m=list(self._emitter_position))

    def select_streams(self, streams: Iterable[str]) -> None:
        """Run exactly these streams from now on (stops and restarts the device's streams).

        A Kinect v1 / PrimeSense runs ``{"depth", "ir"}`` for the geometry and IR reflectometry
        passes and ``{"depth", "rgb"}`` for the RGB pass; asking for IR and colour together raises
        :class:`~appfusion.errors.SourceError`. Frames already delivered are unaffected; an
        iteration in progress continues with the new streams.
        """
        want = frozenset(streams)
        if self._caps is not None:
            self._check_combination(want)
        if not self.is_open:
            self._want_streams = want
            return
        if self._recorder is not None:
            raise SourceError(f"{self.name}: stop the .oni recording before switching streams")
        if want == frozenset(self._streams):
            return
        self._stop_all()
        self._start(want)
        self._want_streams = want

    def select_pass(self, name: str) -> frozenset[str]:
        """Switch to the streams a scanning pass needs (``drivers.streams_for_pass``) and tag its frames.

        Returns the streams selected.
        """
        from drivers import streams_for_pass

        want = streams_for_pass(name, self.caps)
        self.select_streams(want)
        self.pass_name = name
        return want

    @property
    def active_streams(self) -> frozenset[str]:
        """Streams running now (the requested ones before :meth:`open`)."""
        if self._streams:
            return frozenset(self._streams)
        return self._want_streams or frozenset()

    # -- description ---------------------------------------------------------------------------
    @property
    def caps(self) -> StreamCaps:
        if self._caps is None:
            # before open: what any OpenNI2 depth camera can promise without asking the device
            return StreamCaps(frozenset({"depth", "ir", "rgb"}),
                              (frozenset({"depth", "ir"}), frozenset({"depth", "rgb"})), {})
        return self._caps

    @property
    def intrinsics(self) -> dict[str, Intrinsics]:
        return dict(self._intr)

    @property
    def meta(self) -> dict[str, Any]:
        m = dict(self._meta)
        if self._intr:
            m["depth_to_ir"] = self._depth_to_ir.tolist()
            m["depth_to_rgb"] = self._depth_to_rgb.tolist()
        return m

    @property
    def controls(self) -> dict[str, Control]:
        return dict(self._controls)

    def set_control(self, name: str, value: Any) -> None:
        if name == "emitter" and "emitter" not in self._controls:
            if not self.is_open:
                raise SourceError(f"{self.name}: open the device before switching its emitter")
            raise SourceError(f"{self.name}: this device/driver has no software control of the IR emitter "
                              f"(the PS1080 emitter property is not supported); for the emitter-off IR "
                              f"calibration frames (paper §6) cover the emitter with paper instead")
        super().set_control(name, value)

    def _set_control(self, name: str, value: Any) -> None:
        if name != "emitter":  # pragma: no cover - no other control is listed
            raise SourceError(f"{self.name}: control {name!r} cannot be set")
        on = bool(value)
        try:
            self._dev.set_property(self._emitter_pid, ctypes.c_uint64(int(on)))
        except Exception as e:
            raise SourceError(f"{self.name}: switching the emitter {'on' if on else 'off'} failed: "
                              f"{_oni_error_text(e)}") from None
        self._controls["emitter"] = Control("emitter", "bool", on)

    # -- .oni recording (OpenNI2's own format, for interchange) --------------------------------
    def start_oni_recording(self, path: str | os.PathLike, lossy: bool = False) -> None:
        """Record the running streams into an OpenNI ``.oni`` file while frames are read."""
        if not self.is_open:
            raise SourceError(f"{self.name}: open the device before recording")
        if self._recorder is not None:
            raise SourceError(f"{self.name}: already recording to {self._recorder.filename!r}")
        ni = load_openni2(self.library_dir)
        path = os.fspath(path)
        try:
            rec = ni.Recorder(path.encode())
            for vs in self._streams.values():
                rec.attach(vs, lossy)
            rec.start()
        except Exception as e:
            raise SourceError(f"{path}: cannot record .oni: {_oni_error_text(e)}") from None
        self._recorder = rec

    def stop_oni_recording(self, _restart: bool = True) -> None:
        """Stop and finalise the ``.oni`` recording (nothing if none is running).

        The streams are stopped while the recorder is destroyed and then restarted: destroying an
        OpenNI2 recorder while a driver thread hands it a frame deadlocks (seen with Debian's build).
        """
        rec, self._recorder = self._recorder, None
        if rec is None:
            return
        with contextlib.suppress(Exception):
            rec.stop()
        running = frozenset(self._streams)
        self._halt_streams()  # no frame may reach the recorder while it is destroyed ...
        with contextlib.suppress(Exception):
            rec.close()
        self._destroy_streams()  # ... and it must be destroyed before the streams it holds
        if _restart and running and self._dev is not None:
            self._start(running)

    # -- reading -------------------------------------------------------------------------------
    def _teardown(self) -> None:
        self.stop_oni_recording(_restart=False)
        self._stop_all()
        if self._dev is not None:
            with contextlib.suppress(Exception):
                self._dev.close()
        self._dev = None

    def _close(self) -> None:
        self._teardown()

    def _wait(self, stream: str, vs, n_done: int) -> None:
        ni = load_openni2(self.library_dir)
        timeout = self.first_frame_timeout_s if self._restarted else self.timeout_s
        try:
            ready = ni.wait_for_any_stream([vs], timeout)
        except Exception as e:
            raise DeviceError(f"{self.name}: the {stream} stream failed after {n_done} frames: "
                              f"{_oni_error_text(e)} (device unplugged?)") from None
        if ready is None:
            if self.is_recording:
                raise StopIteration
            raise DeviceError(f"{self.name}: no {stream} frame for {timeout:g} s after {n_done} frames "
                              f"(device unplugged or stalled)")

    def _read(self, stream: str, vs, n_done: int):
        try:
            vf = vs.read_frame()
        except Exception as e:
            raise DeviceError(f"{self.name}: reading the {stream} stream failed after {n_done} frames: "
                              f"{_oni_error_text(e)} (device unplugged?)") from None
        try:
            arr, pf, w, h = _frame_pixels(vf)
            ts = int(vf.timestamp)
        finally:
            with contextlib.suppress(Exception):
                vf.close()
        return arr, pf, w, h, ts

    def _frames(self) -> Iterator[Frame]:
        n_done = 0
        while True:
            streams = dict(self._streams)
            if not streams:
                raise SourceError(f"{self.name}: no stream is running")
            order = [s for s in ("depth", "ir", "rgb") if s in streams]
            imgs: dict[str, np.ndarray] = {}
            t_us = None
            try:
                for st in order:
                    self._wait(st, streams[st], n_done)
                    arr, pf, w, h, ts = self._read(st, streams[st], n_done)
                    if st == "depth":
                        imgs[st] = depth_to_metres(arr, pf)
                    elif st == "ir":
                        imgs[st] = ir_to_counts(arr, pf)
                    else:
                        imgs[st] = colour_to_rgb8(arr, pf, w, h)
                    if t_us is None:
                        t_us = ts
            except StopIteration:  # end of an .oni file
                return
            if streams.keys() != self._streams.keys():
                continue  # streams were switched while reading; drop the mixed frame
            t = t_us * 1e-6 + self._t_offset
            if t <= self._last_t:
                # the device clock restarted (stream switch) or stepped back: keep time monotonic
                period = 1.0 / max(1.0, min(float(m.fps) for m in self._modes.values()))
                self._t_offset += self._last_t - t + period
                t = t_us * 1e-6 + self._t_offset
            self._last_t = t
            self._restarted = False
            emitter = self._controls["emitter"].value if "emitter" in self._controls else None
            fr = Frame(index=self._index, timestamp=t, depth=imgs.get("depth"), ir=imgs.get("ir"),
                       rgb=imgs.get("rgb"), rgb_encoding="srgb8",
                       depth_intrinsics=self._intr.get("depth") if "depth" in imgs else None,
                       ir_intrinsics=self._intr.get("ir") if "ir" in imgs else None,
                       rgb_intrinsics=self._intr.get("rgb") if "rgb" in imgs else None,
                       depth_to_ir=self._depth_to_ir.copy(), depth_to_rgb=self._depth_to_rgb.copy(),
                       pass_name=self.pass_name, emitter=emitter)
            self._index += 1
            n_done += 1
            yield fr

    # -- recordings ----------------------------------------------------------------------------
    def __len__(self) -> int:
        if not self.is_recording:
            return super().__len__()
        if not self._streams:
            raise SourceError(f"{self.name}: open the file before asking its length")
        vs = self._streams.get("depth") or next(iter(self._streams.values()))
        return int(vs.get_number_of_frames())

    def seek(self, index: int) -> None:
        if not self.is_recording:
            return super().seek(index)
        vs = self._streams.get("depth") or next(iter(self._streams.values()))
        try:
            self._dev.playback.seek(vs, int(index))
        except Exception as e:
            raise SourceError(f"{self.name}: cannot seek to frame {index}: {_oni_error_text(e)}") from None
        self._index = int(index)


def _oni_error_text(e: BaseException) -> str:
    """A one-line description of an error raised by the ``openni`` binding."""
    args = getattr(e, "args", ())
    if len(args) >= 2 and isinstance(args[1], (bytes, str)):
        code = getattr(args[0], "name", args[0])
        msg = args[1].decode(errors="replace") if isinstance(args[1], bytes) else args[1]
        return f"{msg.strip() or 'error'} ({code})"
    return (str(e).strip().splitlines() or [e.__class__.__name__])[-1]


def _version_text(ni) -> str:
    try:
        v = ni.get_version()
        return f"{v.major}.{v.minor}.{v.maintenance}.{v.build}"
    except Exception:  # pragma: no cover
        return "unknown"
