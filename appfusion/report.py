"""The scan report: an HTML page with PNG figures (paper Figs. 4-7 style).

Figures: clusters on the points (§5.2), each cluster's HBSAB with its fitted Ward lobe (§5.1), the
convergence of alpha and rho_s over frames, rho_d on the points, the environment map with its
coverage (§4.3), relit novel views beside references, and error tables against ground truth where a
truth folder exists. Every figure is a file in ``out_dir/report/``; the page links them.
"""

from __future__ import annotations

import html
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from .frame import linear_to_srgb
from .result import ScanResult


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _tonemap(img: np.ndarray, exposure: float | None = None) -> np.ndarray:
    img = np.asarray(img, np.float32)
    if exposure is None:
        finite = img[np.isfinite(img)]
        p = np.percentile(finite, 99) if finite.size else 1.0
        exposure = 1.0 / max(float(p), 1e-6)
    return linear_to_srgb(img * exposure)


def fig_points(result: ScanResult, colours: np.ndarray, path: Path, title: str) -> Path:
    """Three orthographic views of the sampled points coloured by ``colours`` (P, 3) in [0, 1]."""
    plt = _plt()
    P = result.positions
    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    for ax, (i, j, name) in zip(axes, [(0, 2, "front (x-z)"), (1, 2, "side (y-z)"), (0, 1, "top (x-y)")]):
        depth_axis = ({0, 1, 2} - {i, j}).pop()
        order = np.argsort(P[:, depth_axis] if name != "top (x-y)" else P[:, 2])
        ax.scatter(P[order, i], P[order, j], c=np.clip(colours[order], 0, 1), s=1.5, linewidths=0)
        ax.set_aspect("equal")
        ax.set_title(name)
        ax.set_xticks([]), ax.set_yticks([])
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def fig_envmap(env: np.ndarray, path: Path, coverage: np.ndarray | None = None) -> Path:
    """Lat-long preview of a (2, N, N, 3) environment map, with its coverage mask when given."""
    from . import octahedral as oc

    plt = _plt()
    ll = oc.sphere_to_latlong(env, 128)
    n = 2 if coverage is not None else 1
    fig, axes = plt.subplots(1, n, figsize=(6 * n, 3.3), squeeze=False)
    axes[0, 0].imshow(_tonemap(ll))
    axes[0, 0].set_title("environment (marker frame, lat-long)")
    if coverage is not None:
        cov = oc.sphere_to_latlong(coverage.astype(np.float32)[..., None], 128)[..., 0]
        axes[0, 1].imshow(cov, cmap="gray", vmin=0, vmax=1)
        axes[0, 1].set_title("coverage (white = seen on the ball)")
    for ax in axes.ravel():
        ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _sigma_cell(sig) -> str:
    """A cluster's rho_s standard errors for the materials table ("—" where unknown)."""
    sig = np.asarray(sig, float)
    return ", ".join(f"{v:.4f}" for v in sig) if np.isfinite(sig).all() else "—"


