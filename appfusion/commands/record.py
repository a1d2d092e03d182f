"""``appfusion record SOURCE OUT``: record a live device (or re-record a recording) into a session.

The session (``replay.session``, crash-safe) gets one ``pass`` event per scanning pass (``--pass``).
A Kinect v1 records the paper's passes one after another (§4.1 geometry with IR, §5.3 RGB), e.g.::

    appfusion record openni2 scan1 --pass geometry --seconds 60     # depth + IR
    appfusion record openni2 scan1-rgb --pass rgb --seconds 60      # depth + RGB

Ctrl-C, the frame/time limit, the end of a recording, or an unplugged device end the recording
cleanly: every frame delivered so far is in the session and one summary line says why it stopped.
"""

from __future__ import annotations

import json
import math
import signal
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from appfusion.errors import AppFusionError, DeviceError, SourceError

#: exit status when the device was lost (the frames so far are kept)
EXIT_DEVICE_LOST = 1


@dataclass
class RecordResult:
    """What :func:`record_source` did.

    Attributes
    ----------
    frames : int
        Frames written.
    counts : dict
        Images written per stream.
    seconds : float
        Time spanned by the frames written (source clock), seconds.
    stopped : str
        Why it stopped: "frame limit", "time limit", "end of recording", "Ctrl-C", "device lost".
    error : str or None
        The device error message when ``stopped == "device lost"``.
    out : Path
    """

    frames: int = 0
    counts: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    stopped: str = "end of recording"
    error: str | None = None
    out: Path | None = None

    def summary(self) -> str:
        counts = ", ".join(f"{s} {n}" for s, n in self.counts.items() if n) or "no images"
        line = (f"recorded {self.frames} frames ({counts}) over {self.seconds:.2f} s to {self.out}; "
                f"stopped: {self.stopped}")
        if self.error:
            line += f" ({self.error})"
        return line


def parse_streams(text: str | None) -> frozenset[str] | None:
    """``"depth,ir"`` -> frozenset({"depth", "ir"}); None stays None."""
    if text is None:
        return None
    names = frozenset(s.strip().lower() for s in str(text).split(",") if s.strip())
    bad = names - {"depth", "ir", "rgb"}
    if bad or not names:
        raise AppFusionError(f"record: --streams must list some of depth, ir, rgb separated by commas, got {text!r}")
    return names


def open_source(spec: str, streams: frozenset[str] | None = None):
    """A live device by name (``openni2:Dummy``, ``depthai``, ...) or a recording by path."""
    from drivers import is_device_name, open_device

    if is_device_name(spec):
        return open_device(spec, **({"streams": streams} if streams else {}))
    from replay.open import open_recording

    return open_recording(spec)


def _json_safe(d: dict[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps(d, default=str))


class _StopFlag:
    """SIGINT sets a flag checked between frames, so a frame is never cut in half; a second Ctrl-C aborts."""

    def __init__(self):
        self.set = False
        self._old = None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._old = signal.getsignal(signal.SIGINT)

            def handler(signum, frame):
                if self.set:
                    raise KeyboardInterrupt
                self.set = True

            signal.signal(signal.SIGINT, handler)
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)


