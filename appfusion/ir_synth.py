"""Synthetic IR data for the IR pass's tests and benchmark (paper §5.1 protocol, §5.2 clustering).

Two generators, with their own Ward formula (not :mod:`appfusion.brdf`) and emitter model:

:func:`protocol_pairs`
    The paper's simulation of §5.1: a surface point 40 cm in front of the Kinect (depth), at a random
    pixel, with a random normal facing the camera; ``w_o`` towards the camera, ``w_i`` towards the
    emitter 7.5 cm beside it, both in the point's local frame; pairs with either direction beyond the
    grazing cut-off are dropped. :func:`protocol_alpha_errors` puts Ward BRDF values of these pairs
    into an HBSAB, fits and returns the relative alpha errors.

:class:`SphereIRScanner`
    Ray-casts a sphere with per-region materials (``rho_d, rho_s, alpha``) into depth and raw IR
    images from given camera poses: Kinect v1 emitter at ``(0.075, 0, 0)`` in the camera frame,
    incident intensity ``x = (t + shift) / (scale d)`` with ``t ~ Gamma(k, theta)`` a fixed random field
    over emitter directions, ``raw = gain (x cos(theta_i) f_r)^gamma + b0 + noise``, rounded, 10 bits.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .frame import Intrinsics


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dot(a, b):
    a, b = np.broadcast_arrays(a, b)
    return np.einsum("...i,...i->...", a, b)


def _ward(alpha, wi, wo, n):
    """Isotropic Ward (1992) lobe, independent implementation: directions (..., 3), normal (..., 3)."""
    ci = _dot(wi, n)
    co = _dot(wo, n)
    h = wi + wo
    ch = np.clip(_dot(h, n) / np.sqrt(_dot(h, h)), 1e-9, 1.0)
    t2 = 1.0 / (ch * ch) - 1.0
    ok = (ci > 0) & (co > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.exp(-t2 / (alpha * alpha)) / (4 * np.pi * alpha * alpha * np.sqrt(np.where(ok, ci * co, 1.0)))
    return np.where(ok, f, 0.0)


def _frame_rows(n):
    """Orthonormal (t, b, n) rows for unit vectors n (..., 3) (Frisvad-style, branch by sign)."""
    s = np.where(n[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (s + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    t = np.stack([1 + s * n[..., 0] ** 2 * a, s * b, -s * n[..., 0]], -1)
    bb = np.stack([b, s + n[..., 1] ** 2 * a, -n[..., 1]], -1)
    return t, bb


def protocol_pairs(n: int, distance: float = 0.4, baseline: float = 0.075, max_angle_deg: float = 80.0,
                   width: int = 640, height: int = 480, focal: float = 575.0, seed: int = 0):
    """Random (w_i, w_o) pairs "as the Kinect sees them" (paper §5.1), in local frames.

    Parameters
    ----------
    n : int
        Pairs to draw (fewer are returned: grazing pairs are dropped).
    distance : float
        Depth of the surface points, metres (paper: 40 cm, the minimum).
    baseline : float
        Emitter offset along the camera's x axis, metres (7.5 cm).
    max_angle_deg : float
        Grazing cut-off for both directions.
    width, height, focal : image geometry of the camera (pixels).
    seed : int

    Returns
    -------
    wi, wo : (m, 3) float64
        Unit directions to the emitter and to the camera in the points' local frames (normal = +z).
    """
    rng = np.random.default_rng(seed)
    u = rng.uniform(0, width, n)
    v = rng.uniform(0, height, n)
    p = np.stack([(u - (width - 1) / 2) / focal, (v - (height - 1) / 2) / focal, np.ones(n)], 1) * distance
    wo = _unit(-p)
    wi = _unit(np.array([baseline, 0.0, 0.0]) - p)
    # normals: cosine-weighted around the view direction, within the cut-off (projected-area density)
    cmin = np.cos(np.radians(max_angle_deg))
    c = np.sqrt(rng.uniform(cmin ** 2, 1.0, n))
    s = np.sqrt(1 - c * c)
    ph = rng.uniform(0, 2 * np.pi, n)
    t, b = _frame_rows(wo)
    nrm = _unit(t * (s * np.cos(ph))[:, None] + b * (s * np.sin(ph))[:, None] + wo * c[:, None])
    tn, bn = _frame_rows(nrm)
    loc = lambda w: np.stack([np.sum(w * tn, 1), np.sum(w * bn, 1), np.sum(w * nrm, 1)], 1)  # noqa: E731
    wil, wol = loc(wi), loc(wo)
    ok = (wil[:, 2] > cmin) & (wol[:, 2] > cmin)
    return wil[ok], wol[ok]


def protocol_alpha_errors(alphas=(0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.75), n_pairs: int = 1_000_000,
                          rho_s: float = 1.0, rho_d: float = 0.0, hbsab_n: int = 32, seed: int = 0,
                          pairs=None) -> dict[float, float]:
    """The paper's §5.1 simulation: relative error of the fitted alpha for each true alpha.

    BRDF values ``rho_d / pi + rho_s Ward(alpha; w_i, w_o)`` (no noise) of :func:`protocol_pairs`
    are added to one HBSAB and fitted with :func:`appfusion.ward_fit.fit_ward`.

    Returns
    -------
    dict
        ``alpha -> (fitted - alpha) / alpha``.
    """
    from .hbsab import CH_W, CH_WV, CH_WV2, HBSAB, half_vector_samples
    from .ward_fit import fit_ward

    wi, wo = protocol_pairs(n_pairs, seed=seed) if pairs is None else pairs
    z = np.array([0.0, 0.0, 1.0])
    # the half-vector geometry is the same for every alpha: compute it once, swap the values
    s = half_vector_samples(wi, wo, np.zeros(len(wi)), hbsab_n)
    wi, wo = wi[s.keep], wo[s.keep]
    out = {}
    for a in alphas:
        f = rho_d / np.pi + rho_s * _ward(a, wi, wo, z)
        s.channels[CH_WV] = s.channels[CH_W] * f
        s.channels[CH_WV2] = s.channels[CH_WV] * f
        hb = HBSAB(1, hbsab_n)
        hb.add(s.texel, s.channels)
        out[float(a)] = fit_ward(hb).alpha / a - 1.0
    return out


# -- a scanned sphere ------------------------------------------------------------------------------

def sphere_points(n: int, center=(0.0, 0.0, 0.0), radius: float = 0.1):
    """``n`` evenly spread points (Fibonacci lattice) and outward normals on a sphere; area each
    ``4 pi r^2 / n``."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = i * np.pi * (3 - np.sqrt(5))
    nrm = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    return np.asarray(center) + radius * nrm, nrm


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: x right, y down, z forward) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(x, dtype=float) for x in (eye, target, up))
    z = _unit(target - eye)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x = _unit(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def orbit_poses(center, distance: float, elevations_deg=(-30, -10, 10, 30, 50, 70), per_ring: int = 20,
                seed: int = 0, jitter_deg: float = 4.0, aim_jitter: float = 0.05,
                distance_jitter: float = 0.1) -> list[np.ndarray]:
    """Camera poses on rings around ``center`` looking near it, like a hand-held scan.

    Azimuth and elevation are jittered by ``jitter_deg``, the distance by ``distance_jitter`` (relative)
    and the aim point by up to ``aim_jitter`` metres, so that the object moves about the image (and a
    highlight is lit by different parts of the emitter's pattern from frame to frame).
    """
    rng = np.random.default_rng(seed)
    c = np.asarray(center, dtype=float)
    out = []
    for k, el in enumerate(elevations_deg):
        for j in range(per_ring):
            az = np.radians(360.0 * (j + 0.5 * (k % 2)) / per_ring + rng.uniform(-jitter_deg, jitter_deg))
            e = np.radians(el + rng.uniform(-jitter_deg, jitter_deg))
            dist = distance * (1 + rng.uniform(-distance_jitter, distance_jitter))
            eye = c + dist * np.array([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)])
            out.append(look_at(eye, c + rng.uniform(-aim_jitter, aim_jitter, 3)))
    return out


