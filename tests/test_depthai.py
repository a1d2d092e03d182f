"""depthai driver: message conversion, frame assembly and the dots/flood alternation, run for real through
host-only depthai pipelines (``dai.Pipeline(False)``, host nodes, RecordMessage/ReplayMessage .mcap); the
device tests are marked ``hardware`` and skipped when no OAK is attached."""

from __future__ import annotations

import datetime
import threading
import time
from unittest import mock

import numpy as np
import pytest

from appfusion.errors import DeviceError, SourceError
from drivers import depthai_source as das
from drivers.depthai_source import DepthAIConfig, DepthAISource, FrameAssembler, Packet, dot_score, nominal_geometry

dai = pytest.importorskip("depthai")

W, H = 64, 48
_RNG = np.random.default_rng(7)
SCENE = (60 + 50 * np.sin(np.linspace(0, 3, W))[None, :] * np.linspace(0.6, 1.0, H)[:, None]).astype(np.float32)
DOTS = (_RNG.random((H, W)) < 0.08) * 150.0


def ir_image(dots: bool, gain: float = 1.0) -> np.ndarray:
    """A smooth scene, lit by the flood LED, or by the dot projector (sparse bright speckles)."""
    return np.clip(SCENE * gain + (DOTS if dots else 0.0), 0, 255).astype(np.uint8)


def _img(arr, typ, seq, t):
    f = dai.ImgFrame()
    if typ in (dai.ImgFrame.Type.RAW16, dai.ImgFrame.Type.GRAY8):
        f.setFrame(arr)
        f.setType(typ)
        f.setWidth(arr.shape[1])
        f.setHeight(arr.shape[0])
    else:
        f.setCvFrame(arr, typ)
    f.setSequenceNum(seq)
    f.setTimestamp(datetime.timedelta(seconds=t))
    return f


def synthetic_graph(n: int, dots_phase: int | None = 0, drop: set[int] = frozenset(), rgb_delay_s: float = 0.003,
                    done: threading.Event | None = None):
    """``build_graph`` for DepthAISource: a host node sending depth (mm = 1000 + seq), left IR (dots on
    frames of parity ``dots_phase``, flood on the others; None: flood always) and colour (R = seq).

    Stopping a depthai pipeline drops the messages still queued, so the node sends 4 frames more than
    the test looks at and then waits for ``done`` (set by the test once it has its frames) before
    stopping the pipeline.
    """

    class Gen(dai.node.ThreadedHostNode):
        def __init__(self):
            super().__init__()
            self.outs = {k: self.createOutput() for k in ("depth", "left", "rgb")}

        def run(self):
            for i in range(n + 4):
                t = 1.0 + i / 30.0
                if i not in drop:
                    d = np.full((H, W), 1000 + i, np.uint16)
                    d[0, :4] = 0
                    lit_dots = dots_phase is not None and i % 2 == dots_phase
                    self.outs["depth"].send(_img(d, dai.ImgFrame.Type.RAW16, i, t))
                    self.outs["left"].send(_img(ir_image(lit_dots), dai.ImgFrame.Type.GRAY8, i, t))
                bgr = np.zeros((H, W, 3), np.uint8)
                bgr[..., 2] = i
                self.outs["rgb"].send(_img(bgr, dai.ImgFrame.Type.RGB888i, 5000 + i, t + rgb_delay_s))
                time.sleep(0.001)
            if done is not None:
                done.wait(10.0)
            else:
                time.sleep(0.3)
            self.stopPipeline()

    def build(pipeline):
        return pipeline.create(Gen).outs

    return build


GEO = nominal_geometry((W, H), (W, H), "rgb")
SMALL = {"mono_size": (W, H), "rgb_size": (W, H)}


