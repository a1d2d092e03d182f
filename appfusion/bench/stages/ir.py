"""Bench stage ``ir``: the IR pass (paper §5.1 BRDF fusion, §5.2 BRDF clustering).

Scenes come from :mod:`appfusion.ir_synth` (the IR pass's own small generators; full synthetic scans
of the project's scanner are wired in later by the integrator):

``alpha_protocol_max_rel_err``
    The paper's §5.1 simulation: Ward alpha 0.05 .. 0.75, surface 40 cm from the Kinect, emitter 7.5 cm
    off axis, random ``(w_i, w_o)`` pairs as the Kinect sees them, noise-free BRDF values into one
    32 x 32 HBSAB, fitted; the largest relative alpha error (paper: 0.26 %).
``fps_ir_update``
    HBSAB + tree updates per 640 x 480 IR frame of a sphere of 100k sampled points that fills most of
    the view (~200k registered pixels; registration excluded, it is reported in ``extra``), measured on
    registered frames of an orbit as the median CPU time of the update (single-threaded; wall-clock
    time is in ``extra`` too: on a shared machine it includes waiting for the CPU).
``fps_ir_update_pattern``
    The same update with the emitter's pattern map divided out, as a scan with a calibrated map runs
    it: each sample's emitter direction (its ray met with the registered point's tangent plane), the
    map's look-up, the division (a random map of the camera's pixel pitch; :mod:`calibration.ir_pattern`).
``alpha_cluster_rel_err``, ``label_accuracy``
    A two-material sphere (a spherical cap of a second Ward material) scanned from an orbit with the
    synthetic Kinect IR model (shifted-Gamma emitter pattern, gamma 0.9, 10 bits): the largest
    relative alpha error over the clusters and the area-weighted fraction of correctly labelled points
    (best label permutation), with k chosen automatically.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from ... import ir_synth as S
from ...frame import Intrinsics
from ...ir_pass import IRPass

INTR_VGA = Intrinsics(640, 480, 575.0, 575.0, 319.5, 239.5)


def protocol(quick: bool, seed: int) -> dict[str, Any]:
    alphas = (0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.75)
    t0 = time.perf_counter()
    err = S.protocol_alpha_errors(alphas, n_pairs=1_000_000, seed=seed)
    return {"errors": {str(a): e for a, e in err.items()}, "max_abs": max(abs(e) for e in err.values()),
            "seconds": time.perf_counter() - t0}


def update_rate(quick: bool, seed: int) -> dict[str, Any]:
    """Time the per-frame HBSAB + tree update on full VGA frames of a 100k-point object."""
    from ...points import register_pixels

    sc, P, N, _ = S.two_material_sphere(seed=seed, n_points=100_000, radius=0.2, intrinsics=INTR_VGA)
    ip = IRPass(P, N, sc.profile(), min_leaf=64)
    poses = S.orbit_poses(sc.center, 0.5, per_ring=3 if quick else 6, elevations_deg=(10, 40), seed=seed,
                          aim_jitter=0.02)
    frames = [sc.render(T) for T in poses]
    reg, t_reg = [], []
    for (ir, depth), T in zip(frames, poses):
        c0 = time.process_time()
        reg.append(register_pixels(ip.positions, ip.normals, depth, INTR_VGA, T))
        t_reg.append(time.process_time() - c0)
    pre, cam = [], []                                     # cam: camera-frame xc, yc, z (the pattern's input)
    K = INTR_VGA
    for (ir, depth), T, (pix, pts) in zip(frames, poses, reg):
        z = depth.ravel()[pix]
        u = (pix % K.width).astype(np.float32)
        v = (pix // K.width).astype(np.float32)
        xc = (u - np.float32(K.cx)) / np.float32(K.fx) * z
        yc = (v - np.float32(K.cy)) / np.float32(K.fy) * z
        R = T[:3, :3].astype(np.float32)
        X = [R[a, 0] * xc + R[a, 1] * yc + R[a, 2] * z + np.float32(T[a, 3]) for a in range(3)]
        pre.append((pts, X, ir.ravel()[pix], T[:3, 3], T[:3, :3] @ np.asarray(sc.emitter) + T[:3, 3]))
        cam.append((xc, yc, z))
    # the update: each pixel's tangent offset from its point (the normal tilt, IRPass._frame_terms)
    # and the HBSAB sums; registration is timed apart
    for (pts, X, raw, C, E), (xc, yc, z), T in list(zip(pre, cam, poses))[:2]:   # warm up (page in the HBSABs)
        ip._add(pts, X[0], X[1], X[2], raw, C, E, *ip._frame_terms(pts, xc, yc, z, X, T, sc.emitter))
    times, cpu = [], []
    for rep in range(2 if quick else 3):
        for (pts, X, raw, C, E), (xc, yc, z), T in zip(pre, cam, poses):
            t0, c0 = time.perf_counter(), time.process_time()
            ip._add(pts, X[0], X[1], X[2], raw, C, E, *ip._frame_terms(pts, xc, yc, z, X, T, sc.emitter))
            cpu.append(time.process_time() - c0)
            times.append(time.perf_counter() - t0)
    t_upd = float(np.median(cpu))               # CPU time: the machine may be shared with other jobs
    # the same with the emitter's pattern map divided out, as a scan runs it (calibration.ir_pattern):
    # each sample's emitter direction from its ray met with the registered point's tangent plane
    import copy

    from calibration.ir_pattern import EmitterPattern

    prof = copy.copy(sc.profile())
    rng = np.random.default_rng(seed)
    cells = (int(2 * K.height / K.fy * K.fx) + 64, int(2 * K.width) + 64)
    prof.pattern = EmitterPattern(rng.uniform(0.5, 1.5, cells).astype(np.float32), np.ones(cells, np.uint16),
                                  1.0 / K.fx, (cells[1] / 2, cells[0] / 2))
    ipp = IRPass(P, N, prof, min_leaf=64)
    cpu_p = []
    for rep in range(2 if quick else 3):
        for (pts, X, raw, C, E), (xc, yc, z), T in zip(pre, cam, poses):
            c0 = time.process_time()
            ipp._add(pts, X[0], X[1], X[2], raw, C, E, *ipp._frame_terms(pts, xc, yc, z, X, T, sc.emitter))
            cpu_p.append(time.process_time() - c0)
    t_pat = float(np.median(cpu_p))
    c0 = time.process_time()
    for (ir, depth), T in zip(frames, poses):
        ip.add_frame(ir, depth, INTR_VGA, T)
    t_full = (time.process_time() - c0) / len(frames)
    return {"samples_per_frame": float(np.mean([len(r[0]) for r in reg])), "update_cpu_ms": 1e3 * t_upd,
            "update_with_pattern_cpu_ms": 1e3 * t_pat, "fps_update_with_pattern": 1.0 / t_pat,
            "update_wall_ms": 1e3 * float(np.median(times)), "fps_update": 1.0 / t_upd, "register_cpu_ms": 1e3 * float(np.median(t_reg[1:] or t_reg)),
            "fps_add_frame_with_registration": 1.0 / t_full, "state_mb": ip.nbytes / 2 ** 20,
            "n_points": len(P), "n_leaves": ip.cut.tree.n_leaves}


def clustering(quick: bool, seed: int) -> dict[str, Any]:
    n_points = 20000 if quick else 40000
    sc, P, N, truth = S.two_material_sphere(seed=seed, n_points=n_points)
    ip = IRPass(P, N, sc.profile(), min_leaf=32)
    poses = S.orbit_poses(sc.center, 0.5, per_ring=16 if quick else 30, seed=seed)
    t0 = time.perf_counter()
    S.scan(ip, sc, poses)
    t_scan = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = ip.result()
    t_res = time.perf_counter() - t0
    k = max(res.k, len(sc.materials))
    M = np.zeros((k, k))
    np.add.at(M, (res.labels, truth), 1.0)
    r, c = linear_sum_assignment(-M)
    acc = float(M[r, c].sum() / len(truth))
    errs = {}
    for lab, mat in zip(r, c):
        if lab < res.k and mat < len(sc.materials) and res.clusters[lab].fit is not None:
            errs[str(sc.materials[mat].alpha)] = res.clusters[lab].fit.alpha / sc.materials[mat].alpha - 1
    worst = max(abs(e) for e in errs.values()) if len(errs) == len(sc.materials) else None
    return {"k": res.k, "label_accuracy": acc, "alpha_rel_err": errs, "alpha_max_abs": worst,
            "alphas": [c.alpha for c in res.clusters], "alpha_sigmas": [c.alpha_sigma for c in res.clusters],
            "frames": len(poses), "points": n_points, "scan_s": t_scan, "result_s": t_res,
            "notes": res.notes}


def run(ctx) -> dict[str, float | None]:
    prot = protocol(ctx.quick, ctx.seed)
    rate = update_rate(ctx.quick, ctx.seed)
    clus = clustering(ctx.quick, ctx.seed)
    ctx.extra["ir"] = {"protocol": prot, "update": rate, "clustering": clus}
    return {"alpha_protocol_max_rel_err": prot["max_abs"], "fps_ir_update": rate["fps_update"],
            "fps_ir_update_pattern": rate["fps_update_with_pattern"],
            "alpha_cluster_rel_err": clus["alpha_max_abs"], "label_accuracy": clus["label_accuracy"]}


if __name__ == "__main__":  # pragma: no cover
    import json
    import sys
    from pathlib import Path

    from ..runner import BenchContext

    ctx = BenchContext(workdir=Path("out/bench"), quick="--full" not in sys.argv)
    print(json.dumps(run(ctx), indent=2))
    print(json.dumps(ctx.extra["ir"], indent=2, default=float))