@dataclass
class IRMaterial:
    """A material of the synthetic scanner (IR band): Lambertian + Ward."""

    rho_d: float
    rho_s: float
    alpha: float


@dataclass
class SphereIRScanner:
    """Depth + raw IR renderer of a sphere for the IR pass (module docstring).

    Attributes
    ----------
    center, radius : sphere, metres.
    materials : list of IRMaterial
    material_of : callable
        ``(unit normals (m, 3)) -> (m,) material index``.
    intrinsics : Intrinsics
    emitter : camera-frame emitter position, metres.
    gamma, gain, b0, noise, k, theta, shift, scale : the sensor / emitter model.
    field_cell_deg : resolution of the emitter's random field, degrees.
    seed : int
    """

    center: np.ndarray
    radius: float
    materials: list
    material_of: object
    intrinsics: Intrinsics = field(default_factory=lambda: Intrinsics(320, 240, 287.5, 287.5, 159.5, 119.5))
    emitter: tuple = (0.075, 0.0, 0.0)
    gamma: float = 0.9
    gain: float = 2500.0
    b0: float = 60.0
    noise: float = 1.5
    k: float = 1.6
    theta: float = 2.8
    shift: float = 3.4
    scale: float = 57.7
    field_cell_deg: float = 0.12
    seed: int = 0

    def __post_init__(self):
        self.center = np.asarray(self.center, dtype=float)
        self._rng = np.random.default_rng(self.seed)
        self._cell = np.radians(self.field_cell_deg)
        m = int(np.ceil(np.radians(90) / self._cell))
        self._field = np.random.default_rng(self.seed + 1).gamma(self.k, self.theta, size=(m, m))

    def profile(self):
        """The exact :class:`calibration.ir_profile.IRProfile` of this scanner (normalised form)."""
        from calibration.ir_profile import IRProfile

        r = self.shift / self.theta
        th = 1.0 / (self.k + r)
        gain = self.gain * ((self.theta / self.scale) / th) ** self.gamma
        return IRProfile(emitter_model="shifted_gamma", background=self.b0, noise_sigma=self.noise,
                         gamma=self.gamma, gain=gain, k=self.k, theta=th, shift=r * th, scale=1.0,
                         emitter_position_m=list(self.emitter), device="synthetic sphere")

    def _t(self, d_cam):
        ax = np.arctan2(d_cam[:, 0], d_cam[:, 2])
        ay = np.arctan2(d_cam[:, 1], d_cam[:, 2])
        m = self._field.shape[0]
        i = np.clip(((ay + np.radians(45)) / self._cell).astype(np.int64), 0, m - 1)
        j = np.clip(((ax + np.radians(45)) / self._cell).astype(np.int64), 0, m - 1)
        return self._field[i, j]

    def render(self, pose: np.ndarray):
        """Depth (metres, NaN off the sphere or in the emitter's shadow) and raw IR of one view."""
        K = self.intrinsics
        H, W = K.shape
        R, t = pose[:3, :3], pose[:3, 3]
        oc = R.T @ (self.center - t)                       # sphere centre in the camera frame
        ir = self.b0 + self._rng.normal(0, self.noise, (H, W))
        depth = np.full((H, W), np.nan)
        # only the pixels of the sphere's bounding square (the sphere is in front of the camera)
        r0, r1, c0, c1 = 0, H, 0, W
        if oc[2] > self.radius * 1.01:
            half = self.radius / np.sqrt(oc[2] ** 2 - self.radius ** 2) * 1.05 + 0.02
            cu, cv = K.fx * oc[0] / oc[2] + K.cx, K.fy * oc[1] / oc[2] + K.cy
            hu, hv = half * K.fx * (1 + abs(oc[0]) / oc[2]), half * K.fy * (1 + abs(oc[1]) / oc[2])
            c0, c1 = max(int(cu - hu) - 2, 0), min(int(cu + hu) + 3, W)
            r0, r1 = max(int(cv - hv) - 2, 0), min(int(cv + hv) + 3, H)
        if r0 < r1 and c0 < c1:
            uu, vv = np.meshgrid(np.arange(c0, c1, dtype=np.float64), np.arange(r0, r1, dtype=np.float64))
            rays = np.stack([(uu - K.cx) / K.fx, (vv - K.cy) / K.fy, np.ones_like(uu)], -1).reshape(-1, 3)
            b = rays @ oc
            rr = np.einsum("ij,ij->i", rays, rays)
            disc = b * b - rr * (oc @ oc - self.radius ** 2)
            hit = disc > 0
            s = np.where(hit, (b - np.sqrt(np.where(hit, disc, 0.0))) / rr, np.nan)
            P = rays * s[:, None]                               # camera frame; z = s
            nrm = _unit(np.where(hit[:, None], P - oc, 1.0))
            e = np.asarray(self.emitter, dtype=float)
            L = e - P
            d = np.linalg.norm(L, axis=1)
            wi = L / d[:, None]
            wo = _unit(np.where(hit[:, None], -P, 1.0))
            ci = np.sum(wi * nrm, 1)
            lit = hit & (ci > 0) & (np.sum(wo * nrm, 1) > 0)
            idx = np.flatnonzero(lit)
            mat = np.asarray(self.material_of((R @ nrm[idx].T).T))
            rho_d = np.array([m.rho_d for m in self.materials])[mat]
            rho_s = np.array([m.rho_s for m in self.materials])[mat]
            alpha = np.array([m.alpha for m in self.materials])[mat]
            fr = rho_d / np.pi + rho_s * _ward(alpha, wi[idx], wo[idx], nrm[idx])
            x = (self._t(P[idx] - e) + self.shift) / (self.scale * d[idx])
            sub = ir[r0:r1, c0:c1].reshape(-1)
            sub[idx] += self.gain * (x * ci[idx] * fr) ** self.gamma
            ir[r0:r1, c0:c1] = sub.reshape(r1 - r0, c1 - c0)
            dsub = np.where(lit, P[:, 2], np.nan)
            depth[r0:r1, c0:c1] = dsub.reshape(r1 - r0, c1 - c0)
        ir = np.clip(np.round(ir), 0, 1023).astype(np.float32)
        return ir, depth.astype(np.float32)


