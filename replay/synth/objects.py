"""The scanned objects: triangle meshes with exact normals, per-vertex albedo and material ids.

Every object stands on the support plane (z = 0) centred on the z axis of the marker frame and is
10-20 cm tall. Meshes are built with numpy (20-60k triangles at ``detail="full"``, ~5k at
``detail="test"``); vertex normals are the analytic normals of the surface the mesh samples (or of an
implicit function differentiated with central differences at 1e-6 m, accurate to ~1e-9, for the blob).

Per vertex: ``rho_d`` (RGB diffuse albedo, textured where said), ``ir_rho_d`` (one channel),
``material_id`` (index into ``materials``). Per material: ``rho_s`` (RGB), the lobe roughness, the lobe
name and ``ir_rho_s``. Faces never straddle two materials: where a material changes along a ring of
vertices, that ring is duplicated (same positions and normals), so per-vertex ids are exact.

Objects (``OBJECTS``):

``sphere``       r = 7 cm, one glossy Ward material, uniform albedo.
``vase``         lathe surface of a C2 cubic-spline profile with a concave neck, closed by a flat lid;
                 glazed ceramic with a wavy banded albedo texture, one Ward material.
``pepper``       a deformed sphere with four lobes and a dimple at the stem; red with a green stem area,
                 one glossy Ward material.
``two-material`` a capsule-shaped bottle: glossy blue paint on the top part (z >= 7.5 cm), a matte
                 textured label on the rest; two Ward materials.
``ggx-sphere``   the sphere with a GGX lobe (so a Ward-based estimator meets a model it does not have).
``ggx-two-material`` the two-material capsule with its paint a GGX lobe (alpha 0.08) over the Ward label:
                 two lobes of different shapes on one object (splits, reassignment and merges across lobes).
``matte``        the two-material capsule printed all over on matte paper: one material with no
                 specular lobe in colour or IR (rho_s = 0), so a scan should export it diffuse; a lobe
                 found there is a false one (texture edges, the footprint of a pixel, noise).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from appfusion.errors import AppFusionError

from .materials import Material, MaterialSet

DETAILS = ("test", "full")


@dataclass
class ObjectModel:
    """A scanned object: mesh, normals, reflectance per vertex and per material.

    Attributes
    ----------
    name : str
    vertices : (V, 3) float64, metres, marker frame
    faces : (F, 3) int32, counter-clockwise seen from outside
    normals : (V, 3) float64 unit outward normals
    rho_d : (V, 3) float64 diffuse albedo
    ir_rho_d : (V,) float64 IR diffuse albedo
    material_id : (V,) int32
    materials : MaterialSet
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    rho_d: np.ndarray
    ir_rho_d: np.ndarray
    material_id: np.ndarray
    materials: MaterialSet
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        V = len(self.vertices)
        for nm, a, shp in (("normals", self.normals, (V, 3)), ("rho_d", self.rho_d, (V, 3)),
                           ("ir_rho_d", self.ir_rho_d, (V,)), ("material_id", self.material_id, (V,))):
            if np.shape(a) != shp:
                raise AppFusionError(f"object {self.name}: {nm} has shape {np.shape(a)}, expected {shp}")
        self.faces = np.asarray(self.faces, dtype=np.int32)
        self.material_id = np.asarray(self.material_id, dtype=np.int32)
        if self.faces.min() < 0 or self.faces.max() >= V:
            raise AppFusionError(f"object {self.name}: face indices out of range")
        if self.material_id.min() < 0 or self.material_id.max() >= len(self.materials):
            raise AppFusionError(f"object {self.name}: material ids out of range")
        fm = self.material_id[self.faces]
        if np.any(fm != fm[:, :1]):
            raise AppFusionError(f"object {self.name}: a face straddles two materials")
        self.face_material = fm[:, 0].copy()

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    @property
    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        lo, hi = self.bounds
        c = 0.5 * (lo + hi)
        return c, float(np.linalg.norm(self.vertices - c, axis=1).max())

    def surface_area(self) -> float:
        v = self.vertices[self.faces]
        return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())

    def truth_arrays(self) -> dict[str, np.ndarray]:
        """The arrays of ``truth/object.npz``."""
        return {"vertices": self.vertices.astype(np.float64), "faces": self.faces.astype(np.int32),
                "vertex_normals": self.normals.astype(np.float64), "rho_d": self.rho_d.astype(np.float32),
                "material_id": self.material_id.astype(np.int32), "ir_rho_d": self.ir_rho_d.astype(np.float32),
                "face_material": self.face_material.astype(np.int32)}


# -- mesh helpers ---------------------------------------------------------------------------------

