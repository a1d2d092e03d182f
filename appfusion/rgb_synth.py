"""Synthetic ground truth for the RGB pass (paper §5.3): environment maps, brute-force Eq. 4, scenes.

Everything here is computed by direct quadrature over the environment map's texels and an
independent implementation of the Ward lobe, never by the wavelet code of
:mod:`appfusion.double_product`, so tests and the ``rgb`` bench stage can measure that code against it.

Eq. 4 of the paper, with ``f_r = rho_d / pi + rho_s f(alpha; w_i, w_o)`` (Eq. 1), is

    L(w_o) = rho_d D(n) + rho_s S(n, alpha, w_o),
    D(n)   = (1/pi) sum_t L_t max(n . w_t, 0) dw_t,
    S      = sum_t L_t f(alpha; w_t, w_o) max(n . w_t, 0) dw_t,

where ``t`` runs over the texels of a (2, N, N, 3) octahedral environment map (``w_t`` the texel
centre direction, ``dw_t`` its solid angle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import octahedral as octa
from .frame import Intrinsics, invert_pose, make_pose, transform_points


# -- environment maps ---------------------------------------------------------------------------

def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def synthetic_envmap(n: int = 128, seed: int = 0, n_lights: int = 4, ambient: float = 0.02,
                     light_radius: tuple[float, float] = (0.10, 0.22), softness: float = 0.35,
                     light_power: tuple[float, float] = (4.0, 9.0)) -> np.ndarray:
    """An office-like HDR environment in the marker frame, shape (2, n, n, 3), float32 radiance.

    Soft-edged disc area lights above the support plane (elevation 25-75 degrees), a dim sky
    gradient, and below the horizon the support plane covered with dark paper (paper §6) lit by
    the lights. Radiance is linear and unit-free (a white Lambertian surface facing straight up
    reflects about 1).

    Parameters
    ----------
    n : int
        Side of each octahedral square (paper: 128).
    seed : int
        Random seed of light placement, size and colour.
    n_lights : int
        Number of area lights.
    ambient : float
        Sky radiance at the zenith.
    light_radius : (float, float)
        Range of the lights' angular radii, rad.
    softness : float
        Width of each light's smooth edge as a fraction of its radius.
    light_power : (float, float)
        Range of the lights' peak radiance.
    """
    rng = np.random.default_rng(seed)
    d = octa.sphere_directions(n)  # (2, n, n, 3)
    z = d[..., 2]
    sky = ambient * (0.6 + 0.4 * np.clip(z, 0, 1))[..., None] * np.array([0.9, 0.95, 1.1])
    env = np.where((z >= 0)[..., None], sky, 0.0)
    for _ in range(n_lights):
        el = rng.uniform(np.radians(25), np.radians(75))
        az = rng.uniform(-np.pi, np.pi)
        c = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        r = rng.uniform(*light_radius)
        power = rng.uniform(*light_power)
        tint = np.array([1.0, rng.uniform(0.9, 1.0), rng.uniform(0.75, 0.95)])
        ang = np.arccos(np.clip(d @ c, -1, 1))
        # smoothstep edge from r (1) to r * (1 + softness) (0)
        t = np.clip((r * (1 + softness) - ang) / (r * softness), 0.0, 1.0)
        prof = t * t * (3 - 2 * t)
        env = env + power * prof[..., None] * tint
    # support plane: dark paper, albedo ~0.04, lit by the upper hemisphere (grey, slightly varying)
    up = env[0]
    w = octa.hemi_solid_angles(n)
    irr = (up * (w * octa.hemi_directions(n)[..., 2])[..., None]).sum(axis=(0, 1))  # (3,)
    plane = 0.04 / np.pi * irr
    xy = d[1, ..., :2]
    var = 1.0 + 0.3 * np.cos(3 * xy[..., 0]) * np.cos(2 * xy[..., 1])
    env[1] = plane * var[..., None]
    return env.astype(np.float32)


# -- brute-force quadrature of Eq. 4 ------------------------------------------------------------

def ward_reference(alpha, cos_h, cos_i, cos_o) -> np.ndarray:
    """Isotropic Ward lobe (Ward 1992), written independently of :mod:`appfusion.brdf`; 1/sr."""
    alpha = np.asarray(alpha, dtype=np.float64)
    ok = (cos_i > 0) & (cos_o > 0) & (cos_h > 0)
    ch2 = np.where(ok, cos_h, 1.0) ** 2
    val = np.exp(-(1.0 / ch2 - 1.0) / alpha**2) / (4 * np.pi * alpha**2 * np.sqrt(np.where(ok, cos_i * cos_o, 1.0)))
    return np.where(ok, val, 0.0)


def _env_texels(env: np.ndarray):
    env = np.asarray(env, dtype=np.float64)
    n = env.shape[1]
    dirs = octa.sphere_directions(n).reshape(-1, 3)
    lw = env.reshape(-1, 3) * octa.sphere_solid_angles(n).reshape(-1, 1)
    return dirs, lw


def brute_force_D(env: np.ndarray, normals: np.ndarray, chunk: int = 256) -> np.ndarray:
    """D(n) = (1/pi) sum_t L_t max(n.w_t, 0) dw_t over all env texels (paper §5.3); (P, 3) float64."""
    dirs, lw = _env_texels(env)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    out = np.empty((len(normals), 3))
    for s in range(0, len(normals), chunk):
        c = np.maximum(normals[s:s + chunk] @ dirs.T, 0.0)
        out[s:s + chunk] = c @ lw / np.pi
    return out


def brute_force_S(env: np.ndarray, normals: np.ndarray, alpha, w_o: np.ndarray, chunk: int = 64) -> np.ndarray:
    """S = sum_t L_t f(alpha; w_t, w_o) max(n.w_t, 0) dw_t over all env texels (Eq. 4); (P, 3).

    Parameters
    ----------
    env : (2, N, N, 3) ndarray
        Environment radiance in the world frame.
    normals, w_o : (P, 3) ndarray
        Unit normals and unit view directions (towards the camera), world frame.
    alpha : float or (P,) ndarray
        Ward roughness per sample.

    Notes
    -----
    With ``h = w_t + w_o``: ``tan^2(theta_h) = |h|^2 / (n.h)^2 - 1``, ``|h|^2 = 2 + 2 w_t.w_o`` and
    ``n.h = cos_i + cos_o``; the lobe is evaluated in float64 on every texel (no culling).
    """
    dirs, lw = _env_texels(env)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    w_o = np.asarray(w_o, dtype=np.float64).reshape(-1, 3)
    alpha = np.broadcast_to(np.asarray(alpha, dtype=np.float64), (len(normals),))
    out = np.zeros((len(normals), 3))
    for s in range(0, len(normals), chunk):
        n, wo, a = normals[s:s + chunk], w_o[s:s + chunk], alpha[s:s + chunk, None]
        co = np.sum(n * wo, axis=1)[:, None]
        ci = np.maximum(n @ dirs.T, 0.0)
        e = wo @ dirs.T
        e *= 2.0
        e += 2.0                                         # |h|^2
        nh2 = np.square(ci + co)                         # (n.h)^2
        np.divide(e, np.maximum(nh2, 1e-300), out=e)
        e -= 1.0                                         # tan^2(theta_h)
        e *= -1.0 / a**2
        np.exp(e, out=e)
        e *= np.sqrt(ci)                                 # f * cos_i = exp(.) sqrt(cos_i) / (4 pi a^2 sqrt(cos_o))
        ok = co[:, 0] > 0
        scale = np.where(ok, 1.0 / (4 * np.pi * a[:, 0] ** 2 * np.sqrt(np.where(ok, co[:, 0], 1.0))), 0.0)
        out[s:s + chunk] = (e @ lw) * scale[:, None]
    return out
