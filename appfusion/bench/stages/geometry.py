"""Bench stage ``geometry``: the geometry pass (paper §4.1, §4.2) against ground truth.

For now this stage renders its own sequence (:mod:`appfusion.geometry_synth`: an object of a box, a
sphere and a cylinder on a black plane with four white circles, ray cast with Kinect v1 depth noise,
IR speckle and per-frame RGB colour casts / exposures). The project's full synthetic scanner
(``replay/synth``) is to be wired in here by the integrator.

Metrics:

- ``ate_mm``: RMS camera-position error of the geometry pass (marker frame) over the sequence;
- ``chamfer_mm``: symmetric mean distance between the mesh in the object box and the true object
  (mesh -> object surface, and object points seen in some frame -> mesh);
- ``normal_err_deg``: median angle between the sampled points' filtered normals and the true ones;
- ``crease_normal_err_deg``: the same over the points near the box's and the cylinder's sharp edges
  (a point within 6 mm of another whose true normal differs by over 30 degrees), normals sharpened
  at creases (:func:`appfusion.points.sharpen_creases`, session 17); on the full bench
  ``extra["geometry"]["crease"]`` also holds the figure without the sharpening (``GeometryPass.result`` again with
  ``GeometryConfig.crease_radius_voxels = None``) and the seconds each took;
- ``marker_detect_rate``: frames with all four circles found / frames where all four are fully visible;
- ``white_err``: median over frames of the largest channel error of a held-out circle after white
  balance from the other three (relative to its white level);
- ``fps_tracking_fusion``: 1 / median time of tracking + fusion (not marker detection) of
  640 x 480 depth frames;
- ``skip_fusion_saving``: "frames that add no new coverage skip fusion" (issue #11,
  ``FusionConfig.keyframe_m`` / ``keyframe_deg``): the fraction of the geometry pass's CPU time saved
  on a sequence as dense as a hand-held 30 fps scan (0.5 degrees of orbit per frame), keyframes on
  against off; the before / after chamfer, normal error and ATE are in ``extra["geometry"]
  ["skip_fusion"]`` (the full bench also sweeps the thresholds: knob ``fusion_keyframe``).
"""

from __future__ import annotations

import time

import numpy as np

BUDGET_S = (40.0, 180.0)

#: keyframe thresholds (metres, degrees) measured by the skip; "off" integrates every frame
KEYFRAME_SETTINGS = {"off": (0.0, 0.0), "1cm/2deg": (0.01, 2.0), "2cm/4deg": (0.02, 4.0), "4cm/8deg": (0.04, 8.0)}


def geometry_errors(seq, res) -> dict[str, float]:
    """Chamfer (mm), median normal error (deg) and ATE (mm) of a geometry-pass result against the
    sequence's truth (see the module docstring); mesh samples drawn with a fixed seed."""
    import open3d as o3d

    truth = o3d.t.geometry.RaycastingScene()
    truth.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(seq.object_mesh))
    ours = o3d.t.geometry.RaycastingScene()
    ours.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(res.mesh))
    o3d.utility.random.seed(1)
    acc = truth.compute_distance(o3d.core.Tensor(
        np.asarray(res.mesh.sample_points_uniformly(50000).points, np.float32))).numpy()
    vis = seq.visible_points[seq.visible_points[:, 2] > res.box.z_min].astype(np.float32)
    comp = ours.compute_distance(o3d.core.Tensor(vis)).numpy()
    gn = truth.compute_closest_points(o3d.core.Tensor(res.points.astype(np.float32)))["primitive_normals"].numpy()
    nerr = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", res.normals, gn)), 0, 1)))
    ate = float(np.sqrt(np.nanmean(np.sum((res.poses[:, :3, 3] - seq.poses[:, :3, 3]) ** 2, axis=1))))
    return {"chamfer_mm": float((acc.mean() + comp.mean()) / 2 * 1e3), "normal_err_deg": float(np.median(nerr)),
            "ate_mm": ate * 1e3, "chamfer_accuracy_mm": float(acc.mean() * 1e3),
            "chamfer_completeness_mm": float(comp.mean() * 1e3), "_nerr": nerr, "_truth": truth}


def default_keyframe_setting() -> str:
    """Name in :data:`KEYFRAME_SETTINGS` of :class:`~appfusion.fusion.FusionConfig`'s default thresholds."""
    from appfusion.fusion import FusionConfig

    fc = FusionConfig()
    for name, (km, kd) in KEYFRAME_SETTINGS.items():
        if (km, kd) == (fc.keyframe_m, fc.keyframe_deg):
            return name
    KEYFRAME_SETTINGS["default"] = (fc.keyframe_m, fc.keyframe_deg)
    return "default"


