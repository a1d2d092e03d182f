"""``appfusion record``: live OpenNI2 DummyDevice into a session and back; clean ends on device loss and Ctrl-C."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from appfusion.cli import main
from appfusion.commands import record as rec
from appfusion.errors import AppFusionError, DeviceError, SourceError
from appfusion.frame import Frame, Intrinsics
from appfusion.source import Source, StreamCaps

SessionReader = pytest.importorskip("replay.session").SessionReader

K = Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)


class FakeDevice(Source):
    """A live source with depth, IR and RGB that fails (DeviceError) or interrupts (SIGINT) after some frames."""

    name = "fake:cam"

    def __init__(self, n=100, fail_after=None, sigint_at=None, fps=30.0):
        super().__init__()
        self.n, self.fail_after, self.sigint_at, self.fps = n, fail_after, sigint_at, fps
        self.delivered = []
        self.closed = 0

    @property
    def caps(self):
        return StreamCaps.all_together({"depth", "ir", "rgb"}, {"depth": self.fps})

    @property
    def intrinsics(self):
        return {"depth": K, "ir": K, "rgb": K}

    @property
    def meta(self):
        return {"device": "Fake Cam", "emitter_position_m": [0.05, 0.0, 0.0], "ir_bits": 10}

    def _open(self):
        pass

    def _close(self):
        self.closed += 1

    def _frames(self):
        for i in range(self.n):
            if self.fail_after is not None and i == self.fail_after:
                raise DeviceError(f"{self.name}: no depth frame for 2 s after {i} frames (device unplugged?)")
            if self.sigint_at is not None and i == self.sigint_at:
                os.kill(os.getpid(), signal.SIGINT)
            d = np.full((24, 32), 0.5 + i * 0.01, np.float32)
            d[0, 0] = np.nan
            fr = Frame(i, 10.0 + i / self.fps, depth=d, ir=np.full((24, 32), float(i), np.float32),
                       rgb=np.full((24, 32, 3), i, np.uint8), depth_intrinsics=K, ir_intrinsics=K, rgb_intrinsics=K)
            self.delivered.append(fr)
            yield fr


def _patch_source(monkeypatch, src):
    monkeypatch.setattr(rec, "open_source", lambda spec, streams=None: src)


def test_record_dummy_device_and_read_it_back(tmp_path, capsys):
    pytest.importorskip("openni")
    from drivers.openni2_source import OpenNI2Source, load_openni2

    try:
        load_openni2()
    except DeviceError as e:
        pytest.skip(f"no OpenNI2 runtime: {e}")

    class Tee(OpenNI2Source):
        """The DummyDevice, keeping a copy of what it delivered to compare with the session."""

        def _frames(self):
            self.got = []
            for fr in super()._frames():
                self.got.append(fr)
                yield fr

    src = Tee("Dummy")
    res = rec.record_source(src, tmp_path / "s", frames=20, pass_name="rgb", spec="openni2:Dummy")
    assert (res.frames, res.stopped, res.counts) == (20, "frame limit", {"depth": 20, "ir": 0, "rgb": 20})
    assert "recorded 20 frames (depth 20, rgb 20)" in res.summary() and "stopped: frame limit" in res.summary()
    r = SessionReader(tmp_path / "s")
    assert len(r) == 20
    assert r.meta["device"] == "Table Tennis"
    assert [e[1:] for e in r.events] == [("pass", "rgb")]
    back = list(r)
    for a, b in zip(src.got, back):
        assert b.timestamp == pytest.approx(a.timestamp, abs=1e-6)
        assert b.pass_name == "rgb"
        np.testing.assert_array_equal(np.isnan(a.depth), np.isnan(b.depth))
        np.testing.assert_allclose(b.depth, a.depth, atol=1.01 / 5000, equal_nan=True)  # 0.2 mm PNG steps
        np.testing.assert_array_equal(b.rgb, a.rgb)
    assert r.intrinsics["depth"] == src.got[0].depth_intrinsics
    np.testing.assert_allclose(back[0].depth_to_rgb, src.got[0].depth_to_rgb)


def test_cli_records_the_dummy_device(tmp_path, capsys):
    pytest.importorskip("openni")
    try:
        from drivers.openni2_source import load_openni2

        load_openni2()
    except DeviceError as e:
        pytest.skip(f"no OpenNI2 runtime: {e}")
    out = tmp_path / "cli"
    assert main(["record", "openni2:Dummy", str(out), "--frames", "8", "--streams", "depth", "--quiet"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("recorded 8 frames (depth 8)") and "stopped: frame limit" in line
    r = SessionReader(out)
    assert len(r) == 8 and r.caps.streams == {"depth"}
    # the Kinect v1 rule: a pass the DummyDevice cannot stream is refused before anything is written
    assert main(["record", "openni2:Dummy", str(tmp_path / "x"), "--pass", "geometry", "--quiet"]) == 2
    assert "pass 'geometry' needs {depth, ir}" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())


def test_device_lost_keeps_the_frames_so_far(tmp_path, monkeypatch, capsys):
    src = FakeDevice(fail_after=7)
    _patch_source(monkeypatch, src)
    out = tmp_path / "lost"
    assert main(["record", "fake", str(out), "--quiet"]) == rec.EXIT_DEVICE_LOST
    text = capsys.readouterr().out
    assert "recorded 7 frames (depth 7, ir 7, rgb 7)" in text
    assert "stopped: device lost (fake:cam: no depth frame for 2 s after 7 frames (device unplugged?))" in text
    assert src.closed == 1
    r = SessionReader(out)
    assert len(r) == 7
    fr = r.frame(6)
    assert fr.ir[3, 3] == 6.0 and fr.rgb[0, 0, 0] == 6
    np.testing.assert_allclose(fr.depth[5, 5], 0.56, atol=1e-4)
    assert np.isnan(fr.depth[0, 0])
    assert r.meta["emitter_position_m"] == [0.05, 0.0, 0.0]


def test_device_lost_before_any_frame_is_an_error(tmp_path, monkeypatch, capsys):
    _patch_source(monkeypatch, FakeDevice(fail_after=0))
    assert main(["record", "fake", str(tmp_path / "none"), "--quiet"]) == 2
    assert "after 0 frames" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_ctrl_c_ends_cleanly_after_the_current_frame(tmp_path, monkeypatch, capsys):
    _patch_source(monkeypatch, FakeDevice(sigint_at=5))
    out = tmp_path / "intr"
    before = signal.getsignal(signal.SIGINT)     # Python's default, or SIG_IGN in a background job
    assert main(["record", "fake", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "recorded 6 frames" in text and "stopped: Ctrl-C" in text
    assert len(SessionReader(out)) == 6
    assert signal.getsignal(signal.SIGINT) is before  # handler restored


def test_limits_streams_and_pass(tmp_path):
    src = FakeDevice()
    res = rec.record_source(src, tmp_path / "t", seconds=0.5, streams=frozenset({"depth", "ir"}), pass_name="geometry")
    assert res.stopped == "time limit" and res.frames == 15  # frames at 0, 1/30, ..., 14/30 s
    assert res.seconds == pytest.approx(14 / 30)
    r = SessionReader(tmp_path / "t")
    assert r.caps.streams == {"depth", "ir"} and all(f.rgb is None for f in r)
    assert [e[1:] for e in r.events] == [("pass", "geometry")]
    # re-record a recording (a session) by path
    res2 = rec.record_source(rec.open_source(str(tmp_path / "t")), tmp_path / "t2", frames=4)
    assert (res2.frames, res2.stopped) == (4, "frame limit")
    res3 = rec.record_source(rec.open_source(str(tmp_path / "t")), tmp_path / "t3")
    assert (res3.frames, res3.stopped) == (15, "end of recording")


def test_bad_arguments(tmp_path, monkeypatch):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(AppFusionError, match="not an empty directory"):
        rec.record_source(FakeDevice(), tmp_path / "full")
    with pytest.raises(AppFusionError, match="unknown pass 'lunch'"):
        rec.record_source(FakeDevice(), tmp_path / "a", pass_name="lunch")
    with pytest.raises(AppFusionError, match="--frames must be at least 1"):
        rec.record_source(FakeDevice(), tmp_path / "a", frames=0)
    with pytest.raises(AppFusionError, match="--streams must list"):
        rec.parse_streams("depth,sonar")
    assert rec.parse_streams(" depth, IR ") == {"depth", "ir"}

    class DepthOnly(FakeDevice):
        @property
        def caps(self):
            return StreamCaps.all_together({"depth"})

    with pytest.raises(SourceError, match="has no rgb stream"):
        rec.record_source(DepthOnly(), tmp_path / "b", streams=frozenset({"depth", "rgb"}))
    from drivers import open_device

    with pytest.raises(SourceError, match="unknown device 'kinect2:0'"):
        open_device("kinect2:0")
    with pytest.raises(SourceError):
        rec.open_source(str(tmp_path / "no-such-recording"))
