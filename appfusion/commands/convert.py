"""``appfusion convert SRC DST``: any supported recording to an appfusion session."""

from __future__ import annotations

from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("convert", help="convert a recording to an appfusion session",
                       description="Reads any supported recording (appfusion session, TUM RGB-D or Redwood/Open3D "
                                   "folder, Azure Kinect .mkv) and writes it as a new appfusion session "
                                   "(lossless PNGs, TUM-compatible index files; see docs/session-format.md).")
    p.add_argument("src", type=Path, help="recording to read")
    p.add_argument("dst", type=Path, help="session directory to create (must not exist or be empty)")
    p.add_argument("--skip-bad", action="store_true", help="skip damaged frames of SRC instead of stopping")
    p.add_argument("--depth-units-per-m", type=float, default=None, metavar="U",
                   help="depth PNG scale of DST (default: SRC's if it is a session, else 5000 as in TUM)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    from replay.open import open_recording
    from replay.session import copy_session

    src = open_recording(args.src, skip_bad=args.skip_bad)
    rep = copy_session(src, args.dst, depth_units_per_m=args.depth_units_per_m, show_progress=not args.quiet)
    counts = ", ".join(f"{s} {n}" for s, n in rep["counts"].items() if n)
    print(f"wrote {rep['frames']} frames ({counts}) to {args.dst} in {rep['seconds']:.2f} s")
    if rep["clipped_depth_pixels"]:
        print(f"warning: {rep['clipped_depth_pixels']} depth pixels beyond the 16-bit range were stored as invalid "
              f"(use a smaller --depth-units-per-m)")
    if rep["bad_frames"]:
        print(f"skipped {len(rep['bad_frames'])} bad frame(s) of {args.src}:")
        for p, ln, why in rep["bad_frames"][:10]:
            print(f"  {p}:{ln}: {why}" if ln else f"  {p}: {why}")
    return 0
