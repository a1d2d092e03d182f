"""Pareto fronts of run time against error for the bench's quality-knob sweeps (issue "Run time against
error").

A sweep (contract in :mod:`appfusion.bench`) measures, for several values of one quality knob, the time
per frame and the error against ground truth. Both are "lower is better", so a setting is worth having
only if no other setting is at least as fast *and* at least as accurate: the set of such settings is the
Pareto front. The issue asks that every knob's default sits on the measured front.

Timings on a shared 2-core machine are noisy, so the default is judged with a tolerance
(:func:`default_on_front`): it counts as on the front if no measured point dominates it after its time
is shrunk by ``time_tol`` (10 %) and its error by ``err_tol`` (0 by default), i.e. a point dominates the
default only if it is at least as accurate and more than 10 % faster, or more accurate and more than
10 % faster-or-equal. This is multiplicative epsilon-dominance (Laumanns et al. 2002).

:func:`plot_sweeps` draws one subplot per knob (time on x, error on y, the front as a staircase, the
default marked) with matplotlib's Agg backend.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import Any, Iterable, Mapping

from ..errors import AppFusionError

#: relative timing tolerance used when judging whether a default is on the front (timing noise)
TIME_TOL = 0.10
#: relative error tolerance (errors of deterministic synthetic runs are reproducible: none by default)
ERR_TOL = 0.0


class BenchError(AppFusionError):
    """A bench stage reported something that does not follow the bench's contract."""


def _finite_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(float(x))


def _scalar(x: Any) -> Any:
    """A knob value as a JSON scalar (numpy scalars to Python), or raise."""
    if hasattr(x, "item") and not isinstance(x, (str, bytes)):
        try:
            x = x.item()
        except (TypeError, ValueError):
            pass
    if isinstance(x, bool) or x is None or isinstance(x, (int, float, str)):
        return x
    raise TypeError(type(x).__name__)


def validate_sweep(knob: str, sweep: Mapping[str, Any], where: str = "bench") -> dict[str, Any]:
    """Check one sweep against the contract and return a normalised copy.

    Parameters
    ----------
    knob : str
        The quality knob's name (the key under ``ctx.extra["sweeps"]``).
    sweep : mapping
        ``{"metric": str, "default": value, "points": [{"value", "ms_per_frame", "error"}, ...]}`` and
        optionally ``"note"`` (what the time and the error measure). ``ms_per_frame`` must be a finite
        number >= 0 (milliseconds); ``error`` a finite number >= 0, or ``None`` where that setting failed.
    where : str
        Prefix of error messages (the stage that reported the sweep).

    Returns
    -------
    dict
        ``{"metric", "default", "points", "note"}`` with plain Python numbers.

    Raises
    ------
    BenchError
        Naming the knob and the first thing that is wrong.
    """
    pre = f"{where}: sweep {knob!r}"
    if not isinstance(knob, str) or not knob:
        raise BenchError(f"{where}: a sweep's knob must be a non-empty string, got {knob!r}")
    if not isinstance(sweep, Mapping):
        raise BenchError(f"{pre} must be a dict, got {type(sweep).__name__}")
    missing = [k for k in ("metric", "default", "points") if k not in sweep]
    if missing:
        raise BenchError(f"{pre} lacks {', '.join(missing)}")
    metric = sweep["metric"]
    if not isinstance(metric, str) or not metric:
        raise BenchError(f"{pre}: 'metric' must name the error measure, got {metric!r}")
    try:
        default = _scalar(sweep["default"])
    except TypeError as e:
        raise BenchError(f"{pre}: the default must be a number or a string, got {e}") from None
    pts = sweep["points"]
    if isinstance(pts, (str, bytes)) or not isinstance(pts, Iterable):
        raise BenchError(f"{pre}: 'points' must be a list of dicts")
    out = []
    for i, p in enumerate(pts):
        if not isinstance(p, Mapping) or not {"value", "ms_per_frame", "error"} <= set(p):
            raise BenchError(f"{pre}: point {i} must be a dict with value, ms_per_frame and error, got {p!r}")
        try:
            v = _scalar(p["value"])
        except TypeError as e:
            raise BenchError(f"{pre}: point {i}: value must be a number or a string, got {e}") from None
        t, e = p["ms_per_frame"], p["error"]
        t = t.item() if hasattr(t, "item") else t
        e = e.item() if hasattr(e, "item") else e
        if not _finite_number(t) or t < 0:
            raise BenchError(f"{pre}: point {i} (value {v!r}): ms_per_frame must be a finite number >= 0, got {t!r}")
        if e is not None and (not _finite_number(e) or e < 0):
            raise BenchError(f"{pre}: point {i} (value {v!r}): error must be a finite number >= 0 or None, got {e!r}")
        out.append({"value": v, "ms_per_frame": float(t), "error": None if e is None else float(e)})
    if len(out) < 1:
        raise BenchError(f"{pre} has no points")
    note = sweep.get("note")
    return {"metric": metric, "default": default, "points": out, "note": None if note is None else str(note)}


