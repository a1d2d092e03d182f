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
from .frame import Intrinsics, invert_pose, make_pose


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


def brute_force_S(env: np.ndarray, normals: np.ndarray, alpha, w_o: np.ndarray, chunk: int = 64,
                  lobe: str = "ward") -> np.ndarray:
    """S = sum_t L_t f(alpha; w_t, w_o) max(n.w_t, 0) dw_t over all env texels (Eq. 4); (P, 3).

    Parameters
    ----------
    env : (2, N, N, 3) ndarray
        Environment radiance in the world frame.
    normals, w_o : (P, 3) ndarray
        Unit normals and unit view directions (towards the camera), world frame.
    alpha : float or (P,) ndarray
        Roughness per sample.
    lobe : {"ward", "ggx"}
        The specular lobe (:data:`appfusion.brdf.LOBES`); GGX is evaluated with
        :func:`appfusion.brdf.ggx_half` on every texel.

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
    if lobe == "ggx":
        from .brdf import ggx_half

        for s in range(0, len(normals), chunk):
            n, wo, a = normals[s:s + chunk], w_o[s:s + chunk], alpha[s:s + chunk, None]
            co = np.sum(n * wo, axis=1)[:, None]
            ci = n @ dirs.T
            h2 = 2.0 + 2.0 * (wo @ dirs.T)
            ch = np.where(h2 > 1e-12, (ci + co) / np.sqrt(np.maximum(h2, 1e-12)), 0.0)
            out[s:s + chunk] = (ggx_half(a, ch, ci, np.broadcast_to(co, ci.shape)) * np.maximum(ci, 0.0)) @ lw
        return out
    if lobe != "ward":
        raise ValueError(f"brute_force_S: unknown lobe {lobe!r} (ward or ggx)")
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


# -- a two-material sphere seen by a depth + RGB camera ---------------------------------------------

def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: x right, y down, z forward) at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    z = _unit(np.asarray(target, dtype=np.float64) - eye)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x = _unit(x)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)


def orbit_poses(center, distance: float, n_views: int, elevations_deg=(15.0, 35.0, 55.0, 75.0),
                seed: int = 0) -> list[np.ndarray]:
    """Depth-camera poses on rings around ``center`` (azimuths spread, small random jitter)."""
    rng = np.random.default_rng(seed)
    c = np.asarray(center, dtype=np.float64)
    poses = []
    for i in range(n_views):
        el = np.radians(elevations_deg[i % len(elevations_deg)] + rng.uniform(-4, 4))
        az = 2 * np.pi * i / n_views * 2.39996 + rng.uniform(-0.1, 0.1)     # golden-angle spread
        eye = c + distance * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        poses.append(look_at(eye, c))
    return poses


@dataclass
class SphereScene:
    """A sphere on the support plane (z = 0) with two Ward materials and per-point diffuse albedo.

    Attributes
    ----------
    env : (2, N, N, 3) float32
        Environment radiance (world = marker frame).
    center : (3,) float, radius : float
        Sphere (metres); it touches the plane.
    positions, normals : (P, 3) float64
        Sampled points and their normals.
    labels : (P,) int64
        Material of each point.
    rho_d : (P, 3) float64
        True diffuse albedo per point.
    rho_s : (C, 3) float64, alphas : (C,) float64
        True specular albedo and Ward roughness per material.
    depth_intrinsics, rgb_intrinsics : Intrinsics
    depth_to_rgb : (4, 4) float64
        The RGB camera sits 2.5 cm beside the depth camera (Kinect v1 layout).
    plane_radiance : float
        Radiance of the dark paper on the support plane.
    """

    env: np.ndarray
    center: np.ndarray
    radius: float
    positions: np.ndarray
    normals: np.ndarray
    labels: np.ndarray
    rho_d: np.ndarray
    rho_s: np.ndarray
    alphas: np.ndarray
    depth_intrinsics: Intrinsics
    rgb_intrinsics: Intrinsics
    depth_to_rgb: np.ndarray
    plane_radiance: float = 0.02

    def radiance(self, point_idx: np.ndarray, camera_center: np.ndarray) -> np.ndarray:
        """Noise-free Eq. 4 radiance (k, 3) of the given points towards a camera centre (brute force)."""
        p = self.positions[point_idx]
        n = self.normals[point_idx]
        wo = _unit(np.asarray(camera_center)[None, :] - p)
        lab = self.labels[point_idx]
        if getattr(self, "_D", None) is None:
            self._D = brute_force_D(self.env, self.normals)              # view-independent: once
        D = self._D[point_idx]
        S = brute_force_S(self.env, n, self.alphas[lab], wo)
        return self.rho_d[point_idx] * D + self.rho_s[lab] * S

    def _raycast(self, pose: np.ndarray, K: Intrinsics):
        """Per pixel: hit distance along the ray (camera z), hit kind (0 none, 1 sphere, 2 plane), world hit."""
        rays = K.rays().reshape(-1, 3)                                          # z = 1, float32
        R, o = pose[:3, :3], pose[:3, 3]
        d = rays @ R.T.astype(np.float32)
        oc = (o - self.center).astype(np.float32)
        b = d @ oc
        a = np.einsum("ij,ij->i", d, d)
        disc = b * b - a * np.float32(oc @ oc - self.radius ** 2)
        with np.errstate(invalid="ignore", divide="ignore"):
            ts = (-b - np.sqrt(disc)) / a
            tp = np.float32(-o[2]) / d[:, 2]
        hit_s = (disc > 0) & (ts > 0)
        hit_p = ~hit_s & (tp > 0) & np.isfinite(tp)
        t = np.where(hit_s, ts, np.where(hit_p, tp, np.nan)).astype(np.float64)
        kind = np.where(hit_s, 1, np.where(hit_p, 2, 0))
        X = o + t[:, None] * d
        return t, kind, X

    def render(self, pose: np.ndarray, rng: np.random.Generator | None = None, noise_rel: float = 0.01,
               noise_abs: float = 0.002, exposure: float = 1.0) -> tuple[np.ndarray, np.ndarray, dict]:
        """Depth (metres, NaN off-scene) and linear RGB images of the scene from a depth-camera pose.

        The RGB camera (pose ``pose @ inv(depth_to_rgb)``) sees each sphere pixel with the radiance of
        the nearest sampled point (Eq. 4 by brute force, towards the RGB camera centre), the plane with
        ``plane_radiance``; Gaussian noise ``noise_rel * L + noise_abs`` is added and the image clipped
        to [0, 1] (a camera saturates).

        Returns
        -------
        rgb : (H, W, 3) float32, depth : (h, w) float32, info : dict
            ``info["radiance"]`` maps visible point index -> noise-free radiance (k, 3).
        """
        from scipy.spatial import cKDTree

        Kd, Kc = self.depth_intrinsics, self.rgb_intrinsics
        t, kind, _ = self._raycast(pose, Kd)
        depth = np.where(kind > 0, t, np.nan).reshape(Kd.height, Kd.width).astype(np.float32)
        Trgb = pose @ invert_pose(self.depth_to_rgb)
        C = Trgb[:3, 3]
        t2, kind2, X2 = self._raycast(Trgb, Kc)
        tree = getattr(self, "_tree", None)
        if tree is None:
            tree = self._tree = cKDTree(self.positions)
        sph = np.flatnonzero(kind2 == 1)
        _, nearest = tree.query(X2[sph])
        vis = np.unique(nearest)
        Lp = self.radiance(vis, C) * exposure
        lut = np.zeros((len(self.positions), 3))
        lut[vis] = Lp
        img = np.zeros((Kc.height * Kc.width, 3))
        img[sph] = lut[nearest]
        img[kind2 == 2] = self.plane_radiance * exposure
        if rng is not None:
            img = img + rng.normal(size=img.shape) * (noise_rel * img + noise_abs)
        rgb = np.clip(img, 0.0, 1.0).reshape(Kc.height, Kc.width, 3).astype(np.float32)
        return rgb, depth, {"points": vis, "radiance": Lp, "camera_center": C}


def fibonacci_sphere(n: int) -> np.ndarray:
    """n nearly uniform unit vectors (Fibonacci lattice), (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = i * np.pi * (3 - np.sqrt(5))
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def two_material_sphere(n_points: int = 2000, env: np.ndarray | None = None, env_n: int = 32, seed: int = 0,
                        radius: float = 0.08, image_scale: float = 0.25,
                        materials: tuple = ((0.06, (0.35, 0.3, 0.25)), (0.2, (0.5, 0.5, 0.5)))) -> SphereScene:
    """A sphere on the plane: a cap of material 1 (``n . c > 0.3`` for a random direction c), the rest
    material 0; per-point diffuse albedo a smooth colour pattern in [0.1, 0.8].

    Parameters
    ----------
    n_points : int
        Sampled points (Fibonacci lattice with a little jitter).
    env : (2, N, N, 3) array, optional
        Environment; :func:`synthetic_envmap` (``env_n``, scaled so the brightest highlights stay
        mostly below saturation) when omitted.
    image_scale : float
        Image size as a fraction of 640 x 480 (Kinect v1 intrinsics scaled).
    materials : tuple of (alpha, rho_s RGB)
        Ward roughness and specular albedo of material 0 and 1.
    """
    rng = np.random.default_rng(seed)
    if env is None:
        env = synthetic_envmap(env_n, seed=seed + 11) * 0.7
    n = fibonacci_sphere(n_points) + rng.normal(scale=0.3 / np.sqrt(n_points), size=(n_points, 3))
    n = _unit(n)
    center = np.array([0.0, 0.0, radius])
    P = center + radius * n
    c = _unit(rng.normal(size=3) * np.array([1, 1, 0.3]) + np.array([0, 0, 0.5]))
    labels = (n @ c > 0.3).astype(np.int64)
    # per-point diffuse albedo: smooth coloured pattern
    base = np.array([[0.55, 0.35, 0.2], [0.2, 0.35, 0.6]])[labels]
    pat = 0.5 + 0.5 * np.sin(5 * n[:, 0] + 3 * n[:, 1]) * np.cos(4 * n[:, 2])
    rho_d = np.clip(base * (0.6 + 0.8 * pat[:, None]), 0.1, 0.8)
    alphas = np.array([m[0] for m in materials], dtype=np.float64)
    rho_s = np.array([m[1] for m in materials], dtype=np.float64)
    K0 = Intrinsics(640, 480, 575.8, 575.8, 319.5, 239.5)
    w, h = int(round(640 * image_scale)), int(round(480 * image_scale))
    Kd = K0.scaled(w, h)
    Kc = Intrinsics(w, h, 525.0 * w / 640, 525.0 * h / 480, (w - 1) / 2, (h - 1) / 2)
    E = make_pose(np.eye(3), [-0.025, 0.0, 0.0])
    return SphereScene(np.asarray(env, dtype=np.float32), center, radius, P, n, labels, rho_d, rho_s, alphas,
                       Kd, Kc, E)
