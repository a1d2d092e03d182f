"""A small, independent mirror-ball scene generator for the lighting-pass tests (paper §4.3).

Nothing here uses appfusion's lighting code: a known environment (a smooth gradient plus a few bright
lat-long rectangles) is reflected by an analytic mirror sphere standing on the support plane z = 0 and
rendered, supersampled per pixel, by orbiting pinhole cameras (OpenCV convention, world = marker frame);
depth is the same ray-sphere intersection with Kinect-like noise, holes and outliers.
"""

from __future__ import annotations

import numpy as np

from appfusion import octahedral as octa
from appfusion.frame import Intrinsics, invert_pose, make_pose

INTR = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
CENTER = np.array([0.02, -0.01, 0.05])
RADIUS = 0.05
BOX = np.array([[-0.15, -0.15, 0.01], [0.15, 0.15, 0.25]])
#: depth camera -> RGB camera: the RGB camera sits 2.5 cm beside the IR camera (Kinect v1)
DEPTH_TO_RGB = make_pose(None, [-0.025, 0.0, 0.0])

# (theta0, theta1, phi0, phi1) in degrees (theta from +z, phi from +x, wrapping through 180) and RGB
RECTS = [
    (20.0, 40.0, 10.0, 50.0, (6.0, 5.6, 4.8)),
    (50.0, 75.0, 150.0, 200.0, (2.4, 2.7, 3.0)),
    (100.0, 125.0, -90.0, -40.0, (1.2, 1.0, 0.8)),
]


def env(d: np.ndarray) -> np.ndarray:
    """Radiance (..., 3) of the test environment in directions d (..., 3) (unit)."""
    d = np.asarray(d, float)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = np.stack([0.30 + 0.15 * z + 0.05 * x, 0.33 + 0.18 * z + 0.04 * y, 0.38 + 0.25 * z], axis=-1)
    th = np.degrees(np.arccos(np.clip(z, -1.0, 1.0)))
    ph = np.degrees(np.arctan2(y, x))
    for t0, t1, p0, p1, c in RECTS:
        pm = np.where(ph < 0, ph + 360.0, ph) if p1 > 180 else ph
        inside = (th >= t0) & (th < t1) & (pm >= p0) & (pm < p1)
        out = out + inside[..., None] * np.asarray(c)
    return out


def gt_map(n: int, sub: int = 8) -> np.ndarray:
    """Ground-truth (2, n, n, 3) octahedral map: the environment averaged over each texel."""
    d = octa.sphere_directions(n * sub)
    return env(d).reshape(2, n, sub, n, sub, 3).mean(axis=(2, 4))


def gt_latlong(h: int, sub: int = 4) -> np.ndarray:
    """Ground-truth lat-long image (h, 2h, 3), supersampled."""
    d = octa.latlong_directions(h * sub)
    return env(d).reshape(h, sub, 2 * h, sub, 3).mean(axis=(1, 3))


def look_at(eye, target) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at ``eye`` looking at ``target`` with world z up."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return make_pose(np.stack([x, np.cross(z, x), z], axis=1), eye)


def orbit(k: int, dist: float = 0.65, elev_deg=(20.0, 55.0), seed: int = 0, jitter_m: float = 0.03):
    """k camera poses around the ball: azimuths evenly spread, elevations varying between the limits."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(k):
        az = 2 * np.pi * i / k + rng.normal(0, 0.05)
        el = np.radians(elev_deg[0] + (elev_deg[1] - elev_deg[0]) * (0.5 + 0.5 * np.sin(6 * np.pi * i / k)))
        eye = CENTER + dist * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        out.append(look_at(eye, CENTER + rng.normal(0, jitter_m, 3)))
    return out


def _pixel_rays(intr: Intrinsics, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit camera-frame rays of (sub)pixel coordinates, through the lens distortion if any."""
    if intr.dist:
        import cv2
        pts = np.stack([u.ravel(), v.ravel()], -1).reshape(-1, 1, 2).astype(np.float64)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        xy = cv2.undistortPointsIter(pts, intr.K, np.asarray(intr.dist), None, None, crit).reshape(u.shape + (2,))
        d = np.concatenate([xy, np.ones(u.shape + (1,))], axis=-1)
    else:
        d = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _intersect(dw, o, c=CENTER, r=RADIUS):
    oc = o - c
    b = dw @ oc
    disc = b * b - (oc @ oc - r * r)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return (disc > 0) & (t > 0), t