# -- message conversion on real ImgFrame messages ---------------------------------------------------
def test_depth_ir_rgb_conversion_from_imgframes():
    d = np.array([[0, 1234], [65535, 1]], np.uint16)
    m = das.depth_from_imgframe(_img(d, dai.ImgFrame.Type.RAW16, 3, 2.5))
    assert m.dtype == np.float32 and np.isnan(m[0, 0])
    np.testing.assert_allclose(m[[0, 1, 1], [1, 0, 1]], [1.234, 65.535, 0.001], rtol=1e-6)
    g = np.arange(12, dtype=np.uint8).reshape(3, 4)
    np.testing.assert_array_equal(das.ir_from_imgframe(_img(g, dai.ImgFrame.Type.GRAY8, 0, 0)), g.astype(np.float32))
    bgr = np.zeros((8, 10, 3), np.uint8)
    bgr[..., 0], bgr[..., 1], bgr[..., 2] = 10, 20, 200
    for typ in (dai.ImgFrame.Type.RGB888i, dai.ImgFrame.Type.BGR888i):
        rgb = das.rgb_from_imgframe(_img(bgr, typ, 0, 0))
        assert rgb.dtype == np.uint8 and rgb.shape == (8, 10, 3)
        np.testing.assert_array_equal(rgb[0, 0], [200, 20, 10])
    nv12 = _img(bgr, dai.ImgFrame.Type.NV12, 0, 0)
    rgb = das.rgb_from_imgframe(nv12)
    assert np.all(np.abs(rgb[2, 2].astype(int) - [200, 20, 10]) < 12)  # 4:2:0 chroma, video-range rounding
    y = das.ir_from_imgframe(nv12)  # an NV12 mono frame: the luma plane
    assert y.shape == (8, 10) and np.ptp(y) < 2
    pkt = das.packet_from_imgframe("depth", _img(d, dai.ImgFrame.Type.RAW16, 42, 2.5))
    assert (pkt.stream, pkt.seq, pkt.t) == ("depth", 42, 2.5)
    with pytest.raises(SourceError, match="expected uint16 mm"):
        das.depth_from_imgframe(_img(g, dai.ImgFrame.Type.GRAY8, 0, 0))
    with pytest.raises(SourceError, match="not a colour image"):
        das.rgb_from_imgframe(_img(g, dai.ImgFrame.Type.GRAY8, 0, 0))
    with pytest.raises(SourceError, match="unknown tap stream"):
        das.packet_from_imgframe("thermal", nv12)


def test_dot_score_separates_dot_and_flood_frames():
    s_dots, s_flood = dot_score(ir_image(True)), dot_score(ir_image(False))
    assert s_dots > 3 * s_flood
    # independent of exposure: a brighter flood frame still scores as flood
    assert dot_score(ir_image(False, gain=1.8)) < s_dots / 3
    with pytest.raises(SourceError, match="needs an \\(H, W\\) image"):
        dot_score(np.zeros((4, 4, 3)))


# -- frame assembly (pure Python) ------------------------------------------------------------------
def _packets(i, dots, t=None, rgb=True):
    t = 1.0 + i / 30.0 if t is None else t
    out = [Packet("left", i, t, ir_image(dots).astype(np.float32)),
           Packet("depth", i, t, np.full((H, W), 1.0 + i / 1000, np.float32))]
    if rgb:
        out.append(Packet("rgb", 9000 + i, t + 0.002, np.full((H, W, 3), i, np.uint8)))
    return out