def icosphere(level: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: 20 * 4**level triangles; vertices (V, 3), faces (F, 3) (outward, CCW)."""
    t = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(level):
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        key = np.sort(e, axis=1)
        uniq, inv = np.unique(key, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        base = len(v)
        v = np.concatenate([v, mid])
        nf = len(f)
        ab, bc, ca = inv[:nf] + base, inv[nf:2 * nf] + base, inv[2 * nf:] + base
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        f = np.concatenate([np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1), np.stack([c, ca, bc], 1),
                            np.stack([ab, bc, ca], 1)])
    return v, f.astype(np.int32)


def _ring_faces(n_rings: int, n_phi: int, offset: int = 0) -> np.ndarray:
    """Quads between consecutive rings of a (n_rings, n_phi) vertex grid wrapping in phi, as triangles.

    Ring k+1 lies above ring k (larger z or further along the profile); faces point outward for a
    surface whose rings go counter-clockwise around +z."""
    k, j = np.meshgrid(np.arange(n_rings - 1), np.arange(n_phi), indexing="ij")
    j1 = (j + 1) % n_phi
    a = offset + k * n_phi + j
    b = offset + k * n_phi + j1
    c = offset + (k + 1) * n_phi + j1
    d = offset + (k + 1) * n_phi + j
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])


def _disc(center_z: float, radius: float, n_phi: int, n_r: int, up: bool):
    """A flat disc (rings + centre vertex) at height ``center_z``; normal +z if ``up`` else -z."""
    r = np.linspace(radius, 0, n_r + 1)[:-1]
    ph = np.arange(n_phi) * 2 * np.pi / n_phi
    R, P = np.meshgrid(r, ph, indexing="ij")
    v = np.stack([R * np.cos(P), R * np.sin(P), np.full_like(R, center_z)], -1).reshape(-1, 3)
    v = np.concatenate([v, [[0.0, 0.0, center_z]]])
    f = _ring_faces(n_r, n_phi)
    c = len(v) - 1
    j = np.arange(n_phi)
    last = (n_r - 1) * n_phi
    fan = np.stack([last + j, last + (j + 1) % n_phi, np.full(n_phi, c)], 1)
    f = np.concatenate([f, fan])
    # rings run from the rim inward: for an upward disc that is CCW order reversed -> flip for up
    if not up:
        f = f[:, ::-1]
    nrm = np.tile([0.0, 0.0, 1.0 if up else -1.0], (len(v), 1))
    return v, f, nrm


def _merge(parts):
    vs, fs, ns, off = [], [], [], 0
    for v, f, n in parts:
        vs.append(v)
        fs.append(f + off)
        ns.append(n)
        off += len(v)
    return np.concatenate(vs), np.concatenate(fs).astype(np.int32), np.concatenate(ns)


def _orient_outward(v, f, n):
    """Flip faces whose geometric normal disagrees with the mean of their (outward) vertex normals."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    gn = np.cross(b - a, c - a)
    out = np.einsum("ij,ij->i", gn, n[f].sum(axis=1)) >= 0
    f = f.copy()
    f[~out] = f[~out][:, ::-1]
    return f


def _value_noise(p: np.ndarray, seed: int, scale: float, octaves: int = 3) -> np.ndarray:
    """Smooth band-limited noise in [-1, 1] of 3-D points: a sum of random sinusoids (deterministic)."""
    rng = np.random.default_rng(seed)
    out = np.zeros(len(p))
    amp, tot = 1.0, 0.0
    for o in range(octaves):
        for _ in range(4):
            k = rng.normal(size=3)
            k *= 2 * np.pi / (scale / 2 ** o) / np.linalg.norm(k)
            out += amp * np.sin(p @ k + rng.uniform(0, 2 * np.pi))
            tot += amp
        amp *= 0.5
    return out / tot * 1.6


# -- the objects ----------------------------------------------------------------------------------

def _sphere(detail: str, seed: int, lobe: str) -> ObjectModel:
    level = 5 if detail == "full" else 4
    u, f = icosphere(level)
    r = 0.07
    c = np.array([0.0, 0.0, r])
    v = c + r * u
    V = len(v)
    if lobe == "ward":
        mats = MaterialSet([Material("glossy-orange", (0.25, 0.25, 0.25), 0.12, "ward", ir_rho_s=0.10)])
        rho = np.tile([0.62, 0.20, 0.08], (V, 1))
        ir = np.full(V, 0.55)
        name = "sphere"
    else:
        mats = MaterialSet([Material("ggx-green", (0.22, 0.22, 0.22), 0.15, "ggx", ir_rho_s=0.09)])
        stripe = 0.5 + 0.5 * np.tanh(np.sin(5 * np.arctan2(u[:, 1], u[:, 0]) + 4 * u[:, 2]) / 0.15)
        rho = np.array([0.10, 0.42, 0.16]) * (1 - stripe[:, None]) + np.array([0.45, 0.55, 0.20]) * stripe[:, None]
        ir = 0.45 + 0.15 * stripe
        name = "ggx-sphere"
    return ObjectModel(name, v, f, u.copy(), rho, ir, np.zeros(V, np.int32), mats,
                       {"shape": "sphere", "centre_m": c.tolist(), "radius_m": r})


def _vase(detail: str, seed: int) -> ObjectModel:
    from scipy.interpolate import CubicSpline

    H = 0.18
    zs = np.array([0.0, 0.02, 0.06, 0.10, 0.135, 0.155, 0.172, H])
    rs = np.array([0.045, 0.055, 0.068, 0.056, 0.031, 0.026, 0.031, 0.034])
    prof = CubicSpline(zs, rs, bc_type="natural")
    dprof = prof.derivative()
    n_phi, n_z = (192, 104) if detail == "full" else (64, 40)
    z = np.linspace(0.0, H, n_z)
    ph = np.arange(n_phi) * 2 * np.pi / n_phi
    Z, P = np.meshgrid(z, ph, indexing="ij")
    R = prof(Z)
    side_v = np.stack([R * np.cos(P), R * np.sin(P), Z], -1).reshape(-1, 3)
    dr = dprof(Z)
    side_n = np.stack([np.cos(P), np.sin(P), -dr], -1).reshape(-1, 3)
    side_n /= np.linalg.norm(side_n, axis=1, keepdims=True)
    side_f = _ring_faces(n_z, n_phi)
    n_r = max(4, n_z // 8)
    lid = _disc(H, float(prof(H)), n_phi, n_r, up=True)
    bottom = _disc(0.0, float(prof(0.0)), n_phi, n_r, up=False)
    v, f, n = _merge([(side_v, side_f, side_n), lid, bottom])
    f = _orient_outward(v, f, n)
    # texture: blue glaze, two wavy cream bands, soft mottling
    phi = np.arctan2(v[:, 1], v[:, 0])
    zz = v[:, 2]
    glaze = np.array([0.10, 0.22, 0.55])
    cream = np.array([0.80, 0.76, 0.66])
    band = np.zeros(len(v))
    for zc, half, amp, k in ((0.050, 0.006, 0.006, 6), (0.118, 0.004, 0.004, 9)):
        d = np.abs(zz - (zc + amp * np.sin(k * phi)))
        band = np.maximum(band, 1 - np.clip((d - half) / 0.0008 + 0.5, 0, 1))
    band[np.abs(n[:, 2]) > 0.999] = 0.0  # lid and bottom are plain glaze
    mott = 1 + 0.06 * _value_noise(v, seed + 11, 0.05)
    rho = (glaze * (1 - band[:, None]) + cream * band[:, None]) * mott[:, None]
    ir = 0.50 + 0.22 * band
    mats = MaterialSet([Material("glazed-ceramic", (0.12, 0.12, 0.12), 0.08, "ward", ir_rho_s=0.10)])
    return ObjectModel("vase", v, f, n, np.clip(rho, 0, 0.95), ir, np.zeros(len(v), np.int32), mats,
                       {"shape": "lathe", "height_m": H, "profile_z_m": zs.tolist(), "profile_r_m": rs.tolist(),
                        "profile": "natural cubic spline r(z)"})


def _pepper(detail: str, seed: int) -> ObjectModel:
    level = 5 if detail == "full" else 4
    u, f = icosphere(level)
    R = 0.055
    scale = np.array([1.0, 1.0, 1.12])

    def radius(q):
        """Radius of the blob along unit directions q (..., 3)."""
        th = np.arccos(np.clip(q[..., 2], -1, 1))
        ph = np.arctan2(q[..., 1], q[..., 0])
        lobes = 1 + 0.09 * np.cos(4 * ph + 0.3) * np.sin(th) ** 2
        dimple = 1 - 0.22 * np.exp(-(th / 0.32) ** 2)
        return R * lobes * dimple

    def F(q):
        nq = np.linalg.norm(q, axis=-1)
        return nq - radius(q / nq[..., None])

    q = u * radius(u)[:, None]
    h = 1e-6
    grad = np.stack([(F(q + h * e) - F(q - h * e)) / (2 * h) for e in np.eye(3)], -1)
    n = grad / scale
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = q * scale
    v[:, 2] -= v[:, 2].min()
    th = np.arccos(np.clip(u[:, 2], -1, 1))
    green = 1 - np.clip((th - 0.20) / 0.05 + 0.5, 0, 1)
    red = np.array([0.58, 0.055, 0.035]) * (1 + 0.08 * _value_noise(v, seed + 5, 0.04))[:, None]
    groove = 0.5 + 0.5 * np.cos(4 * np.arctan2(u[:, 1], u[:, 0]) + 0.3)
    red = red * (0.85 + 0.15 * groove)[:, None]
    rho = red * (1 - green[:, None]) + np.array([0.12, 0.30, 0.05]) * green[:, None]
    ir = 0.48 + 0.1 * green
    mats = MaterialSet([Material("glossy-skin", (0.30, 0.30, 0.30), 0.07, "ward", ir_rho_s=0.12)])
    return ObjectModel("pepper", v, f, n, rho, ir, np.zeros(len(v), np.int32), mats,
                       {"shape": "blob", "radius_m": R, "z_scale": 1.12, "normals": "gradient of the implicit "
                        "|q| - r(q/|q|) by central differences (h = 1e-6 m)"})


def _two_material(detail: str, seed: int, paint_lobe: str = "ward") -> ObjectModel:
    r, zc, zb = 0.04, 0.11, 0.075  # radius, cap centre height, material boundary height
    n_phi = 160 if detail == "full" else 56
    n_low, n_up, n_cap = (60, 28, 48) if detail == "full" else (20, 10, 16)
    ph = np.arange(n_phi) * 2 * np.pi / n_phi

    def cyl(z0, z1, n):
        z = np.linspace(z0, z1, n)
        Z, P = np.meshgrid(z, ph, indexing="ij")
        v = np.stack([r * np.cos(P), r * np.sin(P), Z], -1).reshape(-1, 3)
        nn = np.stack([np.cos(P), np.sin(P), np.zeros_like(P)], -1).reshape(-1, 3)
        return v, _ring_faces(n, n_phi), nn

    low = cyl(0.0, zb, n_low)            # matte label part, material 0
    up = cyl(zb, zc, n_up)               # glossy paint, material 1 (its first ring duplicates the boundary)
    # hemispherical cap (glossy), rings from the equator up, plus the pole
    el = np.linspace(0, np.pi / 2, n_cap + 1)[1:-1]
    E, P = np.meshgrid(el, ph, indexing="ij")
    cn = np.stack([np.cos(E) * np.cos(P), np.cos(E) * np.sin(P), np.sin(E)], -1).reshape(-1, 3)
    cv = np.array([0, 0, zc]) + r * cn
    cv = np.concatenate([cv, [[0, 0, zc + r]]])
    cn = np.concatenate([cn, [[0, 0, 1.0]]])
    m = len(el)
    cf = _ring_faces(m, n_phi)
    j = np.arange(n_phi)
    fan = np.stack([(m - 1) * n_phi + j, (m - 1) * n_phi + (j + 1) % n_phi, np.full(n_phi, len(cv) - 1)], 1)
    cap = (cv, np.concatenate([cf, fan]), cn)
    # stitch the cap's first ring to the top ring of the upper cylinder
    bottom = _disc(0.0, r, n_phi, 6 if detail == "full" else 3, up=False)
    v, f, n = _merge([low, up, cap, bottom])
    off_up, off_cap = len(low[0]), len(low[0]) + len(up[0])
    top_ring = off_up + (n_up - 1) * n_phi
    a, b = top_ring + j, top_ring + (j + 1) % n_phi
    c, d = off_cap + (j + 1) % n_phi, off_cap + j
    stitch = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    f = np.concatenate([f, stitch]).astype(np.int32)
    f = _orient_outward(v, f, n)
    mat = np.zeros(len(v), np.int32)
    mat[off_up:off_up + len(up[0]) + len(cap[0])] = 1
    # albedo: blue paint on top; cream label with two brown stripes and soft print-like blocks below
    rho = np.zeros((len(v), 3))
    rho[mat == 1] = [0.05, 0.12, 0.45]
    lo = mat == 0
    zz, phi = v[lo, 2], np.arctan2(v[lo, 1], v[lo, 0])
    stripes = np.zeros(lo.sum())
    for z0 in (0.018, 0.060):
        stripes = np.maximum(stripes, 1 - np.clip((np.abs(zz - z0) - 0.003) / 0.0008 + 0.5, 0, 1))
    blocks = (0.5 + 0.5 * np.tanh(np.sin(3 * phi) * np.sin(2 * np.pi * zz / 0.05) / 0.2)) * (zz > 0.025) * (zz < 0.052)
    label = np.array([0.76, 0.68, 0.50]) * (1 - 0.45 * blocks)[:, None]
    label = label * (1 - stripes[:, None]) + np.array([0.35, 0.18, 0.08]) * stripes[:, None]
    label[np.abs(n[lo, 2]) > 0.999] = [0.70, 0.64, 0.48]
    rho[lo] = label
    ir = np.where(mat == 1, 0.40, 0.62)
    paint = (Material("glossy-paint", (0.35, 0.35, 0.35), 0.06, "ward", ir_rho_s=0.12) if paint_lobe == "ward" else
             Material("ggx-paint", (0.30, 0.30, 0.30), 0.08, "ggx", ir_rho_s=0.10))
    mats = MaterialSet([Material("matte-label", (0.03, 0.03, 0.03), 0.35, "ward", ir_rho_s=0.02), paint])
    name = "two-material" if paint_lobe == "ward" else f"{paint_lobe}-two-material"
    return ObjectModel(name, v, f, n, rho, ir.astype(np.float64), mat, mats,
                       {"shape": "capsule", "radius_m": r, "cap_centre_z_m": zc, "material_boundary_z_m": zb})


def _matte(detail: str, seed: int) -> ObjectModel:
    """The two-material capsule wrapped in printed matte paper (one diffuse material, rho_s = 0)."""
    cap = _two_material(detail, seed)
    v, n = cap.vertices, cap.normals
    zz, phi = v[:, 2], np.arctan2(v[:, 1], v[:, 0])
    # kraft paper, three printed dark-green stripes, a band of soft print blocks, mottling
    stripes = np.zeros(len(v))
    for z0 in (0.018, 0.060, 0.098):
        stripes = np.maximum(stripes, 1 - np.clip((np.abs(zz - z0) - 0.003) / 0.0008 + 0.5, 0, 1))
    blocks = (0.5 + 0.5 * np.tanh(np.sin(3 * phi) * np.sin(2 * np.pi * zz / 0.05) / 0.2)) * (zz > 0.025) * (zz < 0.052)
    mott = 1 + 0.05 * _value_noise(v, seed + 17, 0.04)
    paper = np.array([0.66, 0.52, 0.36]) * (1 - 0.4 * blocks)[:, None] * mott[:, None]
    rho = paper * (1 - stripes[:, None]) + np.array([0.10, 0.24, 0.14]) * stripes[:, None]
    rho[n[:, 2] < -0.999] = [0.60, 0.48, 0.34]                  # the bottom disc, never seen
    ir = 0.60 - 0.25 * stripes
    # alpha is required by the material record but unused: rho_s = 0 in colour and IR
    mats = MaterialSet([Material("matte-paper", (0.0, 0.0, 0.0), 0.3, "ward", ir_rho_s=0.0)])
    return ObjectModel("matte", v, cap.faces, n, np.clip(rho, 0, 0.95), ir, np.zeros(len(v), np.int32), mats,
                       dict(cap.info, material="one diffuse material (rho_s = 0 in colour and IR)"))


OBJECTS = {
    "sphere": lambda detail, seed: _sphere(detail, seed, "ward"),
    "vase": _vase,
    "pepper": _pepper,
    "two-material": _two_material,
    "ggx-sphere": lambda detail, seed: _sphere(detail, seed, "ggx"),
    "ggx-two-material": lambda detail, seed: _two_material(detail, seed, "ggx"),
    "matte": _matte,
}


def build_object(name: str, detail: str = "full", seed: int = 0) -> ObjectModel:
    """Build one of :data:`OBJECTS` at ``detail`` ("full": 20-60k triangles, "test": ~5k)."""
    if detail not in DETAILS:
        raise AppFusionError(f"object detail must be one of {', '.join(DETAILS)}, got {detail!r}")
    try:
        fn = OBJECTS[name]
    except KeyError:
        raise AppFusionError(f"unknown object {name!r} (known: {', '.join(OBJECTS)})") from None
    return fn(detail, seed)


def custom_sphere(radius: float, center, rho_d, material: Material, level: int = 4, name: str = "test-sphere",
                  ir_rho_d: float = 0.5) -> ObjectModel:
    """A sphere of one material and uniform albedo (closed-form tests)."""
    u, f = icosphere(level)
    v = np.asarray(center, dtype=np.float64) + radius * u
    V = len(v)
    return ObjectModel(name, v, f, u.copy(), np.tile(np.asarray(rho_d, dtype=np.float64), (V, 1)),
                       np.full(V, ir_rho_d), np.zeros(V, np.int32), MaterialSet([material]),
                       {"shape": "sphere", "centre_m": list(map(float, center)), "radius_m": radius})
