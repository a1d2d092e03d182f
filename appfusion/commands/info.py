"""``appfusion info PATH``: describe any supported recording (session, TUM, Redwood, Azure MKV), or the
output folder of a scan (its materials with their uncertainties, mesh, files, errors against truth)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def register(sub) -> None:
    p = sub.add_parser("info", help="describe a recording (any supported format) or a scan's output",
                       description="Prints a recording's format, device, streams with frame counts, rates and "
                                   "intrinsics, duration, scanning passes and the depth range of its first "
                                   "frame. Reads appfusion sessions, TUM RGB-D and Redwood/Open3D folders and "
                                   "Azure Kinect .mkv files. Given the output folder of `appfusion scan` (or "
                                   "its result.npz), prints the captured materials instead: per cluster the "
                                   "model, points, Ward alpha and rho_s with their standard errors, then the "
                                   "mesh, the environment map, the files written and the errors against "
                                   "ground truth when the scan had any.")
    p.add_argument("recording", type=Path, help="session directory, TUM/Redwood folder, .mkv file, or a scan's "
                                                "output folder")
    p.add_argument("--skip-bad", action="store_true", help="describe a damaged recording, skipping bad frames")
    p.add_argument("--json", action="store_true", help="print the description as JSON")
    p.set_defaults(func=run)


def _stream_times(src) -> dict[str, np.ndarray] | None:
    f = getattr(src, "stream_timestamps", None)
    return f() if callable(f) else None


def _passes(events: list, times: np.ndarray) -> list[dict[str, Any]]:
    """Scanning passes from ``pass`` events: name, start/end time, number of frames."""
    ev = [(float(t), v) for t, k, v in events if k == "pass"]
    out = []
    for i, (t, name) in enumerate(ev):
        t_end = ev[i + 1][0] if i + 1 < len(ev) else np.inf
        sel = times[(times >= t) & (times < t_end)] if times.size else times
        out.append({"name": name, "start_s": t, "frames": int(sel.size),
                    "end_s": float(sel[-1]) if sel.size else t})
    return out


def describe(src, path: Path, fmt: str) -> dict[str, Any]:
    """A JSON-able description of an open recording (see :func:`register`)."""
    meta = src.meta
    caps = src.caps
    times = np.asarray(getattr(src, "timestamps", np.zeros(0)), dtype=np.float64)
    st = _stream_times(src)
    streams = {}
    for s in ("depth", "ir", "rgb"):
        if s not in caps.streams:
            continue
        d: dict[str, Any] = {}
        if st is not None and s in st:
            d["frames"] = int(len(st[s]))
        else:
            d["frames"] = len(src)  # this reader delivers every stream in every frame
        rate = caps.rates.get(s)
        d["rate_hz"] = None if rate is None else round(float(rate), 3)
        K = src.intrinsics.get(s)
        d["intrinsics"] = None if K is None else K.to_json()
        streams[s] = d
    first_depth = None
    src.seek(0)
    for k, f in enumerate(src):
        if f.depth is not None:
            v = f.depth[np.isfinite(f.depth)]
            first_depth = {"frame": f.index, "valid_fraction": round(float(v.size / f.depth.size), 4)}
            if v.size:
                first_depth.update(min_m=round(float(v.min()), 4), median_m=round(float(np.median(v)), 4),
                                   max_m=round(float(v.max()), 4))
            break
        if k >= 50:
            break
    events = list(getattr(src, "events", []) or [])
    if not any(k == "pass" for _, k, _ in events) and meta.get("format_name") != "session" and times.size:
        pn = getattr(src, "pass_name", None)  # readers that tag every frame with one pass
        if pn:
            events = [(float(times[0]), "pass", pn)]
    poses = getattr(src, "poses", None)
    return {
        "path": str(path),
        "format": fmt,
        "device": str(meta.get("device", "unknown")),
        "frames": len(src),
        "duration_s": round(float(times[-1] - times[0]), 6) if times.size > 1 else 0.0,
        "start_s": float(times[0]) if times.size else None,
        "streams": streams,
        "together": ["+".join(s for s in ("depth", "ir", "rgb") if s in g) for g in caps.together],
        "passes": _passes(events, times),
        "events": len(events),
        "frames_with_pose": None if poses is None else sum(p is not None for p in poses),
        "depth_units_per_m": meta.get("depth_units_per_m"),
        "first_depth": first_depth,
        "bad_frames": [list(b) for b in getattr(src, "bad_frames", [])],
        "dropped_lines": len(getattr(src, "dropped_lines", [])),
    }


def format_description(d: dict[str, Any]) -> str:
    """Human-readable text of :func:`describe`'s dict."""
    from replay.open import FORMATS

    lines = [f"recording   {d['path']}",
             f"format      {d['format']} ({FORMATS.get(d['format'], '')})",
             f"device      {d['device']}",
             f"frames      {d['frames']} over {d['duration_s']:.3f} s"
             + (f" (from t = {d['start_s']:.6f} s)" if d["start_s"] is not None else ""),
             "streams"]
    for s, v in d["streams"].items():
        rate = "? Hz" if v["rate_hz"] is None else f"{v['rate_hz']:.2f} Hz"
        K = v["intrinsics"]
        kk = ("no intrinsics" if K is None else
              f"{K['width']}x{K['height']}  fx={K['fx']:.3f} fy={K['fy']:.3f} cx={K['cx']:.3f} cy={K['cy']:.3f}"
              + (f"  dist={[round(x, 5) for x in K['dist']]}" if K.get("dist") else ""))
        lines.append(f"  {s:<6}{v['frames']:>7} frames  {rate:>10}  {kk}")
    lines.append(f"together    {' | '.join(d['together'])}")
    if d["passes"]:
        lines.append("passes")
        for p in d["passes"]:
            lines.append(f"  {p['name']:<16} from {p['start_s']:.3f} s to {p['end_s']:.3f} s  {p['frames']} frames")
    else:
        lines.append("passes      none recorded")
    if d["depth_units_per_m"] is not None:
        lines.append(f"depth units {d['depth_units_per_m']:g} per metre")
    fd = d["first_depth"]
    if fd is None:
        lines.append("depth       no depth images")
    elif "min_m" in fd:
        lines.append(f"depth       frame {fd['frame']}: {fd['min_m']:.3f} .. {fd['max_m']:.3f} m "
                     f"(median {fd['median_m']:.3f} m, {100 * fd['valid_fraction']:.1f}% valid)")
    else:
        lines.append(f"depth       frame {fd['frame']}: no valid pixel")
    if d["frames_with_pose"] is not None:
        lines.append(f"poses       {d['frames_with_pose']} of {d['frames']} frames")
    if d["bad_frames"]:
        lines.append(f"bad         {len(d['bad_frames'])} skipped:")
        lines += [f"  {p}:{ln}: {why}" if ln else f"  {p}: {why}" for p, ln, why in d["bad_frames"][:10]]
    if d["dropped_lines"]:
        lines.append(f"dropped     {d['dropped_lines']} half-written line(s) at the end of index files")
    return "\n".join(lines)


