"""Measure the synthetic renderer's own error against its brute-force reference.

For a few frames of a scene, the fast RGB renderer (:func:`replay.synth.render.shade_object`) is run
on randomly chosen object pixels and compared with :func:`replay.synth.render.reference_radiance` at
the same surface points (16 times more samples in every part of the integral, exact visibility for
every sample, no per-vertex interpolation of irradiance or visibility). Reported per RGB channel over
all chosen pixels: the RMS relative error and the mean relative error (bias).
"""

from __future__ import annotations

import time

import numpy as np

from . import camera as C
from . import envmaps
from .objects import build_object
from .render import KIND_OBJECT, Quality, Scene, SupportPlane, reference_radiance, shade_object
from .scanner import camera_rays


def render_error(scene: str = "two-material", n_pixels: int = 200, frames: int = 2, size=(320, 240), seed: int = 0,
                 detail: str = "full", quality: Quality | None = None, env: str = "office", plane: bool = True,
                 factor: int = 16, cache_dir=None) -> dict:
    """RMS and mean relative error of the fast renderer against the 16x reference.

    Returns a dict: ``rms_rel``, ``mean_rel`` (bias), ``max_rel``, ``n`` (pixel-channels), per-part
    magnitudes, timings (``fast_s_per_pixel``, ``reference_s``) and the settings.
    """
    quality = quality or Quality()
    obj = build_object(scene, detail, seed)
    sc = Scene(envmaps.get(env), obj=obj, plane=SupportPlane() if plane else None, quality=quality)
    t0 = time.perf_counter()
    sc.ensure_lighting(cache_dir=cache_dir)
    t_pre = time.perf_counter() - t0
    w, h = size
    intr = C.rgb_intrinsics(w, h)
    height = float(obj.vertices[:, 2].max())
    _, poses = C.orbit_path(max(frames, 2) * 7, seed + 17, C.PathParams(target_height_m=0.5 * height))
    rng = np.random.default_rng(seed)
    fast, ref, parts_spec = [], [], []
    part_err: dict = {}
    t_fast = t_ref = 0.0
    npx = 0
    for k in range(frames):
        pose = poses[k * 7]
        o, d, _ = camera_rays(pose, intr)
        hits = sc.intersect(np.ascontiguousarray(o), d)
        idx = np.nonzero(hits.kind == KIND_OBJECT)[0]
        if len(idx) == 0:
            continue
        pick = rng.choice(idx, size=min(n_pixels // frames, len(idx)), replace=False)
        t0 = time.perf_counter()
        Lf, parts = shade_object(sc, hits, pick, pose[:3, 3], rng, return_parts=True)
        t_fast += time.perf_counter() - t0
        npx += len(pick)
        p, n, ng = hits.point[pick], hits.normal[pick], hits.gnormal[pick]
        wo = pose[:3, 3] - p
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        ng = np.where((np.einsum("ij,ij->i", ng, wo) < 0)[:, None], -ng, ng)
        mat = obj.face_material[hits.prim[pick]]
        t0 = time.perf_counter()
        Lr, rparts = reference_radiance(sc, p, n, ng, wo, parts["rho_d"], mat, factor=factor, seed=seed + 99 + k,
                                        return_parts=True)
        for key in rparts:
            part_err.setdefault(key, []).append((parts[key] - rparts[key]) / np.maximum(Lr, 1e-9))
        t_ref += time.perf_counter() - t0
        fast.append(Lf)
        ref.append(Lr)
        parts_spec.append((parts["spec_emitters"] + parts["spec_background"]) / np.maximum(Lr, 1e-9))
    Lf, Lr = np.concatenate(fast), np.concatenate(ref)
    ok = Lr > 1e-6
    rel = (Lf[ok] - Lr[ok]) / Lr[ok]
    spec_frac = np.concatenate(parts_spec)[ok]
    return {"scene": scene, "env": env, "plane": plane, "pixels": int(npx), "n": int(rel.size),
            "rms_rel": float(np.sqrt(np.mean(rel ** 2))), "mean_rel": float(np.mean(rel)),
            "p95_abs_rel": float(np.percentile(np.abs(rel), 95)), "max_abs_rel": float(np.abs(rel).max()),
            "part_rms_rel": {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in part_err.items()},
            "part_mean_rel": {k: float(np.mean(np.concatenate(v))) for k, v in part_err.items()},
            "mean_specular_fraction": float(spec_frac.mean()), "max_specular_fraction": float(spec_frac.max()),
            "precompute_s": t_pre, "fast_s_per_pixel": t_fast / max(npx, 1), "reference_s": t_ref,
            "quality": quality.to_json(), "factor": factor, "size": list(size)}


def frame_timing(scene: str = "two-material", size=(320, 240), frames: int = 3, seed: int = 0, detail: str = "full",
                 quality: Quality | None = None, cache_dir=None) -> dict:
    """Seconds to render one frame of every stream (depth + IR from the depth camera, RGB from the RGB
    camera, camera models included, PNG writing excluded) of the object pass, averaged over ``frames``
    poses after one warm-up frame; the light transport precomputation is timed apart."""
    from .scanner import render_depth_ir, render_radiance
    from .sensors import DepthModel, IRModel, RGBModel

    quality = quality or Quality()
    obj = build_object(scene, detail, seed)
    sc = Scene(envmaps.office(), obj=obj, plane=SupportPlane(), quality=quality)
    t0 = time.perf_counter()
    sc.ensure_lighting(cache_dir=cache_dir)
    t_pre = time.perf_counter() - t0
    w, h = size
    di, ri = C.depth_intrinsics(w, h), C.rgb_intrinsics(w, h)
    off = np.linalg.inv(C.depth_to_rgb())
    _, poses = C.orbit_path(frames + 1, seed, C.PathParams(target_height_m=0.5 * float(obj.vertices[:, 2].max())))
    dm, ir, cam = DepthModel(), IRModel(seed=seed), RGBModel(seed=seed)
    ir.pattern()
    rng = np.random.default_rng(seed)
    t_d, t_r, px, cpu = [], [], [], []
    for k in range(frames + 1):
        c0 = time.process_time()
        t0 = time.perf_counter()
        render_depth_ir(sc, poses[k], di, dm, ir, rng, rng)
        t1 = time.perf_counter()
        L, kind = render_radiance(sc, poses[k] @ off, ri, rng)
        cam.capture(L, 1.0, np.ones(3), rng)
        t2 = time.perf_counter()
        if k:
            t_d.append(t1 - t0)
            t_r.append(t2 - t1)
            cpu.append(time.process_time() - c0)
            px.append(int((kind == KIND_OBJECT).sum()))
    return {"scene": scene, "size": list(size), "depth_ir_s": float(np.mean(t_d)), "rgb_s": float(np.mean(t_r)),
            "all_streams_s": float(np.mean(t_d) + np.mean(t_r)), "cpu_s": float(np.mean(cpu)),
            "object_pixels": float(np.mean(px)),
            "precompute_s": t_pre}
