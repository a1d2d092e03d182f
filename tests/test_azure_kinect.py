"""Tests of replay.azure_kinect on the shared Azure Kinect recording and on synthetic k4arecorder files.

The shared recording (pyk4a's test asset) holds exactly one capture, so everything about several
frames (timestamps 0.2 s apart at 5 fps, seeking, grouping) is tested on recordings written here by a
minimal Matroska writer in the k4arecorder layout, some of them built from the real file's own
payloads and calibration.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from appfusion.errors import SessionFormatError
from appfusion.frame import invert_pose
from appfusion.source import Source
from replay.azure_kinect import AzureKinectReader, parse_calibration

# ------------------------------------------------------------------------------------------------
# a minimal k4arecorder-layout Matroska writer (test helper)
# ------------------------------------------------------------------------------------------------


def _el(eid: int, payload: bytes) -> bytes:
    """One EBML element with an 8-byte size field."""
    return eid.to_bytes((eid.bit_length() + 7) // 8, "big") + b"\x01" + len(payload).to_bytes(7, "big") + payload


def _uint(eid: int, v: int) -> bytes:
    return _el(eid, v.to_bytes(max(1, (v.bit_length() + 7) // 8), "big"))


def _str(eid: int, s: str) -> bytes:
    return _el(eid, s.encode())


def _bitmapinfo(w: int, h: int, bits: int, fourcc: bytes) -> bytes:
    return struct.pack("<IiiHH4sIiiII", 40, w, h, 1, bits, fourcc, w * h * bits // 8, 0, 0, 0, 0)


def _simple_tag(name: str, value: str) -> bytes:
    return _el(0x67C8, _str(0x45A3, name) + _str(0x4487, value))


def write_k4a_mkv(path: Path, captures, calibration: bytes | None, *, depth_mode="NFOV_UNBINNED",
                  color_format="MJPG", fps=5, start_offset_ns=336_277_000, color_delay_us=0,
                  depth_size=(640, 576), color_size=(1280, 720)) -> Path:
    """Write captures ``[(t_us, depth_mm | None, ir | None, color_payload | None), ...]`` as a k4a MKV.

    Depth and IR are uint16 arrays written big-endian ('b16g'); colour payloads are raw bytes in
    ``color_format``. Timecode scale 1000 ns, one cluster per capture, like k4arecorder.
    """
    period_ns = int(1e9 / fps)
    fourcc = {"MJPG": b"MJPG", "NV12": b"NV12", "YUY2": b"YUY2", "BGRA": b"\0\0\0\0"}[color_format]
    bits = {"MJPG": 24, "NV12": 12, "YUY2": 16, "BGRA": 32}[color_format]
    uids = {"COLOR": 1001, "DEPTH": 1002, "IR": 1003}

    def track(num, name, w, h, bitcount, fcc):
        return _el(0xAE, _uint(0xD7, num) + _uint(0x73C5, uids[name]) + _uint(0x83, 1)
                   + _str(0x86, "V_MS/VFW/FOURCC") + _el(0x63A2, _bitmapinfo(w, h, bitcount, fcc))
                   + _str(0x536E, name) + _uint(0x23E383, period_ns)
                   + _el(0xE0, _uint(0xB0, w) + _uint(0xBA, h)))

    dw, dh = depth_size
    tracks = _el(0x1654AE6B, track(1, "COLOR", *color_size, bits, fourcc)
                 + track(2, "DEPTH", dw, dh, 16, b"b16g") + track(3, "IR", dw, dh, 16, b"b16g"))
    info = _el(0x1549A966, _uint(0x2AD7B1, 1000) + _str(0x4D80, "test") + _str(0x5741, "test"))
    tags = _el(0x7373, _el(0x63C0, b"") + _simple_tag("K4A_START_OFFSET_NS", str(start_offset_ns))
               + _simple_tag("K4A_DEVICE_SERIAL_NUMBER", "000000000042"))
    tags += _el(0x7373, _el(0x63C0, _uint(0x63C5, uids["COLOR"]))
                + _simple_tag("K4A_COLOR_MODE", f"{color_format}_{color_size[1]}P"))
    tags += _el(0x7373, _el(0x63C0, _uint(0x63C5, uids["DEPTH"])) + _simple_tag("K4A_DEPTH_MODE", depth_mode))
    tags += _el(0x7373, _el(0x63C0, _uint(0x63C5, uids["IR"])) + _simple_tag("K4A_IR_MODE", "ACTIVE"))
    attachments = b""
    if calibration is not None:
        attachments = _el(0x1941A469, _el(0x61A7, _str(0x466E, "calibration.json")
                                          + _str(0x4660, "application/octet-stream")
                                          + _el(0x465C, calibration) + _uint(0x46AE, 77)))
        tags += _el(0x7373, _el(0x63C0, _uint(0x63C6, 77)) + _simple_tag("K4A_CALIBRATION_FILE", "calibration.json"))
    clusters = b""
    for t_us, depth, ir, color in captures:
        blocks = b""
        if color is not None:
            blocks += _el(0xA3, b"\x81" + struct.pack(">h", color_delay_us) + b"\x80" + bytes(color))
        if depth is not None:
            blocks += _el(0xA3, b"\x82\x00\x00\x80" + depth.astype(">u2").tobytes())
        if ir is not None:
            blocks += _el(0xA3, b"\x83\x00\x00\x80" + ir.astype(">u2").tobytes())
        clusters += _el(0x1F43B675, _uint(0xE7, t_us) + blocks)
    header = _el(0x1A45DFA3, _uint(0x4286, 1) + _uint(0x42F7, 1) + _uint(0x42F2, 4) + _uint(0x42F3, 8)
                 + _str(0x4282, "matroska") + _uint(0x4287, 4) + _uint(0x4285, 2))
    path.write_bytes(header + _el(0x18538067, info + tracks + attachments + _el(0x1254C367, tags) + clusters))
    return path


# ------------------------------------------------------------------------------------------------
# fixtures
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def reader(azure_mkv) -> AzureKinectReader:
    r = AzureKinectReader(azure_mkv)
    yield r
    r.close()


@pytest.fixture(scope="module")
def real_frame(reader):
    return reader.read_frame(0)


@pytest.fixture(scope="module")
def side_calibration(azure_mkv) -> dict:
    return json.loads((azure_mkv.parent / "calibration.json").read_text())


@pytest.fixture(scope="module")
def real_payloads(azure_mkv):
    """(depth_mm, ir, jpeg bytes, calibration bytes) of the real recording's capture, read with PyAV."""
    import av

    out = {}
    with av.open(str(azure_mkv)) as c:
        calib = next(bytes(s.data) for s in c.streams if s.type == "attachment")
        titles = {s.index: s.metadata.get("title") for s in c.streams}
        for p in c.demux():
            if p.size:
                out[titles[p.stream.index]] = bytes(p)
    depth = np.frombuffer(out["DEPTH"], ">u2").reshape(576, 640)
    ir = np.frombuffer(out["IR"], ">u2").reshape(576, 640)
    return depth, ir, out["COLOR"], calib


