"""``appfusion scan``: run every pass of a recording and write mesh, textures and a report."""

from __future__ import annotations

from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "scan", help="scan a recording end to end: geometry, environment, materials; export and report",
        description="Runs the paper's passes (IR calibration, environment, geometry + IR, RGB) over a "
                    "recording and writes the mesh (glb/obj/ply), texture maps for rho_d, rho_s and alpha, "
                    "the cluster map, the environment map and report.html into --out.")
    p.add_argument("session", nargs="?", help="a recording: our session folder, TUM or Redwood folder, Azure .mkv")
    p.add_argument("--demo", action="store_true",
                   help="scan the bundled demo session (generated once by the synthetic scanner and cached)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default out/<session name>)")
    p.add_argument("--envmap", type=Path, help="reuse a saved environment map (.npz/.exr/.hdr) for the same markers")
    p.add_argument("--ir-profile", type=Path, help="reuse a saved IR device profile (JSON) instead of the session's")
    p.add_argument("--points", type=int, default=None, help="points sampled on the surface (default 100000)")
    p.add_argument("--clusters", type=int, default=None, help="number of specular clusters (default: automatic)")
    p.add_argument("--stride", type=int, default=1, help="use every n-th frame")
    p.add_argument("--ball-radius", type=float, default=None, help="mirror-ball radius in metres, if known")
    p.add_argument("--skip-bad", action="store_true", help="skip damaged frames instead of stopping")
    p.add_argument("--fresh", action="store_true", help="ignore checkpoints of an earlier run in --out")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    import shutil

    from appfusion.errors import AppFusionError
    from appfusion.pipeline import ScanConfig, run_scan

    if args.demo == bool(args.session):
        raise AppFusionError("give a SESSION to scan, or --demo (not both)")
    if args.demo:
        from replay.synth import demo_session

        print("demo: preparing the bundled demo session (first run renders it, later runs reuse the cache)")
        session = demo_session(Path("out/cache"))
    else:
        session = Path(args.session)
    out = args.out or Path("out") / session.name
    if args.fresh and (out / "state").exists():
        shutil.rmtree(out / "state")
    cfg = ScanConfig(frame_stride=args.stride, ball_radius_m=args.ball_radius, k_clusters=args.clusters)
    if args.points:
        cfg.n_points = args.points
    summary = run_scan(session, out, config=cfg, envmap=args.envmap, ir_profile=args.ir_profile,
                       skip_bad=args.skip_bad, progress=not args.no_progress, log=print)
    print(summary)
    return 0