def fig_convergence(history: dict[str, list], path: Path, final: dict | None = None) -> Path:
    """alpha and rho_s per cluster against the number of frames used.

    ``final``: the exported ``{"alpha": (k,), "rho_s": (k,) or (k, 3)}``, drawn as markers after the
    last frame. The running estimates are those of the live sweep; a scan whose colour pass split a
    cluster and swept again ends with other clusters and values, which only the markers show."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    for key, ax, label in (("alpha", axes[0], "lobe roughness alpha"), ("rho_s", axes[1], "rho_s (mean of RGB)")):
        h = history.get(key) or []
        x_end = 1.0
        if h:
            frames = [f for f, _ in h]
            x_end = float(max(frames))
            vals = np.array([np.atleast_1d(np.asarray(v, float)) for _, v in h], dtype=object)
            k = max(len(v) for v in vals)
            for c in range(k):
                ys = [np.asarray(v, float).reshape(len(v), -1).mean(axis=-1)[c] if len(v) > c else np.nan
                      for v in vals]
                ax.plot(frames, ys, label=f"cluster {c} (running)")
        fv = None if final is None else final.get(key)
        if fv is not None and len(np.atleast_1d(fv)):
            fv = np.asarray(fv, float)
            fv = fv.reshape(len(fv), -1).mean(axis=-1)
            for c, y in enumerate(fv):
                ax.plot([x_end * 1.04], [y], marker="o", linestyle="none", color=f"C{c}",
                        label=f"cluster {c} exported: {y:.3g}")
        if h or fv is not None:
            ax.legend(fontsize=8)
        if not h:
            ax.set_xticks([])                                # a resumed scan has no running estimates
        if key == "alpha" and ax.lines and all(np.nanmin(ln.get_ydata()) > 0 for ln in ax.lines
                                               if np.isfinite(np.asarray(ln.get_ydata(), float)).any()):
            ax.set_yscale("log")                             # roughnesses span decades (0.06 and 0.35)
        ax.set_xlabel("frames used")
        ax.set_title(label)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def fig_hbsabs(hbsabs: list[np.ndarray | None], fits: list[np.ndarray | None], path: Path, lobes=None) -> Path:
    """Each cluster's merged HBSAB (mean IR value over half vectors) beside its fitted lobe (Ward or GGX,
    named by ``lobes`` where given: each cluster's model). Lists are per cluster; a cluster without an
    HBSAB (None) keeps its column, titled so, and the others keep their numbers and fits."""
    plt = _plt()
    k = max(1, len(hbsabs))
    fig, axes = plt.subplots(2, k, figsize=(3 * k, 6), squeeze=False)
    for c in range(k):
        if c < len(hbsabs) and hbsabs[c] is None:
            axes[0, c].set_title(f"cluster {c}: no HBSAB")
        elif c < len(hbsabs):
            axes[0, c].imshow(hbsabs[c], cmap="inferno")
            axes[0, c].set_title(f"cluster {c}: HBSAB")
            if c < len(fits) and fits[c] is not None:
                axes[1, c].imshow(fits[c], cmap="inferno", vmin=np.nanmin(hbsabs[c]), vmax=np.nanmax(hbsabs[c]))
                name = str(lobes[c]) if lobes is not None and c < len(lobes) else ""
                axes[1, c].set_title({"ward": "fitted Ward lobe", "ggx": "fitted GGX lobe"}.get(name, "fitted lobe"))
        for r in range(2):
            axes[r, c].set_xticks([]), axes[r, c].set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def fig_pairs(pairs: list[tuple[str, np.ndarray, np.ndarray]], path: Path) -> Path:
    """Relit renders beside their references, same exposure per pair."""
    plt = _plt()
    n = max(1, len(pairs))
    fig, axes = plt.subplots(n, 2, figsize=(8, 3.2 * n), squeeze=False)
    for r, (name, ours, ref) in enumerate(pairs):
        p = np.percentile(ref[ref > 0], 99) if np.any(ref > 0) else 1.0
        axes[r, 0].imshow(_tonemap(ours, 1 / p))
        axes[r, 0].set_title(f"{name}: relit capture")
        axes[r, 1].imshow(_tonemap(ref, 1 / p))
        axes[r, 1].set_title("reference")
        for ax in axes[r]:
            ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_report(out_dir: str | os.PathLike, result: ScanResult, *, title: str = "appfusion scan",
                 figures: dict[str, Path] | None = None, tables: dict[str, dict[str, Any]] | None = None,
                 notes: list[str] | None = None) -> Path:
    """Write ``out_dir/report.html`` with the standard figures plus any given ones.

    Parameters
    ----------
    figures : dict caption -> PNG path, extra figures (e.g. convergence, HBSABs, relit views)
    tables : dict title -> {row name: value or dict}, e.g. errors against truth and timings
    notes : list of str, lines shown at the top (what was filled in, what is missing)
    """
    from .export import cluster_colours

    out = Path(out_dir)
    rep = out / "report"
    rep.mkdir(parents=True, exist_ok=True)
    figs: dict[str, Path] = {}
    if len(result.positions):
        models = list(result.model or [])
        kinds = ", ".join(f"{c}: {m}" + (f" alpha {result.alpha[c]:.3f}" if m != "diffuse" else "")
                          for c, m in enumerate(models)) if models else ""
        figs["Material clusters (§5.2)"] = fig_points(result, cluster_colours(result.labels), rep / "clusters.png",
                                                      f"{result.n_clusters} cluster(s)" + (f" ({kinds})" if kinds else ""))
        figs["Diffuse albedo rho_d (§5.3)"] = fig_points(result, linear_to_srgb(result.rho_d), rep / "rho_d.png",
                                                         "rho_d (sRGB)")
    if result.envmap is not None:
        figs["Environment map (§4.3)"] = fig_envmap(result.envmap, rep / "envmap.png")
    figs.update(figures or {})
    rows = []
    for c in range(result.n_clusters):
        a_cell = f"{result.alpha[c]:.4f} ± {result.alpha_sigma[c]:.4f}"
        if result.model[c] == "diffuse":                 # no lobe: the IR pass's alpha is not used
            a_cell = f"— <small>(IR fit {a_cell}, unused)</small>"
        rows.append(f"<tr><td>{c}</td><td>{html.escape(result.model[c])}</td><td>{a_cell}</td>"
                    f"<td>{', '.join(f'{v:.4f}' for v in result.rho_s[c])}</td>"
                    f"<td>{_sigma_cell(result.rho_s_sigma[c])}</td>"
                    f"<td>{int(np.sum(result.labels == c))}</td></tr>")
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}img{max-width:100%}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>"]
    for n in notes or []:
        parts.append(f"<p>{html.escape(n)}</p>")
    parts.append("<h2>Materials (paper Eq. 1: rho_d/pi + rho_s f(alpha), f the model's lobe: Ward, or GGX)</h2><table><tr><th>cluster</th>"
                 "<th>model</th><th>alpha</th><th>rho_s (RGB)</th><th>rho_s standard error</th><th>points</th></tr>" + "".join(rows) + "</table>")
    for t, table in (tables or {}).items():
        parts.append(f"<h2>{html.escape(t)}</h2><table>")
        for k, v in table.items():
            if isinstance(v, dict):
                cells = "".join(f"<td>{html.escape(_fmt(x))}</td>" for x in v.values())
                if not any("<th>" in p for p in parts[-1:]):
                    parts.append("<tr><th></th>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in v) + "</tr>")
            else:
                cells = f"<td>{html.escape(_fmt(v))}</td>"
            parts.append(f"<tr><th>{html.escape(str(k))}</th>{cells}</tr>")
        parts.append("</table>")
    for cap, p in figs.items():
        rel = os.path.relpath(p, out)
        parts.append(f"<h2>{html.escape(cap)}</h2><img src='{html.escape(rel)}' alt='{html.escape(cap)}'>")
    parts.append(f"<h2>Provenance</h2><pre>{html.escape(json.dumps(result.info, indent=1, default=str))}</pre>")
    parts.append("</body></html>")
    path = out / "report.html"
    path.write_text("\n".join(parts))
    return path


def _fmt(v) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