@pytest.mark.parametrize("phase", [0, 1])
def test_assembler_pairs_dots_depth_with_flood_ir(phase):
    asm = FrameAssembler(GEO, {"depth", "ir", "rgb"}, fps=30, alternate=True)
    frames = []
    for i in range(12):
        pk = _packets(i, dots=(i % 2 == phase))
        for p in pk[::-1] if i % 3 == 0 else pk:  # arrival order varies
            frames += asm.push(p)
    frames += asm.flush()
    assert asm.stats["pairs"] == 6 and len(frames) == 6
    for f in frames:
        seq_depth = int(round((float(np.nanmax(f.depth)) - 1.0) * 1000))
        seq_ir = int(f.rgb[0, 0, 0])  # colour matched to the IR (flood) frame's time
        assert seq_depth % 2 == phase and seq_ir % 2 != phase  # depth from dots, IR from flood
        assert abs(seq_depth - seq_ir) == 1
        assert f.emitter is True and f.streams == ("depth", "ir", "rgb")
        assert f.timestamp == pytest.approx(1.0 + seq_ir / 30.0)
        assert dot_score(f.ir) < 0.5 * dot_score(ir_image(True))
    assert np.all(np.diff([f.timestamp for f in frames]) > 0)


def test_assembler_lone_and_ambiguous_groups():
    asm = FrameAssembler(GEO, {"depth", "ir"}, fps=30, alternate=True)
    out = []
    for i in [0, 1, 2, 3, 4, 6, 7]:  # frame 5 lost: 4 (dots) is alone
        for p in _packets(i, dots=(i % 2 == 0), rgb=False):
            out += asm.push(p)
    out += asm.flush()
    assert asm.stats["pairs"] == 3 and asm.stats["lone"] == 1
    lone = [f for f in out if f.ir is None]
    assert len(lone) == 1 and float(np.nanmax(lone[0].depth)) == pytest.approx(1.004)  # classified as dots
    # a flat scene with no dots anywhere: pairs cannot be told apart, both frames kept, emitter unknown
    asm = FrameAssembler(GEO, {"depth", "ir"}, fps=30, alternate=True)
    out = []
    for i in range(4):
        for p in _packets(i, dots=False, rgb=False):
            out += asm.push(p)
    out += asm.flush()
    assert asm.stats["ambiguous"] == 2 and len(out) == 4 and all(f.emitter is None for f in out)


def test_assembler_plain_mode_groups_by_sequence_and_matches_rgb_by_time():
    asm = FrameAssembler(GEO, {"depth", "ir", "rgb"}, fps=30, alternate=False, emitter=True)
    out = []
    pk = [p for i in range(6) for p in _packets(i, dots=True)]
    # seq 1 completes before seq 0, depth before IR and the other way round; colour comes in time order
    order = [pk[j] for j in (3, 1, 4, 0, 2, 6, 7, 5, 9, 10, 8, 12, 11, 13, 14, 15, 16, 17)]
    for p in order:
        out += asm.push(p)
    out += asm.flush()
    assert len(out) == 6
    for i, f in enumerate(out):
        assert f.index == i and f.emitter is True
        assert int(f.rgb[0, 0, 0]) == i and float(np.nanmax(f.depth)) == pytest.approx(1 + i / 1000)
    # colour that never comes: frames go out without it after max_pending groups
    asm = FrameAssembler(GEO, {"depth", "rgb"}, fps=30, max_pending=3)
    out = []
    for i in range(6):
        for p in _packets(i, dots=True, rgb=False):
            out += asm.push(p)
    assert len(out) == 3 and out[0].rgb is None and asm.stats["no_rgb"] == 3  # 6 groups, 3 held
    with pytest.raises(SourceError, match="image is 64x48 but its intrinsics say 32x24"):
        FrameAssembler(nominal_geometry((32, 24), (32, 24)), {"depth"}).push(_packets(0, True)[1])


# -- calibration --------------------------------------------------------------------------------------
def _calibration():
    c = dai.CalibrationHandler()
    A, B, C = dai.CameraBoardSocket.CAM_A, dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C
    c.setCameraIntrinsics(A, [[800.0, 0, 639.5], [0, 800.0, 479.5], [0, 0, 1]], 1280, 960)
    c.setCameraIntrinsics(B, [[400.0, 0, 319.5], [0, 400.0, 199.5], [0, 0, 1]], 640, 400)
    c.setCameraIntrinsics(C, [[400.0, 0, 319.5], [0, 400.0, 199.5], [0, 0, 1]], 640, 400)
    c.setDistortionCoefficients(A, [0.1, -0.05, 0.001, 0.002, 0.0] + [0.0] * 9)
    c.setCameraExtrinsics(B, C, np.eye(3).tolist(), [-7.5, 0, 0], [-7.5, 0, 0])  # left -> right, cm
    c.setCameraExtrinsics(C, A, np.eye(3).tolist(), [3.75, 0, 0], [3.75, 0, 0])  # right -> colour, cm
    return c