def _dominates(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """``a`` = (time, error) Pareto-dominates ``b`` (both lower better)."""
    return a[0] <= b[0] and a[1] <= b[1] and (a[0] < b[0] or a[1] < b[1])


def pareto_front(points: list[Mapping[str, Any]]) -> list[int]:
    """Indices of the non-dominated points (time ``ms_per_frame`` and ``error``, both lower better).

    Points whose error is ``None`` (failed settings) are never on the front. Equal points are all kept.

    Parameters
    ----------
    points : list of dict
        Each with ``ms_per_frame`` and ``error``.

    Returns
    -------
    list of int
        Indices into ``points``, sorted by increasing time (then error).
    """
    ok = [i for i, p in enumerate(points) if p.get("error") is not None]
    te = {i: (float(points[i]["ms_per_frame"]), float(points[i]["error"])) for i in ok}
    # sort by (time, error); a point is on the front iff its error is below every error seen so far
    # among strictly faster-or-equal points that dominate it -> O(n log n) sweep
    order = sorted(ok, key=lambda i: te[i])
    front, best_err = [], math.inf
    k = 0
    while k < len(order):
        j = k                                       # group points with the same time
        while j < len(order) and te[order[j]][0] == te[order[k]][0]:
            j += 1
        group = order[k:j]
        gmin = te[group[0]][1]
        for i in group:
            if te[i][1] == gmin and gmin < best_err:
                front.append(i)
        best_err = min(best_err, gmin)
        k = j
    return front


def default_index(sweep: Mapping[str, Any]) -> int | None:
    """Index of the point measured at the default value, or ``None`` if the default was not measured."""
    for i, p in enumerate(sweep["points"]):
        if p["value"] == sweep["default"]:
            return i
    return None


def default_on_front(sweep: Mapping[str, Any], time_tol: float = TIME_TOL, err_tol: float = ERR_TOL) -> bool | None:
    """Whether the knob's default sits on the measured Pareto front, within noise.

    The default's point ``(t, e)`` is replaced by ``(t / (1 + time_tol), e / (1 + err_tol))`` and
    checked for Pareto domination by every other measured point (multiplicative epsilon-dominance).

    Parameters
    ----------
    sweep : dict
        A validated sweep (:func:`validate_sweep`).
    time_tol, err_tol : float
        Relative tolerances on time and error (>= 0).

    Returns
    -------
    bool or None
        ``None`` when the default value was not among the points or its error is ``None``.
    """
    if time_tol < 0 or err_tol < 0:
        raise BenchError(f"default_on_front: tolerances must be >= 0, got {time_tol}, {err_tol}")
    d = default_index(sweep)
    if d is None or sweep["points"][d]["error"] is None:
        return None
    pd = sweep["points"][d]
    shifted = (pd["ms_per_frame"] / (1.0 + time_tol), pd["error"] / (1.0 + err_tol))
    for i, p in enumerate(sweep["points"]):
        if i == d or p["error"] is None:
            continue
        if _dominates((p["ms_per_frame"], p["error"]), shifted):
            return False
    return True


def analyse(sweeps: Mapping[str, Mapping[str, Any]], time_tol: float = TIME_TOL,
            err_tol: float = ERR_TOL) -> dict[str, Any]:
    """Fronts and default checks of every sweep.

    Returns
    -------
    dict
        ``{"fronts": {knob: [values on the front, fastest first]}, "defaults_on_front": {knob: bool|None},
        "time_tol": time_tol, "err_tol": err_tol}``.
    """
    fronts, on = {}, {}
    for knob, sw in sweeps.items():
        idx = pareto_front(sw["points"])
        fronts[knob] = [sw["points"][i]["value"] for i in idx]
        on[knob] = default_on_front(sw, time_tol, err_tol)
    return {"fronts": fronts, "defaults_on_front": on, "time_tol": time_tol, "err_tol": err_tol}


def plot_sweeps(sweeps: Mapping[str, Mapping[str, Any]], path: str | Path, title: str | None = None,
                time_tol: float = TIME_TOL, err_tol: float = ERR_TOL) -> Path:
    """Draw the Pareto plot: one subplot per knob, time per frame (ms) against error.

    Every measured point is labelled with its knob value; the front is a staircase; the default is a
    large star, green when on the front (within the tolerances), red when not. Axes are logarithmic
    where the values span more than a decade.

    Parameters
    ----------
    sweeps : dict
        ``knob -> sweep`` (validated; may carry a ``"stage"`` key).
    path : str or Path
        PNG to write (folders are created).
    title : str, optional
        Figure title.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    BenchError
        If there is no sweep to draw.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure  # no pyplot: no global state, no GUI backend
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    if not sweeps:
        raise BenchError("Pareto plot: no sweeps were reported by the stages that ran")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    k = len(sweeps)
    cols = min(k, 3)
    rows = (k + cols - 1) // cols
    fig = Figure(figsize=(5.6 * cols, 4.8 * rows), dpi=110, layout="constrained")
    for ax_i, (knob, sw) in enumerate(sweeps.items()):
        ax = fig.add_subplot(rows, cols, ax_i + 1)
        pts = sw["points"]
        good = [p for p in pts if p["error"] is not None]
        front = [pts[i] for i in pareto_front(pts)]
        on = default_on_front(sw, time_tol, err_tol)
        if good:
            ax.scatter([p["ms_per_frame"] for p in good], [p["error"] for p in good], s=28, color="0.45",
                       zorder=3, label="measured")
            for p in good:
                ax.annotate(str(p["value"]), (p["ms_per_frame"], p["error"]), textcoords="offset points",
                            xytext=(4, 4), fontsize=8, color="0.25")
        if front:
            xs, ys = [], []
            for p in front:                          # staircase: the region the front dominates
                if xs:
                    xs.append(p["ms_per_frame"])
                    ys.append(ys[-1])
                xs.append(p["ms_per_frame"])
                ys.append(p["error"])
            ax.plot(xs, ys, color="tab:blue", lw=1.5, zorder=2, label="Pareto front")
        d = default_index(sw)
        if d is not None and pts[d]["error"] is not None:
            colour = "tab:green" if on else "tab:red"
            ax.scatter([pts[d]["ms_per_frame"]], [pts[d]["error"]], marker="*", s=260, color=colour,
                       edgecolor="black", zorder=4,
                       label=f"default {sw['default']} ({'on' if on else 'OFF'} front)")
        for axis, vals in (("x", [p["ms_per_frame"] for p in good]), ("y", [p["error"] for p in good])):
            pos = [v for v in vals if v > 0]
            if len(pos) == len(vals) and pos and max(pos) > 10 * min(pos):
                (ax.set_xscale if axis == "x" else ax.set_yscale)("log")
                if axis == "x":                      # plain 1-2-5 labels: times are read, not compared in decades
                    ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
                    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
                    ax.xaxis.set_minor_formatter(NullFormatter())
        stage = sw.get("stage")
        ax.set_title(f"{knob}" + (f"  [{stage}]" if stage else ""), fontsize=10)
        xlabel = "time per frame, ms"
        if sw.get("note"):                       # what the time and the error cover, wrapped under the axis
            xlabel += "\n" + textwrap.fill(str(sw["note"]), 80)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel(sw["metric"])
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="best")
        failed = [p["value"] for p in pts if p["error"] is None]
        if failed:
            ax.text(0.02, 0.02, f"failed: {failed}", transform=ax.transAxes, fontsize=7, color="tab:red")
    if title:
        fig.suptitle(title, fontsize=11)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, format="png")
    tmp.replace(path)
    return path