def _result_path(path: Path) -> Path | None:
    """``result.npz`` of a scan output folder given as the folder or the file, else None."""
    if path.is_file() and path.name.endswith(".npz"):
        return path
    if path.is_dir() and (path / "result.npz").is_file() and not (path / "meta.json").exists():
        return path / "result.npz"
    return None


def describe_result(path: Path) -> dict[str, Any]:
    """A JSON-able description of a scan's output (:class:`~appfusion.result.ScanResult` and the files
    beside it). Uncertainties that were not estimated are None."""
    from appfusion.result import ScanResult
    from appfusion.result import json_float

    res = ScanResult.load(path)
    folder = path.parent

    clusters = []
    for c in range(res.n_clusters):
        clusters.append({"cluster": c, "model": res.model[c], "points": int(np.sum(res.labels == c)),
                         "alpha": json_float(res.alpha[c]), "alpha_sigma": json_float(res.alpha_sigma[c]),
                         "rho_s": [json_float(v) for v in res.rho_s[c]],
                         "rho_s_sigma": [json_float(v) for v in res.rho_s_sigma[c]]})
    metrics = None
    if (folder / "metrics.json").is_file():
        try:
            metrics = json.loads((folder / "metrics.json").read_text())
        except ValueError:
            metrics = None
    files = sorted(f.name for f in folder.iterdir() if f.is_file() and f.suffix in
                   (".glb", ".obj", ".mtl", ".ply", ".png", ".exr", ".hdr", ".html", ".json", ".npz"))
    return {"path": str(folder), "result": str(path), "points": int(len(res.positions)),
            "rho_d_median": [json_float(v) for v in np.median(res.rho_d, axis=0)] if len(res.rho_d) else None,
            "clusters": clusters,
            "mesh": {"vertices": int(len(res.mesh_vertices)), "faces": int(len(res.mesh_faces))},
            "envmap": None if res.envmap is None else list(res.envmap.shape),
            "rho_d_source": res.info.get("rho_d_source"), "alpha_source": res.info.get("alpha_source"),
            "files": files, "metrics": metrics}


def format_result(d: dict[str, Any]) -> str:
    """Human-readable text of :func:`describe_result`'s dict."""
    def pm(v, s, fmt):
        return f"{v:{fmt}}" + ("" if s is None else f" ± {s:{fmt}}")

    lines = [f"scan result {d['result']}",
             f"points      {d['points']}" + ("" if d["rho_d_median"] is None else
                                             "  (median rho_d " + ", ".join(f"{v:.3f}" for v in d["rho_d_median"]) + ")"),
             "materials   (paper Eq. 1: rho_d/pi + rho_s f(alpha), f the model's lobe, Ward or GGX; ± one standard error)"]
    for c in d["clusters"]:
        rs = ", ".join(pm(v, s, ".4f") for v, s in zip(c["rho_s"], c["rho_s_sigma"]))
        a = pm(c['alpha'], c['alpha_sigma'], '.4f')
        if c["model"] == "diffuse":                         # no lobe: the IR fit's alpha is not used
            a, rs = f"- (IR fit {a}, unused)", "0"
        lines.append(f"  cluster {c['cluster']}: {c['model']:<7} {c['points']:>7} points  alpha {a}  rho_s {rs}")
    m = d["mesh"]
    lines.append(f"mesh        {m['vertices']} vertices, {m['faces']} faces")
    lines.append("envmap      " + ("none" if d["envmap"] is None else "x".join(str(x) for x in d["envmap"][:3])
                                   + " octahedral"))
    lines.append(f"sources     rho_d: {d['rho_d_source']}; alpha: {d['alpha_source']}")
    lines.append("files       " + (", ".join(d["files"]) or "none"))
    if d["metrics"]:
        lines.append("against truth " + ", ".join(f"{k} {v:.4g}" for k, v in d["metrics"].items()
                                                  if isinstance(v, (int, float)) and not isinstance(v, bool)))
    return "\n".join(lines)


def run(args) -> int:
    from replay.open import detect_format, open_recording

    rp = _result_path(args.recording)
    if rp is not None:
        d = describe_result(rp)
        print(json.dumps(d, indent=2) if args.json else format_result(d))
        return 0
    fmt = detect_format(args.recording)
    src = open_recording(args.recording, skip_bad=args.skip_bad)
    with src:
        d = describe(src, args.recording, fmt)
    print(json.dumps(d, indent=2) if args.json else format_description(d))
    return 0
