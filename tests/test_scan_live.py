"""``appfusion scan --device``: live sources recorded pass by pass by ScanRunner, then processed.

A synthetic Kinect v1 session played back as a *live* source (no length, no pass tags, no emitter
flags, streams chosen by ``select_pass`` like a Kinect) goes through the same code as a device to a
full result, with the passes switched by frame counts; Ctrl-C and Enter are exercised for real; the
OpenNI2 DummyDevice (no IR, no markers) ends with one error naming what is missing.
"""

from __future__ import annotations

import os
import queue
import signal
import threading
import time

import numpy as np
import pytest

from appfusion.commands.scan import (DEFAULT_PASS_FRAMES, LiveDevice, live_steps, parse_pass_frames,
                                     scan_live)
from appfusion.errors import AppFusionError
from appfusion.pipeline import ScanConfig, ScanRunner, plan_passes
from appfusion.result import ScanResult
from appfusion.source import Source
from drivers import streams_for_pass
from replay.session import SessionReader

SMALL = dict(n_points=3000, texture_size=64, envmap_n=32, hbsab_n=16)


class SyntheticKinect(Source):
    """A synthetic session played as a live Kinect v1.

    Frames come without pass names, emitter flags or poses (a Kinect v1 has no emitter control and
    knows nothing of passes); the passes in ``skip`` are left out (the user did not record them); after
    the session, ``tail`` more frames follow (a device keeps streaming). Every frame must carry only
    the streams the last ``select_pass`` asked for, as on a Kinect (``wrong_streams`` counts the
    others). ``on_frame(k)`` is called before frame ``k`` is delivered.
    """

    is_recording = False

    def __init__(self, session, skip=(), tail: int = 0, on_frame=None):
        super().__init__()
        self.reader = SessionReader(session)
        self.name = "synthetic-kinect-v1"
        self.skip, self.tail, self.on_frame = set(skip), tail, on_frame
        self.selected: list[str] = []
        self.active: frozenset[str] | None = None
        self.wrong_streams = 0
        self.delivered = 0

    @property
    def caps(self):
        return self.reader.caps

    @property
    def intrinsics(self):
        return self.reader.intrinsics

    @property
    def meta(self):
        m = self.reader.meta
        return {"device": "synthetic Kinect v1 (live)", "emitter_position_m": m["emitter_position_m"],
                "ir_bits": 10, "extra": {"markers": m["extra"]["markers"]}}

    def select_pass(self, name):
        self.active = streams_for_pass(name, self.caps)
        self.selected.append(name)
        return self.active

    def _open(self):
        pass

    def _close(self):
        pass

    def _frames(self):
        frames = (f for f in self.reader if f.pass_name not in self.skip)
        last = None
        for f in frames:
            yield self._deliver(f)
            last = f
        for k in range(self.tail):
            yield self._deliver(last.replace(timestamp=last.timestamp + (k + 1) / 30))

    def _deliver(self, f):
        if self.on_frame is not None:
            self.on_frame(self.delivered)
        if self.active is None or not set(f.streams) <= self.active:
            self.wrong_streams += 1
        self.delivered += 1
        return f.replace(index=self.delivered - 1, pass_name=None, emitter=None, pose=None)


def _truth_passes(session):
    r = SessionReader(session)
    ranges = plan_passes(r)
    a, b = ranges["ir-calibration"]
    dark = sum(1 for i in range(a, b) if r.frame(i).emitter is False)
    return r, ranges, dark