# ------------------------------------------------------------------------------------------------
# the real recording
# ------------------------------------------------------------------------------------------------


def test_real_recording_layout(reader, real_frame):
    assert isinstance(reader, Source) and reader.is_recording
    assert len(reader) == 1  # pyk4a's asset holds one capture
    f = real_frame
    assert f.depth.shape == (576, 640) and f.depth.dtype == np.float32
    assert f.ir.shape == (576, 640) and f.ir.dtype == np.float32
    assert f.rgb.shape == (720, 1280, 3) and f.rgb.dtype == np.uint8 and f.rgb_encoding == "srgb8"
    assert f.streams == ("depth", "ir", "rgb")
    # k4a device time: block time 463945 us + K4A_START_OFFSET_NS 336277 us (pyk4a's tests expect 800222 us)
    assert f.timestamp == pytest.approx(0.800222, abs=1e-9)
    assert f.pass_name == "scan" and f.emitter is True
    assert reader.caps.can_stream({"depth", "ir", "rgb"}) and reader.caps.ir_and_rgb_together
    assert reader.caps.rates["depth"] == pytest.approx(5.0)
    m = reader.meta
    assert m["serial"] == "001514394512"
    assert (m["depth_mode"], m["color_format"], m["color_resolution"], m["ir_mode"]) == \
        ("NFOV_UNBINNED", "MJPG", "720P", "ACTIVE")
    assert m["fps"] == pytest.approx(5.0) and m["start_offset_s"] == pytest.approx(0.336277)
    assert m["depth_units_per_m"] == 1000.0


