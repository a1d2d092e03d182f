"""Render complete synthetic scan sessions (our session format) with a ``truth/`` folder.

:func:`render_session` writes, for one object (``objects.OBJECTS``), the paper's passes in order:

``kinect1`` (a Kinect v1 cannot stream IR and RGB at once)
    ``ir-calibration`` (20 emitter-off frames, then a white sheet at 0.5 ... 1.2 m, 3 frames each;
    depth + IR), ``environment`` (the mirror ball, object absent; depth + RGB), ``geometry`` (the
    object; depth + IR), ``rgb`` (the object; depth + RGB).
``allinone`` (a device that streams depth, IR and RGB in every frame)
    ``ir-calibration``, ``environment``, ``scan``.

Each pass of the object/ball gets ``frames`` frames on its own hand-held orbit; frames are 1/30 s
apart, passes 2 s apart. The session holds no pose (the engine must track); exact poses of the
depth camera are in ``truth/groundtruth.txt``.

``truth/`` (never read by the engine): ``groundtruth.txt`` (TUM), ``object.npz``, ``materials.json``,
``envmaps/{office,sunset}.{exr,hdr}``, ``markers.json``, ``ir_model.json`` + ``ir_pattern.npz``,
``frames.json`` (per-frame exposure, white balance, emitter state, sheet distance), ``scene.json``
(every parameter and the seed) and ``references/`` (the object alone, no plane, under ``sunset`` from
three new views: linear EXR, sRGB PNG, mask PNG, poses and intrinsics in ``views.json``).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from appfusion.errors import AppFusionError
from appfusion.frame import Frame, Intrinsics, invert_pose

from . import camera as C
from . import envmaps
from . import materials as M
from .objects import OBJECTS, ObjectModel, build_object
from .render import (EPS_RAY, KIND_BALL, KIND_NONE, KIND_OBJECT, KIND_PLANE, KIND_SHEET, MirrorBall, Quality,
                     Scene, Sheet, SupportPlane, shade_object, shade_simple)
from .sensors import DepthModel, IRModel, RGBModel

DEVICES = ("kinect1", "allinone")
CALIB_OFF_FRAMES = 20
CALIB_DISTANCES_M = (0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2)
CALIB_FRAMES_EACH = 3
PASS_GAP_S = 2.0
FORMAT_VERSION = 1
#: frames per object/ball pass of the demo: 200 at 30 fps is 6.7 s of scanning a pass (the paper's users
#: scan for minutes); at 100 the dark channels' sensor noise alone left rho_d ~1 point less accurate
DEMO_FRAMES = 200


# -- rendering one frame ----------------------------------------------------------------------------

_RAY_CACHE: dict = {}


def camera_rays(pose: np.ndarray, intr: Intrinsics):
    """World-space origins (N, 3), unit directions (N, 3) of every pixel (row-major) and the length of
    each pixel's unit-z ray (N,) (depth z = t / length)."""
    key = intr.to_json().__repr__()
    if key not in _RAY_CACHE:
        r = intr.rays().reshape(-1, 3).astype(np.float64)
        norm = np.sqrt(np.einsum("ij,ij->i", r, r))
        _RAY_CACHE.clear() if len(_RAY_CACHE) > 8 else None
        _RAY_CACHE[key] = (r / norm[:, None], norm)
    u, norm = _RAY_CACHE[key]
    d = np.einsum("ij,kj->ik", u, pose[:3, :3])
    o = np.broadcast_to(pose[:3, 3], d.shape)
    return o, d, norm


@dataclass
class DepthIR:
    depth: np.ndarray | None
    ir: np.ndarray | None
    radiance_ir: np.ndarray
    z_true: np.ndarray
    kind: np.ndarray


