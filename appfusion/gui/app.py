"""The live scanning window (PySide6 + pyqtgraph): a thin observer of the scan engine.

Layout: a guidance banner and the scan's stages across the top; the fused points in 3-D on the left
(colour by cluster / rho_d / rho_s / alpha / appearance, paint brush for §5.2's manual refinement);
on the right the RGB, IR and depth streams, the environment map filling in with the selected
cluster's HBSAB and fitted lobe, live figures, and a status panel (stage, frames, tracking, markers,
coverage, engine and UI rates, messages).

Threads: the engine (``runner.run()``) runs in :class:`~appfusion.gui.worker.ScanWorker`'s thread
and publishes snapshots; a ``QTimer`` on the UI thread takes the latest one every
:data:`TICK_MS` ms and redraws what changed. The UI thread never waits for the engine: pause, stop,
paint and undo are thread-safe calls into the runner, export and render run in background jobs.

Closing the window during a scan stops the engine (which keeps everything computed so far), waits for
its thread without blocking the UI, exports the partial result to the output folder, then closes.
"""

from __future__ import annotations

import collections
import datetime as _dt
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from ..errors import AppFusionError
from . import colours as C
from .paint import PaintStrokes, gl_camera_to_cv
from .worker import Job, ScanWorker

#: UI timer period: 25 ms, 40 redraws per second at most (>= 20/s measured while scanning, docs/gui.md)
TICK_MS = 25
#: the points, environment map, HBSAB and figures are redrawn at most this often (seconds)
SLOW_VIEWS_S = 0.25

_STAGES = ("ir-calibration", "environment", "geometry", "ir", "rgb", "export", "done")
_PASSES = ("ir-calibration", "environment", "geometry", "rgb", "scan")
_GUIDANCE = {}
try:  # the engine's own stage names and guidance texts
    from ..pipeline import GUIDANCE as _GUIDANCE, PASSES as _PASSES, STAGES as _STAGES  # noqa: F811
except ImportError:  # pragma: no cover - the engine module is missing
    pass

_SEVERITY_STYLE = {
    "info": "background:#1d3b5a; color:#f0f4f8;",
    "ok": "background:#1e4d2b; color:#f0f8f0;",
    "warn": "background:#6b5300; color:#fff8e0;",
    "error": "background:#7a1c1c; color:#fff0f0;",
}


def open_source(spec: str, skip_bad: bool = False):
    """A recording path (any format :func:`replay.open.open_recording` reads) or a device name
    (``openni2``, ``openni2:Dummy``, ``depthai``, ...: :func:`drivers.open_device`) as a Source."""
    from drivers import is_device_name, open_device

    if is_device_name(spec) and not Path(spec).exists():
        return open_device(spec)
    from replay.open import open_recording

    return open_recording(spec, skip_bad=skip_bad)


class RedrawStats:
    """Measured UI rates: timer ticks (redraws) per second and their cost.

    ``rate()`` is over a sliding window; ``busy_rate()`` counts only the time between two
    consecutive ticks while the engine was processing (paused time is not counted).
    """

    def __init__(self, window_s: float = 2.0):
        self.window_s = window_s
        self.ticks: collections.deque = collections.deque()
        self.costs: collections.deque = collections.deque(maxlen=200)
        self.total_ticks = 0
        self.snapshots_drawn = 0
        self.busy_ticks = 0
        self.busy_seconds = 0.0
        self.max_busy_gap_s = 0.0
        self._last: tuple[float, bool] | None = None

    def tick(self, t: float, cost_s: float, busy: bool) -> None:
        self.ticks.append(t)
        self.costs.append(cost_s)
        self.total_ticks += 1
        if busy and self._last is not None and self._last[1]:
            gap = t - self._last[0]
            self.busy_ticks += 1
            self.busy_seconds += gap
            self.max_busy_gap_s = max(self.max_busy_gap_s, gap)
        self._last = (t, busy)
        while self.ticks and self.ticks[0] < t - self.window_s:
            self.ticks.popleft()

    def rate(self) -> float:
        """Redraws per second over the last window."""
        if len(self.ticks) < 2:
            return 0.0
        return (len(self.ticks) - 1) / max(self.ticks[-1] - self.ticks[0], 1e-9)

    def busy_rate(self) -> float:
        """Mean redraws per second over the time the engine was processing."""
        return self.busy_ticks / self.busy_seconds if self.busy_seconds > 0 else 0.0

    def cost_ms(self) -> tuple[float, float]:
        """(mean, max) milliseconds spent per tick recently."""
        if not self.costs:
            return 0.0, 0.0
        c = np.array(self.costs) * 1e3
        return float(c.mean()), float(c.max())


def dark_palette() -> QtGui.QPalette:
    """A dark palette matching the plots' dark backgrounds."""
    p = QtGui.QPalette()
    R = QtGui.QPalette.ColorRole
    for role, rgb in ((R.Window, (36, 36, 42)), (R.WindowText, (225, 225, 230)), (R.Base, (26, 26, 31)),
                      (R.AlternateBase, (40, 40, 48)), (R.Text, (225, 225, 230)), (R.Button, (48, 48, 56)),
                      (R.ButtonText, (225, 225, 230)), (R.Highlight, (47, 111, 176)),
                      (R.HighlightedText, (255, 255, 255)), (R.ToolTipBase, (48, 48, 56)),
                      (R.ToolTipText, (225, 225, 230)), (R.PlaceholderText, (140, 140, 150))):
        p.setColor(role, QtGui.QColor(*rgb))
    for role in (R.WindowText, R.Text, R.ButtonText):
        p.setColor(QtGui.QPalette.ColorGroup.Disabled, role, QtGui.QColor(110, 110, 118))
    return p