def test_real_recording_images(real_frame):
    d = real_frame.depth
    valid = np.isfinite(d)
    assert 0.6 < valid.mean() < 0.95  # the NFOV hexagon with some dropouts
    assert ((d[valid] > 0.25) & (d[valid] < 5.5)).mean() > 0.9
    # big-endian b16g: neighbouring valid depths differ by millimetres, not by 256-mm byte steps
    step = np.abs(np.diff(d, axis=1))
    assert np.nanmedian(step) < 0.005
    ir = real_frame.ir
    assert (ir > 0).mean() > 0.5 and ir.max() > 1000
    assert np.all(np.isnan(d) | (d > 0))
    # a real colour photo, not a blank or garbage decode
    assert 40 < real_frame.rgb.mean() < 220 and real_frame.rgb.std() > 20


def _expected_from_side(cam: dict, binned, crop, out):
    cx, cy, fx, fy = cam["Intrinsics"]["ModelParameters"][:4]
    return (fx * binned[0], fy * binned[1], cx * binned[0] - crop[0] - 0.5, cy * binned[1] - crop[1] - 0.5)


def test_real_intrinsics_match_side_calibration(reader, side_calibration):
    cams = {c["Location"]: c for c in side_calibration["CalibrationInformation"]["Cameras"]}
    d, c = reader.intrinsics["depth"], reader.intrinsics["rgb"]
    assert (d.width, d.height, c.width, c.height) == (640, 576, 1280, 720)
    assert reader.intrinsics["ir"] == d
    exp_d = _expected_from_side(cams["CALIBRATION_CameraLocationD0"], (1024, 1024), (192, 180), (640, 576))
    exp_c = _expected_from_side(cams["CALIBRATION_CameraLocationPV0"], (1280, 960), (0, 120), (1280, 720))
    np.testing.assert_allclose((d.fx, d.fy, d.cx, d.cy), exp_d, rtol=1e-9)
    np.testing.assert_allclose((c.fx, c.fy, c.cx, c.cy), exp_c, rtol=1e-9)
    # sane for the hardware: NFOV unbinned ~504 px, 720p colour ~610 px, principal points near the centre
    assert 480 < d.fx < 530 and abs(d.fx - d.fy) < 2 and abs(d.cx - 320) < 30 and abs(d.cy - 288) < 70
    assert 590 < c.fx < 630 and abs(c.fx - c.fy) < 2 and abs(c.cx - 640) < 30 and abs(c.cy - 360) < 30
    p = cams["CALIBRATION_CameraLocationD0"]["Intrinsics"]["ModelParameters"]
    assert d.dist == pytest.approx((p[4], p[5], p[13], p[12], p[6], p[7], p[8], p[9]))


def test_real_extrinsics(reader, side_calibration):
    T = reader.depth_to_rgb
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
    assert 0.025 < np.linalg.norm(T[:3, 3]) < 0.04  # colour camera ~32 mm beside the depth camera
    angle = np.degrees(np.arccos((np.trace(T[:3, :3]) - 1) / 2))
    assert 3 < angle < 8  # the depth camera is tilted ~6 degrees against the colour camera
    np.testing.assert_allclose(reader.read_frame(0).depth_to_ir, np.eye(4))


def _edge_distance(frame, T) -> float:
    """Median distance (colour px) from projected depth discontinuities to colour-image edges."""
    di, ci = frame.depth_intrinsics, frame.rgb_intrinsics
    edges = cv2.Canny(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY), 50, 150)
    dist = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)
    d = np.nan_to_num(frame.depth, nan=0.0)
    jump = np.maximum(np.abs(np.diff(d, axis=1, append=0)), np.abs(np.diff(d, axis=0, append=0))) > 0.1
    v, u = np.nonzero(jump & np.isfinite(frame.depth))
    n = cv2.undistortPoints(np.stack([u, v], 1).astype(np.float64)[:, None], di.K, np.array(di.dist)).reshape(-1, 2)
    z = frame.depth[v, u].astype(np.float64)
    uv, _ = cv2.projectPoints(np.c_[n * z[:, None], z], cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], ci.K, np.array(ci.dist))
    uv = np.round(uv.reshape(-1, 2)).astype(int)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < ci.width) & (uv[:, 1] >= 0) & (uv[:, 1] < ci.height)
    return float(np.median(dist[uv[ok, 1], uv[ok, 0]]))


