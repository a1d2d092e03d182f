"""``appfusion scan``: run every pass of a recording (or of a live device) and write mesh, textures, report.

``appfusion scan SESSION`` scans a recording; ``appfusion scan --device NAME --out DIR`` scans a live
device headless: :class:`appfusion.pipeline.ScanRunner` records it pass by pass into
``DIR/live-session`` (crash-safe) and then processes that recording like any other. The device's
capability model decides the passes (:func:`drivers.live_pass_plan`): a Kinect v1 / PrimeSense,
which cannot stream IR and colour at once, records ``geometry`` and ``rgb`` one after the other, a
device that streams depth, IR and RGB together one combined ``scan`` pass. Passes advance after the
frame counts of ``--pass-frames`` or, on a terminal, when the user presses Enter; Ctrl-C ends the
recording early and what was recorded is still processed. See docs/hardware.md, "Scanning live".
"""

from __future__ import annotations

import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator

from appfusion.errors import AppFusionError
from appfusion.source import Source, WrappedSource

#: frames recorded per live pass when ``--pass-frames`` does not say (device at 30 fps). From the
#: paper's guidance: §6 averages "a number of" emitter-off IR frames (``DEFAULT_DARK_FRAMES``, 1 s)
#: and then views a white sheet from several distances (a 50 -> 120 cm sweep, ~9 s); §4.3 orbits the
#: mirror ball (30 s: one slow orbit at two heights); §4.1 / §5.1-5.2 orbit the object for geometry
#: and IR highlights, and §5.3 once more for colour (60 s each: Table 1 gives 1.6-4.2 min of geometry
#: and 1.3-2 min of rho_s capture with live feedback, a headless scan records one thorough orbit).
DEFAULT_PASS_FRAMES = {"ir-calibration": 300, "environment": 900, "geometry": 1800, "rgb": 1800, "scan": 1800}
#: emitter-off frames at the start of the ir-calibration pass (§6 background level)
DEFAULT_DARK_FRAMES = 30
#: printed marker sheet defaults (docs/conventions.md: circles of 2.5 cm radius, key circle 3.5 cm)
DEFAULT_MARKERS = {"radius_m": 0.025, "key_radius_m": 0.035, "layout": "square"}

#: what each pass gives the scan (for "not recorded: ..." messages)
PASS_PRODUCES = {
    "ir-calibration": "the IR profile (§6), without which there are no specular clusters or roughness",
    "environment": "the environment map (§4.3), without which rho_d and rho_s cannot be estimated",
    "geometry": "the geometry and the IR reflectometry (§4.1, §5.1-5.2)",
    "rgb": "rho_d and rho_s (§5.3)",
    "scan": "the geometry and the materials (§4.1, §5)",
}