@pytest.fixture(scope="module")
def live_kinect_scan(kinect_sphere, tmp_path_factory):
    """``scan --device``-style run over the synthetic Kinect: passes by frame counts, environment map reused."""
    r0, ranges, dark = _truth_passes(kinect_sphere)
    counts = {p: b - a for p, (a, b) in ranges.items() if p != "environment"}
    src = SyntheticKinect(kinect_sphere, skip={"environment"}, tail=6)
    out = tmp_path_factory.mktemp("live-out") / "out"
    log: list[str] = []
    envmap = kinect_sphere / "truth" / "envmaps" / "office.exr"  # reused: no environment pass recorded
    summary = scan_live(src, out, config=ScanConfig(**SMALL), pass_frames={**DEFAULT_PASS_FRAMES, **counts},
                        dark_frames=dark, envmap=envmap, progress=False, log=log.append)
    return {"src": src, "out": out, "log": log, "summary": summary, "counts": counts, "dark": dark, "truth": r0}


@pytest.mark.slow
def test_live_scan_of_a_synthetic_kinect_switches_passes_by_frame_counts(live_kinect_scan):
    run = live_kinect_scan
    src, out, counts, dark, summary = run["src"], run["out"], run["counts"], run["dark"], run["summary"]
    assert 0 < dark < counts["ir-calibration"]
    # the plan came from the capability model: IR and colour not at once -> geometry and rgb apart
    assert [p for k, p in enumerate(src.selected) if k == 0 or p != src.selected[k - 1]] == \
        ["ir-calibration", "geometry", "rgb"]
    assert src.wrong_streams == 0  # the streams were switched before each pass's first frame
    assert not src.is_open  # the device is released once recorded
    # the recording: exactly the planned frames (the device's tail is not recorded), the same pass
    # boundaries and emitter-off frames as the synthetic session, the Kinect's extrinsics and markers
    rec = SessionReader(out / "live-session")
    n = sum(counts.values())
    assert len(rec) == n == src.delivered  # the plan ended before the tail was even read
    want, off = {}, 0
    for p in ("ir-calibration", "geometry", "rgb"):
        want[p] = (off, off + counts[p])
        off += counts[p]
    assert plan_passes(rec) == want
    emit = [rec.frame(i).emitter for i in range(counts["ir-calibration"])]
    assert emit == [False] * dark + [True] * (counts["ir-calibration"] - dark)
    assert [v for _, k, v in rec.events if k == "emitter"] == ["off", "on"]
    np.testing.assert_allclose(rec.depth_to_rgb, run["truth"].depth_to_rgb)
    assert rec.meta["extra"]["markers"]["side_m"] == pytest.approx(0.3)
    assert rec.meta["device"] == "synthetic Kinect v1 (live)"
    # a full result: geometry of the 7 cm sphere, roughness from the IR pass, colour from the RGB pass
    res = ScanResult.load(out / "result.npz")
    radial = np.abs(np.linalg.norm(res.positions - np.array([0, 0, 0.07]), axis=1) - 0.07)
    assert len(res.positions) == SMALL["n_points"] and np.median(radial) < 0.002
    assert res.info["alpha_source"].startswith("ir pass") and res.info["rho_d_source"].startswith("rgb pass")
    # 30 degrees of orbit a frame: with three circles, and the key circle with the one across the
    # diagonal, numbered by the key circle, all 12 geometry frames track and the IR alpha reads 0.1199
    # (0.123 from 11 frames). Before session 30, 2 frames tracked and it read 0.177; from one, 0.1255
    assert res.alpha[0] == pytest.approx(0.12, rel=0.1)
    assert np.all(res.rho_s.max(axis=1) > 0) and np.all(np.isfinite(res.rho_d))
    for f in ("object.glb", "report.html", "envmap.npz", "summary.txt", "state/ir_profile.json"):
        assert (out / f).stat().st_size > 0
    assert f"recorded ir-calibration {counts['ir-calibration']} frames, geometry 12 frames, rgb 12 frames" in summary
    assert "not recorded" not in summary and "could not produce" not in summary
    assert any("ir-calibration (" in line and "cover the IR emitter" in line for line in run["log"])
    assert any(line.startswith("[4/4] rgb (12 frames)") for line in run["log"])