def record_source(source, out: str | Path, frames: int | None = None, seconds: float | None = None,
                  streams: frozenset[str] | None = None, pass_name: str | None = None,
                  depth_units_per_m: float = 5000.0, notes: str = "", spec: str | None = None,
                  on_frame: Callable[[int], None] | None = None, show_progress: bool = False) -> RecordResult:
    """Write the frames of ``source`` into a new session at ``out`` until a limit, Ctrl-C or device loss.

    Parameters
    ----------
    source : appfusion.source.Source
        Not yet opened (it is opened and closed here).
    out : path-like
        New, empty session directory.
    frames, seconds : optional
        Stop after this many frames / once the frames span this many seconds (source clock).
    streams : frozenset of str, optional
        Streams to record: selected on the device where it can switch (``select_streams``), else the
        other streams are dropped from each frame.
    pass_name : str, optional
        Scanning pass (``geometry``, ``rgb``, ``environment``, ``ir-calibration``, ``scan``): marks
        the frames (``pass`` event) and, without ``streams``, selects the streams the pass needs.
    on_frame : callable, optional
        Called with the number of frames written after each frame.

    Returns
    -------
    RecordResult
        ``stopped == "device lost"`` when the device failed; frames before it are in the session.

    Raises
    ------
    DeviceError / SourceError
        When the source fails before delivering any frame (nothing is recorded then).
    """
    from drivers import PASS_STREAMS, streams_for_pass

    if frames is not None and frames < 1:
        raise AppFusionError(f"record: --frames must be at least 1, got {frames}")
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise AppFusionError(f"record: --seconds must be positive, got {seconds}")
    if pass_name is not None and pass_name not in PASS_STREAMS:
        raise AppFusionError(f"record: unknown pass {pass_name!r} (known: {', '.join(PASS_STREAMS)})")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise AppFusionError(f"record: {out} exists and is not an empty directory; refusing to overwrite it")
    res = RecordResult(out=out)
    writer = None
    t_first = None
    name = spec or getattr(source, "name", type(source).__name__)
    with _StopFlag() as stop, source:
        keep = streams
        if pass_name is not None and keep is None:
            keep = streams_for_pass(pass_name, source.caps)
        if keep is not None:
            missing = keep - set(source.caps.streams)
            if missing:
                raise SourceError(f"record: {name} has no {', '.join(sorted(missing))} stream "
                                  f"(it has {', '.join(sorted(source.caps.streams))})")
            if hasattr(source, "select_streams"):
                source.select_streams(keep)
        it = iter(source)
        bar = None
        if show_progress:
            from tqdm import tqdm
            import sys

            bar = tqdm(total=frames, desc="record", unit="frame", file=sys.stderr, dynamic_ncols=True,
                       disable=None)
        try:
            while True:
                if stop.set:
                    res.stopped = "Ctrl-C"
                    break
                try:
                    fr = next(it)
                except StopIteration:
                    res.stopped = "end of recording"
                    break
                except KeyboardInterrupt:
                    res.stopped = "Ctrl-C"
                    break
                except AppFusionError as e:
                    if writer is None:
                        raise
                    res.stopped = "device lost" if isinstance(e, DeviceError) else "source error"
                    res.error = str(e)
                    break
                if keep is not None and set(fr.streams) - keep:
                    fr = fr.replace(**{s: None for s in fr.streams if s not in keep})
                    if not fr.streams:
                        continue
                if pass_name is not None and fr.pass_name != pass_name:
                    fr = fr.replace(pass_name=pass_name)
                if t_first is None:
                    t_first = fr.timestamp
                if seconds is not None and fr.timestamp - t_first >= seconds:
                    res.stopped = "time limit"
                    break
                if writer is None:
                    writer = _open_writer(source, out, fr, depth_units_per_m, notes, name)
                writer.write(fr)
                res.frames = writer.n_frames
                res.seconds = fr.timestamp - t_first
                if bar is not None:
                    bar.update(1)
                if on_frame is not None:
                    on_frame(res.frames)
                if frames is not None and res.frames >= frames:
                    res.stopped = "frame limit"
                    break
        finally:
            if bar is not None:
                bar.close()
            if writer is not None:
                writer.close()
                res.counts = {k: v for k, v in writer.counts.items()}
            with_close = getattr(it, "close", None)
            if with_close is not None:
                with_close()
    return res