class ProgressStrip(QtWidgets.QWidget):
    """A progress bar that only schedules repaints (QProgressBar repaints synchronously on every
    setValue, which costs a whole-window composition per tick when the window holds an OpenGL view)."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.value, self.total, self.text = 0, 0, ""
        self.setMinimumHeight(22)

    def set(self, value: int, total: int, text: str) -> None:
        if (value, total, text) != (self.value, self.total, self.text):
            self.value, self.total, self.text = value, total, text
            self.update()

    def paintEvent(self, ev) -> None:
        qp = QtGui.QPainter(self)
        r = self.rect().adjusted(0, 0, -1, -1)
        qp.fillRect(r, QtGui.QColor(42, 42, 51))
        if self.total > 0:
            w = int(r.width() * min(self.value / self.total, 1.0))
            qp.fillRect(QtCore.QRect(r.left(), r.top(), w, r.height()), QtGui.QColor(47, 111, 176))
        qp.setPen(QtGui.QColor(235, 235, 235))
        qp.drawText(r, QtCore.Qt.AlignmentFlag.AlignCenter, self.text)
        qp.end()


class MainWindow(QtWidgets.QMainWindow):
    """The scanning window.

    Parameters
    ----------
    source : str or Source, optional
        Recording path, device name, or an already-made Source; None opens an empty window.
    out_dir : path-like, optional
        Output folder (engine checkpoints, exports, partial result on close); default
        ``./appfusion-out/<source name>-<time>``.
    realtime : bool
        Play recordings at their recorded rate (False: as fast as the engine goes).
    config : appfusion.pipeline.ScanConfig, optional
    record_dir : path-like, optional
        Live sources: record the frames into this new session directory.
    runner_factory : callable, optional
        ``factory(source, out_dir, config) -> runner`` with the ScanRunner contract (tests pass a fake).
    autostart : bool
        Start scanning as soon as the window shows.
    """

    def __init__(self, source=None, out_dir=None, realtime: bool = True, config=None, record_dir=None,
                 runner_factory: Callable | None = None, autostart: bool = False):
        super().__init__()
        self.setWindowTitle("appfusion - live scan")
        self.resize(1500, 920)
        self.realtime = realtime
        self.config = config
        self.record_dir = record_dir
        self.runner_factory = runner_factory
        self._explicit_out = out_dir is not None
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.worker: ScanWorker | None = None
        self.source = None
        self.source_label = ""
        self.strokes = PaintStrokes()
        self.stats = RedrawStats()
        self.snapshot = None
        self._seq = 0
        self._slow_seq = 0
        self._t_slow = 0.0
        self._strip_state = None
        self._stages_seen: list[str] = []
        self._points_fp = None
        self._colour_fp = None
        self._camera_key = None
        self._last_recolour = 0.0
        self.export_job: Job | None = None
        self.render_job: Job | None = None
        self.exported: dict | None = None
        self.rendered: list[Path] = []
        self.closing = False
        self.closed_cleanly = False
        self._close_job: Job | None = None
        self._last_message: str | None = None
        self.last_error: str | None = None
        self._build()
        self.timer = QtCore.QTimer(self)
        self.timer.setTimerType(QtCore.Qt.TimerType.PreciseTimer)
        self.timer.timeout.connect(self._tick)
        self.timer.start(TICK_MS)
        if source is not None:
            self.set_source(source)
            if autostart:
                QtCore.QTimer.singleShot(0, self.start)
        self._refresh_controls()

    # ------------------------------------------------------------------------------------------
    # construction
    # ------------------------------------------------------------------------------------------
    def _build(self) -> None:
        from .views import EnvMapView, HBSABView, PlotsView, PointsView, StreamsView

        self.setPalette(dark_palette())
        tb = self.addToolBar("scan")
        tb.setObjectName("scan-toolbar")
        tb.setMovable(False)
        tb.setToolButtonStyle(QtCore.Qt.ToolButtonStyle.ToolButtonTextBesideIcon)
        st = self.style()
        SP = QtWidgets.QStyle.StandardPixmap

        def act(text, slot, icon=None, tip="", checkable=False, shortcut=None):
            a = QtGui.QAction(text, self)
            if icon is not None:
                a.setIcon(st.standardIcon(icon))
            a.setToolTip(tip or text)
            a.setCheckable(checkable)
            if shortcut:
                a.setShortcut(QtGui.QKeySequence(shortcut))
            # triggered(bool) would land in the slots' optional parameters (export(out_dir), ...)
            if checkable:
                a.triggered.connect(lambda checked: slot(bool(checked)))
            else:
                a.triggered.connect(lambda checked=False: slot())
            tb.addAction(a)
            return a

        self.a_open = act("Open...", self._open_dialog, SP.SP_DialogOpenButton, "open a recording folder or file")
        self.a_device = act("Device...", self._device_dialog, SP.SP_DriveHDIcon, "open a live device by name")
        tb.addSeparator()
        self.a_start = act("Start", self.start, SP.SP_MediaPlay, "start scanning")
        self.a_pause = act("Pause", self.toggle_pause, SP.SP_MediaPause, "pause / resume the engine",
                           shortcut="Space")
        self.a_stop = act("Stop", self.stop, SP.SP_MediaStop, "stop: keeps everything computed so far")
        tb.addSeparator()
        tb.addWidget(QtWidgets.QLabel(" pass "))
        self.pass_combo = QtWidgets.QComboBox()
        self.pass_combo.addItems(list(_PASSES))
        self.pass_combo.setToolTip("live sources: the pass you are scanning now")
        tb.addWidget(self.pass_combo)
        self.a_next = act("Next pass", self.next_pass, SP.SP_MediaSkipForward, "live: move on to the chosen pass")
        self.a_record = act("Record", self._toggle_record, SP.SP_DialogSaveButton,
                            "live: also record the frames into a session", checkable=True)
        tb.addSeparator()
        self.a_export = act("Export", self.export, SP.SP_DialogSaveButton, "export mesh, textures and report")
        self.a_render = act("Render", self.render_view, SP.SP_DesktopIcon,
                            "relight the scan from the 3-D view's camera (appfusion.relight)")

        tb2 = QtWidgets.QToolBar("points")
        tb2.setObjectName("points-toolbar")
        self.addToolBarBreak()
        self.addToolBar(tb2)
        tb2.addWidget(QtWidgets.QLabel(" colour "))
        self.mode_combo = QtWidgets.QComboBox()
        self.mode_combo.addItems(list(C.COLOUR_MODES))
        self.mode_combo.currentTextChanged.connect(lambda _: self._recolour(force=True))
        tb2.addWidget(self.mode_combo)
        tb2.addSeparator()
        self.a_paint = QtGui.QAction("Paint", self)
        self.a_paint.setCheckable(True)
        self.a_paint.setToolTip("paint cluster labels on the points (left-drag); other buttons move the view")
        self.a_paint.toggled.connect(lambda on: self.points.set_paint_mode(on))
        tb2.addAction(self.a_paint)
        tb2.addWidget(QtWidgets.QLabel(" brush "))
        self.brush_spin = QtWidgets.QSpinBox()
        self.brush_spin.setRange(2, 200)
        self.brush_spin.setValue(15)
        self.brush_spin.setSuffix(" px")
        self.brush_spin.valueChanged.connect(lambda v: self.points.set_brush(v))
        tb2.addWidget(self.brush_spin)
        tb2.addWidget(QtWidgets.QLabel(" label "))
        self.label_combo = QtWidgets.QComboBox()
        self.label_combo.setSizeAdjustPolicy(QtWidgets.QComboBox.SizeAdjustPolicy.AdjustToContents)
        self.label_combo.setMinimumContentsLength(9)
        self.label_combo.currentIndexChanged.connect(self._label_changed)
        tb2.addWidget(self.label_combo)
        self.a_undo = QtGui.QAction("Undo paint", self)
        self.a_undo.setShortcut(QtGui.QKeySequence.StandardKey.Undo)
        self.a_undo.triggered.connect(lambda checked=False: self.undo_paint())
        tb2.addAction(self.a_undo)
        tb2.addSeparator()
        self.a_fit = QtGui.QAction("Fit view", self)
        self.a_fit.triggered.connect(lambda: self.points.fit_camera())
        tb2.addAction(self.a_fit)
        tb2.addWidget(QtWidgets.QLabel("  HBSAB of cluster "))
        self.hbsab_spin = QtWidgets.QSpinBox()
        self.hbsab_spin.setRange(0, 0)
        self.hbsab_spin.valueChanged.connect(self._hbsab_cluster)
        tb2.addWidget(self.hbsab_spin)

        central = QtWidgets.QWidget()
        v = QtWidgets.QVBoxLayout(central)
        v.setContentsMargins(4, 4, 4, 4)
        v.setSpacing(4)
        self.banner = QtWidgets.QLabel("Open a recording or a device to start.")
        self.banner.setWordWrap(True)
        f = self.banner.font()
        f.setPointSize(f.pointSize() + 3)
        f.setBold(True)
        self.banner.setFont(f)
        self.banner.setMinimumHeight(44)
        self.banner.setContentsMargins(10, 6, 10, 6)
        self._severity = None
        self._set_banner("Open a recording or a device to start.", "info")
        v.addWidget(self.banner)
        strip = QtWidgets.QHBoxLayout()
        strip.setSpacing(2)
        self.stage_labels = {}
        for s in _STAGES:
            lab = QtWidgets.QLabel(s)
            lab.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
            lab.setMinimumWidth(90)
            lab.setStyleSheet("background:#2a2a33; color:#888; padding:3px; border-radius:3px;")
            strip.addWidget(lab)
            self.stage_labels[s] = lab
        self.progress = ProgressStrip()
        self.progress.setMinimumWidth(220)
        strip.addWidget(self.progress, 1)
        v.addLayout(strip)

        split = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)
        self.points = PointsView(on_stroke=self._on_stroke)
        self.points.setMinimumWidth(480)
        split.addWidget(self.points)
        right = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        self.streams = StreamsView()
        right.addWidget(self.streams)
        mid = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)
        self.env = EnvMapView()
        self.hbsab = HBSABView()
        mid.addWidget(self.env)
        mid.addWidget(self.hbsab)
        mid.setSizes([480, 360])
        right.addWidget(mid)
        self.plots = PlotsView()
        right.addWidget(self.plots)
        right.setSizes([230, 280, 300])
        split.addWidget(right)
        side = self._build_status()
        split.addWidget(side)
        split.setSizes([560, 720, 240])
        split.setStretchFactor(0, 3)
        split.setStretchFactor(1, 4)
        v.addWidget(split, 1)
        self.setCentralWidget(central)
        self.statusBar().showMessage("ready")

    def _build_status(self) -> QtWidgets.QWidget:
        w = QtWidgets.QFrame()
        w.setMinimumWidth(230)
        w.setMaximumWidth(320)
        g = QtWidgets.QGridLayout(w)
        g.setContentsMargins(6, 6, 6, 6)
        self.info = {}
        rows = [("source", "source"), ("state", "state"), ("stage", "stage"), ("frames", "frames used"),
                ("tracking", "tracking"), ("markers", "markers"), ("points", "points"),
                ("clusters", "clusters"), ("materials", "materials"), ("env", "env coverage"), ("hbsab", "HBSAB bins"),
                ("fps", "engine fps"), ("ui", "UI redraws"), ("snaps", "snapshots/s"), ("record", "recording"),
                ("out", "output")]
        for r, (key, text) in enumerate(rows):
            t = QtWidgets.QLabel(text)
            t.setStyleSheet("color:#9aa;")
            val = QtWidgets.QLabel("-")
            val.setWordWrap(True)
            val.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
            g.addWidget(t, r, 0, QtCore.Qt.AlignmentFlag.AlignTop)
            g.addWidget(val, r, 1)
            self.info[key] = val
        r = len(rows)
        g.addWidget(QtWidgets.QLabel("messages"), r, 0, 1, 2)
        self.messages = QtWidgets.QListWidget()
        self.messages.setWordWrap(True)
        g.addWidget(self.messages, r + 1, 0, 1, 2)
        g.setRowStretch(r + 1, 1)
        g.setColumnStretch(1, 1)
        return w

    # ------------------------------------------------------------------------------------------
    # source and engine control
    # ------------------------------------------------------------------------------------------
    def set_source(self, source) -> None:
        """Use a recording path, device name or Source for the next scan (not started)."""
        if self.worker is not None and self.worker.busy:
            raise AppFusionError("a scan is running: stop it before opening another source")
        if isinstance(source, (str, os.PathLike)):
            label = str(source)
            source = open_source(str(source))
        else:
            label = getattr(source, "name", "source")
        self.source = source
        self.source_label = label
        if self.out_dir is None or not self._explicit_out:
            stem = Path(label).name or "device"
            stem = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in stem)
            stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
            self.out_dir = Path.cwd() / "appfusion-out" / f"{stem}-{stamp}"
        self.worker = None
        self.snapshot = None
        self._seq = self._slow_seq = 0
        self._last_message = None
        self.strokes = PaintStrokes()
        self._stages_seen = []
        self.exported = None
        self.info["source"].setText(Path(label).name or label)
        self.info["source"].setToolTip(label)
        self.info["out"].setText(self.out_dir.name)
        self.info["out"].setToolTip(str(self.out_dir))
        self._set_banner(f"Ready: press Start to scan {label}.", "info")
        self._refresh_controls()

    def start(self) -> None:
        """Start the scan of the current source in the engine's worker thread."""
        if self.source is None:
            self._set_banner("Open a recording or a device first.", "warn")
            return
        if self.worker is not None:
            if self.worker.busy:
                return
            # scanning again after a finished scan: from the start of a recording, with a fresh snapshot
            if getattr(self.source, "is_recording", False):
                self.source.seek(0)
            self.snapshot, self._seq, self._slow_seq, self._stages_seen, self._last_message = None, 0, 0, [], None
            self.strokes = PaintStrokes()
            self.exported = None
        record = self.record_dir if (self.a_record.isChecked() or self.record_dir) else None
        if record is not None and getattr(self.source, "is_recording", False):
            record = None
        try:
            self.worker = ScanWorker(self.source, self.out_dir, config=self.config, realtime=self.realtime,
                                     record_dir=record, runner_factory=self.runner_factory,
                                     live_pass=self.pass_combo.currentText())
            self.worker.start()
        except AppFusionError as e:
            self._fail(f"cannot start: {e}")
            self.worker = None
            return
        self.statusBar().showMessage(f"scanning {self.source_label} -> {self.out_dir}")
        self._refresh_controls()

    def toggle_pause(self) -> None:
        w = self.worker
        if w is None:
            return
        if w.state == "running":
            w.pause()
        elif w.source.error is not None:  # the engine goes on with the frames it has
            self._set_banner(f"Source lost - {w.source.error}. Processing the {frames} frames received so far; "
                             "the scan is kept.", "error")
        elif w.state == "paused":
            w.resume()
        self._update_state()

    def pause(self) -> None:
        if self.worker is not None:
            self.worker.pause()
        self._update_state()

    def resume(self) -> None:
        if self.worker is not None:
            self.worker.resume()
        self._update_state()

    def stop(self) -> None:
        """Stop the engine; everything computed so far is kept and can be exported."""
        if self.worker is not None:
            self.worker.stop()
        self._update_state()

    def next_pass(self) -> None:
        if self.worker is not None and self.worker.is_live:
            name = self.pass_combo.currentText()
            self.worker.next_pass(name)
            self._add_message(f"pass: {name}")
            i = self.pass_combo.currentIndex()
            if i + 1 < self.pass_combo.count():
                self.pass_combo.setCurrentIndex(i + 1)

    def _toggle_record(self, on: bool) -> None:
        if on and self.record_dir is None:
            base = self.out_dir or Path.cwd()
            self.record_dir = Path(base) / f"recording-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"
        if not on:
            self.record_dir = None
        if self.worker is not None and self.worker.busy:
            self._add_message("recording applies to the next scan started")

    def _open_dialog(self) -> None:
        path = QtWidgets.QFileDialog.getExistingDirectory(self, "Open a recording folder (session, TUM, Redwood)")
        if path:
            self._try(lambda: self.set_source(path))

    def _device_dialog(self) -> None:
        name, ok = QtWidgets.QInputDialog.getText(self, "Open a device",
                                                  "device (openni2, openni2:Dummy, depthai, depthai:MXID):",
                                                  text="openni2")
        if ok and name:
            self._try(lambda: self.set_source(name.strip()))

    def _try(self, fn) -> None:
        try:
            fn()
        except AppFusionError as e:
            self._fail(str(e))

    def _fail(self, msg: str) -> None:
        self.last_error = msg
        self._set_banner(msg, "error")
        self._add_message(msg)

    # ------------------------------------------------------------------------------------------
    # painting (§5.2 manual refinement)
    # ------------------------------------------------------------------------------------------
    def _on_stroke(self, idx: np.ndarray, label: int) -> None:
        if self.worker is not None:
            try:
                self.worker.paint(idx, label)
            except AppFusionError as e:  # e.g. the engine has no points yet
                self._fail(f"paint: {e}")
                self._recolour(force=True)
                return
            self._refresh_after_edit()
        self.strokes.add(idx, label)
        self._recolour(force=True)
        self.statusBar().showMessage(f"painted {len(idx)} points as cluster {label} ({len(self.strokes)} strokes)")

    def undo_paint(self) -> None:
        """Undo the last paint stroke (here and in the engine)."""
        if self.strokes.undo() is None:
            return
        if self.worker is not None:
            self.worker.undo_paint()
            self._refresh_after_edit()
        self._recolour(force=True)
        self.statusBar().showMessage(f"undone: {len(self.strokes)} strokes left")

    def _refresh_after_edit(self) -> None:
        """A finished engine publishes no more snapshots: ask it for one after an edit."""
        w = self.worker
        if w is not None and not w.busy and w.runner is not None:
            try:
                w.box.put(w.runner.snapshot())
            except Exception as e:  # noqa: BLE001
                self._add_message(f"snapshot after edit failed: {e}")

    def _label_changed(self, i: int) -> None:
        self.points.label = max(i, 0)

    def _hbsab_cluster(self, c: int) -> None:
        self.hbsab.set_cluster(c)
        if self.snapshot is not None:
            self.hbsab.update_from(self.snapshot)

    def _update_label_choices(self, n: int) -> None:
        if self.label_combo.count() == n:
            return
        cur = self.label_combo.currentIndex()
        self.label_combo.blockSignals(True)
        self.label_combo.clear()
        for k in range(n):
            col = C.cluster_rgb([k])[0]
            pm = QtGui.QPixmap(14, 14)
            pm.fill(QtGui.QColor(*(int(255 * x) for x in col)))
            self.label_combo.addItem(QtGui.QIcon(pm), f"cluster {k}")
        self.label_combo.setCurrentIndex(min(max(cur, 0), n - 1))
        self.label_combo.blockSignals(False)
        self.points.label = max(self.label_combo.currentIndex(), 0)
        self.hbsab_spin.setRange(0, max(n - 1, 0))

    # ------------------------------------------------------------------------------------------
    # export and render
    # ------------------------------------------------------------------------------------------
    def export(self, out_dir=None) -> Job | None:
        """Export the scan so far (``runner.export``) in a background job; returns the job."""
        if self.worker is None or self.worker.runner is None:
            self._set_banner("Nothing to export yet: start a scan first.", "warn")
            return None
        if self.export_job is not None and not self.export_job.done.is_set():
            return self.export_job
        self.export_job = self.worker.export(out_dir)
        self.statusBar().showMessage(f"exporting to {out_dir or self.out_dir} ...")
        self._refresh_controls()
        return self.export_job

    def render_view(self, size=(320, 240), spp: int = 16) -> Job | None:
        """Relight the scan from the 3-D view's camera (:func:`appfusion.relight.render_view`) in a job."""
        if self.worker is None or self.worker.runner is None:
            self._set_banner("Nothing to render yet: start a scan first.", "warn")
            return None
        if self.render_job is not None and not self.render_job.done.is_set():
            return self.render_job
        _, view = self.points.camera_matrices()
        W, H = size
        K, pose = gl_camera_to_cv(view, self.points.gl.opts["fov"], W, H)
        snap_env = getattr(self.snapshot, "envmap", None)
        worker, out = self.worker, self.out_dir
        n = len(self.rendered)

        def work():
            import dataclasses

            from ..export import mesh_from_points
            from ..relight import render_view
            from ..result import ScanResult

            res = worker.partial_result()
            if res is None or len(res.positions) == 0:
                raise AppFusionError("nothing to render: the scan has no fused points yet")
            if len(res.mesh_faces) == 0 and (out / "result.npz").exists():
                saved = ScanResult.load(out / "result.npz")
                if len(saved.mesh_faces):
                    res = dataclasses.replace(res, mesh_vertices=saved.mesh_vertices, mesh_faces=saved.mesh_faces)
            if len(res.mesh_faces) == 0:
                V, F = mesh_from_points(res.positions, res.normals)
                res = dataclasses.replace(res, mesh_vertices=V, mesh_faces=F)
            env = res.envmap if res.envmap is not None else snap_env
            note = ""
            if env is None:
                env = np.ones((2, 16, 16, 3), np.float32)
                note = " (no environment map yet: uniform white light)"
            img, mask = render_view(res, np.asarray(env, np.float32), K, pose, spp=spp, shadows=True)
            srgb = C.tonemap(np.where(mask[..., None], img, 0.0), 99.5)
            srgb[~mask] = (24, 24, 30)
            out.mkdir(parents=True, exist_ok=True)
            path = out / f"render-{n:02d}.png"
            QtGui.QImage(np.ascontiguousarray(srgb).data, W, H, 3 * W,
                         QtGui.QImage.Format.Format_RGB888).copy().save(str(path))
            return {"path": path, "image": srgb, "note": note}

        self.render_job = Job("render", work)
        self.statusBar().showMessage("rendering the view ...")
        return self.render_job

    def screenshot(self) -> QtGui.QImage:
        """The window as an image, with the native 3-D view composed in (``QWidget.grab`` leaves it out)."""
        img = self.grab().toImage()
        qp = QtGui.QPainter(img)
        gl_img = self.points.grab_image()
        pos = self.points.container.mapTo(self, QtCore.QPoint(0, 0))
        qp.drawImage(QtCore.QRect(pos, self.points.container.size()), gl_img)
        qp.end()
        return img

    def _show_render(self, res: dict) -> None:
        self.rendered.append(res["path"])
        img = np.ascontiguousarray(res["image"])
        h, w = img.shape[:2]
        qi = QtGui.QImage(img.data, w, h, 3 * w, QtGui.QImage.Format.Format_RGB888).copy()
        dlg = QtWidgets.QDialog(self)
        dlg.setWindowTitle(f"render: {res['path'].name}")
        lay = QtWidgets.QVBoxLayout(dlg)
        lab = QtWidgets.QLabel()
        lab.setPixmap(QtGui.QPixmap.fromImage(qi).scaled(2 * w, 2 * h, QtCore.Qt.AspectRatioMode.KeepAspectRatio))
        lay.addWidget(lab)
        lay.addWidget(QtWidgets.QLabel(f"saved to {res['path']}{res['note']}"))
        dlg.setModal(False)
        dlg.show()
        self.render_dialog = dlg

    # ------------------------------------------------------------------------------------------
    # the UI timer
    # ------------------------------------------------------------------------------------------
    def _tick(self) -> None:
        t0 = time.perf_counter()
        w = self.worker
        if w is not None:
            seq, snap = w.box.get()
            if seq != self._seq and snap is not None:
                self._seq = seq
                self._apply_snapshot(snap)
                self.stats.snapshots_drawn += 1
            if self._slow_seq != self._seq and (time.monotonic() - self._t_slow >= SLOW_VIEWS_S or not w.busy):
                self._apply_slow(self.snapshot)
        if (self.mode_combo.currentText() == "appearance" and self.points.positions is not None
                and time.monotonic() - self._last_recolour > 0.15):
            key = self.points.camera_key()
            if key != self._camera_key:
                self._recolour(force=True)
        self._poll_jobs()
        self._update_state()
        busy = w is not None and w.busy and w.state == "running"
        self.stats.tick(time.monotonic(), time.perf_counter() - t0, busy)

    def _apply_snapshot(self, s) -> None:
        """Every new snapshot: the streams and the status; the rest at most every SLOW_VIEWS_S."""
        self.snapshot = s
        if s.stage not in self._stages_seen:
            self._stages_seen.append(s.stage)
        self.streams.update_from(s.last_frame)
        self._new_messages(list(s.messages or []))

    def _new_messages(self, msgs: list[str]) -> None:
        """Show the messages after the last one shown (the engine keeps only its latest ones)."""
        last = self._last_message
        start = 0
        if last is not None:
            for i in range(len(msgs) - 1, -1, -1):
                if msgs[i] == last:
                    start = i + 1
                    break
        for m in msgs[start:]:
            self._add_message(m)
        if msgs:
            self._last_message = msgs[-1]

    def _apply_slow(self, s) -> None:
        """Points, environment map, HBSAB and figures (they change slowly; redrawing them is costly)."""
        self._slow_seq = self._seq
        self._t_slow = time.monotonic()
        self.env.update_from(s)
        self.hbsab.update_from(s)
        self.plots.update_from(s)
        self._recolour()
        n = len(s.alpha) if s.alpha is not None else (int(s.labels.max()) + 1 if s.labels is not None
                                                        and len(s.labels) else 0)
        if n:
            self._update_label_choices(n)

    def _recolour(self, force: bool = False) -> None:
        """Colour the points for the current mode; re-upload positions only when they changed."""
        from .views import fingerprint

        s = self.snapshot
        if s is None or s.positions is None:
            return
        mode = self.mode_combo.currentText()
        labels = self.strokes.apply(s.labels)
        pfp = fingerprint(s.positions)
        new_points = pfp != self._points_fp
        cfp = (mode, fingerprint(labels), fingerprint(s.rho_d), fingerprint(s.rho_s), fingerprint(s.alpha),
               self.points.camera_key() if mode == "appearance" else None)
        if not (new_points or force or cfp != self._colour_fp):
            return
        col = C.point_colours(mode, len(s.positions), labels=labels, rho_d=s.rho_d, rho_s=s.rho_s,
                              alpha=s.alpha, positions=s.positions, normals=s.normals, eye=self.points.eye())
        if new_points:
            self.points.set_points(s.positions, s.normals, col)
            self._points_fp = pfp
        else:
            self.points.set_colours(col)
        self._colour_fp = cfp
        self._camera_key = self.points.camera_key()
        self._last_recolour = time.monotonic()

    def _poll_jobs(self) -> None:
        j = self.export_job
        if j is not None and j.done.is_set() and not getattr(j, "_shown", False):
            j._shown = True
            if j.error:
                self._fail(f"export failed: {j.error}")
            else:
                self.exported = j.result
                extra = f" (partial: {j.result['error']})" if "error" in j.result else ""
                self._add_message(f"exported {len(j.result)} files to {self.out_dir} in {j.seconds:.1f} s{extra}")
                self.statusBar().showMessage(f"exported to {self.out_dir}")
            self._refresh_controls()
        r = self.render_job
        if r is not None and r.done.is_set() and not getattr(r, "_shown", False):
            r._shown = True
            if r.error:
                self._fail(f"render failed: {r.error}")
            else:
                self._show_render(r.result)
                self._add_message(f"rendered {r.result['path'].name} in {r.seconds:.1f} s")
        if self.closing:
            self._continue_close()

    def _update_state(self) -> None:
        from .views import materials_text

        w = self.worker
        s = self.snapshot
        state = "no source" if self.source is None else ("ready" if w is None else w.state)
        self.info["state"].setText(state)
        if s is not None:
            self.info["stage"].setText(s.stage)
            total = int(s.frames_total or 0)
            self.progress.set(int(s.frame), total,
                              f"{s.stage}: {s.frame} / {total} frames" if total else f"{s.stage}: {s.frame} frames (live)")
            self.info["frames"].setText(f"{s.frame} / {total}" if total else str(s.frame))
            col = {"ok": "#5c5", "lost": "#f55"}.get(s.tracking, "#aaa")
            self.info["tracking"].setText(f"<b style='color:{col}'>{s.tracking}</b>")
            mv = int(s.markers_visible or 0)
            self.info["markers"].setText("<span style='color:#eee'>" + "\u25cf" * mv + "</span>"
                                         + "<span style='color:#555'>" + "\u25cb" * max(4 - mv, 0) + f"</span> {mv}/4")
            self.info["points"].setText("-" if s.positions is None else f"{len(s.positions):,}")
            self.info["clusters"].setText("-" if s.alpha is None else str(len(s.alpha)))
            self.info["materials"].setText(materials_text(s.alpha, s.alpha_sigma, s.rho_s,
                                                          getattr(s, "rho_s_sigma", None)))
            cov = self.env.coverage
            self.info["env"].setText("-" if not np.isfinite(cov) else f"{100 * cov:.0f}% of the sphere")
            hb = self.hbsab.coverage
            self.info["hbsab"].setText("-" if not np.isfinite(hb) else f"{100 * hb:.0f}% (cluster {self.hbsab.cluster})")
            self.info["fps"].setText(", ".join(f"{k} {v:.1f}" for k, v in (s.fps or {}).items()) or "-")
            self._update_strip(s.stage)
        mean_ms, max_ms = self.stats.cost_ms()
        self.info["ui"].setText(f"{self.stats.rate():.0f}/s ({mean_ms:.1f} ms, max {max_ms:.0f} ms)")
        self.info["snaps"].setText("-" if w is None else f"{w.box.rate():.1f}")
        if w is not None and w.recorder is not None:
            r = w.recorder
            self.info["record"].setText(f"{r.frames} frames -> {r.path}" + (f" ({r.error})" if r.error else ""))
        elif self.record_dir is not None:
            self.info["record"].setText(f"next scan -> {self.record_dir}")
        else:
            self.info["record"].setText("off")
        self._update_banner()
        self._refresh_controls()

    def _update_strip(self, stage: str) -> None:
        key = (stage, tuple(self._stages_seen))
        if key == self._strip_state:  # style sheets are costly to re-apply
            return
        self._strip_state = key
        order = list(_STAGES)
        cur = order.index(stage) if stage in order else -1
        for k, (name, lab) in enumerate(self.stage_labels.items()):
            if name == stage:
                style, text = "background:#2f6fb0; color:white; font-weight:bold;", f"\u25b6 {name}"
            elif k < cur and name in self._stages_seen:
                style, text = "background:#24502f; color:#dfd;", f"\u2713 {name}"
            elif k < cur:
                style, text = "background:#2a2a33; color:#666;", f"- {name}"
            else:
                style, text = "background:#2a2a33; color:#999;", name
            lab.setStyleSheet(style + " padding:3px; border-radius:3px;")
            lab.setText(text)

    def _set_banner(self, text: str, severity: str = "info") -> None:
        if self.banner.text() != text:
            self.banner.setText(text)
        if severity != self._severity:
            self.banner.setStyleSheet(_SEVERITY_STYLE[severity] + " border-radius:4px; padding:6px;")
            self._severity = severity

    def _update_banner(self) -> None:
        w, s = self.worker, self.snapshot
        if self.closing:
            self._set_banner(f"Closing: stopping the engine and saving the scan so far to {self.out_dir} ...", "warn")
            return
        if self.source is None:
            self._set_banner("Open a recording or a device to start.", "info")
            return
        if w is None:
            if self.last_error:
                return
            self._set_banner(f"Ready: press Start to scan {self.source_label}.", "info")
            return
        frames = w.source.frames
        if w.state == "source-error":
            self.last_error = w.error
            self._set_banner(f"Source lost - {w.error}. The scan so far ({frames} frames) is kept: Export it, "
                             "or reconnect the device and start again.", "error")
        elif w.state == "error":
            self.last_error = w.error
            kept = ("What was computed so far can still be exported." if w.result is not None
                    else "Nothing had been computed yet; the output folder keeps the engine's checkpoints.")
            self._set_banner(f"Engine error - {w.error}. {kept}", "error")
        elif w.state == "stopping":
            self._set_banner("Stopping: keeping everything computed so far ...", "warn")
        elif w.state == "stopped" and w.result is None:
            self._set_banner(f"Stopped after {frames} frames, before there was anything to keep "
                             f"({w.note or 'no geometry yet'}). Start again to scan.", "warn")
        elif w.state == "stopped":
            self._set_banner(f"Stopped after {frames} frames. Paint clusters if needed, then Export "
                             f"(to {self.out_dir}).", "ok")
        elif w.state == "finished":
            what = "Recording finished" if not w.is_live else "Device stream ended"
            self._set_banner(f"{what}: {frames} frames processed. Paint clusters if needed, then Export "
                             f"(to {self.out_dir}).", "ok")
        elif w.source.error is not None:  # the engine goes on with the frames it has
            self._set_banner(f"Source lost - {w.source.error}. Processing the {frames} frames received so far; "
                             "the scan is kept.", "error")
        elif w.state == "paused":
            self._set_banner("Paused - Resume to continue. Export keeps what is computed so far.", "warn")
        elif s is not None and s.tracking == "lost":
            self._set_banner(f"Tracking lost ({s.markers_visible}/4 circles in view): move the camera back "
                             "slowly until the white circles and the object are in view again.", "error")
        elif s is not None:
            g = s.guidance or _GUIDANCE.get(s.stage, "")
            self._set_banner(f"{s.stage}: {g}", "info")
        else:
            self._set_banner(f"Starting the scan of {self.source_label} ...", "info")

    def _refresh_controls(self) -> None:
        w = self.worker
        busy = w is not None and w.busy
        live = w.is_live if w is not None else (self.source is not None
                                                and not getattr(self.source, "is_recording", True))
        self.a_start.setEnabled(self.source is not None and not busy and not self.closing)
        self.a_pause.setEnabled(busy and w.state in ("running", "paused"))
        self.a_pause.setText("Resume" if (w is not None and w.state == "paused") else "Pause")
        self.a_stop.setEnabled(busy and w.state != "stopping")
        self.a_next.setEnabled(busy and live)
        self.pass_combo.setEnabled(live)
        self.a_record.setEnabled(live and not busy)
        has = w is not None and w.runner is not None
        exporting = self.export_job is not None and not self.export_job.done.is_set()
        self.a_export.setEnabled(has and not exporting and not self.closing)
        self.a_render.setEnabled(has and not self.closing)
        self.a_undo.setEnabled(len(self.strokes) > 0)
        self.a_open.setEnabled(not busy)
        self.a_device.setEnabled(not busy)

    def _add_message(self, m: str) -> None:
        stamp = time.strftime("%H:%M:%S")
        self.messages.addItem(f"{stamp} {m}")
        while self.messages.count() > 200:
            self.messages.takeItem(0)
        self.messages.scrollToBottom()

    # ------------------------------------------------------------------------------------------
    # closing mid-scan
    # ------------------------------------------------------------------------------------------
    def closeEvent(self, ev: QtGui.QCloseEvent) -> None:
        """Stop the engine and save the scan so far before closing (a second close forces it)."""
        w = self.worker
        if self.closed_cleanly or w is None or w.runner is None:
            self._finish_close()
            ev.accept()
            return
        if self.closing:  # asked twice: close now, the engine thread is a daemon
            self._add_message("closing without waiting for the engine")
            self._finish_close()
            ev.accept()
            return
        self.closing = True
        if w.busy:
            w.stop()
        self._update_banner()
        ev.ignore()

    def _continue_close(self) -> None:
        w = self.worker
        if w.busy:
            return
        if self._close_job is None:
            if self.export_job is not None and not self.export_job.done.is_set():
                return  # the user's export is still writing
            self._close_job = w.export(self.out_dir)
            return
        if not self._close_job.done.is_set():
            return
        if self._close_job.error:
            print(f"appfusion gui: saving the scan to {self.out_dir} failed: {self._close_job.error}")
        else:
            self.exported = self._close_job.result
        self.closed_cleanly = True
        self.close()

    def _finish_close(self) -> None:
        self.timer.stop()
        self.closing = False


def run_gui(source=None, out_dir=None, realtime: bool = True, config=None, record_dir=None,
            runner_factory=None, autostart: bool = True, argv=None) -> int:
    """Open the window (creating the QApplication) and run the Qt event loop; returns its exit code."""
    from . import views  # noqa: F401 - sets the application attributes the GL view needs

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(argv or ["appfusion-gui"])
    app.setApplicationName("appfusion")
    app.setStyle("Fusion")
    win = MainWindow(source, out_dir=out_dir, realtime=realtime, config=config, record_dir=record_dir,
                     runner_factory=runner_factory, autostart=autostart and source is not None)
    win.show()
    return app.exec()
