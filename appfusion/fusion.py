"""KinectFusion-style tracking and TSDF fusion on Open3D's tensor VoxelBlockGrid (paper §4.1).

The paper acquires geometry "directly ... using KinectFusion" [Izadi et al. 2011]: each depth frame is
tracked against a ray cast of the fused model (frame-to-model, projective point-to-plane ICP) and
then integrated into a truncated signed distance volume. This module does the same with Open3D 0.19:

- the volume is a :class:`open3d.t.geometry.VoxelBlockGrid` (``tsdf``, ``weight``) with voxels of
  ``voxel_size`` (default 4 mm; in a scan :func:`voxel_size_for_box` sets it from the object box, 3 mm for 30 cm);
- integration runs on the depth image downsampled to ``integrate_width`` (2 x 2 block means of valid
  pixels; default 320 px), tracking on a further 2 x downsampled image (``track_width``, 160 px)
  against a ray cast of the model at the last pose (refined on the trilinear TSDF, see
  :meth:`TSDFFusion.raycast`), by projective point-to-plane ICP written here in numpy (two pyramid
  levels, Huber weights, normal-space weighting, optional point anchors such as the marker centres),
  initialised by a constant-velocity prediction. (Open3D's ``rgbd_odometry_multi_scale`` takes the
  target normals from the depth "bilateral" filtered with a value sigma of 5 in metres, i.e. a
  blur across object edges, and has no anchors or robust weights to tune; the own ICP takes 11-14
  ms a frame at 160 x 120.);
- every tracked frame is checked (overlap with the model, inlier fraction, point-to-plane RMSE and
  the pose jump against the prediction); a frame that fails is reported ``lost``, not integrated,
  and the next frames are tracked again from the last good pose with a wider association distance
  until one passes ("relocalisation against the model");
- a region of interest (the object box of :mod:`appfusion.markers`, grown by a margin) can restrict
  integration once the markers are known, which keeps both the volume and the time per frame small.

Why the tensor VoxelBlockGrid and not the legacy ScalableTSDFVolume: at equal voxel size and
truncation it integrates faster (4.8 vs 8.3 ms a frame), its mesh is closer to the truth (0.23 vs
0.42 mm), and only it ray casts its model, which frame-to-model tracking needs; see
``docs/geometry-pass.md`` for the measurements and the Open3D 0.19 behaviours worked around here.

Poses are camera-to-world 4x4 matrices of the depth camera. The fusion's world frame is the frame
of ``initial_pose`` (the first camera by default); :mod:`appfusion.geometry_pass` re-expresses
everything in the marker frame.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import open3d as o3d

from .errors import AppFusionError
from .frame import Intrinsics, invert_pose, transform_points

__all__ = ["FusionConfig", "TrackResult", "TSDFFusion", "downsample_depth", "voxel_size_for_box",
           "rotation_angle_deg", "vertex_normals", "drop_grazing", "kabsch", "orthonormalize",
           "set_openmp_threads", "blas_threads", "depth_range_hint"]

o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)


def set_openmp_threads(n: int | None) -> bool:
    """Set the OpenMP thread count of the calling thread for Open3D's CPU kernels.

    Open3D's TSDF integration and ray casting run OpenMP parallel loops. On a small, shared
    machine a loop with one thread descheduled waits for it: measured on 2 loaded cores, one
    thread made tracking + fusion 3x faster (31 ms vs 105 ms a frame) and was as fast when the
    machine was idle (27 ms either way). The setting applies to the calling thread's later
    parallel regions (all libraries sharing the system libgomp) and sets ``OMP_NUM_THREADS`` in
    the environment if it is unset. Returns False when libgomp cannot be found.
    """
    if not n:
        return False
    global _GOMP
    # Open3D 0.19 sizes its parallel loops with omp_get_max_threads() only while OMP_NUM_THREADS is
    # set (any value), otherwise with the number of cores: set both.
    os.environ.setdefault("OMP_NUM_THREADS", str(int(n)))
    try:
        if _GOMP is None:
            import ctypes
            import ctypes.util
            _GOMP = ctypes.CDLL(ctypes.util.find_library("gomp") or "libgomp.so.1")
        _GOMP.omp_set_num_threads(int(n))
        return True
    except (OSError, AttributeError):
        return False


_GOMP = None
_BLAS = None


def blas_threads(n: int = 1):
    """Context manager limiting the BLAS (OpenBLAS) thread pool to ``n`` threads while inside it.

    OpenBLAS threads spin for a while after each call; on 2 shared cores they starve the next
    Open3D and numpy work (measured: a frame of tracking + fusion after marker detection took
    70-114 ms with the default pool and 31-69 ms with one thread). No-op without threadpoolctl.
    """
    global _BLAS
    try:
        if _BLAS is None:
            from threadpoolctl import ThreadpoolController
            _BLAS = ThreadpoolController()
        return _BLAS.limit(limits=int(n), user_api="blas")
    except Exception:  # pragma: no cover - threadpoolctl missing or failing
        import contextlib
        return contextlib.nullcontext()


def depth_range_hint(depth: np.ndarray, cfg: "FusionConfig") -> str:
    """Why a depth image has no depth in the working range, for an error: ``""`` unless most of its
    valid depth (finite, > 0; metres) lies nearer than ``cfg.depth_min`` or farther than
    ``cfg.depth_max``. Beyond 10 x nearer or 5 x farther than the range it asks about the units (depth
    in the wrong units: millimetres read as metres, 1000 x too far; metres stored in a millimetre PNG,
    1-3 units, 1000 x too near); otherwise it states the working range."""
    d = np.asarray(depth, np.float32)
    with np.errstate(invalid="ignore"):
        d = d[np.isfinite(d) & (d > 0)]
    if d.size == 0:
        return ""
    med = float(np.median(d))
    if np.mean(d <= cfg.depth_min) > 0.5:
        where = f"nearer than depth_min {cfg.depth_min:g} m"
    elif np.mean(d >= cfg.depth_max) > 0.5:
        where = f"farther than depth_max {cfg.depth_max:g} m"
    else:
        return ""
    if cfg.depth_min / 10 <= med <= cfg.depth_max * 5:       # a plausible distance: the camera is too near or far
        return f": most of its depth lies {where} (median {med:.3g} m); the object is scanned from " \
               f"{cfg.depth_min:g} to {cfg.depth_max:g} m"
    return f": most of its depth lies {where} (median {med:.3g} m); are the recording's depth units right?"


STATE_OK = "ok"
STATE_LOST = "lost"
STATE_FIRST = "first"


def mean_motion(T: np.ndarray, n: int) -> np.ndarray:
    """The rigid motion that, repeated ``n`` times, approximates ``T`` (4x4): its rotation vector and
    translation divided by ``n`` (exact for a pure rotation or translation; the frame-to-frame
    motion over a gap of ``n`` frames)."""
    out = orthonormalize(T)
    rvec, _ = cv2.Rodrigues(out[:3, :3])
    out[:3, :3], _ = cv2.Rodrigues(rvec / float(n))
    out[:3, 3] /= float(n)
    return out


def pose_jump(pred: np.ndarray, pose: np.ndarray) -> tuple[float, float]:
    """How far ``pose`` lies from ``pred`` (both 4x4, camera to world): metres and degrees."""
    jump = invert_pose(pred) @ pose
    return float(np.linalg.norm(jump[:3, 3])), rotation_angle_deg(jump[:3, :3])


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """The nearest rigid transform to a 4x4 matrix (rotation by SVD); stops round-off in chains of
    pose products from growing into a scale or shear."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = T[:3, 3]
    return out


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def anchor_information(normal, w_in: float, w_n: float, sight=None, floor: float = 1e-3) -> np.ndarray:
    """(3, 3) weight (information) matrix of an anchor's point-to-point term: ``w_in`` within the
    support plane and ``w_n`` along its unit ``normal`` (``w_in I + (w_n - w_in) n n^T``); ``w_in I``
    without a normal.

    ``sight`` (3,), optional: the line of sight from the camera to the anchor, in the same frame.
    The in-plane error along the sight's projection on the plane then weighs ``w_in sin^2(e)``
    (``e`` the sight's elevation above the plane, the weight at least ``floor w_in``); the one across
    it keeps ``w_in``. A circle seen at elevation ``e`` images as an ellipse ``sin(e)`` as thin as it
    is long, so a pixel's error across the ellipse moves its centre ``1 / sin(e)`` times as far
    along the line of sight on the plane (the same argument as :func:`appfusion.markers.view_weight`;
    beyond the paper). On the ``--quick`` bench's 320 x 240 session a circle seen at 8 degrees was
    3.7 mm off along the sight and 0.1 mm across it.
    """
    if normal is None:
        return np.eye(3) * w_in
    n = np.asarray(normal, float)
    n = n / max(float(np.linalg.norm(n)), 1e-12)
    M = np.eye(3) * w_in + (w_n - w_in) * np.outer(n, n)
    if sight is not None:
        v = np.asarray(sight, float)
        v = v / max(float(np.linalg.norm(v)), 1e-12)
        s2 = float(v @ n) ** 2                                    # sin^2 of the elevation
        t = v - (v @ n) * n                                       # the sight's direction on the plane
        tn = float(np.linalg.norm(t))
        if tn > 1e-9:
            t /= tn
            M -= w_in * (1.0 - max(s2, floor)) * np.outer(t, t)
    return M


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rigid transform (4x4) minimising ``sum |T src_i - dst_i|^2`` (Kabsch / Umeyama, no scale)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    cs, cd = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cd - R @ cs
    return T