def render_depth_ir(scene: Scene, pose: np.ndarray, intr: Intrinsics, depth_model: DepthModel, ir_model: IRModel,
                    rng_depth: np.random.Generator, rng_ir: np.random.Generator, emitter: bool = True,
                    want_depth: bool = True, want_ir: bool = True) -> DepthIR:
    """Depth and IR images of the depth/IR camera (Kinect v1: one camera, emitter 7.5 cm to its +x).

    Parameters
    ----------
    scene : Scene
    pose : (4, 4) camera-to-world pose of the depth camera (marker frame)
    intr : Intrinsics of the depth camera
    depth_model, ir_model : the sensor models (:mod:`replay.synth.sensors`)
    rng_depth, rng_ir : numpy Generators of the two noises
    emitter : bool
        Emitter on; off means no depth at all and IR background only.
    want_depth, want_ir : bool

    Returns
    -------
    DepthIR
        ``depth`` (H, W) float32 metres, NaN invalid; ``ir`` (H, W) float32 counts 0..1023;
        ``radiance_ir`` (H, W) the IR radiance before the camera response; ``z_true`` (H, W) exact depth
        (NaN where nothing is hit); ``kind`` (H, W) what each pixel sees (render.KIND_*).
    """
    H, W = intr.shape
    o, d, rn = camera_rays(pose, intr)
    hits = scene.intersect(o, d)
    hit = hits.kind != KIND_NONE
    z = np.where(hit, hits.t / rn, np.nan)
    p, n = hits.point, hits.normal
    wo = -d
    cos_inc = np.einsum("ij,ij->i", n, wo)
    e_w = pose[:3, :3] @ np.asarray(ir_model.emitter_position_m) + pose[:3, 3]
    to_e = e_w - p
    de = np.linalg.norm(to_e, axis=1)
    wi = to_e / np.maximum(de, 1e-9)[:, None]
    cos_i = np.einsum("ij,ij->i", n, wi)
    lit = hit & (cos_i > 0)
    idx = np.nonzero(lit)[0]
    if len(idx):
        ng = hits.gnormal[idx]
        ng = np.where((np.einsum("ij,ij->i", ng, wi[idx]) < 0)[:, None], -ng, ng)
        occ = scene.occluded(p[idx] + EPS_RAY * ng, wi[idx], de[idx] - 2 * EPS_RAY)
        lit[idx[occ]] = False
    mirror = hits.kind == KIND_BALL
    cos_spec = np.einsum("ij,ij->i", n, M.normalize(wi + wo))
    depth = None
    if want_depth:
        if emitter:
            depth = depth_model.apply(z.reshape(H, W), cos_inc.reshape(H, W), lit.reshape(H, W), rng_depth,
                                      mirror.reshape(H, W), cos_spec.reshape(H, W))
        else:
            depth = np.full((H, W), np.nan, np.float32)  # no projected pattern, no depth
    R = np.zeros(H * W)
    if emitter and np.any(lit):
        v_cam = np.einsum("ij,jk->ik", p[lit] - e_w, pose[:3, :3])  # world -> camera axes
        x = ir_model.incident(v_cam)
        rho = np.zeros(lit.sum())
        spec = np.zeros(lit.sum())
        k = hits.kind[lit]
        li = np.nonzero(lit)[0]
        m = k == KIND_PLANE
        if np.any(m):
            fp = 0.5 * hits.t[li[m]] / intr.fx / np.maximum(cos_inc[li[m]], 0.2)
            rho[m] = scene.plane.ir_albedo_at(p[li[m], :2], fp)
        m = k == KIND_SHEET
        rho[m] = scene.sheet.ir_albedo if scene.sheet is not None else 0.0
        m = k == KIND_BALL
        rho[m] = 0.01
        m = k == KIND_OBJECT
        if np.any(m):
            obj = scene.obj
            jj = li[m]
            f = obj.faces[hits.prim[jj]]
            rho[m] = np.einsum("nk,nk->n", hits.bary[jj], obj.ir_rho_d[f])
            mat = obj.face_material[hits.prim[jj]]
            sv = np.zeros(len(jj))
            for mi in np.unique(mat):
                mt = obj.materials[mi]
                s = mat == mi
                if mt.ir_rho_s > 0 and mt.lobe != "mirror":
                    sv[s] = mt.ir_rho_s * M.lobe_eval(mt.lobe, mt.alpha, wi[jj[s]], wo[jj[s]], n[jj[s]])
            spec[m] = sv
        R[lit] = x * cos_i[lit] * (rho / np.pi + spec)
    ir = ir_model.counts(R.reshape(H, W), rng_ir) if want_ir else None
    return DepthIR(depth, ir, R.reshape(H, W), z.reshape(H, W), hits.kind.reshape(H, W))