def keyframe_skip(quick: bool, seed: int, settings=None, repeats: int = 1) -> dict:
    """The geometry pass on a dense (hand-held 30 fps-like) sequence with each keyframe setting.

    Parameters
    ----------
    quick : bool
        60 frames over 30 degrees (else 120 over 60), 320 x 240; 0.5 degrees and ~4 mm per frame.
    seed : int
    settings : dict, optional
        ``{name: (keyframe_m, keyframe_deg)}``; default :data:`KEYFRAME_SETTINGS`.
    repeats : int
        Runs per setting; the CPU time is the smallest (the machine may be shared).

    Returns
    -------
    dict
        ``{name: {"cpu_ms_per_frame", "wall_ms_per_frame", "integrated", "skipped", "lost", "chamfer_mm",
        "normal_err_deg", "ate_mm"}}`` plus ``"frames"``, ``"degrees_per_frame"``.
    """
    from appfusion.fusion import FusionConfig, voxel_size_for_box
    from appfusion.geometry_pass import GeometryConfig, GeometryPass
    from appfusion.geometry_synth import make_sequence

    n, sweep = (60, 30.0) if quick else (120, 60.0)
    seq = make_sequence(n, 320, 240, seed=seed + 7, sweep_deg=sweep, colour_cast=False)
    out: dict = {"frames": n, "degrees_per_frame": sweep / n, "size": [320, 240]}
    for name, (km, kd) in (settings or KEYFRAME_SETTINGS).items():
        best = None
        for _ in range(repeats):
            fc = FusionConfig(voxel_size=voxel_size_for_box(seq.side), keyframe_m=km, keyframe_deg=kd)
            gp = GeometryPass(GeometryConfig(n_points=30_000, seed=seed, fusion=fc, fixed_voxel=True),
                              meta={"extra": seq.meta_extra})
            c0, w0 = time.process_time(), time.perf_counter()
            for f in seq.frames:
                gp.add_frame(f)
            cpu, wall = time.process_time() - c0, time.perf_counter() - w0
            if best is None or cpu < best[0]:
                best = (cpu, wall, gp)
        cpu, wall, gp = best
        err = geometry_errors(seq, gp.result())
        out[name] = {"keyframe_m": km, "keyframe_deg": kd, "cpu_ms_per_frame": 1e3 * cpu / n,
                     "wall_ms_per_frame": 1e3 * wall / n, "integrated": gp.fusion.n_integrated,
                     "skipped": gp.fusion.n_skipped, "lost": sum(s.state == "lost" for s in gp.states),
                     **{k: v for k, v in err.items() if not k.startswith("_")}}
    return out