def register(sub) -> None:
    p = sub.add_parser(
        "scan", help="scan a recording or a live device end to end: geometry, environment, materials; export and report",
        description="Runs the paper's passes (IR calibration, environment, geometry + IR, RGB) over a "
                    "recording, or over a live device (--device: recorded pass by pass into OUT/live-session, "
                    "then processed), and writes the mesh (glb/obj/ply), texture maps for rho_d, rho_s and "
                    "alpha, the cluster map, the environment map and report.html into --out.",
        epilog="Live: passes advance after --pass-frames frames, or on Enter when stdin is a terminal and "
               "--pass-frames is not given. Ctrl-C ends the recording; what was recorded is processed "
               "(Ctrl-C again stops the processing, keeping what is computed). Default frames per pass: "
               + ", ".join(f"{k}={v}" for k, v in DEFAULT_PASS_FRAMES.items())
               + f" (the first {DEFAULT_DARK_FRAMES} ir-calibration frames with the emitter off or covered).")
    p.add_argument("session", nargs="?", help="a recording: our session folder, TUM or Redwood folder, Azure .mkv")
    p.add_argument("--demo", action="store_true",
                   help="scan the bundled demo session (generated once by the synthetic scanner and cached)")
    p.add_argument("--device", metavar="NAME",
                   help="scan a live device: openni2, openni2:Dummy, openni2:URI, depthai, depthai:MXID, "
                        "depthai-replay:DIR (needs --out)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default out/<session name>)")
    p.add_argument("--envmap", type=Path, help="reuse a saved environment map (.npz/.exr/.hdr) for the same markers")
    p.add_argument("--ir-profile", type=Path, help="reuse a saved IR device profile (JSON) instead of the session's")
    p.add_argument("--points", type=int, default=None, help="points sampled on the surface (default 100000)")
    p.add_argument("--clusters", type=int, default=None, help="number of specular clusters (default: automatic)")
    p.add_argument("--stride", type=int, default=1, help="use every n-th frame")
    p.add_argument("--ball-radius", type=float, default=None, help="mirror-ball radius in metres, if known")
    p.add_argument("--mirror-reflectance", type=float, default=None,
                   help="reflectance of the mirror ball (chrome ~0.65; default: the session's, else 1.0)")
    p.add_argument("--ball-on-plane", choices=("auto", "yes", "no"), default=None,
                   help="the ball rests on the marker sheet (default: the session's setting, else auto)")
    p.add_argument("--normal-refine", type=int, default=None, metavar="ROUNDS",
                   help="rounds of specular normal refinement after the colour pass (default: 3 where the "
                        "object curves tighter than the fusion's voxel, else 0; 0 turns it off; where the "
                        "normals are cubic jet fits it starts from the points the fits describe worst). It moves "
                        "glossy points' normals to where the colour frames' highlights put them: for glossy "
                        "objects with sharp rims (synthetic pepper: relit error 0.0755 -> 0.064); a first "
                        "round whose moves mostly reach the largest tilt is undone, as on smooth capsules "
                        "(docs/rgb-pass.md §5f)")
    p.add_argument("--lobes", default=None, metavar="LIST",
                   help="specular lobes the IR fits may choose between per cluster, comma-separated: ward,ggx "
                        "(default) or ward (the paper's model only; docs/rgb-pass.md §5j)")
    p.add_argument("--texture-size", type=int, default=None, metavar="N",
                   help="side of the exported texture maps in texels (default 1024)")
    p.add_argument("--skip-bad", action="store_true", help="skip damaged frames instead of stopping")
    p.add_argument("--fresh", action="store_true", help="ignore checkpoints of an earlier run in --out")
    p.add_argument("--no-progress", action="store_true")
    g = p.add_argument_group("live scans (--device)")
    g.add_argument("--pass-frames", metavar="LIST",
                   help="frames per pass, e.g. ir-calibration=300,environment=900,geometry=1800,rgb=1800 "
                        "(passes not listed keep their default); the passes advance by these counts")
    g.add_argument("--dark-frames", type=int, default=None, metavar="N",
                   help=f"emitter-off frames at the start of the ir-calibration pass (default {DEFAULT_DARK_FRAMES})")
    g.add_argument("--marker-radius", type=float, default=None, metavar="M",
                   help=f"radius of the printed white circles in metres (default {DEFAULT_MARKERS['radius_m']})")
    g.add_argument("--key-radius", type=float, default=None, metavar="M",
                   help=f"radius of the larger key circle in metres (default {DEFAULT_MARKERS['key_radius_m']}; "
                        "0: four equal circles)")
    g.add_argument("--marker-side", type=float, default=None, metavar="M",
                   help="distance between neighbouring circle centres in metres (needed when the rgb pass is "
                        "separate, as on a Kinect v1: its poses come from the markers)")
    p.set_defaults(func=run)


