"""Colours the GUI draws: point colourings of the 3-D view, stream images, environment map, HBSABs.

All functions are vectorised numpy without Qt, returning float32 RGBA in [0, 1] for points or
uint8 images for image items, so they are tested without a display.

Point colourings (:data:`COLOUR_MODES`):

``clusters``    the specular cluster of each point (§5.2: "we visualize the clustering by rendering
                the points of each cluster with a different color"), palette of :mod:`appfusion.export`
``rho_d``       diffuse albedo (linear RGB, shown sRGB-encoded)
``rho_s``       specular intensity of the point's cluster, normalised by the largest
``alpha``       Ward roughness of the point's cluster on a viridis scale from 0 to 0.5
``appearance``  a cheap preview of Eq. 1 under one light: ``(rho_d + pi rho_s f(alpha; l, v)) (n.l)``
                plus 15 % ambient ``rho_d``, with a light just above the eye (the full environment
                integral of relighting is far too heavy to run per redraw)
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..brdf import ward
from ..export import CLUSTER_COLOURS
from ..frame import REC709_LUMA, linear_to_srgb

COLOUR_MODES = ("clusters", "rho_d", "rho_s", "alpha", "appearance")
#: colour of points whose attribute is not known yet (grey)
UNKNOWN = np.array([0.55, 0.55, 0.55, 1.0], np.float32)

# viridis, 9 stops (matplotlib's, CC0), interpolated linearly
_VIRIDIS = np.array([
    [0.267, 0.005, 0.329], [0.283, 0.141, 0.458], [0.254, 0.265, 0.530], [0.207, 0.372, 0.553],
    [0.164, 0.471, 0.558], [0.128, 0.567, 0.551], [0.135, 0.659, 0.518], [0.267, 0.749, 0.441],
    [0.478, 0.821, 0.318]], np.float32)
_TURBO = np.array([
    [0.190, 0.072, 0.232], [0.275, 0.400, 0.860], [0.157, 0.694, 0.937], [0.141, 0.892, 0.695],
    [0.457, 0.994, 0.340], [0.788, 0.931, 0.204], [0.983, 0.729, 0.220], [0.950, 0.405, 0.087],
    [0.729, 0.150, 0.013], [0.480, 0.016, 0.011]], np.float32)


def colormap(values: np.ndarray, lo: float, hi: float, cmap: str = "viridis") -> np.ndarray:
    """Map scalars to RGB (..., 3) float32 in [0, 1] on ``[lo, hi]``; NaN maps to grey."""
    stops = _VIRIDIS if cmap == "viridis" else _TURBO
    v = np.asarray(values, np.float64)
    t = np.clip((v - lo) / max(hi - lo, 1e-12), 0.0, 1.0) * (len(stops) - 1)
    t = np.where(np.isfinite(t), t, 0.0)
    i0 = np.minimum(np.floor(t).astype(np.int64), len(stops) - 2)
    a = (t - i0)[..., None]
    out = stops[i0] * (1 - a) + stops[i0 + 1] * a
    out[~np.isfinite(v)] = UNKNOWN[:3]
    return out.astype(np.float32)


def _rgba(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, np.float32)
    return np.concatenate([rgb, np.ones(rgb.shape[:-1] + (1,), np.float32)], axis=-1)


def cluster_rgb(labels: np.ndarray) -> np.ndarray:
    """Palette colour (P, 3) of cluster labels (P,), the same palette as the exported clusters.png."""
    return CLUSTER_COLOURS[np.asarray(labels, np.int64) % len(CLUSTER_COLOURS)]


def shade_preview(positions, normals, rho_d, rho_s, alpha, eye, up=(0.0, 0.0, 1.0),
                  ambient: float = 0.15) -> np.ndarray:
    """Eq. 1 under one directional-ish light near the eye: a per-point preview, linear RGB (P, 3).

    Parameters
    ----------
    positions, normals : (P, 3)
        World points and unit normals (metres).
    rho_d, rho_s : (P, 3)
        Diffuse albedo and specular intensity per point (linear).
    alpha : (P,)
        Ward roughness per point.
    eye : (3,)
        Camera position (world, metres); the light sits 30 % of the eye distance above it.
    ambient : float
        Fraction of rho_d added as ambient light.

    Returns
    -------
    (P, 3) float32
        Radiance for unit irradiance, ``(rho_d + pi rho_s f) (n . l) + ambient rho_d``.
    """
    p = np.asarray(positions, np.float64)
    n = np.asarray(normals, np.float64)
    eye = np.asarray(eye, np.float64).reshape(3)
    centre = p.mean(axis=0) if len(p) else np.zeros(3)
    dist = np.linalg.norm(eye - centre)
    light = eye + 0.3 * dist * np.asarray(up, np.float64)
    wo = eye - p
    wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)
    wi = light - p
    wi /= np.maximum(np.linalg.norm(wi, axis=1, keepdims=True), 1e-12)
    # points facing away from the light get the ambient term only (and Ward is 0 below the horizon)
    cos_i = np.clip(np.einsum("ij,ij->i", n, wi), 0.0, 1.0)
    f = ward(np.maximum(np.asarray(alpha, np.float64), 1e-3), wi, wo, n)
    L = (np.asarray(rho_d) + np.pi * np.asarray(rho_s) * f[:, None]) * cos_i[:, None] + ambient * np.asarray(rho_d)
    return L.astype(np.float32)


def point_colours(mode: str, n_points: int, labels=None, rho_d=None, rho_s=None, alpha=None,
                  positions=None, normals=None, eye=None) -> np.ndarray:
    """RGBA (P, 4) float32 colours of the fused points for a colouring mode (:data:`COLOUR_MODES`).

    Attributes missing so far (None, or of the wrong length early in a scan) give grey points
    rather than an error: the GUI draws what is there.
    """
    P = int(n_points)
    grey = np.broadcast_to(UNKNOWN, (P, 4)).copy()
    lab = None
    if labels is not None and len(labels) == P:
        lab = np.asarray(labels, np.int64)
    have_rd = rho_d is not None and len(rho_d) == P

    def per_cluster(v):
        if lab is None or v is None or len(v) == 0:
            return None
        v = np.asarray(v)
        ok = (lab >= 0) & (lab < len(v))
        out = np.full((P,) + v.shape[1:], np.nan, np.float64)
        out[ok] = v[lab[ok]]
        return out

    if mode == "clusters":
        if lab is None:
            return grey
        return _rgba(cluster_rgb(lab))
    if mode == "rho_d":
        return _rgba(linear_to_srgb(rho_d)) if have_rd else grey
    if mode == "rho_s":
        v = per_cluster(rho_s)
        if v is None:
            return grey
        scale = np.nanmax(v) if np.any(np.isfinite(v)) else 1.0
        rgb = linear_to_srgb(np.nan_to_num(v / max(scale, 1e-12)))
        rgb[~np.isfinite(v).all(axis=1)] = UNKNOWN[:3]
        return _rgba(rgb)
    if mode == "alpha":
        v = per_cluster(alpha)
        return grey if v is None else _rgba(colormap(v, 0.0, 0.5))
    if mode == "appearance":
        if not have_rd or positions is None or normals is None or eye is None:
            return grey
        rs = per_cluster(rho_s)
        al = per_cluster(alpha)
        rs = np.zeros((P, 3)) if rs is None else np.nan_to_num(rs)
        al = np.full(P, 0.2) if al is None else np.nan_to_num(al, nan=0.2)
        L = shade_preview(positions, normals, rho_d, rs, al, eye)
        return _rgba(linear_to_srgb(L))
    raise ValueError(f"unknown colour mode {mode!r} (known: {', '.join(COLOUR_MODES)})")


# -- images ----------------------------------------------------------------------------------

_TURBO_LUT = np.concatenate([(colormap(np.linspace(0, 1, 256), 0, 1, "turbo") * 255 + 0.5).astype(np.uint8),
                             np.zeros((1, 3), np.uint8)])  # entry 256: invalid (black)


def depth_image(depth: np.ndarray, lo: float = 0.3, hi: float = 1.5) -> np.ndarray:
    """Colour-mapped depth (H, W) metres -> (H, W, 3) uint8, turbo from ``lo`` to ``hi``; invalid black.

    A 256-entry look-up table (about 3 ms for 640 x 480 instead of ~60 ms interpolating per pixel).
    """
    d = np.asarray(depth, np.float32)
    valid = d > 0  # False for NaN too
    scale = np.float32(255.0 / max(hi - lo, 1e-9))
    q = (np.where(valid, d, np.float32(lo)) - np.float32(lo)) * scale
    np.clip(q, 0, 255, out=q)
    qi = q.astype(np.uint16)
    qi[~valid] = 256
    return _TURBO_LUT[qi]


def ir_levels(ir: np.ndarray) -> tuple[float, float]:
    """Auto levels of an IR image: 1st and 99.5th percentiles of its finite pixels (sampled)."""
    v = np.asarray(ir, np.float32)[::4, ::4]
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [1.0, 99.5])
    return float(lo), float(max(hi, lo + 1e-6))


def rgb_image(frame) -> np.ndarray | None:
    """A frame's colour image as displayable uint8 sRGB (H, W, 3), whatever its encoding."""
    if frame is None or frame.rgb is None:
        return None
    if frame.rgb_encoding == "srgb8" and frame.rgb.dtype == np.uint8:
        return frame.rgb
    return (linear_to_srgb(frame.rgb_linear()) * 255 + 0.5).astype(np.uint8)


