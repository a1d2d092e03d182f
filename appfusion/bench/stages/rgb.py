"""Bench stage ``rgb``: the RGB pass (paper §5.3) against brute-force quadrature of Eq. 4.

Scenes come from :mod:`appfusion.rgb_synth` (the RGB pass's own generators; full synthetic scans of the
project's scanner are wired in later by the integrator). All references are direct sums over the
environment map's texels, never the wavelet code.

``double_product_rel_err``, ``double_product_ggx_rel_err`` (GGX alpha 0.15, the model ladder's third
rung), ``wavelet_tables_mb``, ``wavelet_build_s``
    S tables of a 2 x 128^2 office environment (soft area lights, dark paper on the support plane)
    built for the alphas {0.06, 0.1, 0.2, 0.35} ({0.08, 0.25} with ``--quick``); the relative RMS
    error of S over random (n, alpha, w_o) (normals not facing the plane, cameras above it,
    n.w_o >= 0.2) against brute force; all tables' size (D table, S tables, BRDF tables); the build
    time of every mirror node (``lazy=False``; the RGB pass builds lazily, see the ``scan`` stage's
    ``skip_wavelet_saving``) as CPU seconds summed over the build's threads (the machine may be
    shared: CPU time does not count waiting for it, and on an idle 2-core machine the wall time is
    lower; wall time and per-alpha times are in ``extra``).
``rho_d_median_rel_err``, ``rho_s_rel_err``
    A sphere on the plane with two Ward materials and a per-point diffuse pattern, rendered from brute
    force Eq. 4 with 1 % + 0.001 noise by a depth + RGB camera pair from an orbit, run through
    :class:`~appfusion.rgb_pass.RGBPass`: the median per-point relative rho_d error (observed points,
    all channels) and the largest relative rho_s error over clusters and channels.
``fps_rgb_update``
    :meth:`RGBPass.add_frame` on 640 x 480 frames of a 100k-point sphere (radius 0.2 m at 0.6 m) as
    the inverse of the median CPU time per frame (registration included; the machine may be shared, so
    CPU rather than wall time; both are in ``extra``).
``fps_rgb_update_near_field``
    The same with the support plane as near-field light (what a scan runs: ``dS`` per sample whose
    lobe reaches below the horizon; ``dD`` once, its seconds in ``extra``).

Sweeps: ``rgb_light_keep`` (Haar coefficients of the lighting kept per mirror node: build time against
S error) and ``rgb_registration`` (point projection against the paper's pixel registration: time per
frame against rho_s error).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ...double_product import DoubleProductTables
from ...frame import Intrinsics, make_pose
from ...rgb_pass import RGBPass, denoise_rho_d
from ...rgb_synth import (SphereScene, brute_force_S, fibonacci_sphere, orbit_poses, synthetic_envmap,
                          two_material_sphere)

VGA_DEPTH = Intrinsics(640, 480, 575.8, 575.8, 319.5, 239.5)
VGA_RGB = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
DEPTH_TO_RGB = make_pose(np.eye(3), [-0.025, 0.0, 0.0])


def sample_set(n: int, seed: int, alphas) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random (normal, view, alpha): normals not facing into the plane, views above it, n.w_o >= 0.2."""
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n, 3))
    nrm[:, 2] = np.abs(nrm[:, 2]) * 1.5 - 0.3 * np.linalg.norm(nrm[:, :2], axis=1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    wo = np.empty_like(nrm)
    for i in range(n):
        while True:
            c = rng.normal(size=3)
            c /= np.linalg.norm(c)
            if c[2] > 0.05 and c @ nrm[i] > 0.2:
                wo[i] = c
                break
    return nrm, wo, rng.choice(np.asarray(alphas, dtype=float), size=n)


def rel_rms(est: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(((est - ref) ** 2).sum() / (ref ** 2).sum()))


def double_product(quick: bool, seed: int, keeps=()) -> tuple[DoubleProductTables, dict[str, Any]]:
    """Build the S tables of a 2 x 128^2 map and measure S against brute force."""
    env = synthetic_envmap(128, seed=seed + 1)
    alphas = (0.08, 0.25) if quick else (0.06, 0.1, 0.2, 0.35)
    t0, c0 = time.perf_counter(), time.process_time()
    T = DoubleProductTables(env, alphas, lazy=False)          # every mirror node: the full build time
    build_s, build_cpu = time.perf_counter() - t0, time.process_time() - c0
    n, wo, al = sample_set(200 if quick else 600, seed, alphas)
    ref = brute_force_S(env, n, al, wo)
    got = T.S(n, wo, al)
    rel = np.abs(got - ref).sum(1) / ref.sum(1)
    out = {"alphas": list(alphas), "samples": len(n), "rel_rms": rel_rms(got, ref),
           "median_rel": float(np.median(rel)), "p90_rel": float(np.percentile(rel, 90)),
           "bias": float(got.sum() / ref.sum() - 1),
           "rel_rms_per_alpha": {str(a): rel_rms(got[al == a], ref[al == a]) for a in alphas},
           "tables_mb": T.nbytes / 2 ** 20, "build_s": build_s, "build_cpu_s": build_cpu,
           "per_alpha": {str(a): {k: (round(float(v), 3) if isinstance(v, (float, np.floating)) else v)
                                  for k, v in t.stats.items()} for a, t in T.tables.items()},
           "diffuse_s": T.stats["diffuse_s"]}
    sweep = []
    for k in keeps:
        t0 = time.perf_counter()
        Tk = DoubleProductTables(env, alphas, light_keep=k, d_res=9, lazy=False)
        sweep.append({"value": k, "ms_per_frame": 1e3 * (time.perf_counter() - t0),
                      "error": rel_rms(Tk.S(n, wo, al), ref)})
    if keeps:
        sweep.append({"value": "all", "ms_per_frame": 1e3 * (build_s - T.stats["diffuse_s"]), "error": out["rel_rms"]})
    # the model ladder's GGX rung: its own tables (a wider, stretched cap), against brute force with the GGX lobe
    a_g = 0.15
    t0 = time.perf_counter()
    T.add_alpha(a_g, "ggx")
    T.table(a_g, "ggx").build_all()
    g_build = time.perf_counter() - t0
    ng, wog, _ = sample_set(100 if quick else 300, seed + 7, [a_g])
    got_g = T.S(ng, wog, a_g, "ggx")
    ref_g = brute_force_S(env, ng, a_g, wog, lobe="ggx")
    out["ggx"] = {"alpha": a_g, "samples": len(ng), "rel_rms": rel_rms(got_g, ref_g),
                  "bias": float(got_g.sum() / ref_g.sum() - 1), "table_mb": T.table(a_g, "ggx").nbytes / 2 ** 20,
                  "build_s": g_build}
    return T, out, sweep


def point_set(quick: bool, seed: int, registration: str = "points", scene=None) -> dict[str, Any]:
    """The two-material sphere seen from an orbit: rho_d and rho_s errors."""
    if scene is None:
        n_pts, views, env_n = (1200, 32, 32) if quick else (2500, 80, 48)
        sc = two_material_sphere(n_pts, env_n=env_n, seed=seed, image_scale=0.4 if quick else 0.5,
                                 materials=((0.08, (0.35, 0.3, 0.25)), (0.25, (0.5, 0.5, 0.5))))
        poses = orbit_poses(sc.center, 0.45, views, seed=seed + 1)
        rng = np.random.default_rng(seed + 5)
        t0 = time.perf_counter()
        frames = [sc.render(T, rng, noise_rel=0.01, noise_abs=0.001) for T in poses]
        render_s = time.perf_counter() - t0
        tables = None
    else:
        sc, poses, frames, tables, render_s = scene
    t0 = time.perf_counter()
    kw = {"r_res": lambda a: 65 if a < 0.15 else 41, "d_res": 49} if quick else None
    rp = RGBPass(sc.positions, sc.normals, sc.labels, sc.alphas, sc.env, tables=tables, table_kwargs=kw,
                 registration=registration)
    t_tables = time.perf_counter() - t0
    cpu = []
    for (rgb, depth, _), T in zip(frames, poses):
        c0 = time.process_time()
        rp.add_frame(rgb, depth, sc.rgb_intrinsics, sc.depth_intrinsics, T, sc.depth_to_rgb)
        cpu.append(time.process_time() - c0)
    res = rp.result()
    ob = res.observed
    rel = np.abs(res.rho_d[ob] - sc.rho_d[ob]) / sc.rho_d[ob]
    rs = res.rho_s / sc.rho_s - 1
    # the scan's pooling of the final rho_d (ScanConfig.rho_d_pool_k; docs/rgb-pass.md §5g)
    se = rp.rho_d_stderr(res.rho_s)
    pool = {0: (0.0, float(np.median(rel)))}
    for k in (16, 32, 64):
        t0 = time.perf_counter()
        rd = denoise_rho_d(sc.positions, res.rho_d, se, sc.labels, k=k)
        ms = 1e3 * (time.perf_counter() - t0)
        pool[k] = (ms, float(np.median(np.abs(rd[ob] - sc.rho_d[ob]) / sc.rho_d[ob])))
    return {"rho_d_pool": pool, "points": len(sc.positions), "views": len(poses), "observed": float(ob.mean()),
            "median_samples_per_point": float(np.median(res.counts[ob])),
            "rho_d_median_rel_err": float(np.median(rel)), "rho_d_p90_rel_err": float(np.percentile(rel, 90)),
            "rho_d_median_signed": float(np.median((res.rho_d[ob] - sc.rho_d[ob]) / sc.rho_d[ob])),
            "rho_s_rel_err": [[round(float(x), 4) for x in r] for r in rs], "rho_s_max_abs": float(np.abs(rs).max()),
            "render_s": render_s, "tables_s": t_tables, "ms_per_frame_cpu": 1e3 * float(np.median(cpu)),
            "registration": registration, "skipped": {k: v for k, v in rp.stats.items() if k.startswith("skipped")},
            "_scene": (sc, poses, frames, rp.tables, render_s)}


def facing_points(sc, pose: np.ndarray, min_cos: float = 0.3):
    """Camera centre (3,) of ``pose`` (camera to world), unit view directions ``w_o`` (P, 3) from the
    scene's points to it, and the indices of the points facing it (``n . w_o > min_cos``)."""
    C = pose[:3, 3]
    wo = C - sc.positions
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    return C, wo, np.flatnonzero(np.einsum("ij,ij->i", sc.normals, wo) > min_cos)


def clipped_samples(sc, poses, tables, rho_d: np.ndarray, rng: np.random.Generator, sigma: float = 0.02,
                    rho_s: np.ndarray | None = None):
    """Per pose of ``poses``: (the sphere's points facing the camera, ``n . w_o > 0.3``; their Eq. 5
    radiance ``D rho_d`` (+ ``S rho_s`` of their cluster when ``rho_s`` (C, 3) is given) plus Gaussian
    read noise ``sigma``, clipped at 0 as a sensor clips it; the camera centre). D and S from
    ``tables``. Shared with the tests of the clip correction (docs/rgb-pass.md §5h)."""
    D0 = tables.D(sc.normals).astype(np.float64)
    for T in poses:
        C, wo, vis = facing_points(sc, T)
        L = D0[vis] * rho_d[vis] + rng.normal(0, sigma, (len(vis), 3))
        if rho_s is not None:
            L += tables.S(sc.normals[vis], wo[vis], sc.alphas[sc.labels[vis]]).astype(np.float64) * rho_s[sc.labels[vis]]
        yield vis, np.maximum(L, 0.0), C


def clipped_dark(seed: int, scene) -> dict[str, Any]:
    """Dark channels a noise width above black, the noise clipped at 0 (docs/rgb-pass.md §5h): rho_d of
    the sphere's points from Eq. 5 samples (:func:`clipped_samples`: diffuse only, read noise sigma
    0.02, green and blue at about 1 and 0.5 sigma) with and without ``clip_correction``: the bias
    (largest |median signed relative error| of the two dark channels) and the median |relative
    error| (mostly the noise of ~20 samples a point)."""
    sc, poses, _, tables, _ = scene
    D0 = tables.D(sc.normals).astype(np.float64)
    rho = 0.54 * np.array([1.0, 0.04, 0.02])[None] / np.maximum(D0.mean(1, keepdims=True), 1e-6)
    out = {}
    for corr in (False, True):
        t0 = time.perf_counter()
        rp = RGBPass(sc.positions, sc.normals, sc.labels, sc.alphas, sc.env, tables=tables, clip_correction=corr,
                     specular=[False] * len(sc.alphas))
        for vis, L, C in clipped_samples(sc, poses, tables, rho, np.random.default_rng(seed + 17)):
            rp.add_samples(vis, L, C)
        res = rp.result()
        ms = 1e3 * (time.perf_counter() - t0)
        ok = res.observed & (res.counts >= 8)
        rel = res.rho_d[ok, 1:] / rho[ok, 1:] - 1
        signed = np.median(rel, axis=0)
        out[corr] = {"ms": ms, "median_rel_err": float(np.median(np.abs(rel))),
                     "median_signed": [round(float(v), 4) for v in signed], "bias": float(np.abs(signed).max())}
    return out


def _update_scene(quick: bool, seed: int, tables: DoubleProductTables):
    """The 100k-point sphere filling a 640 x 480 view and its frames (RGB, depth, pose) for
    :func:`update_rate`; rendered once and shared by the rate's variants."""
    env = tables.env
    n = fibonacci_sphere(100_000)
    R, c = 0.2, np.array([0.0, 0.0, 0.2])
    labels = (n[:, 0] > 0.3).astype(np.int64)
    alphas = np.array(tables.alphas[:2] if len(tables.alphas) >= 2 else tables.alphas * 2)
    sc = SphereScene(env, c, R, c + R * n, n, labels, np.full((len(n), 3), 0.4), np.full((2, 3), 0.3), alphas,
                     VGA_DEPTH, VGA_RGB, DEPTH_TO_RGB)
    frames = []
    for T in orbit_poses(c, 0.6, 2 if quick else 8, seed=seed + 2):
        t, kind, _ = sc._raycast(T, VGA_DEPTH)
        depth = np.where(kind > 0, t, np.nan).reshape(480, 640).astype(np.float32)
        _, kind2, X2 = sc._raycast(T @ np.linalg.inv(DEPTH_TO_RGB), VGA_RGB)
        nn = np.nan_to_num((X2 - c) / R)
        img = np.where((kind2 == 1)[:, None], 0.4 * tables.D(nn), 0.02)
        frames.append((np.clip(img, 0, 1).reshape(480, 640, 3).astype(np.float32), depth, T))
    return sc, labels, alphas, frames


def update_rate(quick: bool, seed: int, tables: DoubleProductTables, registration: str = "points",
                near_field: bool = False, scene=None) -> dict[str, Any]:
    """Median CPU time of add_frame on 640 x 480 frames of a 100k-point sphere filling the view;
    ``near_field``: with the support plane as near-field light (white circles at +-0.3 m on the
    sphere's plane z = 0, :mod:`appfusion.near_field`), as a scan runs it. ``scene``: the ``"_scene"``
    of an earlier call (not rendered again)."""
    env = tables.env
    sc, labels, alphas, frames = scene if scene is not None else _update_scene(quick, seed, tables)
    nf = None
    if near_field:
        from appfusion.markers import MarkerConfig
        from appfusion.near_field import SupportPlaneLight

        mc = MarkerConfig(radius_m=0.025, side_m=0.6)
        nf = SupportPlaneLight(env, mc.centres(), mc.radii(), np.full(3, 0.05), extent_m=0.6)
    rp = RGBPass(sc.positions, sc.normals, labels, alphas, env, tables=tables, registration=registration,
                 near_field=nf)
    rp.add_frame(*frames[0][:2], VGA_RGB, VGA_DEPTH, frames[0][2], DEPTH_TO_RGB)      # warm-up
    cpu, wall, used = [], [], []
    for rgb, depth, T in frames * 3:
        c0, w0 = time.process_time(), time.perf_counter()
        used.append(rp.add_frame(rgb, depth, VGA_RGB, VGA_DEPTH, T, DEPTH_TO_RGB))
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    t_cpu = float(np.median(cpu))
    return {"points": len(sc.positions), "samples_per_frame": float(np.mean(used)), "cpu_ms": 1e3 * t_cpu,
            "wall_ms": 1e3 * float(np.median(wall)), "fps_cpu": 1.0 / t_cpu, "registration": registration,
            "state_mb": rp.nbytes / 2 ** 20, "near_field": near_field,
            "near_field_setup_s": float(getattr(rp, "near_field_seconds", 0.0)),
            "_scene": (sc, labels, alphas, frames)}


def run(ctx) -> dict[str, float | None]:
    quick = bool(ctx.quick)
    extra: dict[str, Any] = {}
    T, dp, sweep_keep = double_product(quick, ctx.seed, keeps=() if quick else (64, 128, 256))
    extra["double_product"] = dp
    ps = point_set(quick, ctx.seed)
    scene = ps.pop("_scene")
    extra["point_set"] = ps
    rate = update_rate(quick, ctx.seed, T)
    upd_scene = rate.pop("_scene")
    extra["update"] = rate
    rate_nf = update_rate(quick, ctx.seed, T, near_field=True, scene=upd_scene)
    rate_nf.pop("_scene")
    extra["update_near_field"] = rate_nf
    if sweep_keep:
        ctx.add_sweep("rgb_light_keep", "double_product_rel_err", "all", sweep_keep,
                      note="Haar coefficients of the pre-rotated lighting kept per mirror node (of 1024; 4096 "
                           "for rough lobes, scaled). time = building the S tables of a 2 x 128^2 map for "
                           f"alphas {dp['alphas']} (ms, once per environment, not per frame); error = S rel. RMS "
                           "against brute force")
    if ctx.time_left() > 10 or not quick:
        pix = point_set(quick, ctx.seed, registration="pixels", scene=scene)
        pix.pop("_scene")
        rate_pix = update_rate(quick, ctx.seed, T, registration="pixels", scene=upd_scene)
        rate_pix.pop("_scene")
        extra["point_set_pixels"], extra["update_pixels"] = pix, rate_pix
        ctx.add_sweep("rgb_registration", "rho_s_rel_err", "points",
                      [{"value": "points", "ms_per_frame": rate["cpu_ms"], "error": ps["rho_s_max_abs"]},
                       {"value": "pixels", "ms_per_frame": rate_pix["cpu_ms"], "error": pix["rho_s_max_abs"]}],
                      note="RGB registration: project points (default) or register every depth pixel to its "
                           "nearest point (paper). time = CPU ms per 640x480 frame of a 100k-point sphere; "
                           "error = largest rho_s rel. error on the two-material sphere")
    dark = clipped_dark(ctx.seed, scene)
    extra["clipped_dark"] = {str(k): v for k, v in dark.items()}
    ctx.add_sweep("rho_d_clip_correction", "rho_d_dark_bias", True,
                  [{"value": k, "ms_per_frame": v["ms"], "error": v["bias"]} for k, v in dark.items()],
                  note="rho_d of channels 1 and 0.5 noise widths above black, the noise clipped at 0, with and "
                       "without the zero-fraction correction (docs/rgb-pass.md §5h). time = ms for the whole "
                       "sweep of samples; error = the dark channels' bias (largest |median signed rel. error|)")
    ctx.add_sweep("rho_d_pool_k", "rho_d_median_rel_err", 32,
                  [{"value": k, "ms_per_frame": t, "error": e} for k, (t, e) in ps.pop("rho_d_pool").items()],
                  note="rho_d pooled with the k nearest points of its cluster that agree within 2.5 standard "
                       "errors (0: off). time = ms once per scan on the sphere's points, not per frame; error = "
                       "median rho_d rel. error")
    ctx.extra["rgb"] = extra
    return {"double_product_rel_err": dp["rel_rms"], "double_product_ggx_rel_err": dp["ggx"]["rel_rms"],
            "wavelet_tables_mb": dp["tables_mb"],
            "wavelet_build_s": dp["build_cpu_s"], "rho_d_median_rel_err": ps["rho_d_median_rel_err"],
            "rho_s_rel_err": ps["rho_s_max_abs"], "fps_rgb_update": rate["fps_cpu"],
            "fps_rgb_update_near_field": rate_nf["fps_cpu"],
            "rho_d_dark_bias": dark[True]["bias"]}


if __name__ == "__main__":  # pragma: no cover
    import json
    import sys
    from pathlib import Path

    from ..runner import BenchContext

    ctx = BenchContext(workdir=Path("out/bench"), quick="--full" not in sys.argv)
    print(json.dumps(run(ctx), indent=2))
    print(json.dumps(ctx.extra["rgb"], indent=2, default=float))