def render_radiance(scene: Scene, pose_cam: np.ndarray, intr: Intrinsics, rng: np.random.Generator,
                    lobe_samples: int | None = None, supersample_ball: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB radiance seen by a camera (no camera model: see :class:`.sensors.RGBModel`).

    Parameters
    ----------
    scene : Scene
    pose_cam : (4, 4) camera-to-world pose of *this* camera (for the RGB camera of a depth pose ``P``:
        ``P @ inv(depth_to_rgb)``)
    intr : Intrinsics
    rng : numpy Generator (lobe sample jitter)
    lobe_samples : int, optional
    supersample_ball : bool
        Super-sample pixels on and around the mirror ball.

    Returns
    -------
    radiance : (H, W, 3) float64, the environment's units
    kind : (H, W) int8, what each pixel's centre ray hits (render.KIND_*)
    """
    H, W = intr.shape
    o, d, rn = camera_rays(pose_cam, intr)
    hits = scene.intersect(o, d)
    L = np.zeros((H * W, 3))
    obj = hits.kind == KIND_OBJECT
    if np.any(obj):
        L[obj] = shade_object(scene, hits, np.nonzero(obj)[0], pose_cam[:3, 3], rng, lobe_samples)
    rest = ~obj
    cos_inc = np.abs(np.einsum("ij,ij->i", hits.normal, d))
    fp = 0.5 * np.where(np.isfinite(hits.t), hits.t, 0) / intr.fx / np.maximum(cos_inc, 0.2)
    sub_hits = _subset(hits, rest)
    L[rest] = shade_simple(scene, o[rest], d[rest], sub_hits, fp[rest])
    kind = hits.kind.reshape(H, W)
    if supersample_ball and scene.ball is not None and np.any(kind == KIND_BALL):
        from scipy.ndimage import binary_dilation

        near = binary_dilation(kind == KIND_BALL, iterations=1).ravel()
        ss = scene.quality.ball_supersample
        ix = np.nonzero(near)[0]
        u, v = (ix % W).astype(np.float64), (ix // W).astype(np.float64)
        off = (np.arange(ss) + 0.5) / ss - 0.5
        ou, ov = np.meshgrid(off, off)
        uu = (u[:, None] + ou.ravel()[None]).ravel()
        vv = (v[:, None] + ov.ravel()[None]).ravel()
        r = np.stack([(uu - intr.cx) / intr.fx, (vv - intr.cy) / intr.fy, np.ones_like(uu)], axis=1)
        dd = np.einsum("ij,kj->ik", M.normalize(r), pose_cam[:3, :3])
        oo = np.broadcast_to(pose_cam[:3, 3], dd.shape).copy()
        sh = scene.intersect(oo, dd)
        Ls = np.zeros((len(dd), 3))
        so = sh.kind == KIND_OBJECT
        if np.any(so):
            Ls[so] = shade_object(scene, sh, np.nonzero(so)[0], pose_cam[:3, 3], rng, lobe_samples)
        ci = np.abs(np.einsum("ij,ij->i", sh.normal, dd))
        fps = 0.5 * np.where(np.isfinite(sh.t), sh.t, 0) / intr.fx / ss / np.maximum(ci, 0.2)
        Ls[~so] = shade_simple(scene, oo[~so], dd[~so], _subset(sh, ~so), fps[~so])
        L[ix] = Ls.reshape(len(ix), ss * ss, 3).mean(axis=1)
    return L.reshape(H, W, 3), kind


def _subset(h, m):
    from .render import Hits

    return Hits(h.t[m], h.kind[m], h.point[m], h.normal[m], h.gnormal[m], h.prim[m], h.bary[m])


# -- sessions -----------------------------------------------------------------------------------

@dataclass
class PassSpec:
    name: str
    scene_key: str
    streams: tuple
    times: np.ndarray
    poses: np.ndarray
    emitter: np.ndarray
    extra: dict = field(default_factory=dict)


def _parse_size(size) -> tuple[int, int]:
    if isinstance(size, str):
        try:
            w, h = (int(x) for x in size.lower().split("x"))
        except ValueError:
            raise AppFusionError(f"--size must look like 640x480, got {size!r}") from None
    else:
        w, h = (int(x) for x in size)
    if not (16 <= w <= 4096 and 16 <= h <= 4096):
        raise AppFusionError(f"image size {w}x{h} is out of range (16..4096)")
    return w, h


def _max_env_radiance(env: envmaps.Environment) -> float:
    d, _ = envmaps.latlong_cells(64)
    b = env.background_exact(d).max()
    e = max([em.radiance.max() for em in env.emitters], default=0.0)
    return float(b + e)


def scene_names() -> list[str]:
    """Names accepted by :func:`render_session`."""
    return list(OBJECTS)


def render_session(scene: str, out: str | os.PathLike, frames: int = 60, size=(640, 480), seed: int = 0,
                   device: str = "kinect1", detail: str = "full", quality: Quality | None = None,
                   radius_m: float = 0.6, references: bool = True, show_progress: bool = True,
                   cache_dir: str | os.PathLike | None = None, workers: int | None = None, log=None,
                   rgb_frames: int | None = None) -> Path:
    """Render a complete synthetic session of ``scene`` into the new directory ``out``; returns its path.

    Parameters
    ----------
    scene : str
        An object name (:data:`replay.synth.objects.OBJECTS`).
    out : path-like
        Session directory to create (must not exist or be empty).
    frames : int
        Frames per object pass (environment, geometry, rgb / scan each get this many).
    size : (width, height) or "WxH"
        Image size of every stream (intrinsics scale with it).
    seed : int
        Everything random (paths, noise, the emitter pattern) derives from it: same seed, same bytes.
    device : {"kinect1", "allinone"}
    detail : {"full", "test"}
        Mesh resolution (``test``: ~5k triangles, for fast tests).
    quality : Quality or {"full", "test"}, optional
        Integration settings (default: the preset named like ``detail``).
    radius_m : float
        Orbit radius (0.4-1.0 m is what a person does).
    references : bool
        Also render ``truth/references`` (three sunset views).
    show_progress : bool
        Progress bars on stderr.
    cache_dir : path-like, optional
        Where precomputed light transport is cached between runs (keyed by a hash of everything it
        depends on); None: recompute.
    workers : int, optional
        Processes rendering frames (the bytes do not depend on it). Default: 2 on a machine with at
        least 2 cores for sessions of more than ~40 frames of 320 x 240, else 1.
    log : callable, optional
        Called with one-line status messages.
    rgb_frames : int, optional
        Frames of the pass that captures the object's colour (the ``rgb`` pass of ``kinect1``, the one
        ``scan`` pass of ``allinone``) on the same orbit, sampled more densely; default ``frames``. The
        other passes' bytes do not depend on it (every frame is seeded by seed, pass and index), so the
        geometry and IR stages of a scan give the same results: it measures how the colour estimates
        change with the length of the colour pass (``docs/rgb-pass.md`` §8, session 39).
    """
    from replay.session import SessionWriter, format_timestamp, pose_to_tum

    from appfusion.progress import progress

    t_start = time.perf_counter()
    if scene not in OBJECTS:
        raise AppFusionError(f"unknown synthetic scene {scene!r} (known: {', '.join(OBJECTS)})")
    if device not in DEVICES:
        raise AppFusionError(f"unknown synthetic device {device!r} (known: {', '.join(DEVICES)})")
    frames = int(frames)
    if not 1 <= frames <= 100000:
        raise AppFusionError(f"frames per pass must be >= 1, got {frames}")
    rgb_frames = frames if rgb_frames is None else int(rgb_frames)
    if not 1 <= rgb_frames <= 100000:
        raise AppFusionError(f"frames of the colour pass must be within 1-100000, got {rgb_frames}")
    w, h = _parse_size(size)
    if not (isinstance(seed, (int, np.integer)) and 0 <= int(seed) < 2 ** 32):
        raise AppFusionError(f"synth: the seed must be an integer in [0, 2^32), got {seed!r}")
    if workers is not None and int(workers) < 1:
        raise AppFusionError(f"synth: --workers must be at least 1, got {workers}")
    if quality is None:
        quality = Quality.preset("test" if detail == "test" else "full")
    elif isinstance(quality, str):
        quality = Quality.preset(quality)
    say = log or (lambda s: None)
    out = Path(out)

    # -- scene -------------------------------------------------------------------------------------
    obj = build_object(scene, detail, seed)
    office = envmaps.office()
    plane = SupportPlane()
    ball = MirrorBall()
    scenes = {
        "calib": Scene(office, sheet=Sheet(), quality=quality),
        "env": Scene(office, plane=plane, ball=ball, quality=quality),
        "obj": Scene(office, obj=obj, plane=plane, quality=quality),
    }
    depth_model = DepthModel()
    ir_model = IRModel(seed=seed)
    rgb_model = RGBModel(seed=seed)
    di = C.depth_intrinsics(w, h)
    ri = C.rgb_intrinsics(w, h)
    d2rgb = C.depth_to_rgb()
    rgb_pose_offset = invert_pose(d2rgb)

    # -- passes ------------------------------------------------------------------------------------
    ss = np.random.SeedSequence(seed)
    path_seeds = [int(x) for x in ss.generate_state(8)]
    passes: list[PassSpec] = []
    t = 0.0
    all_streams = ("depth", "ir", "rgb")
    calib_streams = ("depth", "ir") if device == "kinect1" else all_streams
    tc, pc, dc = C.fronto_parallel_poses([0.8], CALIB_OFF_FRAMES, path_seeds[0], t)
    t2, p2, d2 = C.fronto_parallel_poses(CALIB_DISTANCES_M, CALIB_FRAMES_EACH, path_seeds[1], tc[-1] + 1.0)
    passes.append(PassSpec("ir-calibration", "calib", calib_streams, np.concatenate([tc, t2]), np.concatenate([pc, p2]),
                           np.r_[np.zeros(len(tc), bool), np.ones(len(t2), bool)],
                           {"sheet_distance_m": np.r_[np.full(len(tc), np.nan), d2]}))
    t = passes[-1].times[-1] + PASS_GAP_S
    height = float(obj.vertices[:, 2].max())
    plan = [("environment", "env", C.PathParams(radius_m=radius_m, target_height_m=ball.centre_m[2]))]
    # the object pass that fuses IR goes down to 5 degrees above the table: a side-facing surface only
    # shows its IR highlight (emitter next to the camera) to a camera near its own height, and a user
    # follows the guidance "orbit at several heights, down to the table" (at 15 degrees the sides of the
    # two-material bottle never showed theirs, so their material could not be told from the IR)
    low = dict(elev_min_deg=5.0)
    if device == "kinect1":
        plan += [("geometry", "obj", C.PathParams(radius_m=radius_m, target_height_m=0.5 * height, **low)),
                 ("rgb", "obj", C.PathParams(radius_m=radius_m, target_height_m=0.5 * height))]
        stream_of = {"environment": ("depth", "rgb"), "geometry": ("depth", "ir"), "rgb": ("depth", "rgb")}
    else:
        plan += [("scan", "obj", C.PathParams(radius_m=radius_m, target_height_m=0.5 * height, **low))]
        stream_of = {"environment": all_streams, "scan": all_streams}
    for k, (name, key, pp) in enumerate(plan):
        n = rgb_frames if name in ("rgb", "scan") else frames
        tt, pp_ = C.orbit_path(n, path_seeds[2 + k], pp, t)
        passes.append(PassSpec(name, key, stream_of[name], tt, pp_, np.ones(n, bool), {"path": pp.to_json()}))
        t = tt[-1] + PASS_GAP_S

    # -- lighting precomputation -------------------------------------------------------------------
    t0 = time.perf_counter()
    for key in ("env", "obj"):
        scenes[key].ensure_lighting(progress=show_progress, cache_dir=cache_dir)
    precompute_s = time.perf_counter() - t0
    say(f"synth: light transport precomputed in {precompute_s:.1f} s")

    # -- exposure per pass (the user sets it once so nothing clips, paper §3 / §4.2) ----------------
    lt_obj = scenes["obj"].lighting
    env_max = _max_env_radiance(office)
    marker_E = lt_obj.irradiance_up(plane.marker_centres)
    marker_L = plane.marker_albedo / np.pi * marker_E.max()
    obj_diffuse_max = float((obj.rho_d * lt_obj.vert_E).max() / np.pi)
    rs_max = max(max(m.rho_s) for m in obj.materials)
    max_rad = {"calib": Sheet().albedo / np.pi * float(np.max(_sheet_E(scenes["calib"]))),
               "env": max(ball.reflectance * env_max, marker_L),
               "obj": max(obj_diffuse_max + rs_max * env_max, marker_L)}
    base_exposure = {k: rgb_model.base_exposure(v) for k, v in max_rad.items()}

    # -- write -------------------------------------------------------------------------------------
    intr = {"depth": di, "ir": di, "rgb": ri}
    extra = {
        "synthetic": True,
        "generator": "replay.synth",
        "markers": {"radius_m": plane.marker_radius_m, "key_radius_m": plane.key_radius_m, "layout": "square",
                    "side_m": plane.side_m},
        "mirror_ball": {"reflectance": ball.reflectance},
        "depth": {"baseline_m": depth_model.baseline_m, "disparity_subpixel": depth_model.subpixel,
                  "range_m": [depth_model.z_min_m, depth_model.z_max_m]},
        "ir_bits": ir_model.bits,
        "rgb_bits": 8,
    }
    device_name = "synthetic Kinect v1 (replay.synth)" if device == "kinect1" else "synthetic all-in-one depth+IR+RGB (replay.synth)"
    frames_truth = []
    gt_lines = []
    n_total = sum(len(p.times) for p in passes)
    timings = {"depth_ir": [], "rgb": []}
    job = _FrameJob(scenes, passes, depth_model, ir_model, rgb_model, di, ri, d2rgb, base_exposure, seed)
    tasks = [(pno, i) for pno, ps in enumerate(passes) for i in range(len(ps.times))]
    if workers is None:
        workers = 2 if (os.cpu_count() or 1) >= 2 and n_total * w * h >= 40 * 320 * 240 else 1
    pool = None
    tmp_lcache = None                    # a light-transport cache made for the workers alone: removed at the end
    if workers > 1:
        import tempfile
        from concurrent.futures import ProcessPoolExecutor

        # workers rebuild the scenes and load the precomputed light transport from a cache
        lcache = Path(cache_dir) if cache_dir is not None else Path(tempfile.mkdtemp(prefix="synth-lighting-"))
        tmp_lcache = None if cache_dir is not None else lcache
        for key in ("env", "obj"):
            scenes[key].save_lighting(lcache)
        spec = {"scene": scene, "detail": detail, "seed": seed, "quality": quality.to_json(), "size": (w, h),
                "passes": passes, "base_exposure": base_exposure, "cache_dir": str(lcache)}
        # spawned, not forked: a child forked from a process whose Open3D (Embree / TBB) threads already
        # ran inherits their locks held; `test_same_seed_same_bytes_also_with_two_worker_processes` hung
        # for 18 minutes in a forked worker's first ray cast once the suite's order put a ray-casting
        # test before it in the same pytest worker
        import multiprocessing

        pool = ProcessPoolExecutor(max_workers=int(workers), initializer=_worker_init, initargs=(spec,),
                                   mp_context=multiprocessing.get_context("spawn"))
        results = pool.map(_worker_frame, tasks, chunksize=2)
    else:
        results = (job.render(pno, i) for pno, i in tasks)
    try:
        with SessionWriter(out, device=device_name, intrinsics=intr, depth_to_ir=np.eye(4), depth_to_rgb=d2rgb,
                           depth_units_per_m=5000.0, rgb_encoding="srgb8", emitter_position_m=C.EMITTER_POSITION_M,
                           notes=f"synthetic scan of '{scene}' (seed {seed}, {device}); ground truth in truth/",
                           extra=extra, fsync_interval_s=1.0) as wr:
            for index, ((pno, i), res) in enumerate(zip(tasks, progress(results, total=n_total, desc=f"synth {scene}",
                                                                          enable=show_progress))):
                ps = passes[pno]
                imgs, rec, t_d, t_r = res
                fr = Frame(index=index, timestamp=float(ps.times[i]), pass_name=ps.name, emitter=bool(ps.emitter[i]),
                           depth_intrinsics=di, ir_intrinsics=di, rgb_intrinsics=ri, depth_to_ir=np.eye(4),
                           depth_to_rgb=d2rgb, **imgs)
                wr.write(fr)
                rec["index"] = index
                frames_truth.append(rec)
                timings["depth_ir"].append(t_d)
                if t_r is not None:
                    timings["rgb"].append(t_r)
                gt_lines.append(format_timestamp(ps.times[i]) + "".join(f" {v:.10g}" for v in pose_to_tum(ps.poses[i])))
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        if tmp_lcache is not None:
            shutil.rmtree(tmp_lcache, ignore_errors=True)

    # -- truth ----------------------------------------------------------------------------------------
    truth = out / "truth"
    truth.mkdir()
    (truth / "groundtruth.txt").write_text("# ground truth of the depth camera (camera to world, marker frame)\n"
                                           "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt_lines) + "\n")
    np.savez_compressed(truth / "object.npz", **obj.truth_arrays())
    (truth / "materials.json").write_text(json.dumps({"materials": obj.materials.to_json(),
                                                      "note": "lobe 'ward': alpha is Ward's alpha (paper Eq. 1); "
                                                              "lobe 'ggx': alpha is the GGX roughness (replay/synth/"
                                                              "materials.py)"}, indent=2))
    sunset = envmaps.sunset()
    # paths relative to truth/ (as the references' are): the session is rendered into a temporary folder
    # and renamed, so absolute or out-relative paths named a folder that no longer exists
    env_files = {e.name: {k: Path(v).relative_to(truth).as_posix() for k, v in e.save(truth / "envmaps").items()}
                 for e in (office, sunset)}
    lt_env = scenes["env"].lighting
    box = {"min_m": [-plane.side_m / 2, -plane.side_m / 2, 0.0], "max_m": [plane.side_m / 2, plane.side_m / 2, 0.30]}
    markers = {
        "radius_m": plane.marker_radius_m, "key_radius_m": plane.key_radius_m, "layout": "square",
        "side_m": plane.side_m,
        "centres_m": [[float(x), float(y), 0.0] for x, y in plane.marker_centres],
        "numbering": "1 (+x,+y), 2 (+x,-y), 3 (-x,-y), 4 (-x,+y)",
        "albedo": plane.marker_albedo, "ir_albedo": plane.marker_ir_albedo,
        "plane_albedo": plane.albedo, "plane_ir_albedo": plane.ir_albedo, "plane_half_size_m": plane.half_size_m,
        "object_box": box,
        "irradiance_rgb": {"environment": lt_env.irradiance_up(plane.marker_centres).tolist(),
                           "object": marker_E.tolist()},
        "white_radiance_rgb": {"environment": (plane.marker_albedo / np.pi * lt_env.irradiance_up(plane.marker_centres)).tolist(),
                               "object": (plane.marker_albedo / np.pi * marker_E).tolist()},
        "note": "irradiance at each circle centre (environment pass: ball present; object passes: object "
                "present); a white pixel reads exposure * wb_gains * white_radiance (truth/frames.json)",
    }
    (truth / "markers.json").write_text(json.dumps(markers, indent=2))
    (truth / "ir_model.json").write_text(json.dumps(ir_model.to_json(), indent=2))
    np.savez_compressed(truth / "ir_pattern.npz", t=ir_model.pattern(), cell_rad=ir_model.cell_rad,
                        grid_offset_cells=np.asarray(ir_model.grid_offset_cells))
    (truth / "frames.json").write_text(json.dumps({"frames": frames_truth, "base_exposure": base_exposure,
                                                   "max_radiance": max_rad}, indent=1))
    ref_info = None
    if references:
        ref_info = render_references(obj, sunset, truth / "references", ri, seed, quality, cache_dir)
    scene_json = {
        "format_version": FORMAT_VERSION, "scene": scene, "seed": seed, "device": device, "frames_per_pass": frames,
        "rgb_frames": rgb_frames,
        "size": [w, h], "detail": detail, "quality": quality.to_json(),
        "object": {"name": obj.name, "vertices": len(obj.vertices), "faces": len(obj.faces), **obj.info},
        "object_height_m": height,
        "ball": ball.to_json(), "plane": plane.to_json(), "sheet": Sheet().to_json(),
        "environment": office.to_json(), "relight_environment": sunset.to_json(), "envmap_files": env_files,
        "cameras": {"depth": di.to_json(), "rgb": ri.to_json(), "depth_to_rgb": d2rgb.tolist(),
                    "emitter_position_m": list(C.EMITTER_POSITION_M), "fps": C.FPS},
        "depth_model": depth_model.to_json(), "ir_model": "ir_model.json", "rgb_model": rgb_model.to_json(),
        "passes": [{"name": p.name, "streams": list(p.streams), "frames": len(p.times), "t0": float(p.times[0]),
                    "t1": float(p.times[-1]), "scene": p.scene_key,
                    **({"path": p.extra["path"]} if "path" in p.extra else {})} for p in passes],
        "calibration": {"off_frames": CALIB_OFF_FRAMES, "distances_m": list(CALIB_DISTANCES_M),
                        "frames_each": CALIB_FRAMES_EACH},
        "light_transport": "direct lighting from the distant environment with object/plane/ball shadows plus one "
                           "bounce off the support plane; no inter-reflection from the object (paper §3)",
        "timing_s": {"precompute": precompute_s, "total": time.perf_counter() - t_start,
                     "depth_ir_per_frame": float(np.mean(timings["depth_ir"])) if timings["depth_ir"] else None,
                     "rgb_per_frame": float(np.mean(timings["rgb"])) if timings["rgb"] else None},
        "references": ref_info,
    }
    (truth / "scene.json").write_text(json.dumps(scene_json, indent=2, default=float))
    say(f"synth: wrote {out} in {time.perf_counter() - t_start:.1f} s")
    return out


class _FrameJob:
    """Everything needed to render any frame of a session (in this process or a worker)."""

    def __init__(self, scenes, passes, depth_model, ir_model, rgb_model, di, ri, d2rgb, base_exposure, seed):
        self.scenes, self.passes = scenes, passes
        self.depth_model, self.ir_model, self.rgb_model = depth_model, ir_model, rgb_model
        self.di, self.ri, self.d2rgb = di, ri, d2rgb
        self.rgb_pose_offset = invert_pose(d2rgb)
        self.base_exposure, self.seed = base_exposure, seed
        self._drift = {}

    def render(self, pno: int, i: int):
        """Images, truth record and timings of frame ``i`` of pass ``pno``; deterministic (seeded by
        (seed, pass, frame))."""
        from replay.session import format_timestamp

        ps = self.passes[pno]
        sc = self.scenes[ps.scene_key]
        if pno not in self._drift:
            self._drift[pno] = self.rgb_model.drift(ps.times)
        e_t, g_t = self._drift[pno]
        pose = ps.poses[i]
        rs = np.random.SeedSequence([self.seed, 1000 + pno, i]).spawn(3)
        rd, rir, rrgb = (np.random.default_rng(x) for x in rs)
        ta = time.perf_counter()
        dir_ = render_depth_ir(sc, pose, self.di, self.depth_model, self.ir_model, rd, rir, bool(ps.emitter[i]),
                               "depth" in ps.streams, "ir" in ps.streams)
        tb = time.perf_counter()
        imgs = {"depth": dir_.depth, "ir": dir_.ir}
        rec = {"timestamp": format_timestamp(ps.times[i]), "pass": ps.name, "streams": list(ps.streams),
               "emitter": bool(ps.emitter[i])}
        t_r = None
        if "rgb" in ps.streams:
            L, _ = render_radiance(sc, pose @ self.rgb_pose_offset, self.ri, rrgb)
            expo = self.base_exposure[ps.scene_key] * float(e_t[i])
            imgs["rgb"] = self.rgb_model.capture(L, expo, g_t[i], rrgb)
            rec.update(exposure=expo, wb_gains=[float(x) for x in g_t[i]])
            t_r = time.perf_counter() - tb
        if "sheet_distance_m" in ps.extra and np.isfinite(ps.extra["sheet_distance_m"][i]):
            rec["sheet_distance_m"] = float(ps.extra["sheet_distance_m"][i])
        return imgs, rec, tb - ta, t_r


_WORKER: dict = {}


def _worker_init(spec: dict) -> None:
    """Rebuild a session's scenes in a worker process (light transport from the cache)."""
    obj = build_object(spec["scene"], spec["detail"], spec["seed"])
    quality = Quality(**spec["quality"])
    office = envmaps.office()
    plane, ball = SupportPlane(), MirrorBall()
    scenes = {"calib": Scene(office, sheet=Sheet(), quality=quality),
              "env": Scene(office, plane=plane, ball=ball, quality=quality),
              "obj": Scene(office, obj=obj, plane=plane, quality=quality)}
    for key in ("env", "obj"):
        scenes[key].ensure_lighting(cache_dir=spec["cache_dir"])
    w, h = spec["size"]
    d2rgb = C.depth_to_rgb()
    _WORKER["job"] = _FrameJob(scenes, spec["passes"], DepthModel(), IRModel(seed=spec["seed"]),
                               RGBModel(seed=spec["seed"]), C.depth_intrinsics(w, h), C.rgb_intrinsics(w, h), d2rgb,
                               spec["base_exposure"], spec["seed"])


