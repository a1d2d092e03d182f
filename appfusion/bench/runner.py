"""Runs the benchmark stages and writes the report (JSON and a table on stdout)."""

from __future__ import annotations

import importlib
import json
import os
import resource
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import METRICS
from .stages import STAGES


@dataclass
class BenchContext:
    """What a stage gets: where to work, how hard to try, and a shared cache of synthetic sessions."""

    workdir: Path
    quick: bool = True
    seed: int = 0
    cache: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)  # stage-specific figures (sweeps, timings)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MiB."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024.0 if sys.platform != "darwin" else r / 2**20


def run_bench(workdir: Path, quick: bool = True, stages: list[str] | None = None, seed: int = 0,
              log=print) -> dict[str, Any]:
    """Run the stages and return ``{"metrics": {...}, "stages": {...}, "extra": {...}}``."""
    workdir.mkdir(parents=True, exist_ok=True)
    ctx = BenchContext(workdir=workdir, quick=quick, seed=seed)
    values: dict[str, float | None] = {k: None for k in METRICS}
    stage_info: dict[str, Any] = {}
    for name in stages or STAGES:
        try:
            mod = importlib.import_module(f"appfusion.bench.stages.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"appfusion.bench.stages.{name}":
                stage_info[name] = {"status": "not built yet"}
                continue
            raise
        t0 = time.perf_counter()
        log(f"bench: stage {name} ...")
        try:
            got = mod.run(ctx) or {}
        except Exception as e:  # a failing stage is reported, the others still run
            stage_info[name] = {"status": "error", "error": f"{type(e).__name__}: {e}",
                                "traceback": traceback.format_exc(limit=5)}
            log(f"bench: stage {name} FAILED: {type(e).__name__}: {e}")
            continue
        unknown = set(got) - set(METRICS)
        if unknown:
            raise KeyError(f"bench stage {name} reported unknown metrics {sorted(unknown)}")
        values.update({k: (None if v is None else float(v)) for k, v in got.items()})
        stage_info[name] = {"status": "ok", "seconds": round(time.perf_counter() - t0, 2),
                            "metrics": sorted(got)}
    values["peak_rss_mb"] = round(peak_rss_mb(), 1)
    metrics = {k: {"value": values[k], "unit": u, "goal": g, "better": b} for k, (u, g, b) in METRICS.items()}
    return {"metrics": metrics, "stages": stage_info, "extra": ctx.extra, "quick": quick,
            "host": {"cpus": os.cpu_count()}}


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
        rows.append(f"{k:<29} {vs:<12} {m['unit']:<9} {gs:<10} {status}")
    return "\n".join(rows)


def write_json(report: dict[str, Any], path: Path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(report, indent=2, default=float))
    os.replace(tmp, path)