def run(args) -> int:
    import shutil

    from appfusion.pipeline import ScanConfig, run_scan

    if sum(bool(x) for x in (args.session, args.demo, args.device)) != 1:
        raise AppFusionError("give a SESSION to scan, --demo, or --device NAME (exactly one of them)")
    if args.mirror_reflectance is not None and not 0 < args.mirror_reflectance <= 1:
        raise AppFusionError(f"--mirror-reflectance must be in (0, 1], got {args.mirror_reflectance}")
    on_plane = {"auto": "auto", "yes": True, "no": False, None: None}[args.ball_on_plane]
    cfg = ScanConfig(frame_stride=args.stride, ball_radius_m=args.ball_radius, k_clusters=args.clusters,
                     mirror_reflectance=args.mirror_reflectance, ball_on_plane=on_plane)
    if args.points is not None:
        cfg.n_points = args.points                          # checked by ScanRunner (>= 1)
    if args.normal_refine is not None:
        cfg.normal_refine_rounds = args.normal_refine       # checked by ScanRunner (>= 0)
    if args.lobes is not None:
        cfg.ir_lobes = tuple(x.strip() for x in args.lobes.split(",") if x.strip())   # checked by ScanRunner
    if args.texture_size is not None:
        cfg.texture_size = args.texture_size                # checked by ScanRunner ([16, 16384])
    live_only = [f for f, v in (("--pass-frames", args.pass_frames), ("--marker-radius", args.marker_radius),
                                ("--key-radius", args.key_radius), ("--marker-side", args.marker_side),
                                ("--dark-frames", args.dark_frames))
                 if v is not None]
    if live_only and not args.device:
        raise AppFusionError(f"{', '.join(live_only)}: for live scans (--device) only; a recording keeps the "
                             f"pass boundaries and markers it was recorded with")
    dark = DEFAULT_DARK_FRAMES if args.dark_frames is None else args.dark_frames
    if dark < 0:
        raise AppFusionError(f"--dark-frames must be 0 or more frames, got {args.dark_frames}")
    for flag, v, low in (("--marker-radius", args.marker_radius, False), ("--key-radius", args.key_radius, True),
                         ("--marker-side", args.marker_side, False)):
        if v is not None and not (math.isfinite(v) and (v >= 0 if low else v > 0)):
            raise AppFusionError(f"{flag} must be a {'non-negative' if low else 'positive'} length in metres, got {v}")
    if args.device:
        if args.out is None:
            raise AppFusionError("scan --device needs --out DIR (the live recording goes to DIR/live-session)")
        if args.fresh:
            raise AppFusionError("scan --device always starts a fresh scan; --fresh is for recordings")
        counts = parse_pass_frames(args.pass_frames)
        interactive = args.pass_frames is None and sys.stdin is not None and sys.stdin.isatty()
        markers = {k: v for k, v in (("radius_m", args.marker_radius), ("key_radius_m", args.key_radius),
                                     ("side_m", args.marker_side)) if v is not None}
        from drivers import open_device

        source = open_device(args.device)
        summary = scan_live(source, args.out, config=cfg, pass_frames=counts, dark_frames=dark,
                            interactive=interactive, markers=markers, envmap=args.envmap,
                            ir_profile=args.ir_profile, progress=not args.no_progress, spec=args.device)
        print(summary)
        return 0
    if args.demo:
        from replay.synth import demo_session

        print("demo: preparing the bundled demo session (first run renders it, later runs reuse the cache)")
        session = demo_session(Path("out/cache"))
    else:
        session = Path(args.session)
    out = args.out or Path("out") / session.name
    if args.fresh and (out / "state").exists():
        shutil.rmtree(out / "state")
    summary = run_scan(session, out, config=cfg, envmap=args.envmap, ir_profile=args.ir_profile,
                       skip_bad=args.skip_bad, progress=not args.no_progress, log=print)
    print(summary)
    return 0


# ------------------------------------------------------------------------------------------------
# live scans
# ------------------------------------------------------------------------------------------------
def parse_pass_frames(text: str | None) -> dict[str, int]:
    """``"geometry=600,rgb=600"`` -> the frames per pass, defaults (:data:`DEFAULT_PASS_FRAMES`) for the rest.

    Raises
    ------
    AppFusionError
        An unknown pass name, a count that is not a positive integer, or a malformed item.
    """
    counts = dict(DEFAULT_PASS_FRAMES)
    if text is None:
        return counts
    for item in (t.strip() for t in str(text).split(",")):
        if not item:
            continue
        name, eq, value = item.partition("=")
        name = name.strip()
        if not eq:
            raise AppFusionError(f"--pass-frames: expected PASS=FRAMES, got {item!r} (e.g. geometry=600)")
        if name not in DEFAULT_PASS_FRAMES:
            raise AppFusionError(f"--pass-frames: unknown pass {name!r} (passes: {', '.join(DEFAULT_PASS_FRAMES)})")
        try:
            n = int(value)
        except ValueError:
            n = 0
        if n < 1:
            raise AppFusionError(f"--pass-frames: {name} needs a positive whole number of frames, got {value!r}")
        counts[name] = n
    return counts


