"""Runs the benchmark stages and writes the report (JSON, tables on stdout, the Pareto plot).

The report's layout and the sweep contract are described in :mod:`appfusion.bench`.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import resource
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from . import METRICS
from .pareto import BenchError, analyse, plot_sweeps, validate_sweep
from .stages import STAGES

#: the whole ``--quick`` bench must finish within this, seconds (issue: 2 minutes on 2 cores)
QUICK_TOTAL_BUDGET_S = 120.0
#: default per-stage budgets, seconds, (quick, full); a stage module may override with ``BUDGET_S``.
#: The quick budgets add up to less than QUICK_TOTAL_BUDGET_S.
STAGE_BUDGETS_S: dict[str, tuple[float, float]] = {
    "synth": (10.0, 120.0),
    "geometry": (25.0, 600.0),
    "lighting": (15.0, 180.0),
    "ir": (15.0, 300.0),
    "rgb": (15.0, 300.0),
    "scan": (45.0, 900.0),
    "stability": (15.0, 180.0),
}
#: budget of a stage missing from STAGE_BUDGETS_S, (quick, full)
DEFAULT_BUDGET_S = (10.0, 300.0)


@dataclass
class BenchContext:
    """What a stage gets: where to work, how hard to try, and a shared cache of synthetic sessions.

    Attributes
    ----------
    workdir : Path
        Scratch folder of the bench.
    quick : bool
        Small inputs (the whole ``--quick`` bench finishes in under 2 minutes on 2 cores).
    seed : int
        Random seed for the synthetic inputs.
    cache : dict
        Shared between stages (e.g. synthetic sessions built once).
    extra : dict
        Stage-specific figures, ``extra[STAGE] = {...}``; sweeps go to ``extra["sweeps"]`` (see
        :meth:`add_sweep`).
    budget_s : float or None
        Time budget of the running stage, seconds (set by the runner before each stage).
    stage : str or None
        Name of the running stage.
    log : callable
        Progress lines and warnings (the runner's ``log``).
    notes : dict
        ``{metric: text}`` set with :meth:`note`; the report's ``"notes"``.
    """

    workdir: Path
    quick: bool = True
    seed: int = 0
    cache: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)  # stage-specific figures (sweeps, timings)
    budget_s: float | None = None
    stage: str | None = None
    started: float = field(default_factory=time.perf_counter)
    log: Callable[[str], Any] = print
    notes: dict[str, str] = field(default_factory=dict)

    def note(self, metric: str, text: str) -> None:
        """Say how a reported metric was measured where it differs from its definition (report ``notes``)."""
        if metric not in METRICS:
            raise BenchError(f"bench stage {self.stage or '?'}: note for unknown metric {metric!r}")
        self.notes[metric] = str(text)

    def time_left(self) -> float:
        """Seconds of the running stage's budget still left (``inf`` without a budget)."""
        if self.budget_s is None:
            return math.inf
        return self.budget_s - (time.perf_counter() - self.started)

    def add_sweep(self, knob: str, metric: str, default: Any, points: list[dict[str, Any]],
                  note: str | None = None) -> dict[str, Any]:
        """Record a time-against-error sweep of one quality knob (contract in :mod:`appfusion.bench`).

        Parameters
        ----------
        knob : str
            Name of the knob, unique over all stages (e.g. ``"hbsab_n"``).
        metric : str
            What the error measures (a :data:`~appfusion.bench.METRICS` name where one fits).
        default : number or str
            The engine's default value of the knob; must be one of the points' values.
        points : list of dict
            ``{"value": v, "ms_per_frame": t, "error": e}`` per setting; ``t`` in ms (>= 0), ``e`` >= 0
            or ``None`` where the setting failed.
        note : str, optional
            What the time and the error cover.

        Returns
        -------
        dict
            The validated sweep, as stored in ``extra["sweeps"][knob]``.

        Raises
        ------
        BenchError
            The sweep breaks the contract, the default is not among the values, or another stage
            already swept ``knob``.
        """
        where = f"bench stage {self.stage or '?'}"
        sw = validate_sweep(knob, {"metric": metric, "default": default, "points": points, "note": note}, where)
        if all(p["value"] != sw["default"] for p in sw["points"]):
            raise BenchError(f"{where}: sweep {knob!r}: the default {sw['default']!r} is not among the values "
                             f"{[p['value'] for p in sw['points']]}; measure it too")
        sweeps = self.extra.setdefault("sweeps", {})
        if knob in sweeps:
            raise BenchError(f"{where}: sweep {knob!r} was already reported (knob names are global)")
        sweeps[knob] = sw
        return sw


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MiB."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024.0 if sys.platform != "darwin" else r / 2**20


def stage_budget(name: str, mod: Any, quick: bool) -> float:
    """Time budget of a stage, seconds: the module's ``BUDGET_S = (quick, full)`` or the runner's default."""
    b = getattr(mod, "BUDGET_S", None) or STAGE_BUDGETS_S.get(name, DEFAULT_BUDGET_S)
    return float(b[0] if quick else b[1])


def _clean_value(name: str, stage: str, v: Any, warnings: list[str]) -> float | None:
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise BenchError(f"bench stage {stage}: metric {name} is not a number: {v!r}") from None
    if not math.isfinite(f):
        warnings.append(f"metric {name} was {f} (reported as null)")
        return None
    return f


def run_bench(workdir: Path, quick: bool = True, stages: list[str] | None = None, seed: int = 0,
              log: Callable[[str], Any] = print, plot: Path | str | None = None) -> dict[str, Any]:
    """Run the stages and return the report (layout in :mod:`appfusion.bench`).

    Parameters
    ----------
    workdir : Path
        Scratch folder (created).
    quick : bool
        Small inputs; per-stage budgets from the first column of :data:`STAGE_BUDGETS_S`.
    stages : list of str, optional
        Stage names to run (default: all of :data:`~appfusion.bench.stages.STAGES`).
    seed : int
        Random seed passed to the stages.
    log : callable
        Receives progress lines and warnings.
    plot : path, optional
        Write the Pareto plot of the sweeps there (PNG); skipped with a warning when no stage reported
        a sweep.

    Returns
    -------
    dict
        ``{"metrics", "notes", "stages", "sweeps", "defaults_on_front", "extra", "quick", "seconds",
        "budget_s", "plot", "host"}``.
    """
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    ctx = BenchContext(workdir=workdir, quick=quick, seed=seed, log=log)
    values: dict[str, float | None] = {k: None for k in METRICS}
    stage_info: dict[str, Any] = {}
    sweep_stage: dict[str, str] = {}
    t_all = time.perf_counter()
    budget_total = 0.0
    for name in stages or STAGES:
        try:
            mod = importlib.import_module(f"appfusion.bench.stages.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"appfusion.bench.stages.{name}":
                if name not in STAGES:
                    raise BenchError(f"bench: unknown stage {name!r}; the stages are {', '.join(STAGES)}") from None
                stage_info[name] = {"status": "not built yet"}
                continue
            raise
        budget = stage_budget(name, mod, quick)
        budget_total += budget
        ctx.stage, ctx.budget_s = name, budget
        before = set(ctx.extra.get("sweeps", {}))
        notes_before = set(ctx.notes)
        log(f"bench: stage {name} (budget {budget:g} s) ...")
        ctx.started = t0 = time.perf_counter()
        warnings: list[str] = []
        try:
            got = mod.run(ctx) or {}
            if not isinstance(got, dict):
                raise BenchError(f"bench stage {name}: run() must return a dict of metrics, got {type(got).__name__}")
            unknown = set(got) - set(METRICS)
            if unknown:
                raise BenchError(f"bench stage {name} reported unknown metrics {sorted(unknown)}: add them to "
                                 "appfusion.bench.METRICS or put them in ctx.extra")
            clean = {k: _clean_value(k, name, v, warnings) for k, v in got.items()}
        except Exception as e:  # a failing stage is reported, the others still run
            secs = time.perf_counter() - t0
            stage_info[name] = {"status": "error", "error": f"{type(e).__name__}: {e}",
                                "traceback": traceback.format_exc(limit=5), "seconds": round(secs, 2),
                                "budget_s": budget, "over_budget": secs > budget}
            log(f"bench: stage {name} FAILED after {secs:.1f} s: {type(e).__name__}: {e}")
            for k in set(ctx.extra.get("sweeps", {})) - before:   # half-reported sweeps are dropped
                del ctx.extra["sweeps"][k]
            for k in set(ctx.notes) - notes_before:               # so are its notes
                del ctx.notes[k]
            continue
        secs = time.perf_counter() - t0
        values.update(clean)
        for k in set(ctx.extra.get("sweeps", {})) - before:
            sweep_stage[k] = name
        info = {"status": "ok", "seconds": round(secs, 2), "budget_s": budget, "over_budget": secs > budget,
                "metrics": sorted(got), "peak_rss_mb": round(peak_rss_mb(), 1)}
        if warnings:
            info["warnings"] = warnings
        stage_info[name] = info
        if secs > budget:
            log(f"bench: WARNING: stage {name} took {secs:.1f} s, over its {budget:g} s budget"
                + (" (--quick)" if quick else ""))
    total = time.perf_counter() - t_all
    if quick and total > QUICK_TOTAL_BUDGET_S:
        log(f"bench: WARNING: --quick took {total:.1f} s, over its {QUICK_TOTAL_BUDGET_S:g} s budget")

    # sweeps: validated, tagged with their stage, fronts and default checks
    extra = dict(ctx.extra)
    raw = extra.pop("sweeps", {}) or {}
    sweeps: dict[str, Any] = {}
    for knob, sw in raw.items():
        st = sweep_stage.get(knob, "?")
        try:
            sweeps[knob] = validate_sweep(knob, sw, f"bench stage {st}")
        except BenchError as e:
            log(f"bench: WARNING: {e} (sweep dropped)")
            if st in stage_info:
                stage_info[st].setdefault("warnings", []).append(str(e))
            continue
        sweeps[knob]["stage"] = st
    ana = analyse(sweeps)
    for knob, sw in sweeps.items():
        sw["front"] = ana["fronts"][knob]
        sw["default_on_front"] = ana["defaults_on_front"][knob]
        if sw["default_on_front"] is False:
            log(f"bench: WARNING: the default {sw['default']!r} of {knob} is not on the measured Pareto front "
                f"(front: {sw['front']})")
    plot_path = None
    if plot is not None:
        if sweeps:
            plot_path = str(plot_sweeps(sweeps, plot, title=f"appfusion bench{' --quick' if quick else ''}: "
                                                            "time against error"))
            log(f"bench: wrote Pareto plot {plot_path}")
        else:
            log("bench: no stage reported a sweep: no Pareto plot")

    values["peak_rss_mb"] = round(peak_rss_mb(), 1)
    metrics = {k: {"value": values[k], "unit": u, "goal": g, "better": b} for k, (u, g, b) in METRICS.items()}
    return {"metrics": metrics, "notes": dict(ctx.notes), "stages": stage_info, "sweeps": sweeps,
            "defaults_on_front": ana["defaults_on_front"], "pareto_tolerance": {"time": ana["time_tol"],
                                                                                "error": ana["err_tol"]},
            "extra": extra, "quick": quick, "seconds": round(total, 2), "budget_s": budget_total,
            "plot": plot_path, "host": {"cpus": os.cpu_count(), "load_avg_1min": _loadavg()}}


def _loadavg() -> float | None:
    try:
        return round(os.getloadavg()[0], 2)
    except (OSError, AttributeError):
        return None


def format_table(report: dict[str, Any]) -> str:
    """Human-readable table of the metrics, with a mark where a goal is met (ok) or missed (MISS)."""
    rows = ["metric                        value        unit      goal       status"]
    for k, m in report["metrics"].items():
        v, g = m["value"], m["goal"]
        if v is None:
            status, vs = "-", "null"
        else:
            vs = f"{v:.4g}"
            if g is None:
                status = ""
            else:
                ok = v <= g if m["better"] == "lower" else v >= g
                status = "ok" if ok else "MISS"
        gs = "" if g is None else f"{'<=' if m['better'] == 'lower' else '>='}{g:g}"
        mark = " *" if k in report.get("notes", {}) else ""
        rows.append(f"{k:<29} {vs:<12} {m['unit']:<9} {gs:<10} {status}{mark}".rstrip())
    for k, text in report.get("notes", {}).items():
        rows.append(f"* {k}: {text}")
    return "\n".join(rows)


def format_stage_table(report: dict[str, Any]) -> str:
    """Per-stage time report: status, seconds against budget, and the sweeps with their default checks."""
    rows = ["stage        status          seconds   budget_s  note"]
    for k, s in report["stages"].items():
        secs = s.get("seconds")
        b = s.get("budget_s")
        note = ""
        if s.get("over_budget"):
            note = "OVER BUDGET"
        if s.get("status") == "error":
            note = (note + " " + s.get("error", "")).strip()[:90]
        elif s.get("warnings"):
            note = (note + " " + "; ".join(s["warnings"])).strip()[:90]
        rows.append(f"{k:<12} {s.get('status', '?'):<15} {'' if secs is None else f'{secs:.1f}':<9} "
                    f"{'' if b is None else f'{b:g}':<9} {note}")
    total = report.get("seconds")
    if total is not None:
        rows.append(f"{'total':<12} {'':<15} {total:<9.1f} {report.get('budget_s', 0):<9g}"
                    + (f" (--quick limit {QUICK_TOTAL_BUDGET_S:g} s)" if report.get("quick") else ""))
    if report.get("sweeps"):
        rows.append("")
        rows.append("sweep (stage)                     default      on front  front (fastest first)")
        for knob, sw in report["sweeps"].items():
            on = {True: "yes", False: "NO", None: "?"}[sw.get("default_on_front")]
            rows.append(f"{knob + ' (' + sw.get('stage', '?') + ')':<33} {str(sw['default']):<12} {on:<9} "
                        f"{sw.get('front')}")
    return "\n".join(rows)


def _json_ready(o: Any) -> Any:
    """Plain JSON values: numpy scalars and arrays to Python, non-finite floats to None, paths to str."""
    if isinstance(o, dict):
        return {str(k): _json_ready(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_json_ready(v) for v in o]
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "tolist") and not isinstance(o, (str, bytes)):   # numpy arrays and scalars
        return _json_ready(o.tolist())
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if o is None or isinstance(o, (bool, int, float, str)):
        return o
    return str(o)


def write_json(report: dict[str, Any], path: Path) -> None:
    """Write the report as strict JSON (no NaN: non-finite numbers become null), atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(_json_ready(report), indent=2, allow_nan=False))
    os.replace(tmp, path)