def test_real_depth_registers_onto_colour(real_frame):
    """Depth edges land on colour edges with the parsed calibration, not with a wrong one."""
    good = _edge_distance(real_frame, real_frame.depth_to_rgb)
    assert good < 6.0  # measured 4.8 px
    assert good < 0.5 * _edge_distance(real_frame, invert_pose(real_frame.depth_to_rgb))  # 15.3 px
    assert good < 0.5 * _edge_distance(real_frame, np.eye(4))  # 13.1 px


# ------------------------------------------------------------------------------------------------
# synthetic recordings
# ------------------------------------------------------------------------------------------------


def test_multi_frame_timestamps_and_seek(tmp_path, real_payloads):
    depth, ir, jpeg, calib = real_payloads
    times = [463_945 + 200_000 * k for k in range(5)]
    path = write_k4a_mkv(tmp_path / "five.mkv", [(t, depth, ir, jpeg) for t in times], calib)
    with AzureKinectReader(path) as r:
        assert len(r) == 5
        ts = r.timestamps
        np.testing.assert_allclose(ts, (np.array(times) + 336_277) * 1e-6, atol=1e-9)
        assert np.all(np.diff(ts) > 0)
        np.testing.assert_allclose(np.diff(ts), 0.2, atol=1e-6)
        frames = list(r)
        assert [f.index for f in frames] == [0, 1, 2, 3, 4]
        np.testing.assert_array_equal(frames[2].depth, np.where(depth == 0, np.nan, depth * np.float32(1e-3)).astype(np.float32))
        np.testing.assert_array_equal(frames[4].ir, ir.astype(np.float32))
        r.seek(3)
        f3 = next(iter(r))
        assert f3.index == 3 and f3.timestamp == pytest.approx(ts[3])
        r.seek(-1)
        assert [f.index for f in r] == [4]
        with pytest.raises(IndexError):
            r.seek(5)


def test_exact_values_grouping_and_dropped_frames(tmp_path, real_payloads):
    calib = real_payloads[3]
    rng = np.random.default_rng(0)
    depth = rng.integers(1, 6000, size=(576, 640), dtype=np.uint16)
    depth[:10] = 0
    ir = rng.integers(0, 65536, size=(576, 640), dtype=np.uint16)
    rgb = rng.integers(0, 256, size=(720, 1280, 3), dtype=np.uint8)
    bgra = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGRA).tobytes()
    # colour 8 ms after depth (depth delay), a capture without colour, a lone colour block
    caps = [(100_000, depth, ir, bgra), (300_000, depth, ir, None), (500_000, None, None, bgra)]
    path = write_k4a_mkv(tmp_path / "bgra.mkv", caps, calib, color_format="BGRA", color_delay_us=8000,
                         start_offset_ns=0)
    with AzureKinectReader(path) as r:
        assert len(r) == 3
        f0, f1, f2 = list(r)
    assert f0.streams == ("depth", "ir", "rgb") and f0.timestamp == pytest.approx(0.1)
    assert np.isnan(f0.depth[:10]).all()
    np.testing.assert_array_equal(f0.depth[10:], depth[10:].astype(np.float32) * np.float32(1e-3))
    np.testing.assert_array_equal(f0.ir, ir)
    np.testing.assert_array_equal(f0.rgb, rgb)
    assert f1.streams == ("depth", "ir") and f1.rgb is None
    assert f2.streams == ("rgb",) and f2.timestamp == pytest.approx(0.508)