def render_rgb(pose_rgb, intr: Intrinsics = INTR, ss: int = 3, rho=1.0, noise: float = 0.01, bg: float = 0.2,
               seed: int = 0, user_deg: float = 0.0, user_radiance: float = 0.02,
               center=CENTER, radius=RADIUS, environment=env) -> np.ndarray:
    """Linear RGB image (H, W, 3) float32 of the mirror ball, ``ss x ss`` samples per pixel.

    ``rho``: mirror reflectance. ``noise``: relative Gaussian noise (plus 30% of it absolute).
    ``user_deg`` > 0 puts the user (radiance ``user_radiance``) in the reflection: a disc of that angular
    radius around the direction from the ball towards the camera.
    """
    rng = np.random.default_rng(seed)
    img = np.full((intr.height, intr.width, 3), bg, np.float32)
    Ti = invert_pose(pose_rgb)
    cc = Ti[:3, :3] @ center + Ti[:3, 3]
    u0, v0 = intr.fx * cc[0] / cc[2] + intr.cx, intr.fy * cc[1] / cc[2] + intr.cy
    rp = 1.7 * intr.fx * radius / cc[2] + 6
    x0, x1 = int(max(u0 - rp, 0)), int(min(u0 + rp + 1, intr.width))
    y0, y1 = int(max(v0 - rp, 0)), int(min(v0 + rp + 1, intr.height))
    if x0 >= x1 or y0 >= y1:
        return img
    vv, uu = np.mgrid[y0:y1, x0:x1].astype(float)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    acc = np.zeros(vv.shape + (3,))
    o = pose_rgb[:3, 3]
    to_cam = (o - center) / np.linalg.norm(o - center)
    for oy in off:
        for ox in off:
            dw = _pixel_rays(intr, uu + ox, vv + oy) @ pose_rgb[:3, :3].T
            hit, t = _intersect(dw, o, center, radius)
            n = (o + t[..., None] * dw - center) / radius
            r = dw - 2.0 * (dw * n).sum(-1, keepdims=True) * n
            L = np.asarray(rho) * environment(r)
            if user_deg > 0:
                L = np.where((r @ to_cam > np.cos(np.radians(user_deg)))[..., None], user_radiance, L)
            acc += np.where(hit[..., None], L, bg)
    acc /= ss * ss
    acc = acc * (1 + noise * rng.normal(size=acc.shape)) + 0.3 * noise * rng.normal(size=acc.shape)
    img[y0:y1, x0:x1] = acc
    return img


def render_depth(pose, intr: Intrinsics = INTR, sigma: float = 0.003, drop: float = 0.3, outliers: float = 0.05,
                 min_cos: float = 0.25, seed: int = 0, hole: int = 20) -> np.ndarray:
    """Kinect-like depth (metres, NaN invalid) of the ball on the plane z = 0 from a depth-camera pose.

    Noise ``sigma`` along the ray; no return where the mirror is seen at ``w_o . n < min_cos``; random
    drop-outs; ``outliers`` of the ball's pixels get a depth up to 10 cm wrong; a square hole of
    2 * ``hole`` pixels in the middle of the ball's image.
    """
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(float)
    dc = _pixel_rays(intr, u, v)
    dw = dc @ pose[:3, :3].T
    o = pose[:3, 3]
    hit, t = _intersect(dw, o)
    nrm = (o + t[..., None] * dw - CENTER) / RADIUS
    cos = -(dw * nrm).sum(-1)
    tp = -o[2] / np.where(dw[..., 2] < -1e-9, dw[..., 2], -1e-9)
    z = np.where(hit, t * dc[..., 2], tp * dc[..., 2])
    z = z + rng.normal(size=z.shape) * sigma
    z[hit & (cos < min_cos)] = np.nan
    z[hit & (rng.random(z.shape) < drop)] = np.nan
    bad = hit & (rng.random(z.shape) < outliers)
    z[bad] += rng.uniform(-0.1, 0.1, bad.sum())
    if hole:
        cc = invert_pose(pose) @ np.r_[CENTER, 1.0]
        uc, vc = intr.fx * cc[0] / cc[2] + intr.cx, intr.fy * cc[1] / cc[2] + intr.cy
        z[max(int(vc) - hole, 0):int(vc) + hole, max(int(uc) - hole, 0):int(uc) + hole] = np.nan
    return z.astype(np.float32)