def live_steps(passes: list[str], counts: dict[str, int] | None, dark_frames: int = DEFAULT_DARK_FRAMES,
               ) -> list[tuple[str, int | None, bool | None]]:
    """The recording steps ``(pass, frames, emitter)`` of a live scan (see ``ScanRunner.set_live_plan``).

    The ``ir-calibration`` pass (paper §6) is two steps: ``dark_frames`` frames with the emitter off
    (switched off, or covered by the user on a Kinect v1: the background level), then the rest with it
    on (the white sheet at several distances). ``counts`` None gives steps without frame counts (the
    user advances them).
    """
    steps: list[tuple[str, int | None, bool | None]] = []
    for name in passes:
        n = None if counts is None else int(counts[name])
        if name == "ir-calibration":
            if dark_frames < 1:
                raise AppFusionError(f"--dark-frames must be at least 1 (the §6 background), got {dark_frames}")
            if n is not None and dark_frames >= n:
                raise AppFusionError(f"--dark-frames {dark_frames} leaves no white-sheet frames in an "
                                     f"ir-calibration pass of {n} frames")
            steps += [(name, dark_frames if n is not None else None, False),
                      (name, None if n is None else n - dark_frames, True)]
        else:
            steps.append((name, n, None))
    return steps


def step_guidance(step: tuple[str, int | None, bool | None], has_emitter_control: bool, caps=None) -> str:
    """What the user does during one live step (pipeline.GUIDANCE, with the §6 dark/sheet split);
    ``caps`` (the device's StreamCaps) names the streams of a combined ``scan`` pass."""
    from appfusion.pipeline import GUIDANCE

    name, _, emitter = step
    if name == "ir-calibration" and emitter is False:
        if has_emitter_control:
            return "IR calibration, background: the emitter is switched off; keep the camera still."
        return ("IR calibration, background: cover the IR emitter (the projector window) with paper or a "
                "hand and keep the camera still.")
    if name == "ir-calibration":
        return ("IR calibration, response: " + ("" if has_emitter_control else "uncover the emitter; ")
                + "hold a white sheet facing the camera and move it slowly from 50 to 120 cm.")
    if name == "scan":
        streams = "depth, IR and colour"
        if caps is not None:
            from drivers import streams_for_pass

            streams = " + ".join(s.upper() if s != "depth" else s for s in sorted(streams_for_pass(name, caps)))
        return GUIDANCE["geometry"] + f" ({streams} recorded together.)"
    return GUIDANCE.get(name, name)


class LiveDevice(WrappedSource):
    """A live device with the printed marker layout added to its meta (``extra.markers``), so that the
    live session records it (the tracker, the white balance and the RGB-pass poses read it).

    Everything else (streams, controls, ``select_pass``) is the device's.
    """

    is_recording = False

    def __init__(self, inner: Source, extra: dict[str, Any]):
        super().__init__(inner)
        self.extra = dict(extra)
        self.name = getattr(inner, "name", "device")

    @property
    def meta(self):
        m = dict(self.inner.meta or {})
        m["extra"] = {**dict(m.get("extra") or {}), **self.extra}
        return m

    def select_pass(self, name: str):
        select = getattr(self.inner, "select_pass", None)
        if callable(select):
            return select(name)
        return None


class _Interrupts:
    """SIGINT while a live scan runs: the first Ctrl-C ends the recording (or, once processing, stops
    it keeping what is computed), the next one during processing stops that, a third aborts."""

    def __init__(self, runner, say: Callable[[str], None]):
        self.runner, self.say = runner, say
        self.count = 0
        self.during_recording = False
        self._old = None

    def handler(self, signum, frame) -> None:
        self.count += 1
        recording = not getattr(self.runner.source, "is_recording", False)
        if self.count >= 3 or (self.count == 2 and not self.during_recording):
            raise KeyboardInterrupt
        if recording:
            self.during_recording = True
            self.say("Ctrl-C: recording stopped; processing what was recorded (Ctrl-C again stops the processing)")
        else:
            self.say("Ctrl-C: stopping the processing after the current frame; the result so far is kept")
        self.runner.stop()

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._old = signal.getsignal(signal.SIGINT)
            signal.signal(signal.SIGINT, self.handler)
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)