def test_nv12_colour(tmp_path, real_payloads):
    calib = real_payloads[3]
    yy, xx = np.mgrid[0:720, 0:1280]
    rgb = np.stack([xx * 255 // 1279, yy * 255 // 719, np.full_like(xx, 128)], -1).astype(np.uint8)
    i420 = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_I420).ravel()
    y, u, v = i420[:1280 * 720], i420[1280 * 720:1280 * 720 * 5 // 4], i420[1280 * 720 * 5 // 4:]
    nv12 = np.concatenate([y, np.stack([u, v], 1).ravel()]).tobytes()
    d = np.full((576, 640), 1000, np.uint16)
    path = write_k4a_mkv(tmp_path / "nv12.mkv", [(0, d, d, nv12)], calib, color_format="NV12")
    with AzureKinectReader(path) as r:
        f = r.read_frame(0)
    assert f.rgb.shape == (720, 1280, 3)
    assert np.abs(f.rgb.astype(int) - rgb).mean() < 3


def test_calibration_comes_from_the_attachment(tmp_path, real_payloads):
    depth, ir, jpeg, calib = real_payloads
    doc = json.loads(calib)
    cam = doc["CalibrationInformation"]["Cameras"][0]
    cam["Intrinsics"]["ModelParameters"][2] = 0.25  # fx_n of the depth camera
    path = write_k4a_mkv(tmp_path / "recal.mkv", [(0, depth, ir, jpeg)], json.dumps(doc).encode())
    r = AzureKinectReader(path)
    assert r.intrinsics["depth"].fx == pytest.approx(256.0)
    assert r.meta["serial"] == "000000000042"


def test_binned_depth_mode_intrinsics(real_payloads):
    calib = real_payloads[3]
    full = parse_calibration(calib, "NFOV_UNBINNED", None)["intrinsics"]["depth"]
    half = parse_calibration(calib, "NFOV_2X2BINNED", None)["intrinsics"]["depth"]
    assert (half.width, half.height) == (320, 288)
    assert half.fx == pytest.approx(full.fx / 2)
    # the same ray: pixel centres scale as (c + 0.5) / 2 - 0.5
    assert half.cx == pytest.approx((full.cx + 0.5) / 2 - 0.5)
    wide = parse_calibration(calib, "WFOV_UNBINNED", "1080P")["intrinsics"]
    assert wide["depth"].cx == pytest.approx(full.cx + 192)
    assert wide["rgb"].fx == pytest.approx(1.5 * parse_calibration(calib, "NFOV_UNBINNED", "720P")["intrinsics"]["rgb"].fx)


# ------------------------------------------------------------------------------------------------
# errors
# ------------------------------------------------------------------------------------------------


def test_truncated_copy(tmp_path, azure_mkv, real_payloads):
    data = azure_mkv.read_bytes()
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(data[:1_000_000])
    with pytest.raises(SessionFormatError, match="truncated") as e:
        AzureKinectReader(cut)
    assert str(cut) in str(e.value)
    cut.write_bytes(data[:5000])  # inside the header
    with pytest.raises(SessionFormatError, match="truncated"):
        AzureKinectReader(cut)
    # skip_bad keeps the captures before the cut
    depth, ir, jpeg, calib = real_payloads
    path = write_k4a_mkv(tmp_path / "three.mkv", [(t, depth, ir, jpeg) for t in (0, 200_000, 400_000)], calib)
    raw = path.read_bytes()
    path.write_bytes(raw[:len(raw) - 1000])
    with pytest.raises(SessionFormatError, match="truncated"):
        AzureKinectReader(path)
    with AzureKinectReader(path, skip_bad=True) as r:
        assert len(r) == 2 and r.meta["truncated"]
        assert [f.streams for f in r] == [("depth", "ir", "rgb")] * 2


def test_not_mkv(tmp_path, redwood_dir):
    txt = tmp_path / "notes.mkv"
    txt.write_text("hello, this is not a video\n")
    with pytest.raises(SessionFormatError, match="not a Matroska") as e:
        AzureKinectReader(txt)
    assert str(txt) in str(e.value)
    png = next(redwood_dir.rglob("*.png"))
    with pytest.raises(SessionFormatError, match="not a Matroska"):
        AzureKinectReader(png)
    with pytest.raises(SessionFormatError, match="no such file"):
        AzureKinectReader(tmp_path / "missing.mkv")
    empty = tmp_path / "empty.mkv"
    empty.write_bytes(b"")
    with pytest.raises(SessionFormatError):
        AzureKinectReader(empty)


def test_mkv_without_calibration(tmp_path, real_payloads):
    depth, ir, jpeg, _ = real_payloads
    path = write_k4a_mkv(tmp_path / "nocal.mkv", [(0, depth, ir, jpeg)], None)
    with pytest.raises(SessionFormatError, match="calibration.json") as e:
        AzureKinectReader(path)
    assert str(path) in str(e.value)


def test_damaged_colour(tmp_path, real_payloads):
    depth, ir, jpeg, calib = real_payloads
    path = write_k4a_mkv(tmp_path / "badjpeg.mkv", [(0, depth, ir, b"\xff\xd8garbage" * 10)], calib)
    with AzureKinectReader(path) as r, pytest.raises(SessionFormatError, match="frame 0.*MJPG"):
        r.read_frame(0)
    with AzureKinectReader(path, skip_bad=True) as r:
        f = r.read_frame(0)
        assert f.rgb is None and f.depth is not None