def tonemap(img: np.ndarray, percentile: float = 99.0) -> np.ndarray:
    """HDR linear RGB -> uint8 sRGB, exposure set so the ``percentile`` luminance maps to 1."""
    x = np.nan_to_num(np.asarray(img, np.float32), nan=0.0, posinf=0.0)
    lum = x @ REC709_LUMA.astype(np.float32) if x.ndim == 3 else x
    ref = np.percentile(lum[lum > 0], percentile) if np.any(lum > 0) else 1.0
    return (linear_to_srgb(x / max(float(ref), 1e-12)) * 255 + 0.5).astype(np.uint8)


def envmap_latlong(envmap: np.ndarray, coverage: np.ndarray | None, height: int = 96) -> tuple[np.ndarray, float]:
    """The octahedral environment map (2, N, N, 3) as a lat-long uint8 image (H, 2H, 3) with coverage.

    Texels not yet seen by the mirror ball (``coverage`` False) are drawn as a dark checkerboard so
    the map visibly "fills in" (paper §4.3). Returns the image and the covered fraction of the
    sphere (solid-angle weighted, 0..1; NaN when no coverage is given).
    """
    env = np.asarray(envmap, np.float32)
    face, i00, i01, i10, i11, w00, w01, w10, w11, sin_t, checker = _latlong_lut(env.shape[1], height)
    flat = env.reshape(-1, *env.shape[3:])
    ll = (flat[i00] * w00[..., None] + flat[i01] * w01[..., None] + flat[i10] * w10[..., None]
          + flat[i11] * w11[..., None])
    img = tonemap(ll)
    frac = float("nan")
    if coverage is not None:
        c = np.asarray(coverage, np.float32).reshape(-1)
        cov = (c[i00] * w00 + c[i01] * w01 + c[i10] * w10 + c[i11] * w11) > 0.5
        frac = float((sin_t * cov).sum() / np.broadcast_to(sin_t, cov.shape).sum())
        img = img.copy()
        img[~cov] = checker[~cov][:, None]
    return img, frac