def _enter_thread(runner, steps, has_control: bool, say, lines=None, caps=None) -> threading.Thread:
    """Advance the live steps on each line read (Enter); after the last step, end the recording."""
    lines = lines if lines is not None else sys.stdin

    def work():
        for k in range(1, len(steps) + 1):
            line = lines.readline()
            if not line or getattr(runner.source, "is_recording", False):
                return  # stdin closed, or the recording already ended (Ctrl-C, device lost)
            if k == len(steps):
                say("Enter: recording finished; processing")
                runner.stop()
                return
            name, _, emitter = steps[k]
            runner.next_pass(name, emitter=emitter)
            say(f"[{k + 1}/{len(steps)}] {name}: {step_guidance(steps[k], has_control, caps)} Press Enter when done.")

    t = threading.Thread(target=work, name="appfusion-scan-enter", daemon=True)
    t.start()
    return t


def scan_live(source: Source, out: str | Path, config=None, pass_frames: dict[str, int] | None = None,
              dark_frames: int = DEFAULT_DARK_FRAMES, interactive: bool = False,
              markers: dict[str, float] | None = None, envmap=None, ir_profile=None, progress: bool = True,
              spec: str | None = None, log: Callable[[str], None] = print, lines=None) -> str:
    """``appfusion scan --device``: record a live source pass by pass, process it, export; a summary.

    Parameters
    ----------
    source : Source
        A live source (``is_recording`` False), not yet opened; opened, and closed once recorded.
    out : path-like
        Output folder; the recording goes to ``out/live-session`` (must not exist yet).
    config : ScanConfig, optional
    pass_frames : dict, optional
        Frames per pass (:func:`parse_pass_frames`); default :data:`DEFAULT_PASS_FRAMES`. Unused when
        ``interactive``.
    dark_frames : int
        Emitter-off frames at the start of ``ir-calibration`` (§6).
    interactive : bool
        Advance the passes when a line is read from ``lines`` (Enter on stdin) instead of by counts.
    markers : dict, optional
        ``radius_m`` / ``key_radius_m`` / ``side_m`` of the printed sheet, over the source's own
        ``extra.markers`` and :data:`DEFAULT_MARKERS`; ``key_radius_m`` 0 means no key circle.
    envmap, ir_profile : optional
        Reused environment map / IR profile: their passes are not recorded.
    progress : bool
        Print recording progress every few seconds.
    log : callable
        Receives the guidance and progress lines.

    Returns
    -------
    str
        Summary lines: what was recorded, the result, the files written, what could not be produced.

    Raises
    ------
    AppFusionError
        The device cannot be opened or scanned with the options given; or the recording cannot be
        processed, in one message naming what is missing (markers, IR, passes) and where the
        recording is kept.
    """
    from drivers import live_pass_plan
    from appfusion.pipeline import ScanConfig, ScanRunner

    out = Path(out)
    rec_path = out / "live-session"
    if rec_path.exists():
        raise AppFusionError(f"scan --device: {rec_path} already holds a recording; choose another --out or "
                             f"process it with `appfusion scan {rec_path} --out {out}`")
    if getattr(source, "is_recording", False):
        raise AppFusionError(f"scan --device: {getattr(source, 'name', source)} is a recording, not a live "
                             "device; scan it with `appfusion scan PATH`")
    if (out / "state").exists():
        import shutil

        shutil.rmtree(out / "state")  # checkpoints of another scan would be reused by mistake
    config = config or ScanConfig()
    t0 = time.perf_counter()
    source.open()
    try:
        src_meta = source.meta if isinstance(source.meta, dict) else {}
        mk = {**DEFAULT_MARKERS, **dict((src_meta.get("extra") or {}).get("markers") or {}), **dict(markers or {})}
        if not mk.get("key_radius_m"):
            mk["key_radius_m"] = None
        from appfusion.markers import marker_config_from_meta

        marker_config_from_meta({"markers": mk})  # bad sizes fail now, not after the recording
        caps = source.caps
        passes = live_pass_plan(caps, envmap=envmap is not None, ir_profile=ir_profile is not None)
        if "rgb" in passes and "geometry" in passes and not (mk.get("side_m") and mk.get("key_radius_m")):
            raise AppFusionError(
                f"scan --device: {getattr(source, 'name', 'the device')} records the rgb pass apart from the "
                "geometry (it cannot stream IR and colour at once), and the rgb frames take their poses from "
                "the printed markers: give --marker-side (distance between neighbouring circle centres, "
                "metres) and print the sheet with the larger key circle (--key-radius)")
        counts = None if interactive else (pass_frames or dict(DEFAULT_PASS_FRAMES))
        steps = live_steps(passes, counts, dark_frames)
        has_control = "emitter" in (source.controls or {})
        dev = LiveDevice(source, {"markers": mk}).open()  # the device itself is open already
        runner = ScanRunner(dev, out, config=config, envmap=envmap, ir_profile=ir_profile, log=log,
                            progress=progress)  # loads --envmap / --ir-profile: bad files fail here
    except BaseException:
        source.close()
        raise
    name = getattr(source, "name", spec or "device")
    log(f"live scan of {name}: passes {', '.join(passes)} "
        f"(streams together: {' | '.join('+'.join(sorted(g)) for g in caps.together)}); recording to {rec_path}")
    if interactive:
        runner.next_pass(steps[0][0], emitter=steps[0][2])
        log(f"[1/{len(steps)}] {steps[0][0]}: {step_guidance(steps[0], has_control, caps)} Press Enter when done.")
        _enter_thread(runner, steps, has_control, log, lines, caps)
    else:
        runner.set_live_plan(steps)
        log("passes advance by frame counts: "
            + ", ".join(f"{n} {f} frames" + ("" if e is None else f" (emitter {'on' if e else 'off'})")
                        for n, f, e in steps))
        _announce_steps(runner, steps, has_control, log, caps)
    if progress:
        _progress_lines(runner, log)
    failure = None
    with _Interrupts(runner, log) as ints:
        try:
            res = runner.run()
        except AppFusionError as e:
            source.close()
            try:  # the geometry exists: keep the scan so far, say what stopped it
                res = runner.result()
            except AppFusionError:
                raise AppFusionError(diagnose_live(rec_path, e, out, envmap=envmap is not None,
                                                   ir_profile=ir_profile is not None)) from None
            failure = e
            res.save(out / "result.npz")
            log(f"live scan: processing stopped early: {e}; exporting the scan so far")
        finally:
            source.close()
        files = runner.export(out)
    recorded = _recorded_passes(rec_path)
    lines_out = [f"live scan of {name}: recorded " + ", ".join(f"{k} {v} frames" for k, v in recorded.items())
                 + f" into {rec_path}" + ("; stopped by Ctrl-C" if ints.during_recording else ""),
                 f"result: {len(res.positions)} points, {res.n_clusters} cluster(s), alpha = "
                 + ", ".join(f"{a:.3f}" for a in res.alpha) + f"; {time.perf_counter() - t0:.1f} s",
                 f"wrote {files['glb']}, {files['obj']}, {files['ply']}, report {files['report']}"]
    missing = [f"{p}: {PASS_PRODUCES[p]}" for p in passes if p not in recorded]
    if missing:
        lines_out.append("not recorded: " + "; ".join(missing))
    not_made = [what for what, src in (("rho_d and rho_s", res.info.get("rho_d_source", "")),
                                       ("roughness and specular clusters", res.info.get("alpha_source", "")))
                if str(src).startswith("not estimated")]
    if not_made:
        lines_out.append("could not produce: " + ", ".join(not_made)
                         + (f" ({failure})" if failure is not None else " (see the notes above and in the report)"))
    (out / "summary.txt").write_text("\n".join(lines_out) + "\n")
    return "\n".join(lines_out)


