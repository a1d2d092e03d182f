"""The session format: writer/reader round trip, Source API, events, poses, crash safety."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from appfusion.errors import AppFusionError
from appfusion.frame import Frame, Intrinsics, make_pose
from appfusion.source import Source
from replay.session import SessionReader, SessionWriter, copy_session, pose_to_tum, tum_to_pose

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _kill_writer  # noqa: E402

W, H = 40, 30
K_D = Intrinsics(W, H, 36.0, 36.5, 19.5, 14.5)
K_I = Intrinsics(W, H, 36.0, 36.5, 19.0, 14.0, (0.1, -0.02, 0.0, 0.0))
K_C = Intrinsics(2 * W, 2 * H, 70.0, 70.0, 39.5, 29.5)
D2RGB = make_pose(t=[-0.025, 0.0, 0.0])


def _rot(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _depth(u):
    d = u.astype(np.float32) / np.float32(5000.0)
    d[u == 0] = np.nan
    return d


def _kinect_v1_session(path, n=6, rgb_encoding="srgb8", seed=0, **kw):
    """A Kinect-v1-like session: depth+IR frames (geometry pass) then depth+RGB frames (rgb pass)."""
    rng = np.random.default_rng(seed)
    frames = []
    with SessionWriter(path, device="kinect-v1-sim", intrinsics={"depth": K_D, "ir": K_I, "rgb": K_C},
                       depth_to_rgb=D2RGB, rgb_encoding=rgb_encoding, notes="unit test",
                       extra={"object": "mug"}, **kw) as w:
        w.event(0.0, "pass", "geometry")
        w.event(0.0, "emitter", "on")
        for i in range(n):
            u = rng.integers(0, 65536, (H, W)).astype(np.uint16)
            u[0, :5] = [0, 1, 65535, 5000, 2]
            f = Frame(i, 0.5 + i / 30.0, depth=_depth(u), pose=make_pose(_rot(0.1 * i), [0.01 * i, 0.2, -0.3]))
            if i < n // 2:
                f.ir = rng.integers(0, 1024, (H, W)).astype(np.float32)
            else:
                if i == n // 2:
                    f.pass_name = "rgb"
                if rgb_encoding == "srgb8":
                    f.rgb = rng.integers(0, 256, (2 * H, 2 * W, 3)).astype(np.uint8)
                else:
                    f.rgb = (rng.integers(0, 65536, (2 * H, 2 * W, 3)) / np.float32(65535.0)).astype(np.float32)
                    f.rgb_encoding = "linear"
                f.emitter = False
            w.write(f)
            frames.append(f)
    return frames


def test_round_trip_bit_exact(tmp_path):
    path = tmp_path / "s"
    frames = _kinect_v1_session(path, fsync_interval_s=0.0)
    r = SessionReader(path)
    assert isinstance(r, Source) and r.is_recording
    assert len(r) == len(frames) == 6
    got = list(r)
    assert len(got) == 6
    for f, g in zip(frames, got):
        assert g.index == f.index
        assert abs(g.timestamp - f.timestamp) <= 5e-7
        assert g.streams == f.streams
        np.testing.assert_array_equal(g.depth, f.depth)  # NaN where invalid, same bits elsewhere
        assert g.depth.dtype == np.float32
        if f.ir is not None:
            np.testing.assert_array_equal(g.ir, f.ir)
            assert g.ir.dtype == np.float32
        if f.rgb is not None:
            assert g.rgb.dtype == np.uint8 and g.rgb_encoding == "srgb8"
            np.testing.assert_array_equal(g.rgb, f.rgb)
        np.testing.assert_allclose(g.pose, f.pose, atol=1e-9)
        assert g.depth_intrinsics == K_D and g.ir_intrinsics == K_I and g.rgb_intrinsics == K_C
        np.testing.assert_array_equal(g.depth_to_rgb, D2RGB)
        np.testing.assert_array_equal(g.depth_to_ir, np.eye(4))
    assert [g.pass_name for g in got] == ["geometry"] * 3 + ["rgb"] * 3
    assert [g.emitter for g in got] == [True] * 3 + [False] * 3
    # the depth values of the fixed pixels: 1 unit = 0.2 mm, 65535 units = 13.107 m, 0 = invalid
    d0 = got[0].depth[0, :5]
    assert np.isnan(d0[0]) and d0[1] == np.float32(1 / 5000) and d0[2] == np.float32(65535 / 5000)
    assert d0[3] == 1.0


def test_round_trip_linear16(tmp_path):
    frames = _kinect_v1_session(tmp_path / "s", rgb_encoding="linear", threads=3)
    r = SessionReader(tmp_path / "s")
    assert r.meta["streams"]["rgb"]["encoding"] == "linear16"
    for f, g in zip(frames, r):
        if f.rgb is not None:
            assert g.rgb_encoding == "linear" and g.rgb.dtype == np.float32
            np.testing.assert_array_equal(g.rgb, f.rgb)


def test_meta_caps_events_and_files(tmp_path):
    path = tmp_path / "s"
    _kinect_v1_session(path)
    r = SessionReader(path)
    m = r.meta
    assert m["format"] == "appfusion-session" and m["version"] == 1 and m["device"] == "kinect-v1-sim"
    assert m["notes"] == "unit test" and m["extra"] == {"object": "mug"}
    assert m["emitter_position_m"] == [0.075, 0.0, 0.0]
    assert m["streams"]["depth"]["units_per_m"] == 5000.0 and m["streams"]["ir"]["bits"] == 10
    assert r.intrinsics == {"depth": K_D, "ir": K_I, "rgb": K_C}
    # a Kinect v1 never streams IR and RGB together: caps say so, from the frames recorded
    assert r.caps.streams == {"depth", "ir", "rgb"}
    assert set(r.caps.together) == {frozenset({"depth", "ir"}), frozenset({"depth", "rgb"})}
    assert not r.caps.ir_and_rgb_together
    assert r.caps.rates["depth"] == pytest.approx(30.0, rel=1e-3)
    assert [e[1:] for e in r.events] == [("pass", "geometry"), ("emitter", "on"), ("pass", "rgb"),
                                         ("emitter", "off")]
    st = r.stream_timestamps()
    assert len(st["depth"]) == 6 and len(st["ir"]) == 3 and len(st["rgb"]) == 3
    # the files are TUM-style: timestamp with 6 decimals, path in the stream's folder
    lines = [ln for ln in (path / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    assert lines[0] == "0.600000 rgb/0.600000.png"
    assert (path / "rgb" / "0.600000.png").is_file()
    ev = (path / "events.txt").read_text().splitlines()
    assert "0.600000 pass rgb" in ev and "0.600000 emitter off" in ev
    json.loads((path / "meta.json").read_text())
    assert not [p for p in path.rglob("*.tmp")]


def test_seek_len_getitem(tmp_path):
    _kinect_v1_session(tmp_path / "s")
    r = SessionReader(tmp_path / "s")
    r.seek(4)
    assert [f.index for f in r] == [4, 5]
    r.seek(-1)
    assert [f.index for f in r] == [5]
    r.seek(6)
    assert list(r) == []
    assert r[2].index == 2 and r[-1].index == 5
    with pytest.raises(IndexError):
        r.seek(7)
    with pytest.raises(IndexError):
        r[6]
    with r:
        assert r.is_open
    assert not r.is_open


def test_pose_quaternion_round_trip():
    rng = np.random.default_rng(3)
    from scipy.spatial.transform import Rotation

    for R in Rotation.random(20, random_state=4).as_matrix():
        T = make_pose(R, rng.normal(size=3))
        np.testing.assert_allclose(tum_to_pose(pose_to_tum(T)), T, atol=1e-12)


def test_pose_needs_match_within_1ms(tmp_path):
    path = tmp_path / "s"
    with SessionWriter(path, intrinsics={"depth": K_D}) as w:
        for i in range(3):
            w.write(Frame(i, float(i), depth=np.ones((H, W), np.float32)))
    (path / "groundtruth.txt").write_text("# t tx ty tz qx qy qz qw\n"
                                          "0.0009 1 2 3 0 0 0 1\n"
                                          "1.0020 4 5 6 0 0 0 1\n"
                                          "1.9995 7 8 9 0 0 0.7071068 0.7071068\n")
    poses = [f.pose for f in SessionReader(path)]
    np.testing.assert_allclose(poses[0][:3, 3], [1, 2, 3])
    assert poses[1] is None  # 2 ms away
    np.testing.assert_allclose(poses[2][:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)


def test_writer_rejects_bad_input(tmp_path):
    path = tmp_path / "s"
    with SessionWriter(path, intrinsics={"depth": K_D}) as w:
        w.write(Frame(0, 1.0, depth=np.ones((H, W), np.float32)))
        with pytest.raises(AppFusionError, match="not after the previous"):
            w.write(Frame(1, 1.0000004, depth=np.ones((H, W), np.float32)))  # same microsecond
        with pytest.raises(AppFusionError, match="intrinsics say"):
            w.write(Frame(1, 2.0, depth=np.ones((H + 1, W), np.float32)))
        with pytest.raises(AppFusionError, match="without ir intrinsics"):
            w.write(Frame(1, 2.0, depth=np.ones((H, W), np.float32), ir=np.ones((H, W), np.float32)))
        with pytest.raises(AppFusionError, match="NaN"):
            w.write(Frame(1, 2.0, ir=np.full((H, W), np.nan, np.float32), ir_intrinsics=K_D))
        with pytest.raises(AppFusionError, match="no images"):
            w.write(Frame(1, 2.0))
        w.event(1.0, "pass", "geometry")
        with pytest.raises(AppFusionError, match="events must be in time order"):
            w.event(0.5, "pass", "x")
        with pytest.raises(AppFusionError, match="on/off"):
            w.event(3.0, "emitter", "maybe")
        # a stream first seen with its own intrinsics is added to meta.json
        w.write(Frame(1, 2.0, depth=np.ones((H, W), np.float32), ir=np.ones((H, W), np.float32), ir_intrinsics=K_I))
    with pytest.raises(AppFusionError, match="closed"):
        w.write(Frame(2, 3.0, depth=np.ones((H, W), np.float32)))
    r = SessionReader(path)
    assert len(r) == 2 and r.intrinsics["ir"] == K_I and r[1].streams == ("depth", "ir")
    with pytest.raises(AppFusionError, match="not empty"):
        SessionWriter(path, intrinsics={"depth": K_D})
    with pytest.raises(AppFusionError, match="rgb_encoding"):
        SessionWriter(tmp_path / "t", rgb_encoding="jpeg")
    with pytest.raises(AppFusionError, match="JSON"):
        SessionWriter(tmp_path / "u", extra={"a": object()})


def test_depth_out_of_range_is_counted_and_invalid(tmp_path):
    d = np.full((H, W), 2.0, np.float32)
    d[0, 0], d[0, 1], d[0, 2] = 20.0, -1.0, np.nan  # 20 m does not fit 16 bits at 5000 units/m
    with SessionWriter(tmp_path / "s", intrinsics={"depth": K_D}) as w:
        w.write(Frame(0, 0.0, depth=d))
    assert w.clipped_depth_pixels == 1
    g = SessionReader(tmp_path / "s")[0].depth
    assert np.isnan(g[0, :3]).all() and np.all(g.flat[3:] == 2.0)


def test_rgb_encoding_conversion(tmp_path):
    rgb8 = np.arange(H * W * 3, dtype=np.int64).reshape(H, W, 3).astype(np.uint8)
    with SessionWriter(tmp_path / "s", intrinsics={"rgb": K_D}, rgb_encoding="linear") as w:
        w.write(Frame(0, 0.0, rgb=rgb8))
    f = SessionReader(tmp_path / "s")[0]
    assert f.rgb_encoding == "linear"
    np.testing.assert_allclose(f.rgb, Frame(0, 0, rgb=rgb8).rgb_linear(), atol=1 / 65535)


def test_copy_session_preserves_everything(tmp_path):
    frames = _kinect_v1_session(tmp_path / "a")
    rep = copy_session(SessionReader(tmp_path / "a"), tmp_path / "b")
    assert rep["frames"] == 6 and rep["counts"] == {"depth": 6, "ir": 3, "rgb": 3}
    a, b = SessionReader(tmp_path / "a"), SessionReader(tmp_path / "b")
    assert a.events == b.events and a.intrinsics == b.intrinsics
    assert b.meta["extra"]["object"] == "mug" and b.meta["extra"]["converted_from"]["format"] == "session"
    for f, fa, g in zip(frames, a, b):
        np.testing.assert_array_equal(g.depth, f.depth)
        assert (g.timestamp, g.streams, g.pass_name, g.emitter) == (fa.timestamp, fa.streams, fa.pass_name, fa.emitter)
        np.testing.assert_allclose(g.pose, f.pose, atol=1e-9)
    for name in ("depth", "ir", "rgb"):
        files = sorted(os.listdir(tmp_path / "a" / name))
        assert files == sorted(os.listdir(tmp_path / "b" / name)) and files
        for fn in files:  # a frame read from a session writes back to identical PNGs
            assert (tmp_path / "a" / name / fn).read_bytes() == (tmp_path / "b" / name / fn).read_bytes()


def _kill_round(tmp_path, run_s):
    path = tmp_path / f"killed{run_s}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, str(Path(_kill_writer.__file__)), str(path)],
                            stdout=subprocess.PIPE, text=True, env=env)
    written: list[tuple[int, float]] = []
    try:
        first = proc.stdout.readline()
        assert first.startswith("ready"), first
        t_ready = time.time()
        while time.time() - t_ready < run_s:
            line = proc.stdout.readline()
            if not line:
                break
            i, t = line.split()
            written.append((int(i), float(t)))
        t_kill = time.time()
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert len(written) > 5, "the writer recorded too few frames to test anything"
    # strict reading: nothing may be damaged after a kill -9 (at most a half-written last line)
    r = SessionReader(path)
    assert r.bad_frames == []
    by_t = {round(f.timestamp / _kill_writer.DT): f for f in r}
    must = [i for i, t in written if t <= t_kill - 1.0]
    assert set(must) <= set(by_t), "frames written more than 1 s before the kill are missing"
    assert len(by_t) >= len(written) - 1  # in fact nothing acknowledged is lost on a process kill
    for i, f in by_t.items():
        du, ir, rgb = _kill_writer.frame_images(i, 160, 120)
        if f.depth is not None:
            np.testing.assert_array_equal(f.depth, _depth(du))
        if f.ir is not None:
            np.testing.assert_array_equal(f.ir, ir.astype(np.float32))
        if f.rgb is not None:
            np.testing.assert_array_equal(f.rgb, rgb)
        assert f.pass_name == "scan"
    # all but possibly the very last frame (killed between its index lines) have all three streams
    complete = [f for f in by_t.values() if f.streams == ("depth", "ir", "rgb")]
    assert len(complete) >= len(by_t) - 1
    return len(written)


def test_kill_9_mid_recording_replays(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:  # two recordings at once, killed at different moments
        n = sum(pool.map(lambda s: _kill_round(tmp_path, s), (1.6, 1.23)))
    print(f"frames written before the kills: {n}")
    assert n > 20


def test_empty_session_and_streams_declared_late(tmp_path, capsys):
    from appfusion.cli import main

    with SessionWriter(tmp_path / "e", device="nothing yet"):
        pass
    r = SessionReader(tmp_path / "e")
    assert len(r) == 0 and list(r) == [] and r.caps.streams == frozenset() and r.meta["streams"] == {}
    assert main(["info", str(tmp_path / "e")]) == 0
    assert "no depth images" in capsys.readouterr().out
    # meta.json exists from the start, and gains the stream of the first frame
    w = SessionWriter(tmp_path / "l")
    assert json.loads((tmp_path / "l" / "meta.json").read_text())["streams"] == {}
    w.write(Frame(0, 0.0, depth=np.ones((H, W), np.float32), depth_intrinsics=K_D))
    assert SessionReader(tmp_path / "l").intrinsics == {"depth": K_D}  # readable before close
    w.close()