def run(ctx) -> dict:
    import open3d as o3d

    from appfusion.frame import invert_pose
    from appfusion.fusion import FusionConfig, TSDFFusion
    from appfusion.geometry_pass import GeometryConfig, GeometryPass
    from appfusion.geometry_synth import make_sequence
    from calibration.white_balance import WhiteBalancer, circle_pixel_masks

    n_frames = 30 if ctx.quick else 60
    size = (320, 240) if ctx.quick else (640, 480)
    n_points = 30_000 if ctx.quick else 100_000
    t0 = time.perf_counter()
    seq = make_sequence(n_frames, *size, seed=ctx.seed)
    t_render = time.perf_counter() - t0

    # -- the geometry pass --------------------------------------------------------------------------
    gp = GeometryPass(GeometryConfig(n_points=n_points, seed=ctx.seed), meta={"extra": seq.meta_extra})
    states = [gp.add_frame(f) for f in seq.frames]
    t1 = time.perf_counter()
    res = gp.result()
    t_result = time.perf_counter() - t1
    err = geometry_errors(seq, res)
    truth, nerr = err["_truth"], err["_nerr"]
    gn = truth.compute_closest_points(o3d.core.Tensor(res.points.astype(np.float32)))["primitive_normals"].numpy()
    # -- normals at sharp edges, with and without sharpen_creases ------------------------------------
    from scipy.spatial import cKDTree

    def near_crease(points, normals_true):
        """Points within 6 mm of another whose true normal differs by over 30 degrees."""
        d, j = cKDTree(points).query(points, k=48, distance_upper_bound=0.006)
        ok = np.isfinite(d)
        cosg = np.abs(np.einsum("nkc,nc->nk", normals_true[np.where(ok, j, 0)], normals_true))
        return (ok & (cosg < np.cos(np.radians(30.0)))).any(1)

    near = near_crease(res.points, gn)
    crease = {"points": int(near.sum()), "median_deg": float(np.median(nerr[near])) if near.any() else None,
              "p90_deg": float(np.percentile(nerr[near], 90)) if near.any() else None}
    if not ctx.quick:                       # the same without the sharpening (5-10 s more)
        gp.config.crease_radius_voxels = None
        t2 = time.perf_counter()
        res_off = gp.result()
        t_off = time.perf_counter() - t2
        gp.config.crease_radius_voxels = GeometryConfig().crease_radius_voxels
        gn_off = truth.compute_closest_points(o3d.core.Tensor(res_off.points.astype(np.float32)))["primitive_normals"].numpy()
        nerr_off = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", res_off.normals, gn_off)), 0, 1)))
        near_off = near_crease(res_off.points, gn_off)
        crease.update({"points_off": int(near_off.sum()),
                       "median_deg_off": float(np.median(nerr_off[near_off])) if near_off.any() else None,
                       "p90_deg_off": float(np.percentile(nerr_off[near_off], 90)) if near_off.any() else None,
                       "seconds_with": round(t_result, 2), "seconds_without": round(t_off, 2),
                       "normal_err_deg_off": float(np.median(nerr_off))})
    visible = seq.markers_visible.all(1)
    found = np.array([s.markers_complete for s in states])
    detect_rate = float(found[visible].mean()) if visible.any() else None

    # -- white balance, leave one circle out ----------------------------------------------------------
    up = np.array([0.0, 0.0, 1.0])
    werr = []
    for hold in range(4):
        use = [i for i in range(4) if i != hold]
        wb = WhiteBalancer(res.marker_centers[use], gp.marker_config.radius_m)
        for f, pose in zip(seq.frames, res.poses):
            r = wb.balance(f, pose)
            if r.flagged:
                continue
            m = circle_pixel_masks(seq.marker_centers[[hold]], seq.marker_radius, up,
                                   invert_pose(seq.poses[f.index] @ invert_pose(f.depth_to_rgb)), f.rgb_intrinsics)[0]
            if m is None:
                continue
            mask, (r0, r1, c0, c1) = m
            werr.append(float(np.abs(r.rgb[r0:r1, c0:c1][mask].mean(0) / wb.white_level - 1).max()))

    # -- speed of tracking + fusion at 640 x 480 ------------------------------------------------------
    sp = seq if size == (640, 480) else make_sequence(12, 640, 480, seed=ctx.seed + 1, colour_cast=False)
    fu = TSDFFusion(sp.intrinsics, FusionConfig(), initial_pose=sp.poses[0])
    h = sp.side / 2 + 0.05
    fu.set_roi(np.eye(4), [-h, -h, -0.05], [h, h, 0.35])
    times, parts = [], {}
    for f in sp.frames:
        t = time.perf_counter()
        r = fu.process(f.depth)
        times.append(time.perf_counter() - t)
        for k, v in r.ms.items():
            parts.setdefault(k, []).append(v)
    frame_s = float(np.median(times[1:]))

    ctx.extra["geometry"] = {
        "frames": n_frames, "size": list(size), "n_points": n_points, "voxel_mm": res.voxel_size * 1e3,
        "lost_frames": res.lost_frames, "render_s": round(t_render, 2), "result_s": round(t_result, 2),
        "ms_per_frame_geometry_pass": {k: round(float(np.median([s.ms.get(k, 0.0) for s in states[1:]])), 2)
                                       for k in ("markers", "prep", "raycast", "track", "integrate")},
        "ms_per_frame_tracking_fusion_640": {k: round(float(np.median(v[1:])), 2) for k, v in parts.items()},
        "chamfer_accuracy_mm": err["chamfer_accuracy_mm"], "chamfer_completeness_mm": err["chamfer_completeness_mm"],
        "normal_err_raw_deg": float(np.median(np.degrees(np.arccos(np.clip(
            np.abs(np.einsum("ij,ij->i", res.raw_normals, gn)), 0, 1))))),
        "marker_center_err_mm": float(np.linalg.norm(res.marker_centers - seq.marker_centers, axis=1).max() * 1e3),
        "box_half_side_err_mm": float(abs(res.box.half_x - seq.side / 2) * 1e3),
        "white_err_max": float(max(werr)) if werr else None,
        "source": "appfusion.geometry_synth (own ray-cast sequence; replay/synth to be wired in)",
        "crease": crease,
    }
    # -- skip: frames that add no new coverage skip fusion -----------------------------------------------
    default = default_keyframe_setting()
    settings = KEYFRAME_SETTINGS if not ctx.quick else {"off": KEYFRAME_SETTINGS["off"], default: KEYFRAME_SETTINGS[default]}
    kf = keyframe_skip(ctx.quick, ctx.seed, settings, repeats=1 if ctx.quick else 2)
    off, on = kf["off"], kf[default]
    saving = 1.0 - on["cpu_ms_per_frame"] / off["cpu_ms_per_frame"]
    ctx.extra["geometry"]["skip_fusion"] = {**kf, "default": default, "saving": saving,
                                            "what": "CPU time of GeometryPass.add_frame (markers, tracking, fusion) "
                                                    "per frame, keyframes at the default setting against off"}
    if not ctx.quick:
        ctx.add_sweep("fusion_keyframe", "chamfer_mm", default,
                      [{"value": k, "ms_per_frame": kf[k]["cpu_ms_per_frame"], "error": kf[k]["chamfer_mm"]}
                       for k in settings],
                      note="keyframe thresholds of 'frames that add no new coverage skip fusion'. time = CPU ms "
                           "per frame of the geometry pass on a 0.5 deg/frame 320x240 sequence; error = chamfer mm")
    return {
        "skip_fusion_saving": saving,
        "ate_mm": err["ate_mm"],
        "chamfer_mm": err["chamfer_mm"],
        "normal_err_deg": float(np.median(nerr)),
        "crease_normal_err_deg": crease["median_deg"],
        "marker_detect_rate": detect_rate,
        "white_err": float(np.median(werr)) if werr else None,
        "fps_tracking_fusion": 1.0 / frame_s,
    }
