"""The GUI's side of the engine: a worker thread running the scan, the latest snapshot, pacing, recording.

The GUI is a thin observer. :class:`ScanWorker` runs ``runner.run()`` (the blocking engine,
:class:`appfusion.pipeline.ScanRunner` or anything with the same contract) in a
:class:`threading.Thread`; the engine publishes :class:`~appfusion.pipeline.Snapshot` objects from
that thread into a :class:`SnapshotBox` (a lock and a reference: the publisher never waits on the
UI), and the UI thread takes the latest one on a ``QTimer``. Nothing here imports Qt, so the
whole life cycle (start, pause, stop, a source that fails, export of a partial scan) is tested
without a display.

:class:`PacedSource` wraps the frame source the engine reads:

- recordings play at their recorded rate (``realtime=True``: it sleeps to each frame's timestamp,
  re-anchoring its clock after a pause or when the engine is slower than real time, so it never
  bursts to catch up) or as fast as the engine takes them;
- every frame from a live device can be written to a session (:class:`replay.session.SessionWriter`),
  with the pass the user is in;
- an error raised by the source (an unplugged device: :class:`~appfusion.errors.DeviceError`) is
  remembered before it propagates, so the GUI shows it even if the engine handles it itself.
"""

from __future__ import annotations

import json
import threading
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Iterator

from ..errors import AppFusionError, DeviceError, PassMissingError, SourceError
from ..source import Source, WrappedSource

#: worker states, as the GUI shows them
STATES = ("idle", "running", "paused", "stopping", "finished", "stopped", "source-error", "error")


class SnapshotBox:
    """The latest snapshot published by the engine, with a sequence number.

    ``put`` is the engine's subscriber callback (called from its thread); ``get`` is called by the
    UI thread. Neither blocks for longer than an assignment.
    """

    def __init__(self):
        self._lock = threading.Lock()
        self._snap = None
        self._seq = 0
        self._t_first = None
        self._t_last = None

    def put(self, snapshot) -> None:
        now = time.monotonic()
        with self._lock:
            self._snap = snapshot
            self._seq += 1
            if self._t_first is None:
                self._t_first = now
            self._t_last = now

    def get(self) -> tuple[int, Any]:
        """(sequence number, snapshot); (0, None) before the first one."""
        with self._lock:
            return self._seq, self._snap

    def rate(self) -> float:
        """Snapshots per second published so far (0 with fewer than two)."""
        with self._lock:
            if self._seq < 2 or self._t_last == self._t_first:
                return 0.0
            return (self._seq - 1) / (self._t_last - self._t_first)


class SessionRecorder:
    """Writes the frames of a live source into a session directory (opened at the first frame).

    Parameters
    ----------
    path : path-like
        New, empty session directory.
    source : Source
        The live source (its name, intrinsics and meta fill ``meta.json``).
    """

    def __init__(self, path, source: Source):
        self.path = Path(path)
        self.source = source
        self.writer = None
        self.frames = 0
        self.error: str | None = None
        self.pass_name: str | None = None

    def _open(self, frame) -> None:
        from replay.session import SessionWriter

        intr = {}
        for s in ("depth", "ir", "rgb"):
            k = getattr(frame, f"{s}_intrinsics") or self.source.intrinsics.get(s)
            if k is not None:
                intr[s] = k
        meta = self.source.meta or {}
        self.writer = SessionWriter(
            self.path, device=str(getattr(self.source, "name", "device")), intrinsics=intr,
            depth_to_ir=frame.depth_to_ir, depth_to_rgb=frame.depth_to_rgb,
            rgb_encoding=frame.rgb_encoding,
            emitter_position_m=meta.get("emitter_position_m", (0.075, 0.0, 0.0)),
            notes="recorded by appfusion gui", fsync_interval_s=0.5)

    def write(self, frame) -> None:
        """Append a frame (tagged with the current pass); a failing disk stops recording, not the scan."""
        if self.error is not None:
            return
        try:
            if self.writer is None:
                self._open(frame)
            if frame.pass_name is None and self.pass_name is not None:
                frame = frame.replace(pass_name=self.pass_name)
            self.writer.write(frame)
            self.frames += 1
        except (AppFusionError, OSError) as e:
            self.error = f"recording to {self.path} stopped: {e}"

    def close(self) -> None:
        if self.writer is not None:
            try:
                self.writer.close()
            except (AppFusionError, OSError) as e:
                self.error = self.error or f"recording to {self.path}: closing failed: {e}"
            self.writer = None