def anchor_pose(anchors) -> np.ndarray | None:
    """Camera-to-world pose fixed by tracking anchors, or None.

    Three or more anchors: their rigid fit (:func:`kabsch`). Two, with the support plane's normal in
    both frames (``anchors[2]`` world, ``anchors[3]`` camera): the rotation that takes the camera
    normal to the world one and the line between the two points (projected on the plane) to theirs,
    the translation that matches their midpoints (beyond the paper; two circles numbered by the key
    circle, :meth:`appfusion.markers.MarkerTracker.number_two`).
    """
    if anchors is None:
        return None
    src, dst = np.asarray(anchors[0], float).reshape(-1, 3), np.asarray(anchors[1], float).reshape(-1, 3)
    if len(src) >= 3:
        return kabsch(src, dst)
    if len(src) != 2 or len(anchors) < 4 or anchors[2] is None or anchors[3] is None:
        return None
    nw = np.asarray(anchors[2], float).reshape(-1, 3)[0]
    nc = np.asarray(anchors[3], float).reshape(3)

    def basis(P, n):
        n = n / np.linalg.norm(n)
        u = P[1] - P[0]
        u = u - (u @ n) * n
        if not np.linalg.norm(u) > 1e-6:
            return None
        u /= np.linalg.norm(u)
        return np.stack([u, np.cross(n, u), n], 1)

    Bc, Bw = basis(src, nc), basis(dst, nw)
    if Bc is None or Bw is None:
        return None
    T = np.eye(4)
    T[:3, :3] = Bw @ Bc.T
    T[:3, 3] = dst.mean(0) - T[:3, :3] @ src.mean(0)
    return T


def _twist_to_pose(xi: np.ndarray) -> np.ndarray:
    """4x4 rigid transform of a twist (omega (3,), tau (3,)): Rodrigues rotation, translation tau."""
    w, t = xi[:3], xi[3:]
    th = np.linalg.norm(w)
    Kx = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        R = np.eye(3) + Kx
    else:
        R = np.eye(3) + np.sin(th) / th * Kx + (1 - np.cos(th)) / th ** 2 * Kx @ Kx
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def vertex_normals(depth: np.ndarray, K: Intrinsics, max_jump: float = 0.02, smooth_px: float = 2.0,
                   max_slope: float | None = None) -> np.ndarray:
    """Camera-frame unit normals of a depth image (KinectFusion's normal map), facing the camera.

    The depth is first smoothed with a NaN-aware Gaussian of ``smooth_px`` pixels (pixels that the
    smoothing moves by more than ``max_jump / 2`` sit at a discontinuity and get no normal), then the
    normal is the cross product of the central differences of the vertex map. Smooth normals matter
    for projective point-to-plane ICP: noisy ones pin the pose where the projective associations are.

    Parameters
    ----------
    depth : (H, W) float array, metres, NaN invalid.
    K : Intrinsics of the image.
    max_jump : float
        A pixel whose 4-neighbours differ from it in depth by more gets no normal, metres.
    smooth_px : float
        Gaussian sigma in pixels (0: no smoothing).
    max_slope : float, optional
        With it, the threshold of a pixel at depth ``z`` is ``max(max_jump, max_slope * z / f)``
        (``f`` the smaller focal length, pixels): a neighbour's depth step in units of the pixel's
        footprint, the tangent of the largest incidence angle kept (4: 76 degrees). A fixed
        ``max_jump`` drops ever steeper-looking surfaces with distance: at 1-1.6 m and 160 x 120 it
        left normals on a quarter of the real Redwood frames' ray cast, and tracking lost every frame.

    Returns
    -------
    (H, W, 3) float32, NaN where there is no normal.
    """
    depth = np.asarray(depth, np.float32)
    valid = np.isfinite(depth)
    if max_slope is not None:
        with np.errstate(invalid="ignore"):
            thr = np.maximum(np.float32(max_jump), np.float32(max_slope / min(K.fx, K.fy)) * depth)
    else:
        thr = np.float32(max_jump)
    if smooth_px > 0:
        k = 2 * int(np.ceil(2 * smooth_px)) + 1
        num = cv2.GaussianBlur(np.where(valid, depth, 0).astype(np.float32), (k, k), smooth_px)
        den = cv2.GaussianBlur(valid.astype(np.float32), (k, k), smooth_px)
        with np.errstate(invalid="ignore", divide="ignore"):
            sm = num / den
            sm[~valid | (np.abs(sm - depth) > thr / 2)] = np.nan
        depth = sm
    V = K.backproject(depth)
    N = np.full(V.shape, np.nan, np.float32)
    dx = V[1:-1, 2:] - V[1:-1, :-2]
    dy = V[2:, 1:-1] - V[:-2, 1:-1]
    n = np.cross(dx, dy)
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        z = depth[1:-1, 1:-1]
        jump = np.maximum.reduce([np.abs(depth[1:-1, 2:] - z), np.abs(depth[1:-1, :-2] - z),
                                  np.abs(depth[2:, 1:-1] - z), np.abs(depth[:-2, 1:-1] - z)])
        n[~(jump <= (thr if np.ndim(thr) == 0 else thr[1:-1, 1:-1]))] = np.nan
        flip = np.einsum("hwc,hwc->hw", n, V[1:-1, 1:-1]) > 0
    n[flip] *= -1
    N[1:-1, 1:-1] = n
    return N


def drop_grazing(depth: np.ndarray, K: Intrinsics, max_incidence_deg: float = 70.0,
                 unit_rays: np.ndarray | None = None, smooth_px: float = 1.0) -> np.ndarray:
    """The depth image without its grazing and discontinuity pixels (what a surface should not rest on).

    A pixel is dropped (NaN) when :func:`vertex_normals` gives it no normal (a depth jump next to it,
    the image border) or when the angle between its normal and the ray to the camera exceeds
    ``max_incidence_deg``. Kinect v1 depth noise grows steeply towards grazing angles (Nguyen et al.
    2012: ~6 mm at 78 degrees against 1.2 mm facing the camera), and a projective TSDF update along
    a ray that skims the surface writes that noise across the truncation band.

    Parameters
    ----------
    depth : (H, W) float array, metres, NaN invalid.
    K : Intrinsics of the image.
    max_incidence_deg : float
        Largest kept angle between the surface normal and the ray, degrees.
    unit_rays : (H, W, 3) array, optional
        Unit viewing rays of ``K`` (precomputed by the caller).
    smooth_px : float
        Depth smoothing before the normals, pixels (see :func:`vertex_normals`).

    Returns
    -------
    (H, W) float32 depth, NaN where dropped.
    """
    depth = np.asarray(depth, np.float32)
    if unit_rays is None:
        r = K.rays().astype(np.float32)
        unit_rays = r / np.linalg.norm(r, axis=-1, keepdims=True)
    n = vertex_normals(depth, K, smooth_px=smooth_px)
    cos_inc = -np.einsum("hwc,hwc->hw", n, unit_rays)
    with np.errstate(invalid="ignore"):
        keep = cos_inc >= np.cos(np.radians(max_incidence_deg)) - 1e-6
    return np.where(keep, depth, np.nan).astype(np.float32)