@pytest.mark.slow
def test_ctrl_c_ends_the_recording_and_what_was_recorded_is_processed(kinect_sphere, live_kinect_scan, tmp_path):
    stop_at = 10  # Ctrl-C before the 11th geometry frame: that frame is the last one recorded

    def ctrl_c(k):
        if k == stop_at:
            os.kill(os.getpid(), signal.SIGINT)  # a real SIGINT, handled between two frames
            time.sleep(0.05)

    # the IR profile of the first scan is reused: only geometry and rgb are planned
    src = SyntheticKinect(kinect_sphere, skip={"environment", "ir-calibration"}, on_frame=ctrl_c)
    out = tmp_path / "out"
    log: list[str] = []
    summary = scan_live(src, out, config=ScanConfig(**{**SMALL, "n_points": 1500}),
                        pass_frames={"geometry": 12, "rgb": 12}, progress=False, log=log.append,
                        envmap=kinect_sphere / "truth" / "envmaps" / "office.exr",
                        ir_profile=live_kinect_scan["out"] / "state" / "ir_profile.json")
    assert any(line.startswith("Ctrl-C: recording stopped") for line in log)
    rec = SessionReader(out / "live-session")
    assert plan_passes(rec) == {"geometry": (0, 11)}
    res = ScanResult.load(out / "result.npz")
    assert len(res.positions) == 1500 and res.info["alpha_source"].startswith("ir pass")
    assert "stopped by Ctrl-C" in summary
    assert "not recorded: rgb: rho_d and rho_s" in summary
    assert "could not produce: rho_d and rho_s" in summary


class _Lines:
    """stdin for the Enter mode: ``readline`` blocks until the test presses Enter."""

    def __init__(self):
        self.q: queue.Queue[str] = queue.Queue()

    def readline(self):
        return self.q.get(timeout=30)

    def enter(self):
        self.q.put("\n")


def test_enter_advances_the_passes_of_a_depth_and_colour_device(tmp_path):
    """A depth + RGB device without IR (the DummyDevice's capability model): environment then scan on
    Enter, the next Enter ends the recording; processing then says what is missing, in one error."""
    from appfusion.frame import Frame, Intrinsics
    from appfusion.source import StreamCaps

    K = Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)
    lines = _Lines()
    gate = threading.Event()

    class DepthColour(Source):
        is_recording = False
        name = "depth-colour"
        caps = StreamCaps.all_together({"depth", "rgb"})
        intrinsics = {"depth": K, "rgb": K}

        def _open(self):
            pass

        def _close(self):
            pass

        def _frames(self):
            for i in range(400):
                if i in (8, 20):
                    gate.clear()
                    lines.enter()
                    gate.wait(5.0)  # let the Enter thread act, as a person is slower than one frame
                yield Frame(i, 1.0 + i / 30, depth=np.full((48, 64), 1.0, np.float32),
                            rgb=np.full((48, 64, 3), 90, np.uint8), depth_intrinsics=K, rgb_intrinsics=K)

    say: list[str] = []

    def log(msg):
        say.append(msg)
        if msg.startswith("[") or msg.startswith("Enter"):
            gate.set()

    with pytest.raises(AppFusionError) as e:
        scan_live(DepthColour(), tmp_path / "out", config=ScanConfig(**SMALL), interactive=True, lines=lines,
                  progress=False, log=log)
    msg = str(e.value)
    assert "no frame shows the four white circles" in msg and "no IR stream" in msg
    assert f"kept in {tmp_path / 'out' / 'live-session'}" in msg
    rec = SessionReader(tmp_path / "out" / "live-session")
    got = plan_passes(rec)
    # the pass is read before each frame is fetched (so that a Kinect switches streams first): Enter,
    # pressed while frame 8 is fetched, starts the scan pass at frame 9; the next Enter, pressed while
    # frame 20 is fetched, ends the recording after that frame
    assert got == {"environment": (0, 9), "scan": (9, 21)}
    assert say[1].startswith("[1/2] environment") and any(s.startswith("[2/2] scan") for s in say)
    assert any("Enter: recording finished" in s for s in say)


