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
- ``marker_detect_rate``: frames with all four circles found / frames where all four are fully visible;
- ``white_err``: median over frames of the largest channel error of a held-out circle after white
  balance from the other three (relative to its white level);
- ``fps_tracking_fusion``: 1 / median time of tracking + fusion (not marker detection) of
  640 x 480 depth frames.
"""

from __future__ import annotations

import time

import numpy as np

BUDGET_S = (40.0, 120.0)


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
    ate = float(np.sqrt(np.nanmean(np.sum((res.poses[:, :3, 3] - seq.poses[:, :3, 3]) ** 2, axis=1))))

    truth = o3d.t.geometry.RaycastingScene()
    truth.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(seq.object_mesh))
    ours = o3d.t.geometry.RaycastingScene()
    ours.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(res.mesh))
    acc = truth.compute_distance(o3d.core.Tensor(
        np.asarray(res.mesh.sample_points_uniformly(50000).points, np.float32))).numpy()
    vis = seq.visible_points[seq.visible_points[:, 2] > res.box.z_min].astype(np.float32)
    comp = ours.compute_distance(o3d.core.Tensor(vis)).numpy()
    chamfer = float((acc.mean() + comp.mean()) / 2)
    gn = truth.compute_closest_points(o3d.core.Tensor(res.points.astype(np.float32)))["primitive_normals"].numpy()
    nerr = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", res.normals, gn)), 0, 1)))
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
        "chamfer_accuracy_mm": float(acc.mean() * 1e3), "chamfer_completeness_mm": float(comp.mean() * 1e3),
        "normal_err_raw_deg": float(np.median(np.degrees(np.arccos(np.clip(
            np.abs(np.einsum("ij,ij->i", res.raw_normals, gn)), 0, 1))))),
        "marker_center_err_mm": float(np.linalg.norm(res.marker_centers - seq.marker_centers, axis=1).max() * 1e3),
        "box_half_side_err_mm": float(abs(res.box.half_x - seq.side / 2) * 1e3),
        "white_err_max": float(max(werr)) if werr else None,
        "source": "appfusion.geometry_synth (own ray-cast sequence; replay/synth to be wired in)",
    }
    return {
        "ate_mm": ate * 1e3,
        "chamfer_mm": chamfer * 1e3,
        "normal_err_deg": float(np.median(nerr)),
        "marker_detect_rate": detect_rate,
        "white_err": float(np.median(werr)) if werr else None,
        "fps_tracking_fusion": 1.0 / frame_s,
    }
