"""``appfusion bench``: run time against error for every stage that exists."""

from __future__ import annotations

from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("bench", help="measure run time against error on synthetic sessions",
                       description="Runs each pipeline stage on synthetic sessions with ground truth and "
                                   "reports time and error per stage, per-stage time against its budget, "
                                   "sweeps of quality knobs with their Pareto fronts (is each default on the "
                                   "front?) and a Pareto plot. Metrics of stages not built yet are null.")
    p.add_argument("--quick", action="store_true", help="small sessions; finishes in under 2 minutes on 2 cores")
    p.add_argument("--json", metavar="FILE", type=Path, help="write the report as JSON")
    p.add_argument("--plot", metavar="FILE", type=Path,
                   help="write the Pareto plot (PNG) here; default <workdir>/pareto.png on the full bench, "
                        "none with --quick unless given")
    p.add_argument("--stage", action="append", help="run only this stage (repeatable)")
    p.add_argument("--workdir", type=Path, default=Path("out/bench"), help="scratch folder (default out/bench)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)


def run(args) -> int:
    from appfusion.bench.runner import format_stage_table, format_table, run_bench, write_json

    plot = args.plot
    if plot is None and not args.quick:
        plot = args.workdir / "pareto.png"
    report = run_bench(args.workdir, quick=args.quick, stages=args.stage, seed=args.seed, plot=plot)
    print(format_table(report))
    print()
    print(format_stage_table(report))
    if args.json:
        write_json(report, args.json)
        print(f"wrote {args.json}")
    failed = [k for k, s in report["stages"].items() if s.get("status") == "error"]
    return 1 if failed else 0