def test_geometry_from_calibration_units_and_directions():
    g = das.geometry_from_calibration(_calibration(), (640, 400), (640, 480), "rgb")
    rgb = g.intrinsics["rgb"]
    assert (rgb.width, rgb.height) == (640, 480) and rgb.fx == pytest.approx(400.0)
    assert rgb.dist[:4] == pytest.approx((0.1, -0.05, 0.001, 0.002))
    assert g.intrinsics["depth"] == rgb  # depth aligned to the colour camera
    assert g.intrinsics["ir"].fx == pytest.approx(400.0) and g.intrinsics["ir"].dist == ()
    # the colour camera's origin is 3.75 cm right of the left camera: +0.0375 m seen from the left camera
    np.testing.assert_allclose(g.depth_to_ir[:3, 3], [0.0375, 0, 0], atol=1e-9)
    np.testing.assert_allclose(g.depth_to_rgb, np.eye(4))
    g2 = das.geometry_from_calibration(_calibration(), (640, 400), (640, 480), "ir")
    assert g2.intrinsics["depth"] == g2.intrinsics["ir"]
    np.testing.assert_allclose(g2.depth_to_rgb[:3, 3], [-0.0375, 0, 0], atol=1e-9)
    with pytest.raises(SourceError, match=r"no left mono \(IR\) camera intrinsics"):
        das.geometry_from_calibration(dai.CalibrationHandler(), (640, 400), (640, 480))


# -- host-only pipelines through DepthAISource ------------------------------------------------------
def test_host_pipeline_alternating_dots_and_flood():
    n = 24
    done = threading.Event()
    src = DepthAISource(build_graph=synthetic_graph(n, dots_phase=0, done=done), calibration=GEO,
                        illumination="alternate", **SMALL)
    frames = []
    with src:
        for f in src:
            frames.append(f)
            if len(frames) == n // 2:
                done.set()
                break
        meta, caps = src.meta, src.caps
    assert len(frames) == n // 2 and src._assembler.stats["pairs"] >= n // 2
    assert [int(round(float(np.nanmax(f.depth)) * 1000)) - 1000 for f in frames] == list(range(0, n, 2))
    for f in frames:
        seq_depth = int(round(float(np.nanmax(f.depth)) * 1000)) - 1000
        assert seq_depth % 2 == 0  # dot frames give the depth ...
        assert int(f.rgb[0, 0, 0]) == seq_depth + 1  # ... the next (flood) frame the IR and the colour
        assert np.isnan(f.depth[0, :4]).all() and f.ir.dtype == np.float32
        assert dot_score(f.ir) == pytest.approx(dot_score(ir_image(False)), rel=1e-3)
        assert f.emitter is True and f.depth_intrinsics == GEO.intrinsics["depth"]
    assert np.all(np.diff([f.timestamp for f in frames]) > 0)
    assert meta["ir_illuminator"] == "flood" and meta["illumination"] == "alternate"
    assert caps.rates["ir"] == 15.0 and caps.ir_and_rgb_together