def _open_writer(source, out: Path, first, depth_units_per_m: float, notes: str, spec: str):
    from replay.session import SessionWriter

    meta = dict(source.meta)
    intr = {}
    src_intr = dict(source.intrinsics)
    for s in first.streams:
        fi = getattr(first, f"{s}_intrinsics") or src_intr.get(s)
        if fi is not None:
            intr[s] = fi
    em = meta.get("emitter_position_m") or (0.075, 0.0, 0.0)
    ir_bits = meta.get("ir_bits") or meta.get("streams", {}).get("ir", {}).get("bits") or 10
    extra = {"recorded_from": spec, "recorder": "appfusion record"}
    drv = {k: v for k, v in meta.items() if k not in ("depth_to_ir", "depth_to_rgb", "streams", "extra")}
    extra["source_meta"] = _json_safe(drv)
    return SessionWriter(out, device=str(meta.get("device", getattr(source, "name", "unknown"))), intrinsics=intr,
                         depth_to_ir=first.depth_to_ir, depth_to_rgb=first.depth_to_rgb,
                         depth_units_per_m=depth_units_per_m, rgb_encoding=first.rgb_encoding,
                         emitter_position_m=em, notes=notes, extra=extra, ir_bits=int(ir_bits))


def register(sub) -> None:
    p = sub.add_parser(
        "record", help="record a live device (or a recording) into an appfusion session",
        description="Records frames from a live depth camera (openni2, openni2:Dummy, openni2:URI, depthai, "
                    "depthai:MXID, depthai-replay:DIR) or from any recording `appfusion convert` reads, into a "
                    "crash-safe appfusion session. Ctrl-C or an unplugged device ends the recording cleanly: "
                    "the frames so far are kept and a summary line says why it stopped (exit status 1 when the "
                    "device was lost). A Kinect v1 cannot stream IR and RGB at once: record --pass geometry "
                    "(depth,ir) and --pass rgb (depth,rgb) one after the other.")
    p.add_argument("source", help="device name or recording path")
    p.add_argument("out", type=Path, help="session directory to create (must not exist or be empty)")
    p.add_argument("--frames", type=int, metavar="N", help="stop after N frames")
    p.add_argument("--seconds", type=float, metavar="S", help="stop after S seconds of frames")
    p.add_argument("--streams", metavar="LIST", help="streams to record, e.g. depth,ir or depth,rgb")
    p.add_argument("--pass", dest="pass_name", metavar="NAME",
                   help="scanning pass: geometry, rgb, environment, ir-calibration or scan (selects its streams "
                        "unless --streams is given)")
    p.add_argument("--emitter", choices=("on", "off"), help="switch the IR emitter before recording (if the "
                                                            "device can)")
    p.add_argument("--depth-units-per-m", type=float, default=5000.0, metavar="U",
                   help="depth PNG scale (default 5000, TUM)")
    p.add_argument("--notes", default="", help="free text stored in meta.json")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    streams = parse_streams(args.streams)
    src = open_source(args.source, streams)
    if args.emitter is not None:
        src = _EmitterOnOpen(src, args.emitter == "on")
    try:
        res = record_source(src, args.out, frames=args.frames, seconds=args.seconds, streams=streams,
                            pass_name=args.pass_name, depth_units_per_m=args.depth_units_per_m, notes=args.notes,
                            spec=args.source, show_progress=not args.quiet)
    except KeyboardInterrupt:
        print(f"record: interrupted before the first frame; nothing recorded in {args.out}")
        return 130
    print(res.summary())
    return EXIT_DEVICE_LOST if res.stopped in ("device lost", "source error") else 0


class _EmitterOnOpen:
    """Wrap a source so that its ``emitter`` control is set right after it opens."""

    def __init__(self, src, on: bool):
        self._src, self._on = src, on

    def __getattr__(self, name):
        return getattr(self._src, name)

    def __enter__(self):
        self._src.open()
        try:
            self._src.set_control("emitter", self._on)
        except BaseException:
            self._src.close()
            raise
        return self

    def __exit__(self, *exc):
        self._src.close()

    def __iter__(self):
        return iter(self._src)