class PacedSource(WrappedSource):
    """A source wrapper that paces recordings, records live frames and remembers source errors.

    Parameters
    ----------
    inner : Source
        The recording or device.
    realtime : bool
        Recordings only: sleep to each frame's timestamp (True) or deliver as fast as asked (False).
    recorder : SessionRecorder, optional
        Every frame delivered is also written there.

    Attributes
    ----------
    error : Exception or None
        The exception the inner source raised, if any.
    frames : int
        Frames delivered so far.
    ended : bool
        The inner source ran out of frames.
    """

    #: at most this far behind the recording's clock before re-anchoring it (seconds)
    MAX_LAG_S = 0.25
    #: a gap between two recorded frames longer than this is not slept through (seconds)
    MAX_GAP_S = 1.0

    def __init__(self, inner: Source, realtime: bool = True, recorder: SessionRecorder | None = None):
        super().__init__(inner)
        self.realtime = bool(realtime) and bool(getattr(inner, "is_recording", False))
        self.recorder = recorder
        self.name = getattr(inner, "name", "source")
        self.is_recording = bool(getattr(inner, "is_recording", False))
        self.error: BaseException | None = None
        self.frames = 0
        self.ended = False
        self.last_timestamp: float | None = None
        self._wake = threading.Event()
        self._anchor: tuple[float, float] | None = None  # (wall clock, frame timestamp)

    # -- forwarding ----------------------------------------------------------------------------
    def __getattr__(self, name):  # events, timestamps, frame, poses, ... of recordings
        if name.startswith("__") or name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def __len__(self) -> int:
        return len(self.inner)

    def seek(self, index: int) -> None:
        self.inner.seek(index)
        self._anchor = None

    def interrupt(self) -> None:
        """Wake a pacing sleep at once (called on stop)."""
        self._wake.set()

    # -- Source --------------------------------------------------------------------------------
    def _open(self) -> None:
        self.inner.open()

    def _close(self) -> None:
        try:
            self.inner.close()
        finally:
            if self.recorder is not None:
                self.recorder.close()

    def _pace(self, t: float) -> None:
        now = time.monotonic()
        if self._anchor is None:
            self._anchor = (now, t)
            return
        due = self._anchor[0] + (t - self._anchor[1])
        if now - due > self.MAX_LAG_S or t < self._anchor[1] or due - now > self.MAX_GAP_S:
            self._anchor = (now, t)  # paused, slower than real time, seeked, or a gap: no burst, no wait
        elif due > now:
            self._wake.wait(due - now)

    def _frames(self) -> Iterator:
        it = iter(self.inner)
        while True:
            try:
                frame = next(it)
            except StopIteration:
                self.ended = True
                return
            except BaseException as e:  # remembered, then the engine decides what to do with it
                self.error = e
                raise
            if self.realtime and not self._wake.is_set():
                self._pace(float(frame.timestamp))
            if self.recorder is not None:
                self.recorder.write(frame)
            self.frames += 1
            self.last_timestamp = float(frame.timestamp)
            yield frame


class Job:
    """A function run once in a background thread (export, render): poll ``done``."""

    def __init__(self, name: str, fn: Callable[[], Any]):
        self.name = name
        self.result = None
        self.error: str | None = None
        self.done = threading.Event()
        self.t0 = time.monotonic()
        self.seconds = 0.0

        def run():
            try:
                self.result = fn()
            except AppFusionError as e:
                self.error = str(e)
            except Exception as e:  # noqa: BLE001 - shown in the GUI, never crashes it
                self.error = f"{type(e).__name__}: {e}"
                traceback.print_exc()
            finally:
                self.seconds = time.monotonic() - self.t0
                self.done.set()

        self.thread = threading.Thread(target=run, name=f"appfusion-{name}", daemon=True)
        self.thread.start()