@lru_cache(maxsize=8)
def _latlong_lut(n: int, height: int):
    """Bilinear gather indices and weights from a (2, n, n) map to an (height, 2 height) lat-long
    image (the same sampling as :func:`appfusion.octahedral.sphere_to_latlong`), computed once."""
    from .. import octahedral as oc

    d = oc.latlong_directions(height)
    face, uv = oc.sphere_encode(d)
    fx = (uv[..., 0] + 1.0) * 0.5 * n - 0.5
    fy = (uv[..., 1] + 1.0) * 0.5 * n - 0.5
    x0 = np.clip(np.floor(fx).astype(np.int64), 0, n - 1)
    y0 = np.clip(np.floor(fy).astype(np.int64), 0, n - 1)
    x1, y1 = np.clip(x0 + 1, 0, n - 1), np.clip(y0 + 1, 0, n - 1)
    ax, ay = np.clip(fx - x0, 0, 1), np.clip(fy - y0, 0, 1)
    base = face * n * n
    idx = [base + y0 * n + x0, base + y0 * n + x1, base + y1 * n + x0, base + y1 * n + x1]
    w = [(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay]
    theta = (np.arange(height) + 0.5) * np.pi / height
    yy, xx = np.mgrid[0:height, 0:2 * height]
    checker = np.where(((yy // 6 + xx // 6) % 2) == 0, 40, 70).astype(np.uint8)
    return (face, *idx, *(x.astype(np.float32) for x in w), np.sin(theta)[:, None], checker)