def test_record_mcap_then_replay_through_the_same_host_side(tmp_path):
    n = 16
    calib = _calibration()
    rec = tmp_path / "oak"
    cfg = {"mono_size": (W, H), "rgb_size": (W, H), "illumination": "off"}
    live = DepthAISource(build_graph=synthetic_graph(n, dots_phase=None), calibration=calib, record_dir=rec, **cfg)
    with live:
        first = list(live)
    # the source sends n + 4 frames; stopping the pipeline may drop the last few queued messages
    assert len(first) >= n and all(f.emitter is None for f in first)
    first = first[:n]
    for name in ("depth.mcap", "left.mcap", "rgb.mcap", "calibration.json", "config.json"):
        assert (rec / name).stat().st_size > 0
    replay = das.DepthAISource(replay_dir=rec)  # calibration and configuration come from the folder
    with replay:
        again = list(replay)
        intr = replay.intrinsics
    # a replay ends when its first stream ends; the last frame of another stream can be cut
    assert len(again) >= n
    for a, b in zip(first, again[:n]):
        assert b.timestamp == pytest.approx(a.timestamp, abs=1e-6)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.ir, b.ir)
        np.testing.assert_array_equal(a.rgb, b.rgb)
    assert intr["rgb"].fx == pytest.approx(800.0 * W / 1280)  # from calibration.json, scaled to the output
    np.testing.assert_allclose(again[0].depth_to_ir[:3, 3], [0.0375, 0, 0], atol=1e-9)
    with pytest.raises(SourceError, match="no such depthai recording folder"):
        DepthAISource(replay_dir=tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match="no depth.mcap"):
        DepthAISource(replay_dir=tmp_path / "empty").open()


def test_scan_device_depthai_replay_records_the_combined_pass_then_one_error(tmp_path, capsys):
    """``appfusion scan --device depthai-replay:DIR``: a host replay streams depth, IR and RGB together, so
    the live plan is ir-calibration, environment and one combined scan pass, advanced by frame counts;
    the frames show no markers, so the scan ends with one error that names them and keeps the recording."""
    from appfusion.cli import main
    from appfusion.pipeline import plan_passes
    from replay.session import SessionReader

    rec = tmp_path / "oak"
    with DepthAISource(build_graph=synthetic_graph(30, dots_phase=None), calibration=_calibration(),
                       record_dir=rec, mono_size=(W, H), rgb_size=(W, H), illumination="off") as live:
        assert len(list(live)) >= 30  # a replay may lose a few of the last messages: the plan needs 15
    out = tmp_path / "scan"
    rc = main(["scan", "--device", f"depthai-replay:{rec}", "--out", str(out), "--pass-frames",
               "ir-calibration=6,environment=4,scan=5", "--dark-frames", "2", "--points", "500", "--no-progress"])
    cap = capsys.readouterr()
    assert rc == 2
    assert "passes ir-calibration, environment, scan (streams together: depth+ir+rgb)" in cap.out
    err = [line for line in cap.err.splitlines() if line.strip()]
    assert len(err) == 1 and "no frame shows the four white circles" in err[0]
    assert f"kept in {out / 'live-session'}" in err[0] and "no IR stream" not in err[0]
    r = SessionReader(out / "live-session")
    assert plan_passes(r) == {"ir-calibration": (0, 6), "environment": (6, 10), "scan": (10, 15)}
    assert [r.frame(i).emitter for i in range(6)] == [False, False, True, True, True, True]
    f = r.frame(12)
    assert f.streams == ("depth", "ir", "rgb") and f.depth.shape == (H, W)
    assert r.meta["extra"]["markers"]["radius_m"] == pytest.approx(0.025)  # the printed-sheet defaults
    np.testing.assert_allclose(r.depth_to_ir[:3, 3], [0.0375, 0, 0], atol=1e-9)  # from the replay's calibration