def _announce_steps(runner, steps, has_control: bool, log, caps=None) -> None:
    """Print each step's guidance when the recording reaches it (frame-count mode)."""
    state = {"gen": None}

    def on_snap(snap) -> None:
        ctl = runner._ctl
        gen = ctl.live_gen
        if gen == state["gen"] or getattr(runner.source, "is_recording", False):
            return
        state["gen"] = gen
        done = len(steps) - len(ctl.live_plan)
        step = steps[done - 1] if 0 < done <= len(steps) else None
        if step is not None:
            log(f"[{done}/{len(steps)}] {step[0]} ({step[1]} frames): {step_guidance(step, has_control, caps)}")

    runner.subscribe(on_snap)


def _progress_lines(runner, log, every_s: float = 3.0) -> None:
    """A line every few seconds while recording: the pass and the frames recorded so far."""
    state = {"t": time.monotonic()}

    def on_snap(snap) -> None:
        if getattr(runner.source, "is_recording", False):
            return
        now = time.monotonic()
        if now - state["t"] >= every_s:
            state["t"] = now
            left = runner._ctl.live_left
            log(f"recording {snap.stage}: {snap.frame} frames so far"
                + ("" if left is None else f", {left} left in this step"))

    runner.subscribe(on_snap)


def _recorded_passes(rec_path: Path) -> dict[str, int]:
    from appfusion.pipeline import plan_passes
    from replay.session import SessionReader

    try:
        return {k: b - a for k, (a, b) in plan_passes(SessionReader(rec_path)).items()}
    except AppFusionError:
        return {}