def _default_runner_factory(source, out_dir, config):
    from ..pipeline import ScanRunner

    return ScanRunner(source, out_dir, config=config)


class ScanWorker:
    """Runs one scan in a worker thread and exposes its state to the UI (which polls it).

    Parameters
    ----------
    source : Source
        Recording or live device (not yet opened).
    out_dir : path-like
        Output folder of the scan (engine checkpoints, exports, the partial result on close).
    config : appfusion.pipeline.ScanConfig, optional
    realtime : bool
        Play recordings at their recorded rate.
    record_dir : path-like, optional
        Live sources: also record the frames into this new session directory.
    runner_factory : callable, optional
        ``factory(source, out_dir, config) -> runner`` (default: :class:`appfusion.pipeline.ScanRunner`).
    live_pass : str, optional
        Live sources: the pass the user starts with (given to the runner before its first frame).
    """

    def __init__(self, source: Source, out_dir, config=None, realtime: bool = True, record_dir=None,
                 runner_factory: Callable | None = None, live_pass: str | None = None):
        self.out_dir = Path(out_dir)
        self.recorder = None
        if record_dir is not None:
            if getattr(source, "is_recording", False):
                raise AppFusionError(f"{getattr(source, 'name', 'source')}: only a live device can be "
                                     "recorded (a recording is already on disk)")
            self.recorder = SessionRecorder(record_dir, source)
        self.source = PacedSource(source, realtime=realtime, recorder=self.recorder)
        self.box = SnapshotBox()
        self.config = config
        self._factory = runner_factory or _default_runner_factory
        self.runner = None
        self.state = "idle"
        self.error: str | None = None
        self.note: str | None = None
        self.result = None
        self.thread: threading.Thread | None = None
        self.finished = threading.Event()
        self.t_start: float | None = None
        self.t_end: float | None = None
        self.live_pass: str | None = live_pass
        self._stop_asked = False

    @property
    def is_live(self) -> bool:
        return not self.source.is_recording

    @property
    def busy(self) -> bool:
        """The engine thread is alive (running, paused or stopping)."""
        return self.thread is not None and self.thread.is_alive()

    def start(self) -> None:
        """Create the runner and start ``runner.run()`` in a new thread (once)."""
        if self.thread is not None:
            raise AppFusionError("this scan was already started; open the source again for a new scan")
        self.out_dir.mkdir(parents=True, exist_ok=True)
        config = self.config
        if config is None:
            from ..pipeline import ScanConfig

            config = ScanConfig()
        self.runner = self._factory(self.source, self.out_dir, config)
        self.runner.subscribe(self.box.put)
        if self.is_live and self.live_pass is not None:
            self.next_pass(self.live_pass)
        self.state = "running"
        self.t_start = time.monotonic()
        self.thread = threading.Thread(target=self._run, name="appfusion-scan", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        err: BaseException | None = None
        try:
            self.result = self.runner.run()
        except BaseException as e:  # noqa: BLE001 - the scan so far is kept either way
            err = e
            if not isinstance(e, AppFusionError):
                traceback.print_exc()
        finally:
            if self.result is None:
                try:
                    self.result = self.runner.result()
                except Exception:  # noqa: BLE001 - nothing computed yet
                    self.result = None
            src_err = self.source.error or (err if isinstance(err, SourceError) else None)
            if src_err is not None:
                kind = "device" if isinstance(src_err, DeviceError) else "source"
                self.error = f"{kind} error: {src_err}"
                self.state = "source-error"
            elif err is not None and self._stop_asked and isinstance(err, PassMissingError):
                self.note = f"stopped before there was a result: {err}"  # nothing computed yet: no error
                self.state = "stopped"
            elif err is not None:
                self.error = f"{type(err).__name__}: {err}" if not isinstance(err, AppFusionError) else str(err)
                self.state = "error"
            else:
                self.state = "stopped" if self._stop_asked else "finished"
            self.t_end = time.monotonic()
            try:
                self.source.close()
            except Exception:  # noqa: BLE001
                pass
            self.finished.set()

    # -- controls (thread-safe in the engine) ---------------------------------------------------
    def pause(self) -> None:
        if self.runner is not None and self.state == "running":
            self.runner.pause()
            self.state = "paused"

    def resume(self) -> None:
        if self.runner is not None and self.state == "paused":
            self.runner.resume()
            self.state = "running"

    def stop(self) -> None:
        """Ask the engine to stop; everything computed so far is kept (``finished`` is set when done)."""
        if self.runner is None or not self.busy:
            return
        self._stop_asked = True
        self.state = "stopping"
        self.source.interrupt()
        self.runner.stop()
        try:  # a paused engine must wake up to see the stop
            self.runner.resume()
        except Exception:  # noqa: BLE001
            pass

    def next_pass(self, name: str) -> None:
        """Live sources: the user moves on to pass ``name`` (also marked in the recording)."""
        self.live_pass = name
        if self.recorder is not None:
            self.recorder.pass_name = name
        if self.runner is not None:
            self.runner.next_pass(name)

    def paint(self, idx, label: int) -> None:
        if self.runner is not None:
            self.runner.paint(idx, int(label))

    def undo_paint(self) -> None:
        if self.runner is not None:
            self.runner.undo_paint()

    def partial_result(self):
        """The engine's current result (partial allowed), or None when nothing is computed yet."""
        if self.runner is None:
            return None
        try:
            return self.runner.result()
        except Exception:  # noqa: BLE001
            return self.result

    def export(self, out_dir=None) -> Job:
        """Export in a background job: ``runner.export``; if that fails on a partial scan, the
        result so far is still saved as ``result.npz``. The job's result is a dict of paths."""
        out = Path(out_dir) if out_dir is not None else self.out_dir

        def work():
            return export_partial(self.runner, out, self.status())

        return Job("export", work)

    def status(self) -> dict[str, Any]:
        """A JSON-able summary (written beside exports as ``gui-session.json``)."""
        return {"state": self.state, "error": self.error, "note": self.note, "frames_delivered": self.source.frames,
                "source": str(self.source.name), "source_ended": self.source.ended,
                "recorded_frames": None if self.recorder is None else self.recorder.frames,
                "recording_error": None if self.recorder is None else self.recorder.error,
                "seconds": None if self.t_start is None else round((self.t_end or time.monotonic()) - self.t_start, 3)}


def export_partial(runner, out_dir, status: dict | None = None) -> dict[str, str]:
    """Export whatever the runner has: ``runner.export`` or, failing that, ``result.npz`` alone.

    Returns a dict name -> path of what was written; ``error`` holds why the full export failed.
    Raises :class:`AppFusionError` only if nothing at all could be written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, str] = {}
    why = None
    if runner is None:
        raise AppFusionError("nothing to export: no scan was started")
    try:
        paths = runner.export(out) or {}
        written.update({str(k): str(v) for k, v in paths.items()})
    except Exception as e:  # noqa: BLE001 - a partial scan may lack what a full export needs
        why = f"{type(e).__name__}: {e}" if not isinstance(e, AppFusionError) else str(e)
        try:
            res = runner.result()
        except Exception as e2:  # noqa: BLE001
            res, why = None, f"{why}; no result either ({e2})"
        if res is not None:
            written["result"] = str(res.save(out / "result.npz"))
    info = dict(status or {})
    info["export_error"] = why
    info["written"] = written
    p = out / "gui-session.json"
    p.write_text(json.dumps(info, indent=2, default=str))
    written["gui_session"] = str(p)
    if why is not None and "result" not in written:
        raise AppFusionError(f"export to {out} failed: {why}")
    if why is not None:
        written["error"] = why
    return written