def _normal_space_weights(normals: np.ndarray, bins: int = 6, cap: float = 20.0) -> np.ndarray:
    """Weights that even out the distribution of normal directions (normal-space sampling,
    Rusinkiewicz & Levoy 2001, as weights): ``1 / count`` of the normal's cell on a
    ``bins^3`` grid over [-1, 1]^3, scaled to mean 1 and capped at ``cap`` x the smallest."""
    cell = np.clip(((normals + 1.0) * (bins / 2.0)).astype(np.int64), 0, bins - 1)
    key = (cell[:, 0] * bins + cell[:, 1]) * bins + cell[:, 2]
    counts = np.bincount(key, minlength=bins ** 3)[key].astype(np.float64)
    w = 1.0 / counts
    w = np.minimum(w, cap * w.min())
    return w * (len(w) / w.sum())


def voxel_size_for_box(side_m: float, height_m: float = 0.30, pixel_m: float | None = None) -> float:
    """TSDF voxel edge for an object box: 3 mm for a 30 cm box, proportional, and at least 1.5 depth
    pixels' footprint at the working distance; clipped to [2, 12] mm.

    Measured on the demo scan (30 cm box, 640 x 480 at ~0.6 m, where a depth pixel is ~1 mm): 4 mm
    voxels gave normals 1.43 degrees (median), Chamfer 0.30 mm, ATE 1.18 mm and a glossy alpha 15 %
    too broad (the normal error widens the lobe); 3 mm: 1.26 degrees, 0.21 mm, 0.96 mm, +8.9 %, for
    45 instead of 41 ms of tracking + fusion a frame. 2 mm lost the mirror ball's tracking. Coarser
    depth needs coarser voxels: a 320 x 240 live scan at 3 mm fitted alpha 0.166 for 0.12, hence the
    floor of 1.5 pixel footprints (3.9 mm at 320 x 240 with the circles 0.75 m away; the 4 mm of
    before).

    Parameters
    ----------
    side_m, height_m : float
        Box side (the marker square) and height, metres.
    pixel_m : float, optional
        Footprint of one depth pixel at the working distance (distance / fx), metres.
    """
    size = max(float(side_m), float(height_m))
    if not (np.isfinite(size) and float(side_m) > 0 and float(height_m) > 0):
        raise AppFusionError(f"voxel_size_for_box: box size must be positive, got side={side_m}, height={height_m}")
    v = 0.003 * size / 0.30
    if pixel_m is not None:
        if not (np.isfinite(pixel_m) and pixel_m > 0):
            raise AppFusionError(f"voxel_size_for_box: pixel footprint must be positive, got {pixel_m}")
        v = max(v, 1.5 * float(pixel_m))
    return float(np.clip(v, 0.002, 0.012))


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a 3x3 rotation matrix, degrees."""
    c = (np.trace(R[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def downsample_depth(depth: np.ndarray, factor: int, max_jump: float = 0.03, min_valid: float = 1.0) -> np.ndarray:
    """Downsample a depth image by an integer factor with block means of valid pixels.

    A block is invalid (NaN) when fewer than ``min_valid`` of its pixels are valid or when its valid
    depths span more than ``max_jump`` metres (a depth discontinuity: averaging would invent a surface).
    The block centre sits at ``(f * i + (f - 1) / 2)`` of the input, matching
    :meth:`Intrinsics.scaled`.

    The default keeps only complete blocks: the mean of a partly valid block belongs to its valid
    pixels' centroid, not to the block centre, and along an object's silhouette (the far side invalid)
    that moves the surface outwards by up to half an output pixel. On the demo scan, blocks half valid
    or more (the rule until session 9) left the fused bottle 0.11 mm outside the truth on the
    cylinder (0.05-0.07 mm with complete blocks) and the mesh's Chamfer distance at 0.127 mm (0.108).

    Parameters
    ----------
    depth : (H, W) float array, metres; NaN, infinite and non-positive values are invalid.
    factor : int >= 1
    max_jump : float, metres.
    min_valid : float in (0, 1]
        Smallest share of valid pixels a block needs.

    Returns
    -------
    (H // factor, W // factor) float32 array, never a view of ``depth``.
    """
    f = int(factor)
    if f == 1:
        # a copy: callers mask the result in place, and the input is the caller's frame (TSDFFusion
        # NaN-ed a 320-wide frame's out-of-range depth in the Frame itself until session 29)
        return np.array(depth, np.float32, copy=True)
    H, W = depth.shape
    h, w = H // f, W // f
    d = np.asarray(depth[: h * f, : w * f], np.float32)
    valid = np.isfinite(d) & (d > 0)                    # NaN, +-inf and <= 0 are no depth
    d0 = np.where(valid, d, np.float32(0))
    # block sums via OpenCV's area resampling (exact block means for integer factors)
    s = cv2.resize(d0, (w, h), interpolation=cv2.INTER_AREA)
    n = cv2.resize(valid.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    kernel = np.ones((f, f), np.uint8)
    mx = cv2.dilate(d0, kernel, anchor=(0, 0))[::f, ::f]
    mn = cv2.erode(np.where(valid, d, np.float32(1e6)), kernel, anchor=(0, 0))[::f, ::f]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = s / n
    out[(n < min_valid - 1e-6) | (mx - mn > max_jump)] = np.nan
    return out.astype(np.float32, copy=False)


@dataclass
class FusionConfig:
    """Settings of :class:`TSDFFusion` (metres unless stated).

    Attributes
    ----------
    voxel_size : float
        TSDF voxel edge (default 4 mm, for a ~30 cm object box).
    trunc_voxels : float
        Truncation distance in voxels (sdf_trunc = trunc_voxels * voxel_size).
    depth_min, depth_max : float
        Depth range used for integration and tracking.
    integrate_width : int
        Width the depth image is downsampled to (integer factor) before integration.
    track_width : int
        Width of the finest tracking level (an integer factor below ``integrate_width``).
    track_iterations : tuple of int
        Gauss-Newton iterations per pyramid level, coarsest first.
    depth_diff : float
        Projective association distance of tracking.
    relocalise_depth_diff : float
        Association distance while relocalising after a loss.
    min_overlap : float
        Lost if fewer than this fraction of the frame's valid (ROI) pixels land on the model.
    min_inliers : float
        Lost if fewer than this fraction of the overlapping pixels agree with the model within
        ``inlier_dist``.
    inlier_dist : float
        Point-to-plane distance of an inlier.
    normal_cos : float
        An association is dropped when source and model normals differ by more (cosine).
    icp_tolerance : float
        A pyramid level stops when a Gauss-Newton step is smaller (radians / metres).
    normal_space_weighting : bool
        Weight correspondences by the inverse frequency of their normal direction (a dominant
        support plane otherwise drowns the object's few constraints on in-plane motion).
    normal_smooth_px : float
        Gaussian smoothing (pixels at tracking size) of the depth before normals are taken.
    normal_max_slope, normal_min_coverage : float or None, float
        A tracking pixel is at a depth discontinuity (no normal, no association) where a neighbour
        differs by more than 4 voxels; where that leaves fewer than ``normal_min_coverage`` of an
        image's valid pixels a normal, by more than ``max(4 voxels, normal_max_slope x its
        footprint z / f)`` (:func:`vertex_normals`; None: 4 voxels always). With 4 voxels alone
        the real Redwood frames (1-1.6 m) kept normals on 25 % of the model and tracking lost 4 of
        5 frames; with the fallback at 4 (76 degrees of incidence) all 5 track, within 2 mm of their
        trajectory. Applied everywhere, the footprint rule also changed the synthetic sessions
        beyond 0.53 m (4 footprints of a 160 x 120 tracking pixel = 4 voxels there), and the
        12-frames-a-pass synthetic Kinect sphere (0.94 m), which tracks 2 of its 12 geometry frames,
        came out with alpha 0.28 for 0.12; as a fallback it leaves them as they were.
    anchor_weight : float
        Total weight of anchor correspondences relative to the pixel terms. The marker centres are
        known to ~0.1 mm (:func:`appfusion.markers.circle_on_plane`), the depth's ICP drifts by
        more: on the demo scan the tracked frames put the object's centre 0.51 mm (rms) off the
        truth along the vertical at 0.2 (the default until session 9; early, high frames +1 mm,
        low ones -0.6 mm), which the fused cap kept as a 0.3 mm bulge at its top (normals 0.5-0.6
        degrees off there, the sun's highlight moved: relit error 0.19-0.21). At 1 / 3 / 10: 0.19 /
        0.11 / 0.09 mm, normals 0.265 / 0.257 / 0.252 degrees, relit 0.100 / 0.069 / 0.059, but
        cluster labels 0.964 / 0.962 / 0.952 (more of the label's foot taken for paint) and the
        label's IR alpha falling (0.339 / 0.329 / 0.320 for 0.35); 3 is the default. It is the
        weight for a 640-pixel-wide depth image, scaled by ``(width / 640)^2`` below (the centres'
        precision follows the pixel footprint): on the ``--quick`` bench's 320 x 240 session a flat
        0.2 / 1 / 3 gave camera ATE 2.4 / 3.5 / 4.5 mm.
    anchor_normal_weight : float
        The weight of an anchor's error along the support plane's normal, where the anchors carry it
        (the geometry pass's marker centres do); ``anchor_weight`` then weighs the error within the
        plane. A centre is fitted on the RANSAC plane of the depth (:func:`appfusion.markers.circle_on_plane`):
        measured against the truth on the demo's geometry frames its error across the plane is
        0.06 mm (std), within it 0.30-0.42 mm from the blob's contour (biased along the line of
        sight), 0.22-0.29 mm fitted to its pixels (:func:`appfusion.markers.refine_circle`). At 30 (3 within the
        plane) the objects' centre sat 0.08 mm (rms) off the truth vertically (0.11 at a flat 3),
        the cap's top no longer bulged (+11 um against +47 at 55-90 degrees of elevation), and the
        relit error of the same geometry over four point samplings was 0.051-0.065 against
        0.079-0.082; 100 gave 0.047-0.065. Scaled with the pixel footprint like ``anchor_weight``.
    anchor_sight_weighting : bool
        Weigh an anchor's in-plane error along its line of sight by ``sin^2`` of the sight's
        elevation above the plane (:func:`anchor_information`): a circle seen at a grazing angle is
        known across the sight, not along it. Also used by :meth:`GeometryPass.refuse`'s
        :class:`~appfusion.geometry_pass.PoseRefiner`. Off by default: it made the demo's poses
        worse (ATE 0.51 -> 0.78 mm with a looser circle test) and lost frames of the ``--quick``
        bench's coarse scan before circles were checked for size (docs/geometry-pass.md).
    refine_raycast : bool
        Refine ray-cast hits on the trilinear TSDF (see :meth:`TSDFFusion.raycast`).
    omp_threads : int or None
        OpenMP threads for Open3D's kernels, set on the calling thread (see
        :func:`set_openmp_threads`); None leaves it alone.
    max_rmse : float
        Lost if the inliers' point-to-plane RMSE is larger.
    max_jump_m, max_jump_deg : float
        Lost if the tracked pose differs from the prediction by more (per frame). Where three or more
        anchors fit the fused circles rigidly (within ``anchor_fit_tol_m`` RMS) at a pose beyond these
        limits from the prediction, that pose is the prediction instead, as in a relocalisation: the
        circles, paired by their numbering, know where the camera went in a sweep faster than
        tracking follows (session 29).
    anchor_fit_tol_m : float
        RMS residual (metres) of the anchors' rigid fit below which their pose may replace the
        prediction (above); 0 turns that off.
    relocalise_velocity_frames : int
        A frame relocalised at most this many frames after the last good one predicts the next
        frame with the mean motion per frame over that gap (0: with no motion, as before). With
        no motion, a sweep of 12 degrees per frame lost every other frame: each frame after a
        relocalised one jumped a whole step from its prediction (the 30-frame quick matte session:
        15 of 30 environment frames lost; 2 with it).
    block_resolution, block_count : int
        VoxelBlockGrid block edge (voxels) and initial block capacity.
    weight_threshold : float
        Minimum TSDF weight of a surface in ray casts and extraction.
    keyframe_m, keyframe_deg : float
        "Frames that add no new coverage skip fusion" (issue #11): a tracked frame closer than
        ``keyframe_m`` metres *and* ``keyframe_deg`` degrees to the last integrated frame (the
        keyframe) whose depth falls only in voxel blocks the volume already has is not integrated,
        and while no frame is integrated the model's ray cast at the keyframe is reused for tracking
        (the model has not changed). Default 1 cm / 2 degrees: on a hand-held-like sequence (0.5 deg,
        ~4 mm per frame) ~70 of 120 frames skip integration, the geometry pass takes ~25 % less CPU
        and chamfer, normal and trajectory errors stay within run-to-run noise (``docs/performance.md``;
        4 cm / 8 degrees starts to cost normal accuracy). 0 integrates every frame (KinectFusion).
    keyframe_new_blocks : float
        A frame whose depth would allocate more than this fraction of its voxel blocks anew (new
        coverage) is integrated whatever its motion (1 %: a sliver at the frustum's edge is not
        coverage; a new surface is).
    surface_max_incidence_deg : float or None
        With a value, the surface that :meth:`TSDFFusion.extract_mesh` returns comes from a second
        volume (the *surface volume*) that integrates each fused frame without the pixels seen at a
        larger angle between ray and normal and without the pixels at depth discontinuities
        (:func:`drop_grazing`); tracking still ray casts the volume of all pixels. Grazing Kinect
        depth is noisy (~6 mm at 78 degrees) and a silhouette pixel's ray skims the surface: on the
        demo bottle they bent the fused surface by ~0.15 mm at wavelengths of 2.5-25 cm (median normal
        error 1.08 -> 0.76 degrees with 70; 0.34 with the local-linear normal filter of
        :func:`appfusion.points.bilateral_filter_normals`). Tracking against the masked volume was worse
        (demo ATE 1.00 -> 1.27 mm, markerless test sequence 3.0 -> 5.2 mm): the grazing plane and the
        silhouettes constrain the pose. ``docs/geometry-pass.md``. None: one volume, all pixels.
    """

    voxel_size: float = 0.004
    trunc_voxels: float = 4.0
    depth_min: float = 0.15
    depth_max: float = 1.6
    integrate_width: int = 320
    track_width: int = 160
    track_iterations: tuple[int, ...] = (8, 6)
    depth_diff: float = 0.04
    relocalise_depth_diff: float = 0.10
    min_overlap: float = 0.35
    min_inliers: float = 0.6
    inlier_dist: float = 0.01
    max_rmse: float = 0.006
    normal_cos: float = 0.8
    icp_tolerance: float = 2e-5
    normal_space_weighting: bool = True
    normal_smooth_px: float = 1.0
    normal_max_slope: float | None = 4.0
    normal_min_coverage: float = 0.5
    anchor_weight: float = 3.0
    anchor_normal_weight: float = 30.0
    anchor_sight_weighting: bool = False
    refine_raycast: bool = True
    omp_threads: int | None = 1
    max_jump_m: float = 0.08
    max_jump_deg: float = 12.0
    anchor_fit_tol_m: float = 0.005
    relocalise_velocity_frames: int = 3
    block_resolution: int = 8
    block_count: int = 20000
    weight_threshold: float = 2.0
    keyframe_m: float = 0.01
    keyframe_deg: float = 2.0
    keyframe_new_blocks: float = 0.01
    surface_max_incidence_deg: float | None = 70.0


@dataclass
class TrackResult:
    """What tracking said about one frame (the state the GUI shows).

    Attributes
    ----------
    index : int
        Frame counter of the fusion (0-based, frames given to :meth:`TSDFFusion.process`).
    state : {"first", "ok", "lost"}
    pose : (4, 4) ndarray
        Camera-to-world pose of the depth camera: the tracked pose when ``ok``, the last good pose
        when ``lost``.
    overlap, inlier_fraction : float
        Tracking quality (see :class:`FusionConfig`); 1.0 for the first frame.
    rmse : float
        Point-to-plane RMSE of the inliers, metres.
    integrated : bool
        Whether the frame was fused into the volume.
    reason : str
        Why the frame is lost ("" when ok).
    ms : dict
        Milliseconds spent per step ("prep", "raycast", "track", "integrate").
    """

    index: int
    state: str
    pose: np.ndarray
    overlap: float = 1.0
    inlier_fraction: float = 1.0
    rmse: float = 0.0
    integrated: bool = False
    reason: str = ""
    ms: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.state != STATE_LOST


class TSDFFusion:
    """Frame-to-model tracking and TSDF fusion of a depth stream (paper §4.1, KinectFusion).

    Parameters
    ----------
    intrinsics : Intrinsics
        Of the input depth images.
    config : FusionConfig, optional
    initial_pose : (4, 4) array, optional
        Camera-to-world pose of the first frame (default identity: the first camera is the world).
    """

    def __init__(self, intrinsics: Intrinsics, config: FusionConfig | None = None,
                 initial_pose: np.ndarray | None = None):
        self.config = cfg = config or FusionConfig()
        if not (cfg.voxel_size > 0 and cfg.trunc_voxels > 0 and cfg.depth_max > cfg.depth_min >= 0):
            raise AppFusionError(f"fusion: invalid configuration {cfg}")
        self.intrinsics = intrinsics
        set_openmp_threads(cfg.omp_threads)
        self.f_int = max(1, int(round(intrinsics.width / cfg.integrate_width)))
        # a circle centre is as precise as the pixels it was found in: the anchors' weight (inverse
        # variance) falls with the square of the pixel footprint below 640 px (see FusionConfig)
        footprint = min(1.0, intrinsics.width / 640.0) ** 2
        self.anchor_weight = cfg.anchor_weight * footprint
        self.anchor_normal_weight = cfg.anchor_normal_weight * footprint
        self.K_int = intrinsics.scaled(intrinsics.width // self.f_int, intrinsics.height // self.f_int)
        self.f_trk = max(1, int(round(self.K_int.width / cfg.track_width)))
        self.K_trk = self.K_int.scaled(self.K_int.width // self.f_trk, self.K_int.height // self.f_trk)
        self._dev = o3d.core.Device("CPU:0")
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            ["tsdf", "weight"], [o3d.core.float32, o3d.core.float32], [[1], [1]],
            cfg.voxel_size, cfg.block_resolution, cfg.block_count, self._dev)
        self._Kt_int = o3d.core.Tensor(self.K_int.K)
        # the surface volume (``surface_max_incidence_deg``): the same grid, fed without grazing pixels
        self.surface_vbg = None if cfg.surface_max_incidence_deg is None else o3d.t.geometry.VoxelBlockGrid(
            ["tsdf", "weight"], [o3d.core.float32, o3d.core.float32], [[1], [1]],
            cfg.voxel_size, cfg.block_resolution, cfg.block_count, self._dev)
        # Open3D's TSDF integration kernel truncates the projected (u, v) to pick a pixel, i.e. it reads
        # the pixel up to one pixel left/up of the projection (a systematic ~1 mm bias at 320 px); with
        # the principal point moved by +0.5 px it reads the nearest pixel.
        Kr = self.K_int.K.copy()
        Kr[0, 2] += 0.5
        Kr[1, 2] += 0.5
        self._Kt_int_round = o3d.core.Tensor(Kr)
        self.pose = np.eye(4) if initial_pose is None else np.asarray(initial_pose, float).copy()
        self._last_good = self.pose.copy()
        self._velocity = np.eye(4)           # last frame-to-frame motion (camera-to-camera)
        self._last_good_idx = 0              # frame number (0-based, this volume's) of _last_good
        self._frustum_blocks = None
        self._n_integrated = 0
        self._key_pose: np.ndarray | None = None   # pose of the last integrated frame
        self._raycast_cache = None                 # (key, depth, normals) of the last tracking ray cast
        self.n_skipped = 0                         # tracked frames not integrated (no new coverage)
        self.n_frames = 0
        self.lost = False
        self.roi = None                      # (world_to_roi 4x4, lo (3,), hi (3,))
        self.results: list[TrackResult] = []
        self._rays_int = self.K_int.rays().astype(np.float32)
        self._unit_rays_int = self._rays_int / np.linalg.norm(self._rays_int, axis=-1, keepdims=True)
        self._warm_up_raycaster()

    def _warm_up_raycaster(self, n_blocks: int = 8192) -> None:
        """Grow Open3D's ray-cast range-map buffer before the first real ray cast.

        Open3D 0.19's CPU ray caster sizes its range-map fragment buffer on demand: a call that needs
        more fragments than allocated returns an incomplete range map (missing and wrong hits) and
        only grows the buffer for the next call. Ray casting ``n_blocks`` temporary blocks placed
        far away once allocates enough; the blocks are erased again.
        """
        side = int(np.sqrt(n_blocks / 2))
        g = np.stack(np.meshgrid(np.arange(-side // 2, side - side // 2), np.arange(-side // 2, side - side // 2),
                                 np.arange(100000, 100002), indexing="ij"), -1).reshape(-1, 3).astype(np.int32)
        keys = o3d.core.Tensor(g)
        hm = self.vbg.hashmap()
        if hm.capacity() < len(g) + 16:
            return
        hm.activate(keys)
        K = self.K_int
        far = 100000 * self.config.voxel_size * self.config.block_resolution
        self.vbg.ray_cast(keys, o3d.core.Tensor(K.K), o3d.core.Tensor(np.eye(4)), K.width, K.height, ["depth"],
                          1.0, 0.1, 2 * far, 0.5, self.config.trunc_voxels)
        hm.erase(keys)

    # -- region of interest ----------------------------------------------------------------------
    def set_roi(self, world_to_roi: np.ndarray, lo, hi) -> None:
        """Integrate and track only depth points inside an axis-aligned box of another frame.

        Parameters
        ----------
        world_to_roi : (4, 4) array
            Maps fusion-world points into the box's frame (e.g. world -> marker frame).
        lo, hi : (3,) array-like
            Box corners in that frame, metres.
        """
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
            raise AppFusionError(f"fusion: region of interest needs lo < hi (3 values each), got {lo}, {hi}")
        self.roi = (np.asarray(world_to_roi, float).copy(), lo, hi)

    def _mask_roi(self, d: np.ndarray, K: Intrinsics, pose: np.ndarray) -> np.ndarray:
        if self.roi is None:
            return d
        M, lo, hi = self.roi
        T = M @ pose
        rays = self._rays_int if K is self.K_int else K.rays().astype(np.float32)
        with np.errstate(invalid="ignore"):
            keep = np.ones(d.shape, bool)
            for a in range(3):
                c = (rays @ T[a, :3].astype(np.float32)) * d + np.float32(T[a, 3])
                keep &= (c >= lo[a]) & (c <= hi[a])
        return np.where(keep, d, np.nan).astype(np.float32)

    # -- steps -----------------------------------------------------------------------------------
    def _o3d_depth(self, d: np.ndarray) -> o3d.t.geometry.Image:
        d = np.where(np.isfinite(d) & (d > self.config.depth_min) & (d < self.config.depth_max), d, 0.0)
        return o3d.t.geometry.Image(np.ascontiguousarray(d, dtype=np.float32))

    def _frame_blocks(self, depth_int: np.ndarray, pose: np.ndarray, img=None) -> o3d.core.Tensor:
        """Voxel-block coordinates (B, 3) a depth image at integration size touches (truncation band);
        none (0, 3) for an image without a valid pixel, where Open3D raises "No block is touched"
        (the surface volume's image of depth striped with NaN rows: every pixel lacks a normal, so
        :func:`drop_grazing` drops them all)."""
        cfg = self.config
        img = self._o3d_depth(depth_int) if img is None else img
        if not (img.as_tensor().numpy() > 0).any():
            return o3d.core.Tensor(np.zeros((0, 3), np.int32))
        return self.vbg.compute_unique_block_coordinates(img, self._Kt_int, o3d.core.Tensor(invert_pose(pose)),
                                                         1.0, cfg.depth_max, cfg.trunc_voxels)

    def integrate(self, depth_int: np.ndarray, pose: np.ndarray, blocks: o3d.core.Tensor | None = None) -> None:
        """Fuse a depth image at integration resolution (``K_int``) seen from ``pose`` (camera-to-world).

        ``blocks``: the image's voxel blocks if already computed (:meth:`_frame_blocks`). With a surface
        volume, the image without its grazing and discontinuity pixels goes into it too.
        """
        cfg = self.config
        img = self._o3d_depth(depth_int)
        ext = o3d.core.Tensor(invert_pose(pose))
        if blocks is None:
            blocks = self._frame_blocks(depth_int, pose, img)
        if blocks.shape[0] == 0:
            return
        self.vbg.integrate(blocks, img, self._Kt_int_round, ext, 1.0, cfg.depth_max, cfg.trunc_voxels)
        if self.surface_vbg is not None:
            simg = self._o3d_depth(drop_grazing(depth_int, self.K_int, cfg.surface_max_incidence_deg,
                                                self._unit_rays_int))
            sblocks = self._frame_blocks(None, pose, simg)
            if sblocks.shape[0]:
                self.surface_vbg.integrate(sblocks, simg, self._Kt_int_round, ext, 1.0, cfg.depth_max,
                                           cfg.trunc_voxels)
        self._frustum_blocks = blocks
        self._n_integrated += 1
        self._key_pose = np.asarray(pose, float).copy()

    def raycast(self, pose: np.ndarray, K: Intrinsics | None = None, normals: bool = False,
                refine: bool | None = None, all_blocks: bool = False):
        """Ray cast the model's zero level set from ``pose`` (camera-to-world); tracking size by default.

        Open3D's CPU ray caster marches with nearest-lower voxel look-ups (no interpolation), which
        leaves view-dependent terraces of up to a voxel in the depth. With ``refine`` every hit is
        moved by one Newton step along its ray on the trilinearly interpolated TSDF (using the 8
        voxel indices the ray caster reports), and the normal is the trilinear TSDF gradient.

        Returns
        -------
        depth : (H, W) float32
            z-depth in metres, NaN where no surface.
        normals : (H, W, 3) float32, only with ``normals=True``
            Unit normals in the camera frame, facing the camera, NaN where none.

        Only the voxel blocks of the last integrated frame are marched unless ``all_blocks``
        (for views far from the last one, e.g. when relocalising).
        """
        cfg = self.config
        K = K or self.K_trk
        refine = cfg.refine_raycast if refine is None else refine
        if self._frustum_blocks is None:
            d = np.full(K.shape, np.nan, np.float32)
            return (d, np.full(K.shape + (3,), np.nan, np.float32)) if normals else d
        thr = float(min(self._n_integrated - 0.5, cfg.weight_threshold))
        attrs = ["depth", "index", "mask"] if refine else ["depth"]
        blocks = self.active_blocks() if all_blocks else self._frustum_blocks
        r = self.vbg.ray_cast(blocks, o3d.core.Tensor(K.K), o3d.core.Tensor(invert_pose(pose)),
                              K.width, K.height, attrs, 1.0, cfg.depth_min, cfg.depth_max, thr, cfg.trunc_voxels)
        d = r["depth"].numpy()[..., 0].astype(np.float32)
        d[~(d > 0)] = np.nan
        if not refine:
            return (d, self._track_normals(d, K)) if normals else d
        hit = np.isfinite(d) & r["mask"].numpy().all(axis=-1)
        vv, uu = np.nonzero(hit)
        t = d[hit].astype(np.float64)
        R, o = pose[:3, :3], pose[:3, 3]
        ray = np.stack([(uu - K.cx) / K.fx, (vv - K.cy) / K.fy, np.ones(len(uu))], axis=1) @ R.T
        vs = cfg.voxel_size
        g = (o + t[:, None] * ray) / vs                      # voxel i sits at i * voxel_size
        fr = g - np.floor(g)
        vals = self.vbg.attribute("tsdf").numpy().reshape(-1)[r["index"].numpy()[hit]].astype(np.float64)
        bits = np.array([[(k >> a) & 1 for a in range(3)] for k in range(8)], np.float64)   # (8, 3) dx,dy,dz
        wa = np.where(bits[None], fr[:, None, :], 1.0 - fr[:, None, :])                      # (N, 8, 3)
        w = wa.prod(axis=2)
        f = (w * vals).sum(1)
        grad = np.stack([((2 * bits[:, a] - 1)[None] * wa[:, :, (a + 1) % 3] * wa[:, :, (a + 2) % 3] * vals).sum(1)
                         for a in range(3)], axis=1) / vs       # d tsdf / d x, 1/m (tsdf in units of trunc)
        slope = np.einsum("ij,ij->i", grad, ray)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = -f / slope
        good = np.isfinite(step) & (slope < 0) & (np.abs(step) <= 1.5 * vs)
        out = d.copy()                                       # where it cannot be refined: the raw hit
        out[vv[good], uu[good]] = (t + step)[good]
        if not normals:
            return out
        return out, self._track_normals(out, K)

    def _track_normals(self, depth: np.ndarray, K: Intrinsics) -> np.ndarray:
        """Normals of a tracking-size depth image (source or ray cast) for the ICP: discontinuities at
        4 voxels; where that leaves fewer than ``normal_min_coverage`` of the valid pixels a normal
        (surfaces far away or steep to the ray: 1-1.6 m of the real Redwood frames kept 25 %),
        at ``max(4 voxels, normal_max_slope x z / f)`` instead (:func:`vertex_normals`)."""
        cfg = self.config
        n = vertex_normals(depth, K, max_jump=4 * cfg.voxel_size, smooth_px=cfg.normal_smooth_px)
        if cfg.normal_max_slope is None:
            return n
        valid = int(np.isfinite(depth).sum())
        if valid and np.isfinite(n[..., 0]).sum() < cfg.normal_min_coverage * valid:
            n = vertex_normals(depth, K, max_jump=4 * cfg.voxel_size, smooth_px=cfg.normal_smooth_px,
                               max_slope=cfg.normal_max_slope)
        return n

    def _anchor_information(self, anchors, rotation: np.ndarray | None = None) -> list:
        """Per anchor, the 3 x 3 weight (information) matrix of its point-to-point term.

        ``anchor_weight * I`` without normals; with a normal ``n`` (the support plane's),
        ``anchor_weight (I - n n^T) + anchor_normal_weight n n^T``: a circle centre found on the
        depth's plane (:func:`appfusion.markers.circle_on_plane`) is far better known across the
        plane than within it (see :class:`FusionConfig`). With ``anchor_sight_weighting`` and the
        source-to-target ``rotation``, the in-plane error along each anchor's line of sight weighs
        ``sin^2`` of its elevation (:func:`anchor_information`).
        """
        if anchors is None or not len(anchors[0]):
            return []
        k = len(anchors[0])
        if len(anchors) < 3 or anchors[2] is None:
            return [anchor_information(None, self.anchor_weight, self.anchor_normal_weight)] * k
        n = np.broadcast_to(np.asarray(anchors[2], float).reshape(-1, 3), (k, 3))
        if self.config.anchor_sight_weighting and rotation is not None:
            sight = np.asarray(anchors[0], float) @ np.asarray(rotation, float).T      # target frame
            return [anchor_information(v, self.anchor_weight, self.anchor_normal_weight, s) for v, s in zip(n, sight)]
        return [anchor_information(v, self.anchor_weight, self.anchor_normal_weight) for v in n]

    def icp(self, src: np.ndarray, tgt_depth: np.ndarray, tgt_normals: np.ndarray, init: np.ndarray,
            max_dist: float, anchors: tuple[np.ndarray, np.ndarray] | None = None
            ) -> tuple[np.ndarray, float, float, float]:
        """Projective point-to-plane ICP (KinectFusion) of a depth image against a model ray cast.

        Minimises ``sum_p w_p [n_q . (T x_p - v_q)]^2`` over rigid ``T`` (source camera -> target
        camera), where ``q`` is the target pixel that ``T x_p`` projects to, with Huber weights
        ``w_p`` and associations farther than ``max_dist`` dropped; Gauss-Newton on a twist,
        coarse to fine over a 2-level pyramid (stride-2 subsampling).

        Parameters
        ----------
        src : (H, W) float32
            Source depth, metres, NaN invalid, at tracking size (``K_trk``).
        tgt_depth, tgt_normals : (H, W), (H, W, 3)
            Ray-cast model depth and camera-frame normals at the reference pose.
        init : (4, 4)
            Initial source-to-target transform.
        max_dist : float
            Association distance, metres.
        anchors : (src_pts (K, 3), tgt_pts (K, 3)[, normals (K, 3)]), optional
            Known point correspondences (e.g. marker centres) in the source and target camera
            frames, added as point-to-point terms of total weight ``anchor_weight`` times the
            pixel terms' (Huber, 1 cm). With ``normals`` (unit, target camera frame: the support
            plane's normal at each anchor) the component of an anchor's error along its normal
            weighs ``anchor_normal_weight`` instead (:meth:`_anchor_information`).

        Returns
        -------
        T : (4, 4) source-to-target transform.
        overlap : float
            Fraction of valid source pixels that project onto the model.
        inlier_fraction : float
            Fraction of those within ``inlier_dist`` of the model plane.
        rmse : float
            Point-to-plane RMSE of the inliers, metres.
        """
        cfg = self.config
        K = self.K_trk
        T = init.copy()
        anchor_info = self._anchor_information(anchors, T[:3, :3])
        src_normals = self._track_normals(src, K)
        levels = []
        for lev in range(len(cfg.track_iterations)):
            f = 2 ** (len(cfg.track_iterations) - 1 - lev)        # coarsest first
            sd = src[::f, ::f]
            ok = np.isfinite(sd)
            vv, uu = np.nonzero(ok)
            z = sd[ok]
            P = np.stack([(uu * f - K.cx) / K.fx * z, (vv * f - K.cy) / K.fy * z, z], axis=1).astype(np.float32)
            Ns = src_normals[::f, ::f][ok]
            td = tgt_depth[::f, ::f]
            th, tw = td.shape
            ru = ((np.arange(tw) * f - K.cx) / K.fx).astype(np.float32)
            rv = ((np.arange(th) * f - K.cy) / K.fy).astype(np.float32)
            tgt = np.empty((th, tw, 6), np.float32)              # vertex and normal per target pixel
            tgt[..., 0] = ru[None, :] * td
            tgt[..., 1] = rv[:, None] * td
            tgt[..., 2] = td
            tgt[..., 3:] = tgt_normals[::f, ::f]
            levels.append(((K.fx / f, K.fy / f, K.cx / f, K.cy / f), P, Ns, tgt.reshape(-1, 6), tw, th,
                           cfg.track_iterations[lev]))
        huber = max_dist / 4
        n_src = len(levels[-1][1])
        if n_src < 50:
            return T, 0.0, 0.0, np.inf
        for li, ((fx, fy, cx, cy), P, Ns, tgt, tw, th, iters) in enumerate(levels):
            last = li == len(levels) - 1
            for it in range(iters + 1 if last else iters):
                R32 = T[:3, :3].astype(np.float32)
                Q = P @ R32.T + T[:3, 3].astype(np.float32)
                with np.errstate(divide="ignore", invalid="ignore"):
                    iz = 1.0 / Q[:, 2]
                    u = np.rint(fx * Q[:, 0] * iz + cx)
                    v = np.rint(fy * Q[:, 1] * iz + cy)
                qi = np.flatnonzero((Q[:, 2] > 0) & (u >= 0) & (u < tw) & (v >= 0) & (v < th))
                g = tgt[v[qi].astype(np.int64) * tw + u[qi].astype(np.int64)]
                hit = np.isfinite(g[:, 2]) & np.isfinite(g[:, 3])
                qi, g = qi[hit], g[hit]
                tn = g[:, 3:]
                Qh = Q[qi]
                diff = Qh - g[:, :3]
                r = np.einsum("ij,ij->i", diff, tn)
                ncos = np.einsum("ij,ij->i", Ns[qi] @ R32.T, tn)
                near = ((np.abs(r) < max_dist) & (np.einsum("ij,ij->i", diff, diff) < (2 * max_dist) ** 2)
                        & ~(np.abs(ncos) < cfg.normal_cos))            # NaN source normal: kept
                if last and it == iters:          # after the last update: quality only
                    break
                Qn, tnn, rn = Qh[near].astype(np.float64), tn[near].astype(np.float64), r[near].astype(np.float64)
                if len(rn) < 30:
                    return T, len(qi) / n_src, 0.0, np.inf
                w = np.where(np.abs(rn) < huber, 1.0, huber / np.maximum(np.abs(rn), 1e-12))
                if cfg.normal_space_weighting:
                    w *= _normal_space_weights(tnn)
                J = np.concatenate([np.cross(Qn, tnn), tnn], axis=1)
                Jw = J * w[:, None]
                A = Jw.T @ J
                b = -Jw.T @ rn
                if anchors is not None and len(anchors[0]):
                    Qa = anchors[0] @ T[:3, :3].T + T[:3, 3]
                    ea = Qa - anchors[1]
                    na = np.linalg.norm(ea, axis=1)
                    wa = w.sum() / len(Qa) * np.where(na < 0.01, 1.0, 0.01 / np.maximum(na, 1e-12))
                    for q, e_, w_, M in zip(Qa, ea, wa, anchor_info):
                        Ja = np.concatenate([-_skew(q), np.eye(3)], axis=1)
                        JM = w_ * Ja.T @ M
                        A += JM @ Ja
                        b -= JM @ e_
                A += np.eye(6) * (1e-9 + 1e-6 * np.trace(A) / 6)
                xi = np.linalg.solve(A, b)
                T = _twist_to_pose(xi) @ T
                if np.abs(xi).max() < cfg.icp_tolerance:
                    if not last:
                        break
                    iters = it + 1            # converged: one more pass for the quality numbers
        overlap = len(qi) / n_src
        rr = r[near]
        inl = np.abs(rr) < cfg.inlier_dist
        frac = inl.sum() / max(len(qi), 1)
        rmse = float(np.sqrt(np.mean(rr[inl] ** 2))) if inl.any() else np.inf
        return T, float(overlap), float(frac), rmse

    def track(self, depth_trk: np.ndarray, init_pose: np.ndarray, ref_pose: np.ndarray,
              depth_diff: float, anchors: tuple[np.ndarray, np.ndarray] | None = None,
              all_blocks: bool = False) -> tuple[np.ndarray, float, float, float, dict]:
        """Align a tracking-size depth image to the model ray cast at ``ref_pose`` (frame-to-model).

        ``anchors`` are (camera-frame points, world points) correspondences. Returns the
        camera-to-world pose, overlap, inlier fraction, RMSE and timings (ms).
        """
        t0 = time.perf_counter()
        # the model changes only when a frame is integrated: a ray cast from the same pose is reused
        key = (self._n_integrated, self.n_blocks if all_blocks else -1, np.asarray(ref_pose, float).tobytes())
        if self._raycast_cache is not None and self._raycast_cache[0] == key:
            model, normals = self._raycast_cache[1:]
        else:
            model, normals = self.raycast(ref_pose, normals=True, all_blocks=all_blocks)
            self._raycast_cache = (key, model, normals)
        t1 = time.perf_counter()
        init = invert_pose(ref_pose) @ init_pose          # source (current camera) -> target (ref camera)
        anc = None
        if anchors is not None and len(anchors[0]):
            anc = (np.asarray(anchors[0], float), transform_points(invert_pose(ref_pose), np.asarray(anchors[1], float)))
            if len(anchors) > 2 and anchors[2] is not None:       # world normals -> reference camera
                anc = anc + (np.asarray(anchors[2], float).reshape(-1, 3) @ np.asarray(ref_pose, float)[:3, :3],)
        T, overlap, frac, rmse = self.icp(depth_trk, model, normals, init, depth_diff, anc)
        t2 = time.perf_counter()
        return (orthonormalize(ref_pose @ T), overlap, frac, rmse,
                {"raycast": (t1 - t0) * 1e3, "track": (t2 - t1) * 1e3})

    # -- the per-frame entry point -------------------------------------------------------------
    def process(self, depth: np.ndarray, anchors: tuple[np.ndarray, np.ndarray] | None = None) -> TrackResult:
        """Track one depth frame against the model and fuse it (KinectFusion step).

        Parameters
        ----------
        depth : (H, W) float array
            Depth in metres (NaN or 0 invalid) of the size of ``intrinsics``.
        anchors : (cam_pts (K, 3), world_pts (K, 3)[, world normal (3,) or (K, 3)[, camera normal (3,)]]), optional
            Points of this frame (depth camera frame) whose world positions are known, e.g. the
            marker centres: they join the ICP as point-to-point terms, and with three or more (or
            two and the plane's normal in both frames, :func:`anchor_pose`) a lost frame is
            relocalised from their pose instead of the last good pose. With a normal (the support
            plane's) their error along it weighs ``anchor_normal_weight``.

        Returns
        -------
        TrackResult
        """
        with blas_threads(1):
            return self._process(depth, anchors)

    def _process(self, depth: np.ndarray, anchors: tuple[np.ndarray, np.ndarray] | None = None) -> TrackResult:
        cfg = self.config
        depth = np.asarray(depth)
        if depth.shape != self.intrinsics.shape:
            raise AppFusionError(f"fusion: depth image of shape {depth.shape} does not match the intrinsics "
                                 f"{self.intrinsics.shape}")
        idx = self.n_frames
        self.n_frames += 1
        set_openmp_threads(cfg.omp_threads)
        t0 = time.perf_counter()
        d_int = downsample_depth(depth, self.f_int)
        with np.errstate(invalid="ignore"):
            d_int[~((d_int > cfg.depth_min) & (d_int < cfg.depth_max))] = np.nan
        ms = {}
        if self._frustum_blocks is None:
            d_roi = self._mask_roi(d_int, self.K_int, self.pose)
            if np.isfinite(d_roi).sum() < 0.01 * d_roi.size:
                res = TrackResult(idx, STATE_LOST, self.pose.copy(), 0.0, 0.0, np.inf, False,
                                  "no valid depth to start the model from" + depth_range_hint(depth, cfg))
                self.results.append(res)
                return res
            ms["prep"] = (time.perf_counter() - t0) * 1e3
            t1 = time.perf_counter()
            self.integrate(d_roi, self.pose)
            ms["integrate"] = (time.perf_counter() - t1) * 1e3
            self._last_good = self.pose.copy()
            self._last_good_idx = idx
            res = TrackResult(idx, STATE_FIRST, self.pose.copy(), integrated=True, ms=ms)
            self.results.append(res)
            return res

        relocalising = self.lost
        prev = self._last_good
        pred = prev if relocalising else prev @ self._velocity
        # with keyframes on, track against the (cached) ray cast at the last integrated frame
        ref = self._key_pose if (self._keyframes and not relocalising and self._key_pose is not None) else prev
        far_ref = False
        if relocalising and (fixed := anchor_pose(anchors)) is not None:
            # relocalise from the anchors' rigid fit, against the model seen from there
            pred = fixed
            ref, far_ref = orthonormalize(pred), True
        elif anchors is not None and len(anchors[0]) >= 2 and (
                (far := self._anchor_pose_beyond_jump(anchors, pred)) is not None):
            # three or more circles, or two with the plane's normal, paired by their numbering, fix a pose
            # beyond the jump limit from the prediction (a sweep faster than tracking follows): start
            # there, as a relocalisation does
            pred, ref = far, far.copy()
            far_ref = relocalising = True
        pred = orthonormalize(pred)
        d_roi_pred = self._mask_roi(d_int, self.K_int, pred)
        d_trk = downsample_depth(d_roi_pred, self.f_trk)
        ms["prep"] = (time.perf_counter() - t0) * 1e3
        if np.isfinite(d_trk).sum() < 50:
            pose, overlap, frac, rmse, tms = pred, 0.0, 0.0, np.inf, {}
        else:
            pose, overlap, frac, rmse, tms = self.track(
                d_trk, pred, ref, cfg.relocalise_depth_diff if relocalising else cfg.depth_diff, anchors,
                all_blocks=far_ref)
        ms.update(tms)
        jump_m, jump_deg = pose_jump(pred, pose)
        scale = 2.5 if relocalising else 1.0
        reason = ""
        if overlap < cfg.min_overlap:
            reason = f"overlap with the model {overlap:.2f} < {cfg.min_overlap}"
        elif frac < cfg.min_inliers:
            reason = f"inlier fraction {frac:.2f} < {cfg.min_inliers}"
        elif rmse > cfg.max_rmse:
            reason = f"residual {rmse * 1e3:.1f} mm > {cfg.max_rmse * 1e3:.1f} mm"
        elif jump_m > cfg.max_jump_m * scale or jump_deg > cfg.max_jump_deg * scale:
            reason = f"pose jump {jump_m * 1e3:.0f} mm / {jump_deg:.1f} deg"
        if reason:
            self.lost = True
            self._velocity = np.eye(4)
            res = TrackResult(idx, STATE_LOST, self._last_good.copy(), overlap, frac, rmse, False, reason, ms)
            self.results.append(res)
            return res
        self.lost = False
        if not relocalising:
            self._velocity = orthonormalize(invert_pose(prev) @ pose)
        else:
            gap = idx - self._last_good_idx
            self._velocity = (mean_motion(invert_pose(prev) @ pose, gap)
                              if 0 < gap <= cfg.relocalise_velocity_frames else np.eye(4))
        self.pose = pose
        self._last_good = pose.copy()
        self._last_good_idx = idx
        t1 = time.perf_counter()
        d_roi = self._mask_roi(d_int, self.K_int, pose)
        blocks = None
        if not relocalising and self._keyframes:
            redundant, blocks = self._redundant(d_roi, pose)
            if redundant:
                self.n_skipped += 1
                ms["skip_check"] = (time.perf_counter() - t1) * 1e3
                res = TrackResult(idx, STATE_OK, pose.copy(), overlap, frac, rmse, False, "", ms)
                self.results.append(res)
                return res
        self.integrate(d_roi, pose, blocks)
        ms["integrate"] = (time.perf_counter() - t1) * 1e3
        res = TrackResult(idx, STATE_OK, pose.copy(), overlap, frac, rmse, True, "", ms)
        self.results.append(res)
        return res

    def _anchor_pose_beyond_jump(self, anchors, pred: np.ndarray) -> np.ndarray | None:
        """The anchors' pose (camera to world, :func:`anchor_pose`) where it fits the fused circles
        within ``anchor_fit_tol_m`` RMS and lies beyond the jump limit from ``pred``; else None."""
        cfg = self.config
        if not cfg.anchor_fit_tol_m > 0:
            return None
        T = anchor_pose(anchors)
        if T is None:
            return None
        T = orthonormalize(T)
        r = transform_points(T, anchors[0]) - anchors[1]
        if np.sqrt(np.mean(np.sum(r * r, axis=1))) > cfg.anchor_fit_tol_m:
            return None
        jump_m, jump_deg = pose_jump(pred, T)
        return T if (jump_m > cfg.max_jump_m or jump_deg > cfg.max_jump_deg) else None

    @property
    def _keyframes(self) -> bool:
        return self.config.keyframe_m > 0 and self.config.keyframe_deg > 0

    def _redundant(self, depth_int: np.ndarray, pose: np.ndarray) -> tuple[bool, o3d.core.Tensor | None]:
        """Whether a tracked frame adds no new coverage: within ``keyframe_m`` / ``keyframe_deg`` of the
        keyframe, and at most ``keyframe_new_blocks`` of the voxel blocks its depth (integration size,
        ROI applied) touches are not in the volume yet. Also returns the frame's blocks when computed."""
        cfg = self.config
        if self._key_pose is None:
            return False, None
        moved_m, turned_deg = pose_jump(self._key_pose, pose)
        if not (moved_m < cfg.keyframe_m and turned_deg < cfg.keyframe_deg):
            return False, None
        blocks = self._frame_blocks(depth_int, pose)
        if blocks.shape[0] == 0:
            return True, blocks
        _, found = self.vbg.hashmap().find(blocks)
        new = int(blocks.shape[0] - found.to(o3d.core.int64).sum().item())
        return new <= cfg.keyframe_new_blocks * blocks.shape[0], blocks

    def predicted_pose(self) -> np.ndarray:
        """Pose the next frame is expected at: the last good pose moved by the last motion (the last
        good pose itself while lost)."""
        return self._last_good.copy() if self.lost else orthonormalize(self._last_good @ self._velocity)

    # -- outputs -----------------------------------------------------------------------------
    def active_blocks(self) -> o3d.core.Tensor:
        """Coordinates (B, 3) int32 of the allocated voxel blocks.

        ``hashmap().key_tensor()`` is the hash map's whole key *buffer* (its capacity, default
        20,000 rows), including slots never used and the erased warm-up blocks of
        :meth:`_warm_up_raycaster`; ray casting that buffer hung Open3D 0.19 for minutes on a
        relocalisation (measured on a 160 x 120 session). Only the active slots are blocks.
        """
        hm = self.vbg.hashmap()
        return hm.key_tensor()[hm.active_buf_indices().to(o3d.core.int64)]

    @property
    def n_integrated(self) -> int:
        """Number of frames integrated into the volume so far (tracked frames skipped as redundant,
        :attr:`n_skipped`, and lost ones are not counted)."""
        return int(self._n_integrated)

    @property
    def n_blocks(self) -> int:
        """Number of allocated voxel blocks."""
        return int(self.vbg.hashmap().size())

    @property
    def _surface(self) -> o3d.t.geometry.VoxelBlockGrid:
        return self.vbg if self.surface_vbg is None else self.surface_vbg

    def extract_mesh(self, weight_threshold: float | None = None) -> o3d.geometry.TriangleMesh:
        """Marching-cubes mesh of the zero level set (fusion world frame), legacy Open3D mesh with
        vertex normals, from the surface volume when there is one (``surface_max_incidence_deg``).
        Empty if nothing was integrated."""
        if self._n_integrated == 0:
            return o3d.geometry.TriangleMesh()
        thr = self.config.weight_threshold if weight_threshold is None else weight_threshold
        try:
            mesh = self._surface.extract_triangle_mesh(float(min(thr, self._n_integrated - 0.5))).to_legacy()
        except RuntimeError:                 # Open3D raises on an empty extraction
            return o3d.geometry.TriangleMesh()
        mesh.compute_vertex_normals()
        return mesh

    def extract_point_cloud(self, weight_threshold: float | None = None) -> o3d.geometry.PointCloud:
        """Surface points of the (surface) volume with normals (fusion world frame)."""
        if self._n_integrated == 0:
            return o3d.geometry.PointCloud()
        thr = self.config.weight_threshold if weight_threshold is None else weight_threshold
        try:
            return self._surface.extract_point_cloud(float(min(thr, self._n_integrated - 0.5))).to_legacy()
        except RuntimeError:
            return o3d.geometry.PointCloud()