def rel_errors(est: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Texel-wise relative error |est - gt| / gt (mean over RGB) of the texels in mask."""
    return (np.abs(est - gt).mean(-1) / gt.mean(-1))[mask]


def lit(gt: np.ndarray, frac: float = 0.05) -> np.ndarray:
    """Texels whose ground-truth luminance exceeds ``frac`` of the median (the 'lit' directions)."""
    lum = gt.mean(-1)
    return lum > frac * np.median(lum)


#: the depth camera's emitter in its own frame (Kinect v1: 7.5 cm to the right of the IR camera)
EMITTER = np.array([0.075, 0.0, 0.0])


def render_mirror_depth(pose, intr: Intrinsics = INTR, emitter=EMITTER, spot_deg: float = 5.0, sigma: float = 0.003,
                        plane_sigma: float = 0.0015, outliers: float = 0.03, outlier_sigma: float = 0.02,
                        center=CENTER, radius=RADIUS, seed: int = 0) -> np.ndarray:
    """Depth (metres, NaN invalid) of a MIRROR ball on the plane z = 0 as a structured-light camera sees it.

    The ball returns depth only where it reflects the emitter into the camera: where its normal is within
    ``spot_deg`` of the bisector of the directions to the camera and to the emitter (noise ``sigma``);
    ``outliers`` of its other pixels return a depth behind the surface by ``|N(0, outlier_sigma)|``; the
    rest of the ball is invalid. The plane returns depth (noise ``plane_sigma``) except where the ball
    hides it from the emitter (its shadow beside the ball, away from the emitter).
    """
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(float)
    dc = _pixel_rays(intr, u, v)
    dw = dc @ pose[:3, :3].T
    o = pose[:3, 3]
    center = np.asarray(center, float)
    hit, t = _intersect(dw, o, center, radius)
    pw = o + t[..., None] * dw
    nrm = (pw - center) / radius
    pc = t[..., None] * dc                                     # hit point in the camera frame
    to_cam = -pc / np.linalg.norm(pc, axis=-1, keepdims=True)
    to_em = np.asarray(emitter, float) - pc
    to_em /= np.linalg.norm(to_em, axis=-1, keepdims=True)
    h = to_cam + to_em
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    n_cam = nrm @ pose[:3, :3]
    spot = hit & ((n_cam * h).sum(-1) >= np.cos(np.radians(spot_deg)))
    z = np.full(u.shape, np.nan)
    z[spot] = (t * dc[..., 2])[spot] + rng.normal(size=int(spot.sum())) * sigma
    out = hit & ~spot & (rng.random(u.shape) < outliers)
    z[out] = (t * dc[..., 2])[out] + np.abs(rng.normal(size=int(out.sum())) * outlier_sigma)
    # the plane, where the ball does not cover it, lit by the emitter
    tp = -o[2] / np.where(dw[..., 2] < -1e-9, dw[..., 2], -1e-9)
    pl = ~hit & (dw[..., 2] < -1e-9)
    P = o + tp[..., None] * dw
    e_w = pose[:3, :3] @ np.asarray(emitter, float) + o
    seg = e_w - P
    L = np.linalg.norm(seg, axis=-1)
    sd = seg / L[..., None]
    oc = P - center                                            # per-pixel origins: inline ray-sphere test
    b = (sd * oc).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - radius * radius)
    ts = -b - np.sqrt(np.maximum(disc, 0.0))
    shadow = (disc > 0) & (ts > 0) & (ts < L)
    ok = pl & ~shadow
    z[ok] = (tp * dc[..., 2])[ok] + rng.normal(size=int(ok.sum())) * plane_sigma
    return z.astype(np.float32)