def test_cli_scan_device_openni2_dummy(tmp_path, capsys):
    """The DummyDevice (320x240 depth + RGB, no IR, no markers) records both passes, then ONE error."""
    from appfusion.cli import main

    try:
        from drivers.openni2_source import load_openni2

        load_openni2()
    except AppFusionError as e:
        if os.environ.get("CI"):
            raise
        pytest.skip(f"OpenNI2 runtime not installed: {e}")
    out = tmp_path / "dummy"
    rc = main(["scan", "--device", "openni2:Dummy", "--out", str(out), "--pass-frames",
               "environment=10,scan=15", "--points", "500", "--no-progress"])
    cap = capsys.readouterr()
    assert rc == 2
    err = [line for line in cap.err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("appfusion: error: live scan could not be processed")
    assert "no frame shows the four white circles" in err[0] and "no IR stream" in err[0]
    assert f"kept in {out / 'live-session'}" in err[0]
    assert "passes environment, scan" in cap.out  # from the capability model: no IR -> depth + RGB scan
    rec = SessionReader(out / "live-session")
    assert plan_passes(rec) == {"environment": (0, 10), "scan": (10, 25)}
    assert rec.intrinsics["depth"].width == 320 and set(rec.caps.streams) == {"depth", "rgb"}
    # a second scan into the same folder refuses to overwrite the recording
    assert main(["scan", "--device", "openni2:Dummy", "--out", str(out)]) == 2
    assert "already holds a recording" in capsys.readouterr().err


def test_options_and_plans():
    assert parse_pass_frames("geometry=600, rgb=700")["rgb"] == 700
    assert parse_pass_frames(None) == DEFAULT_PASS_FRAMES
    for bad, what in (("geometry", "expected PASS=FRAMES"), ("lunch=3", "unknown pass"),
                      ("rgb=0", "positive whole number"), ("rgb=x", "positive whole number")):
        with pytest.raises(AppFusionError, match=what):
            parse_pass_frames(bad)
    assert live_steps(["ir-calibration", "scan"], {"ir-calibration": 50, "scan": 9}, 20) == [
        ("ir-calibration", 20, False), ("ir-calibration", 30, True), ("scan", 9, None)]
    assert live_steps(["ir-calibration", "geometry"], None, 20)[1] == ("ir-calibration", None, True)
    with pytest.raises(AppFusionError, match="leaves no white-sheet frames"):
        live_steps(["ir-calibration"], {"ir-calibration": 20}, 20)
    runner = ScanRunner(LiveDevice(SyntheticKinectStub(), {}), "/nonexistent")
    for steps, what in (([], "no steps"), ([("lunch", 3, None)], "unknown pass"),
                        ([("rgb", None, None), ("scan", 3, None)], "needs a frame count"),
                        ([("rgb", 0, None)], "at least 1 frame")):
        with pytest.raises(AppFusionError, match=what):
            runner.set_live_plan(steps)


def test_kinect_without_marker_side_is_refused_before_recording(tmp_path):
    """A Kinect v1's rgb pass takes its poses from the markers: without their layout the scan would fail
    only after minutes of recording, so it is refused at once (and the device is closed again)."""
    from appfusion.source import StreamCaps

    class Kinect(SyntheticKinectStub):
        @property
        def caps(self):
            return StreamCaps(frozenset({"depth", "ir", "rgb"}),
                              (frozenset({"depth", "ir"}), frozenset({"depth", "rgb"})))

    src = Kinect()
    with pytest.raises(AppFusionError, match=r"give --marker-side .*key circle"):
        scan_live(src, tmp_path / "out", progress=False, log=lambda m: None)
    assert not src.is_open and not (tmp_path / "out" / "live-session").exists()
    with pytest.raises(AppFusionError, match="key_radius_m 0.02 must exceed radius_m"):
        scan_live(Kinect(), tmp_path / "out", markers={"key_radius_m": 0.02, "side_m": 0.3}, progress=False)


def test_cli_argument_errors(capsys):
    from appfusion.cli import main

    assert main(["scan", "--device", "openni2:Dummy"]) == 2
    assert "needs --out" in capsys.readouterr().err
    assert main(["scan", "some/session", "--device", "openni2:Dummy", "--out", "x"]) == 2
    assert "exactly one of them" in capsys.readouterr().err
    assert main(["scan", "--device", "kinect9", "--out", "x"]) == 2
    assert "unknown device 'kinect9'" in capsys.readouterr().err


@pytest.mark.parametrize("args, msg", [
    (["--points", "0"], "n_points (points sampled on the surface) must be a positive integer, got 0"),
    (["--clusters", "0"], "k_clusters must be None (automatic) or a positive integer"),
    (["--stride", "0"], "frame_stride must be a positive integer"),
    (["--ball-radius", "-0.03"], "ball_radius_m must be None (fitted) or a positive radius"),
    (["--ball-radius", "nan"], "ball_radius_m must be None (fitted) or a positive radius"),
    (["--texture-size", "0"], "texture_size (side of the exported texture maps, texels) must be an integer in [16, 16384]"),
    (["--lobes", "ward,phong"], "ir_lobes must name one or more lobes among"),
    (["--lobes", ","], "ir_lobes must name one or more lobes among"),
    (["--marker-side", "0.3"], "--marker-side: for live scans (--device) only"),
    (["--pass-frames", "geometry=10", "--dark-frames", "3"], "--pass-frames, --dark-frames: for live scans"),
    (["--device", "openni2:Dummy", "--marker-side", "-1"], "--marker-side must be a positive length"),
    (["--device", "openni2:Dummy", "--key-radius", "nan"], "--key-radius must be a non-negative length"),
    (["--device", "openni2:Dummy", "--dark-frames", "-2"], "--dark-frames must be 0 or more frames"),
])
def test_cli_scan_arguments_out_of_range_are_refused_before_any_frame(args, msg, redwood_dir, tmp_path, capsys):
    """Each out-of-range option is one line naming it, before the recording (or the device) is opened
    and before anything is written (``--points 0`` silently meant the default before)."""
    from appfusion.cli import main

    out = tmp_path / "out"
    target = [] if "--device" in args else [str(redwood_dir)]
    assert main(["scan", *target, "--out", str(out), "--no-progress", *args]) == 2
    err = capsys.readouterr().err
    assert msg in err and err.count("\n") == 1, err
    assert not out.exists()


def test_cli_scan_lobes_and_texture_size_reach_the_scan_config(tmp_path, monkeypatch, capsys):
    """``--lobes ward`` (the paper's model only) and ``--texture-size`` set ScanConfig.ir_lobes and
    texture_size; without them the defaults stand (Ward and GGX, 1024). (run_scan is a stand-in: no
    recording is opened.)"""
    import appfusion.pipeline as P
    from appfusion.cli import main

    seen = []
    monkeypatch.setattr(P, "run_scan", lambda session, out, config=None, **kw: seen.append(config) or "ok")
    session = str(tmp_path / "session")
    assert main(["scan", session, "--out", str(tmp_path / "a"), "--lobes", " ward ", "--texture-size", "256"]) == 0
    assert main(["scan", session, "--out", str(tmp_path / "b")]) == 0
    assert seen[0].ir_lobes == ("ward",) and seen[0].texture_size == 256
    assert tuple(seen[1].ir_lobes) == ("ward", "ggx") and seen[1].texture_size == 1024


class SyntheticKinectStub(Source):
    is_recording = False
    name = "stub"

    @property
    def caps(self):
        from appfusion.source import StreamCaps

        return StreamCaps.all_together({"depth", "rgb"})

    def _open(self):
        pass

    def _close(self):
        pass

    def _frames(self):
        return iter(())