def diagnose_live(rec_path: Path, err: BaseException, out: Path, envmap: bool = False, ir_profile: bool = False,
                  sample: int = 8) -> str:
    """One message for a live scan that could not be processed: what the recording lacks (markers in
    view, IR stream, IR calibration, RGB, passes), the first error met, and where the recording is kept.

    Marker visibility is checked on up to ``sample`` evenly spaced frames of each pass; ``envmap`` /
    ``ir_profile`` say that the environment map / IR profile were given (their passes are not missing).
    """
    import numpy as np

    from appfusion.markers import detect_markers, marker_config_from_meta
    from appfusion.pipeline import plan_passes
    from replay.session import SessionReader

    if not (rec_path / "meta.json").exists():
        return f"live scan: {err} (nothing was recorded)"
    try:
        r = SessionReader(rec_path)
        ranges = plan_passes(r)
    except AppFusionError as e:
        return f"live scan: {err}; the recording in {rec_path} cannot be read back either: {e}"
    missing: list[str] = []
    cfg = marker_config_from_meta(r.meta)
    checked, best = 0, 0
    for a, b in ranges.values():
        for i in np.unique(np.linspace(a, b - 1, min(sample, b - a)).round().astype(int)):
            f = r.frame(int(i))
            if f.depth is None or (f.ir is None and f.rgb is None):
                continue
            checked += 1
            try:
                best = max(best, int(detect_markers(f, cfg).n))
            except AppFusionError:
                continue
            if best >= 4:
                break
        if best >= 4:
            break
    if checked and best < 4:
        missing.append(f"no frame shows the four white circles (checked {checked} frames, at most {best} "
                       f"circle(s) seen; radius {cfg.radius_m * 1000:.0f} mm): tracking, the object box, white "
                       "balance and the environment map are all anchored to them (§4.1-4.3); put the printed "
                       "sheet around the object, in view")
    streams = r.caps.streams
    if "ir" not in streams:
        missing.append("the device has no IR stream: no IR calibration (§6), specular clusters or roughness "
                       "(§5.1-5.2)")
    elif "ir-calibration" not in ranges and not ir_profile:
        missing.append("no ir-calibration pass (§6): give --ir-profile or record it")
    if "rgb" not in streams:
        missing.append("the device has no RGB stream: no environment map, rho_d or rho_s")
    elif "environment" not in ranges and not envmap:
        missing.append("no environment pass (§4.3): give --envmap or record it")
    if not ({"geometry", "scan"} & set(ranges)):
        missing.append("no geometry or scan pass: nothing to reconstruct")
    counts = ", ".join(f"{k} {b - a}" for k, (a, b) in ranges.items()) or "no frames"
    what = "; ".join(missing) if missing else "see the error"
    return (f"live scan could not be processed: {what}. First error: {err}. The recording is kept in {rec_path} "
            f"({counts} frames); process it again with `appfusion scan {rec_path} --out {out}`")
