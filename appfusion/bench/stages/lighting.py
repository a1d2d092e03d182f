"""Bench stage ``lighting``: the mirror-ball lighting pass (paper §4.3) against a known environment.

For now the scene comes from a small generator in this module (NOT the project's synthetic scanner,
which the integrator will wire in later): a mirror ball on the support plane, reflecting an analytic
environment (sky gradient, a small bright "sun", two windows, a floor), is rendered analytically
(ray-sphere, supersampled pixels, 1% noise) by orbiting 640x480 cameras; its depth is what a
structured-light camera gets from a mirror (only the specular spot, wrong returns behind the surface,
the emitter's shadow beside the ball; see :func:`render_depth`). The stage fits the ball from the depth frames (specular spot + silhouette,
:func:`appfusion.sphere_fit.fit_mirror_ball`), accumulates the RGB frames and compares with the
environment averaged over each texel: the same figure as :func:`appfusion.evaluate.envmap_comparison`
(mean over RGB of ``|est - truth|`` over the truth's mean, median over measured, lit texels; here the
RGB is in the environment's own units and the ball sees the analytic floor, so no calibration and no
plane mask are needed).

Reported: ``envmap_median_rel_err`` and ``sphere_center_err_mm``; extra figures (energy error, radius
error, coverage, timings) go to ``ctx.extra["lighting"]``.

``python -m appfusion.bench.stages.lighting --figure docs/img/lighting-filling.png`` draws the map
filling in over the pass (the figure of docs/lighting-pass.md).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ... import octahedral as octa
from ...frame import Intrinsics, invert_pose, make_pose

INTR = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
BALL_C = np.array([-0.01, 0.015, 0.06])
BALL_R = 0.06
BOX = np.array([[-0.2, -0.2, 0.008], [0.2, 0.2, 0.3]])
DEPTH_TO_RGB = make_pose(None, [-0.025, 0.0, 0.0])
SUN = np.array([0.5, -0.3, 0.81]) / np.linalg.norm([0.5, -0.3, 0.81])
#: the depth camera's emitter in its own frame (Kinect v1)
EMITTER = np.array([0.075, 0.0, 0.0])


def environment(d: np.ndarray) -> np.ndarray:
    """Radiance (..., 3) of the bench environment (marker frame, z up) in unit directions d (..., 3)."""
    d = np.asarray(d, dtype=np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    up = np.clip(z, 0, 1)[..., None]
    sky = np.array([0.35, 0.45, 0.7]) * (0.6 + 0.8 * up) + np.array([0.25, 0.2, 0.1]) * (1 - up)
    floor = np.array([0.3, 0.26, 0.22]) * (0.7 + 0.3 * np.abs(x))[..., None]
    out = np.where((z >= 0)[..., None], sky, floor)
    sun = (d @ SUN > np.cos(np.radians(6.0)))[..., None] * np.array([9.0, 8.5, 7.5])
    win1 = ((np.abs(np.arctan2(y, x) - 2.2) < 0.3) & (z > 0.1) & (z < 0.5))[..., None] * np.array([2.0, 2.1, 2.3])
    win2 = ((np.abs(np.arctan2(y, x) + 1.8) < 0.2) & (z > -0.05) & (z < 0.35))[..., None] * np.array([1.5, 1.4, 1.2])
    return out + sun + win1 + win2


def truth_map(n: int, sub: int = 6) -> np.ndarray:
    """The environment averaged over every texel of a (2, n, n) octahedral map, (2, n, n, 3)."""
    return environment(octa.sphere_directions(n * sub)).reshape(2, n, sub, n, sub, 3).mean(axis=(2, 4))


def camera_poses(k: int, seed: int, dist: float = 0.75, arc_deg: float = 360.0) -> list[np.ndarray]:
    """Depth-camera poses on an orbit around the ball (elevation 15-60 deg), looking near its centre;
    ``arc_deg`` < 360 keeps the cameras on part of the circle (a user who does not walk all round)."""
    rng = np.random.default_rng(seed)
    poses = []
    for i in range(k):
        az = np.radians(arc_deg) * (i + 0.3 * rng.random()) / k
        el = np.radians(15 + 45 * rng.random())
        eye = BALL_C + dist * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        f = BALL_C + rng.normal(0, 0.02, 3) - eye
        f /= np.linalg.norm(f)
        r = np.cross(f, [0, 0, 1.0])
        r /= np.linalg.norm(r)
        poses.append(make_pose(np.stack([r, np.cross(f, r), f], axis=1), eye))
    return poses


def _rays(pose: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d, d @ pose[:3, :3].T


def _ball_hit(o: np.ndarray, dw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    oc = o - BALL_C
    b = dw @ oc
    disc = b * b - oc @ oc + BALL_R ** 2
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return (disc > 0) & (t > 0), t


def render_rgb(pose_rgb: np.ndarray, rng: np.random.Generator, ss: int = 3) -> np.ndarray:
    """Linear RGB (480, 640, 3) of the ball, ss x ss samples per pixel (only a window around it)."""
    img = np.full((INTR.height, INTR.width, 3), 0.25, np.float32)
    Ti = invert_pose(pose_rgb)
    cc = Ti[:3, :3] @ BALL_C + Ti[:3, 3]
    uc, vc = INTR.fx * cc[0] / cc[2] + INTR.cx, INTR.fy * cc[1] / cc[2] + INTR.cy
    half = 1.6 * INTR.fx * BALL_R / cc[2] + 6
    x0, x1 = max(int(uc - half), 0), min(int(uc + half) + 1, INTR.width)
    y0, y1 = max(int(vc - half), 0), min(int(vc + half) + 1, INTR.height)
    v, u = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    acc = np.zeros(v.shape + (3,))
    o = pose_rgb[:3, 3]
    for k in range(ss * ss):
        du, dv = (k % ss + 0.5) / ss - 0.5, (k // ss + 0.5) / ss - 0.5
        _, dw = _rays(pose_rgb, u + du, v + dv)
        hit, t = _ball_hit(o, dw)
        nrm = (o + t[..., None] * dw - BALL_C) / BALL_R
        refl = dw - 2 * (dw * nrm).sum(-1, keepdims=True) * nrm
        acc += np.where(hit[..., None], environment(refl), 0.25)
    acc /= ss * ss
    img[y0:y1, x0:x1] = acc * (1 + 0.01 * rng.normal(size=acc.shape)) + 0.003 * rng.normal(size=acc.shape)
    return img


def render_depth(pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Kinect-like depth of the MIRROR ball (metres, NaN invalid), as a structured-light camera sees a mirror:
    depth only at the specular spot (normal within 5 deg of the bisector of the directions to the camera
    and to the emitter ``EMITTER``; 3 mm noise), 3% of the other ball pixels a wrong return behind the
    surface by |N(0, 2 cm)|, the rest of the ball invalid; the support plane z = 0 around it (1.5 mm noise)
    except in the ball's shadow from the emitter."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width].astype(np.float64)
    dc, dw = _rays(pose, u, v)
    o = pose[:3, 3]
    hit, t = _ball_hit(o, dw)
    nrm_c = ((o + t[..., None] * dw - BALL_C) / BALL_R) @ pose[:3, :3]      # normal, camera frame
    pc = t[..., None] * dc
    h = -pc / np.linalg.norm(pc, axis=-1, keepdims=True)
    to_em = EMITTER - pc
    h = h + to_em / np.linalg.norm(to_em, axis=-1, keepdims=True)
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    spot = hit & ((nrm_c * h).sum(-1) >= np.cos(np.radians(5.0)))
    z = np.full(u.shape, np.nan)
    zb = t * dc[..., 2]
    z[spot] = zb[spot] + rng.normal(0, 0.003, int(spot.sum()))
    bad = hit & ~spot & (rng.random(u.shape) < 0.03)
    z[bad] = zb[bad] + np.abs(rng.normal(0, 0.02, int(bad.sum())))
    plane = ~hit & (dw[..., 2] < -1e-9)
    t_plane = -o[2] / np.where(plane, dw[..., 2], -1.0)
    P = o + t_plane[..., None] * dw
    seg = (pose[:3, :3] @ EMITTER + o) - P                                   # towards the emitter
    L = np.linalg.norm(seg, axis=-1)
    sd = seg / np.maximum(L, 1e-12)[..., None]
    oc = P - BALL_C
    b = (sd * oc).sum(-1)
    disc = b * b - (oc * oc).sum(-1) + BALL_R ** 2
    ts = -b - np.sqrt(np.maximum(disc, 0.0))
    lit = plane & ~((disc > 0) & (ts > 0) & (ts < L))
    z[lit] = (t_plane * dc[..., 2])[lit] + rng.normal(0, 0.0015, int(lit.sum()))
    return z.astype(np.float32)


def run_scene(n: int, n_rgb: int, n_depth: int, seed: int = 0, snapshots: tuple[int, ...] = (),
              arc_deg: float = 360.0, **pass_kwargs) -> dict[str, Any]:
    """Run the lighting pass on the generated scene; returns metrics, timings and optional snapshots.

    ``pass_kwargs`` go to :class:`~appfusion.lighting_pass.LightingPass`.
    """
    from ...lighting_pass import LightingPass

    rng = np.random.default_rng(seed)
    pass_kwargs = {"emitter": EMITTER, **pass_kwargs}
    lp = LightingPass(n=n, box=BOX, **pass_kwargs)
    for p in camera_poses(n_depth, seed + 1):
        lp.add_depth(render_depth(p, rng), INTR, p)
    t0 = time.perf_counter()
    fit = lp.fit()
    fit_s = time.perf_counter() - t0
    snaps = []
    t_rgb = 0.0
    for i, p in enumerate(camera_poses(n_rgb, seed + 2, arc_deg=arc_deg)):
        pose_rgb = p @ invert_pose(DEPTH_TO_RGB)
        img = render_rgb(pose_rgb, rng)
        t0 = time.perf_counter()
        lp.add_rgb(img, INTR, pose_rgb)
        t_rgb += time.perf_counter() - t0
        if i + 1 in snapshots:
            snaps.append((i + 1, lp.envmap()))
    env = lp.envmap()
    gt = truth_map(n)
    lum = gt.mean(-1)
    m = env.coverage & (lum > 0.05 * np.median(lum))
    rel = np.abs(env.radiance - gt).mean(-1)[m] / lum[m]
    w = env.solid_angles()[m][:, None]
    energy = (env.radiance[m] * w).sum(0) / (gt[m] * w).sum(0) - 1
    return {
        "envmap_median_rel_err": float(np.median(rel)),
        "envmap_p90_rel_err": float(np.percentile(rel, 90)),
        "energy_rel_err": float(np.abs(energy).max()),
        "coverage": env.coverage_fraction(),
        "sphere_center_err_mm": 1000 * float(np.linalg.norm(fit.center - BALL_C)),
        "sphere_radius_rel_err": float(abs(fit.radius - BALL_R) / BALL_R),
        "sphere_fit_s": fit_s,
        "ms_per_rgb_frame": 1000 * t_rgb / n_rgb,
        "n": n, "rgb_frames": n_rgb, "depth_frames": n_depth,
        "env": env, "snapshots": snaps,
    }


def run(ctx) -> dict[str, float]:
    """Bench entry point. Quick: n = 64, 16 RGB views, 3 depth views; full: n = 128, 48 and 8."""
    n, n_rgb, n_depth = (64, 16, 3) if ctx.quick else (128, 48, 8)
    res = run_scene(n, n_rgb, n_depth, seed=ctx.seed)
    ctx.extra["lighting"] = {k: v for k, v in res.items() if k not in ("env", "snapshots")}
    ctx.extra["lighting"]["source"] = "appfusion.bench.stages.lighting generator (not the synthetic scanner yet)"
    return {"envmap_median_rel_err": res["envmap_median_rel_err"],
            "sphere_center_err_mm": res["sphere_center_err_mm"]}


def figure(path: str, n: int = 128, steps: tuple[int, ...] = (1, 2, 4, 24), seed: int = 0) -> dict[str, Any]:
    """Write the 'map filling in' figure as a PNG: previews after ``steps`` views (one exposure; grey
    checkerboard = not seen yet), then the one-view map with its holes filled (blue hatching = filled)."""
    import cv2

    from ...envmap import filling_strip

    res = run_scene(n, max(steps), 4, seed=seed, snapshots=steps)
    final = res["snapshots"][-1][1]
    panels = [(f"{k} view{'s' if k > 1 else ''}", e) for k, e in res["snapshots"]]
    panels.append(("1 view, filled", res["snapshots"][0][1].fill("harmonic")))
    img = filling_strip(panels, exposure=final.auto_exposure(), columns=3, scale=1)
    cv2.imwrite(path, img[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return {k: v for k, v in res.items() if k not in ("env", "snapshots")}


if __name__ == "__main__":  # pragma: no cover - documentation helper
    import argparse
    import json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--figure", help="write the filling-in figure to this PNG")
    ap.add_argument("--full", action="store_true", help="full-size run (n = 128, 48 views)")
    a = ap.parse_args()
    if a.figure:
        print(json.dumps(figure(a.figure), indent=2))
    else:
        from types import SimpleNamespace
        c = SimpleNamespace(quick=not a.full, seed=0, extra={})
        print(json.dumps({**run(c), **c.extra["lighting"]}, indent=2))