def two_material_sphere(seed: int = 0, n_points: int = 20000, radius: float = 0.12,
                        intrinsics: Intrinsics | None = None, cap_axis=(0.5, -0.4, 0.77), cap_offset: float = 0.3,
                        materials=None, one_material: bool = False):
    """A sphere with a spherical cap of a second material, its sampled points and the truth.

    Returns
    -------
    scanner : SphereIRScanner
    positions, normals : (n_points, 3)
    truth : (n_points,) int  material index of each point (all 0 with ``one_material``)
    """
    axis = _unit(np.asarray(cap_axis, dtype=float))
    if materials is None:
        materials = [IRMaterial(0.5, 0.08, 0.12), IRMaterial(0.35, 0.25, 0.35)]
    if one_material:
        materials = materials[:1]
        fn = lambda n: np.zeros(len(n), np.int64)  # noqa: E731
    else:
        fn = lambda n: (n @ axis > cap_offset).astype(np.int64)  # noqa: E731
    center = np.array([0.0, 0.0, radius])
    kw = {} if intrinsics is None else {"intrinsics": intrinsics}
    sc = SphereIRScanner(center=center, radius=radius, materials=materials, material_of=fn, seed=seed, **kw)
    P, N = sphere_points(n_points, center, radius)
    return sc, P, N, fn(N)


def scan(ir_pass, scanner: SphereIRScanner, poses) -> int:
    """Render every pose and add it to ``ir_pass``; returns the samples added."""
    n = 0
    for T in poses:
        ir, depth = scanner.render(T)
        n += ir_pass.add_frame(ir, depth, scanner.intrinsics, T, scanner.emitter)
    return n