def _worker_frame(task):
    return _WORKER["job"].render(*task)


def _sheet_E(scene: Scene) -> np.ndarray:
    from .render import lt_sheet_irradiance

    return lt_sheet_irradiance(scene)


REFERENCE_VIEWS = ((30.0, 25.0, 0.5), (150.0, 42.0, 0.55), (270.0, 58.0, 0.5))  # azimuth, elevation (deg), radius


def render_references(obj: ObjectModel, env: envmaps.Environment, folder: Path, intr: Intrinsics, seed: int,
                      quality: Quality | None = None, cache_dir=None) -> dict:
    """The object alone (no plane) under ``env`` from three new views: EXR (linear radiance, background 0),
    PNG (sRGB of radiance * png_exposure), mask PNG; ``views.json`` holds poses (camera to world,
    OpenCV axes) and intrinsics."""
    import cv2

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    q = Quality(**{**(quality or Quality()).to_json(), "lobe_samples": 256})
    sc = Scene(env, obj=obj, quality=q)
    sc.ensure_lighting(cache_dir=cache_dir)
    height = float(obj.vertices[:, 2].max())
    views = []
    imgs = []
    for k, (az, el, r) in enumerate(REFERENCE_VIEWS):
        a, e = np.radians(az), np.radians(el)
        target = np.array([0.0, 0.0, 0.5 * height])
        eye = target + r * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        pose = C.look_at(eye, target)
        rng = np.random.default_rng(np.random.SeedSequence([seed, 9000, k]))
        L, kind = render_radiance(sc, pose, intr, rng, supersample_ball=False)
        mask = kind == KIND_OBJECT
        L[~mask] = 0.0
        imgs.append((L, mask))
        views.append({"name": f"view-{k + 1}", "pose": pose.tolist(), "azimuth_deg": az, "elevation_deg": el,
                      "radius_m": r})
    allv = np.concatenate([L[m].max(axis=1) for L, m in imgs]) if imgs else np.ones(1)
    expo = float(0.9 / max(np.percentile(allv, 99.5), 1e-9))
    for (L, mask), v in zip(imgs, views):
        cv2.imwrite(str(folder / f"{v['name']}.exr"), np.ascontiguousarray(L[..., ::-1].astype(np.float32)))
        from appfusion.frame import linear_to_srgb

        png = np.rint(linear_to_srgb(L * expo) * 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"{v['name']}.png"), np.ascontiguousarray(png[..., ::-1]))
        cv2.imwrite(str(folder / f"{v['name']}-mask.png"), mask.astype(np.uint8) * 255)
        v.update(exr=f"{v['name']}.exr", png=f"{v['name']}.png", mask=f"{v['name']}-mask.png")
    info = {"environment": env.name, "plane": False, "intrinsics": intr.to_json(), "png_exposure": expo,
            "png_encoding": "sRGB(clip(radiance * png_exposure)), 8-bit; EXR: linear radiance, background 0",
            "pose": "camera-to-world of the reference camera (OpenCV axes, marker frame)", "views": views,
            "lobe_samples": q.lobe_samples}
    (folder / "views.json").write_text(json.dumps(info, indent=2))
    return {"folder": "references", "views": [v["name"] for v in views]}


