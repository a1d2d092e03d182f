"""``appfusion gui [SOURCE]``: the live scanning window (see docs/gui.md)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from ..errors import AppFusionError


def register(sub) -> None:
    p = sub.add_parser(
        "gui", help="the live scanning window (PySide6 + pyqtgraph)",
        description="Scan with live feedback: the RGB/IR/depth streams, the fused points coloured by "
                    "material cluster, rho_d, rho_s, alpha or a shaded preview, the environment map "
                    "filling in, each cluster's HBSAB with its Ward fit, fps/tracking/coverage figures and "
                    "what to do next. Paint cluster labels with a brush (paper §5.2), export and render. "
                    "SOURCE is a recording (session, TUM, Redwood folder or Azure .mkv) or a device name "
                    "(openni2, openni2:Dummy, depthai, ...); without it the window opens empty. Closing the "
                    "window mid-scan stops the engine and saves the scan so far to --out.")
    p.add_argument("source", nargs="?", help="recording path or device name")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--realtime", dest="realtime", action="store_true", default=True,
                   help="play recordings at their recorded rate (default)")
    g.add_argument("--fast", dest="realtime", action="store_false",
                   help="play recordings as fast as the engine goes")
    p.add_argument("--out", type=Path, default=None,
                   help="output folder (default ./appfusion-out/<source>-<time>)")
    p.add_argument("--record", type=Path, default=None, metavar="DIR",
                   help="live device: also record the frames into this new session folder")
    p.add_argument("--points", type=int, default=None, help="points sampled on the object (ScanConfig.n_points)")
    p.add_argument("--stride", type=int, default=None, help="use every n-th frame (ScanConfig.frame_stride)")
    p.add_argument("--skip-bad", action="store_true", help="skip damaged frames of a recording")
    p.add_argument("--no-start", dest="autostart", action="store_false",
                   help="open the source but wait for the Start button")
    p.set_defaults(func=run)


def _check_display() -> None:
    plat = os.environ.get("QT_QPA_PLATFORM", "")
    if sys.platform.startswith("linux") and not plat and not (
            os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise AppFusionError("gui: no display (DISPLAY is not set); run it on a desktop, or headless as "
                             "`xvfb-run -a appfusion gui ...`")


def run(args) -> int:
    _check_display()
    config = None
    if args.points is not None or args.stride is not None:
        from ..pipeline import ScanConfig

        kw = {}
        if args.points is not None:
            if args.points < 100:
                raise AppFusionError(f"gui: --points must be at least 100, got {args.points}")
            kw["n_points"] = args.points
        if args.stride is not None:
            if args.stride < 1:
                raise AppFusionError(f"gui: --stride must be at least 1, got {args.stride}")
            kw["frame_stride"] = args.stride
        config = ScanConfig(**kw)
    source = None
    if args.source:
        from ..gui.app import open_source

        source = open_source(args.source, skip_bad=args.skip_bad)
    from ..gui.app import run_gui

    return run_gui(source, out_dir=args.out, realtime=args.realtime, config=config, record_dir=args.record,
                   autostart=args.autostart)
