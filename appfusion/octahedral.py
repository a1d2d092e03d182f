"""Octahedral square parameterisation of directions (Praun & Hoppe 2003), as used by the paper.

The paper stores environment maps as two squares (``2 x 128^2``: upper and lower hemisphere, §4.3, §7)
and HBSABs as one square over half vectors on the upper hemisphere (§5.1). One hemisphere maps to one
square by the octahedral map rotated by 45 degrees, so the hemisphere's diamond fills the square:

    p = d / (|x| + |y| + |z|),    (u, v) = (p_x + p_y, p_x - p_y)  in [-1, 1]^2,

with the pole (0, 0, 1) at the square's centre and the equator on its border. The inverse is
``x = (u + v) / 2, y = (u - v) / 2, z = 1 - |x| - |y|``, normalised. The Jacobian is exact:
``d omega = (1/2) du dv / |p|^3`` with ``p = (x, y, 1 - |x| - |y|)``.

Texel (i, j) of an N x N square (row i, column j) has centre ``u = (j + 0.5) * 2 / N - 1``,
``v = (i + 0.5) * 2 / N - 1``. A full-sphere map has shape (2, N, N, ...): index 0 is the upper
hemisphere (z >= 0), index 1 the lower one, stored with z mirrored (z -> -z).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


def hemi_encode(d: np.ndarray) -> np.ndarray:
    """Map directions with z >= 0 to the square; ``d`` (..., 3) need not be unit. Returns (..., 2)."""
    d = np.asarray(d, dtype=np.float64)
    s = np.abs(d[..., 0]) + np.abs(d[..., 1]) + np.abs(d[..., 2])
    s = np.where(s > 0, s, 1.0)
    px, py = d[..., 0] / s, d[..., 1] / s
    return np.stack([px + py, px - py], axis=-1)


def hemi_decode(uv: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hemi_encode`: (..., 2) in [-1, 1]^2 to unit directions (..., 3), z >= 0."""
    uv = np.asarray(uv, dtype=np.float64)
    x = 0.5 * (uv[..., 0] + uv[..., 1])
    y = 0.5 * (uv[..., 0] - uv[..., 1])
    z = np.maximum(1.0 - np.abs(x) - np.abs(y), 0.0)
    p = np.stack([x, y, z], axis=-1)
    return p / np.linalg.norm(p, axis=-1, keepdims=True)


def texel_centers(n: int) -> np.ndarray:
    """(u, v) texel centres of an n x n square, shape (n, n, 2): [..., 0] = u (column), [..., 1] = v (row)."""
    c = (np.arange(n) + 0.5) * (2.0 / n) - 1.0
    u, v = np.meshgrid(c, c)
    return np.stack([u, v], axis=-1)


@lru_cache(maxsize=16)
def _hemi_directions(n: int) -> np.ndarray:
    d = hemi_decode(texel_centers(n))
    d.setflags(write=False)
    return d


def hemi_directions(n: int) -> np.ndarray:
    """Unit direction of each texel centre of an n x n hemisphere square, shape (n, n, 3), read-only."""
    return _hemi_directions(int(n))


@lru_cache(maxsize=16)
def _hemi_solid_angles(n: int, sub: int) -> np.ndarray:
    # Integrate the exact Jacobian (1/2)|p|^-3 du dv over each texel with sub x sub midpoints.
    m = n * sub
    c = (np.arange(m) + 0.5) * (2.0 / m) - 1.0
    u, v = np.meshgrid(c, c)
    x, y = 0.5 * (u + v), 0.5 * (u - v)
    z = 1.0 - np.abs(x) - np.abs(y)
    w = 0.5 * (x * x + y * y + z * z) ** -1.5 * (2.0 / m) ** 2
    w = w.reshape(n, sub, n, sub).sum(axis=(1, 3))
    w.setflags(write=False)
    return w


def hemi_solid_angles(n: int, sub: int = 8) -> np.ndarray:
    """Solid angle (sr) of each texel of an n x n hemisphere square, shape (n, n); sums to 2*pi."""
    return _hemi_solid_angles(int(n), int(sub))


def texel_index(uv: np.ndarray, n: int) -> np.ndarray:
    """Flat index ``row * n + col`` of the texel containing each (u, v); shape (...,), int64."""
    uv = np.asarray(uv)
    col = np.clip(((uv[..., 0] + 1.0) * 0.5 * n).astype(np.int64), 0, n - 1)
    row = np.clip(((uv[..., 1] + 1.0) * 0.5 * n).astype(np.int64), 0, n - 1)
    return row * n + col


# -- full sphere: two squares ------------------------------------------------------------------