def test_bad_message_is_reported_with_frames_so_far():
    class Gen(dai.node.ThreadedHostNode):
        def __init__(self):
            super().__init__()
            self.outs = {"depth": self.createOutput()}

        def run(self):
            for i in range(3):
                self.outs["depth"].send(_img(np.full((H, W), 900, np.uint16), dai.ImgFrame.Type.RAW16, i, 1 + i / 30))
            self.outs["depth"].send(_img(np.zeros((H, W), np.uint8), dai.ImgFrame.Type.GRAY8, 3, 1.2))
            while self.isRunning():  # the source stops the pipeline when it closes
                time.sleep(0.01)

    src = DepthAISource(build_graph=lambda p: p.create(Gen).outs, calibration=GEO, streams={"depth"}, **SMALL)
    got = []
    with pytest.raises(SourceError, match="bad message after 3 frames.*expected uint16 mm"):
        with src:
            for f in src:
                got.append(f)
    assert len(got) == 3 and all(f.streams == ("depth",) for f in got)


def test_live_source_that_goes_silent_is_a_lost_device():
    """A live graph that stops sending (unplugged camera): frames so far, then DeviceError."""

    class Gen(dai.node.ThreadedHostNode):
        def __init__(self):
            super().__init__()
            self.outs = {"depth": self.createOutput()}

        def run(self):
            for i in range(5):
                self.outs["depth"].send(_img(np.full((H, W), 800, np.uint16), dai.ImgFrame.Type.RAW16, i, 1 + i / 30))
            while self.isRunning():
                time.sleep(0.02)

    src = DepthAISource(build_graph=lambda p: p.create(Gen).outs, calibration=GEO, streams={"depth"}, live=True,
                        timeout_s=0.3, **SMALL)
    got = []
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match=r"no frame for 0.3 s after 5 frames \(device unplugged or stalled\)"):
        with src:
            for f in src:
                got.append(f)
    assert len(got) == 5 and time.monotonic() - t0 < 5.0
    assert not src.is_open


# -- device-side pieces without a device ------------------------------------------------------------
class _FakeIn:
    def __init__(self, items):
        self.items = list(items)

    def get(self):
        if not self.items:
            raise EOFError
        return self.items.pop(0)

    def tryGet(self):
        return self.items.pop(0) if self.items else None


def test_alternation_script_switches_every_frame_and_obeys_ctrl():
    calls = []

    class Device:
        @staticmethod
        def setIrLaserDotProjectorIntensity(v):
            calls.append(("dots", v))

        @staticmethod
        def setIrFloodLightIntensity(v):
            calls.append(("flood", v))

    class Buf:
        def __init__(self, text):
            self.text = text

        def getData(self):
            return list(self.text.encode())

    ctrl = [None, None, None, Buf("0 0.5 0.5"), None]
    node = mock.Mock()
    node.inputs = {"frame": _FakeIn(range(5)), "ctrl": _FakeIn(ctrl)}
    with pytest.raises(EOFError):  # the script loops until its input closes
        exec(das.alternation_script(0.8, 0.6), {"Device": Device, "node": node})
    lit = []
    for k in range(0, len(calls), 2):
        (a, va), (b, vb) = calls[k], calls[k + 1]
        on = {a: va, b: vb}
        lit.append("dots" if on["dots"] > 0 else "flood" if on["flood"] > 0 else "off")
    # initial dots, then one switch per frame; the 4th frame's ctrl "0 ..." switches both off
    assert lit == ["dots", "flood", "dots", "flood", "off", "off"]
    assert ("dots", 0.8) in calls and ("flood", 0.6) in calls


