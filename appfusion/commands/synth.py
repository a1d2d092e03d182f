"""``appfusion synth``: render a synthetic scan session of a known object, with ground truth."""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_dir() -> Path:
    """Where precomputed light transport is cached: ``$APPFUSION_CACHE/synth`` or ``~/.cache/appfusion/synth``."""
    base = os.environ.get("APPFUSION_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "appfusion")
    return Path(base) / "synth"


def register(sub) -> None:
    p = sub.add_parser(
        "synth", help="render a synthetic scan session with ground truth",
        description="Render a complete synthetic scan session (our session format) of a known object: IR "
                    "calibration, mirror-ball environment, geometry (depth + IR) and RGB passes of a simulated "
                    "Kinect v1 (or an all-in-one device), plus a truth/ folder (poses, mesh, materials, "
                    "environment maps, IR model, relighting references) the engine never reads. "
                    "Deterministic for a seed. `appfusion synth list` lists the scenes.")
    p.add_argument("scene", help="object to scan (or 'list')")
    p.add_argument("out", nargs="?", type=Path, help="new session directory")
    p.add_argument("--frames", type=int, default=60, help="frames per object pass (default 60)")
    p.add_argument("--rgb-frames", type=int, default=None,
                   help="frames of the colour pass (kinect1: rgb; allinone: scan) on the same orbit, sampled more "
                        "densely (default: --frames); every other pass byte for byte as without it")
    p.add_argument("--size", default="640x480", help="image size WxH of every stream (default 640x480)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="kinect1", choices=["kinect1", "allinone"],
                   help="kinect1: IR and RGB in separate passes (default); allinone: depth+IR+RGB in every frame")
    p.add_argument("--detail", default="full", choices=["full", "test"], help="mesh resolution (test: ~5k triangles)")
    p.add_argument("--radius", type=float, default=0.6, help="orbit radius in metres (default 0.6)")
    p.add_argument("--no-references", action="store_true", help="skip the relighting reference renders")
    p.add_argument("--contact", type=Path, metavar="PNG", help="also write a contact sheet PNG")
    p.add_argument("--cache", type=Path, default=None,
                   help=f"light-transport cache folder (default {default_cache_dir()})")
    p.add_argument("--workers", type=int, default=None,
                   help="frame-rendering processes (default: 2 for big sessions on >= 2 cores, else 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    from appfusion.errors import AppFusionError
    from replay.synth import OBJECTS, render_session
    from replay.synth.objects import build_object

    if args.scene == "list":
        for name in OBJECTS:
            o = build_object(name, "test")
            mats = ", ".join(f"{m.name} ({m.lobe}, alpha {m.alpha:g})" for m in o.materials)
            print(f"{name:14s} {mats}")
        return 0
    if args.out is None:
        raise AppFusionError("synth: give an output directory: appfusion synth SCENE OUT")
    path = render_session(args.scene, args.out, frames=args.frames, size=args.size, seed=args.seed,
                          device=args.device, detail=args.detail, radius_m=args.radius,
                          references=not args.no_references, show_progress=not args.quiet,
                          cache_dir=args.cache or default_cache_dir(), workers=args.workers,
                          log=None if args.quiet else print, rgb_frames=args.rgb_frames)
    if args.contact:
        from replay.synth.contact import contact_sheet

        contact_sheet(path, args.contact)
        print(f"wrote {args.contact}")
    print(f"wrote {path}")
    return 0