#: bumped whenever the scanner's output for the demo changes, so that a cached demo is rendered anew
#: (2: the IR object pass orbits down to 5 degrees; 3: 200 frames a pass; 4: the emitter pattern's grid
#: offset from the camera's pixel grid)
DEMO_VERSION = 4


def demo_session(cache_dir: str | os.PathLike, show_progress: bool = True) -> Path:
    """The bundled demo session (scene ``two-material``, 640 x 480, Kinect v1, ``DEMO_FRAMES`` per pass),
    generated once into ``cache_dir/synth-demo-two-material`` and reused afterwards."""
    cache_dir = Path(cache_dir)
    path = cache_dir / "synth-demo-two-material"
    done = path / "truth" / "scene.json"
    stamp = path / "demo-version.txt"
    if done.exists() and stamp.exists() and stamp.read_text().strip() == str(DEMO_VERSION):
        return path
    if path.exists() and not done.exists():
        import shutil

        shutil.rmtree(path)  # an interrupted earlier generation
    cache_dir.mkdir(parents=True, exist_ok=True)
    tmp = cache_dir / f".synth-demo-two-material.{os.getpid()}.tmp"
    if tmp.exists():
        import shutil

        shutil.rmtree(tmp)
    render_session("two-material", tmp, frames=DEMO_FRAMES, size=(640, 480), seed=0, device="kinect1",
                   show_progress=show_progress, cache_dir=cache_dir / "lighting")
    (tmp / "demo-version.txt").write_text(f"{DEMO_VERSION}\n")
    if path.exists():                      # an older version of the demo
        import shutil

        shutil.rmtree(path)
    os.replace(tmp, path)
    return path