def test_device_graph_wiring():
    created = []

    def create(kind):
        m = mock.MagicMock(name=kind._extract_mock_name() if hasattr(kind, "_extract_mock_name") else str(kind))
        m.build.return_value = m
        created.append((kind, m))
        return m

    fdai = mock.MagicMock()
    pipe = mock.MagicMock()
    pipe.create.side_effect = create
    cfg = DepthAIConfig(streams={"depth", "ir", "rgb"}, illumination="alternate", rgb_size=(640, 480))
    outs = das.build_device_graph(pipe, fdai, cfg, "alternate")
    kinds = [k for k, _ in created]
    assert kinds.count(fdai.node.Camera) == 3 and kinds.count(fdai.node.StereoDepth) == 1
    assert kinds.count(fdai.node.Script) == 1
    cams = [m for k, m in created if k is fdai.node.Camera]
    (stereo,) = [m for k, m in created if k is fdai.node.StereoDepth]
    (script,) = [m for k, m in created if k is fdai.node.Script]
    left_out = cams[0].requestOutput.return_value
    right_out = cams[1].requestOutput.return_value
    assert [c.args[0] for c in (cams[0].build.call_args, cams[1].build.call_args, cams[2].build.call_args)] == \
        [fdai.CameraBoardSocket.CAM_B, fdai.CameraBoardSocket.CAM_C, fdai.CameraBoardSocket.CAM_A]
    left_out.link.assert_any_call(stereo.left)
    right_out.link.assert_any_call(stereo.right)
    left_out.link.assert_any_call(script.inputs.__getitem__.return_value)
    stereo.setDepthAlign.assert_called_once_with(fdai.CameraBoardSocket.CAM_A)
    stereo.setOutputSize.assert_called_once_with(640, 480)
    assert "Device.setIrFloodLightIntensity(flood)" in script.setScript.call_args.args[0]
    assert outs["depth"] is stereo.depth and outs["left"] is left_out
    assert outs["rgb"] is cams[2].requestOutput.return_value
    # no IR wanted, no projector: no script, no left tap
    created.clear()
    outs = das.build_device_graph(pipe, fdai, DepthAIConfig(streams={"depth"}, align="ir"), "off")
    assert set(outs) == {"depth"} and all(k is not fdai.node.Script for k, _ in created)


def test_config_validation_and_illumination_resolution():
    assert DepthAIConfig().resolved_illumination(True) == "alternate"
    assert DepthAIConfig(streams={"depth", "rgb"}).resolved_illumination(True) == "dots"
    assert DepthAIConfig(streams={"ir"}).resolved_illumination(True) == "flood"
    assert DepthAIConfig().resolved_illumination(False) == "off"
    with pytest.raises(SourceError, match="needs an OAK-D Pro"):
        DepthAIConfig(illumination="alternate").resolved_illumination(False)
    with pytest.raises(SourceError, match="illumination must be one of"):
        DepthAIConfig(illumination="strobe")
    with pytest.raises(SourceError, match="dot_intensity must be in"):
        DepthAIConfig(dot_intensity=2.0)
    with pytest.raises(SourceError, match="unknown option"):
        DepthAISource(exposure=3)
    src = DepthAISource(build_graph=synthetic_graph(2), calibration=GEO, **SMALL)
    with pytest.raises(SourceError, match="no IR projector control"):
        src.set_control("emitter", False)


def _oak_attached() -> bool:
    try:
        return bool(dai.Device.getAllAvailableDevices())
    except Exception:
        return False


def test_no_device_is_a_clear_device_error():
    if _oak_attached():
        pytest.skip("an OAK is attached")
    assert das.list_devices() == []
    with pytest.raises(DeviceError, match="no OAK device found.*udev"):
        DepthAISource().open()


@pytest.mark.hardware
@pytest.mark.skipif(not _oak_attached(), reason="no OAK device attached")
def test_real_oak_streams_calibrated_frames():  # pragma: no cover - needs hardware
    with DepthAISource(fps=15) as src:
        frames = []
        for f in src:
            frames.append(f)
            if len(frames) == 10:
                break
        intr, meta = src.intrinsics, src.meta
    assert meta["geometry_from"] == "calibration"
    for f in frames:
        assert f.depth is not None and f.depth.dtype == np.float32 and f.depth.shape == intr["depth"].shape
        d = f.depth[np.isfinite(f.depth)]
        assert d.size and 0.1 < np.median(d) < 20.0
        if f.ir is not None:
            assert f.ir.shape == intr["ir"].shape
    assert np.all(np.diff([f.timestamp for f in frames]) > 0)