def sphere_encode(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map any directions (..., 3) to (face, uv): face 0 for z >= 0, 1 for z < 0 (z mirrored)."""
    d = np.asarray(d, dtype=np.float64)
    face = (d[..., 2] < 0).astype(np.int64)
    dm = d.copy()
    dm[..., 2] = np.abs(dm[..., 2])
    return face, hemi_encode(dm)


def sphere_decode(face: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Inverse of :func:`sphere_encode`."""
    d = hemi_decode(uv)
    d[..., 2] = np.where(np.asarray(face) == 1, -d[..., 2], d[..., 2])
    return d


def sphere_directions(n: int) -> np.ndarray:
    """Unit directions of every texel of a (2, n, n) map, shape (2, n, n, 3)."""
    up = hemi_directions(n)
    down = up.copy()
    down[..., 2] *= -1
    return np.stack([up, down])


def sphere_solid_angles(n: int, sub: int = 8) -> np.ndarray:
    """Solid angle of every texel of a (2, n, n) map, shape (2, n, n); sums to 4*pi."""
    w = hemi_solid_angles(n, sub)
    return np.stack([w, w])


def sphere_texel_index(d: np.ndarray, n: int) -> np.ndarray:
    """Flat index into a (2, n, n) map of the texel containing each direction (..., 3)."""
    face, uv = sphere_encode(d)
    return face * (n * n) + texel_index(uv, n)


def sample_sphere_map(m: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Bilinearly sample a (2, n, n[, C]) map in directions ``d`` (..., 3).

    Interpolation runs within each face; samples near a face's border clamp to it, which is exact
    on the equator where both faces meet.
    """
    m = np.asarray(m)
    n = m.shape[1]
    face, uv = sphere_encode(d)
    fx = (uv[..., 0] + 1.0) * 0.5 * n - 0.5
    fy = (uv[..., 1] + 1.0) * 0.5 * n - 0.5
    x0 = np.clip(np.floor(fx).astype(np.int64), 0, n - 1)
    y0 = np.clip(np.floor(fy).astype(np.int64), 0, n - 1)
    x1 = np.clip(x0 + 1, 0, n - 1)
    y1 = np.clip(y0 + 1, 0, n - 1)
    ax = np.clip(fx - x0, 0.0, 1.0)
    ay = np.clip(fy - y0, 0.0, 1.0)
    if m.ndim == 4:
        ax, ay = ax[..., None], ay[..., None]
    top = m[face, y0, x0] * (1 - ax) + m[face, y0, x1] * ax
    bot = m[face, y1, x0] * (1 - ax) + m[face, y1, x1] * ax
    return top * (1 - ay) + bot * ay


# -- lat-long conversion --------------------------------------------------------------------

def latlong_directions(height: int, width: int | None = None) -> np.ndarray:
    """Directions of the pixel centres of a lat-long map, shape (H, W, 3).

    Row 0 is the zenith (+z), the last row the nadir; column 0 starts at azimuth -pi around +z
    (x = cos(phi) sin(theta), y = sin(phi) sin(theta), z = cos(theta)).
    """
    width = width or 2 * height
    theta = (np.arange(height) + 0.5) * np.pi / height
    phi = (np.arange(width) + 0.5) * 2 * np.pi / width - np.pi
    ph, th = np.meshgrid(phi, theta)
    return np.stack([np.cos(ph) * np.sin(th), np.sin(ph) * np.sin(th), np.cos(th)], axis=-1)


def sample_latlong(img: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Bilinearly sample a lat-long map (H, W[, C]) in directions ``d`` (..., 3), wrapping in azimuth."""
    h, w = img.shape[:2]
    d = np.asarray(d, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    theta = np.arccos(np.clip(d[..., 2], -1, 1))
    phi = np.arctan2(d[..., 1], d[..., 0])
    fy = theta / np.pi * h - 0.5
    fx = (phi + np.pi) / (2 * np.pi) * w - 0.5
    x0 = np.floor(fx).astype(np.int64)
    y0 = np.clip(np.floor(fy).astype(np.int64), 0, h - 1)
    y1 = np.clip(y0 + 1, 0, h - 1)
    ax = fx - x0
    ay = np.clip(fy - y0, 0, 1)
    x0w, x1w = x0 % w, (x0 + 1) % w
    if img.ndim == 3:
        ax, ay = ax[..., None], ay[..., None]
    top = img[y0, x0w] * (1 - ax) + img[y0, x1w] * ax
    bot = img[y1, x0w] * (1 - ax) + img[y1, x1w] * ax
    return top * (1 - ay) + bot * ay


def latlong_to_sphere(img: np.ndarray, n: int, sub: int = 2) -> np.ndarray:
    """Resample a lat-long map to a (2, n, n[, C]) octahedral map (sub x sub supersampling per texel)."""
    m = n * sub
    d = sphere_directions(m)
    vals = sample_latlong(img, d)
    shp = (2, n, sub, n, sub) + vals.shape[3:]
    return vals.reshape(shp).mean(axis=(2, 4))


def sphere_to_latlong(m: np.ndarray, height: int, width: int | None = None) -> np.ndarray:
    """Resample a (2, n, n[, C]) octahedral map to a lat-long map (H, W[, C])."""
    return sample_sphere_map(m, latlong_directions(height, width))
