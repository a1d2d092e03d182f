"""Geometry, ray casting and the radiance integrators of the synthetic scanner.

Scene contents (marker frame, metres): an optional object mesh (ray-cast with Open3D's
``RaycastingScene``), an optional analytic support plane (z = 0, black paper with four white circles),
an optional analytic mirror ball, an optional analytic calibration sheet, and a distant
:class:`~replay.synth.envmaps.Environment`.

Light transport (what is and is not simulated):

- The object is lit by the environment, shadowed by its own geometry and by the plane (and the ball),
  plus **one bounce off the support plane**: a ray from the object that hits the plane sees the plane's
  radiance ``rho_plane(x) / pi * E_plane(x)``. Light the object reflects onto the plane or onto itself
  is not simulated (the paper's assumption, §3: no inter-reflection). The plane itself is Lambertian,
  lit by the environment with the object's (or ball's) shadow.
- RGB (Eq. 2 of the paper): ``L(w_o) = int L_in(w_i) f_r(w_i, w_o) cos(theta_i) dw_i`` with
  ``f_r = rho_d / pi + rho_s f``; the integral is split as

  * diffuse: ``rho_d / pi * E`` with the irradiance ``E`` computed per vertex (background by a
    lat-long cell quadrature with a ray cast per cell, emitters by their exact cells, the plane's
    black paper, the white circles as small area lights) and interpolated barycentrically;
  * specular, emitters and circles: a sum over the cells (about 2 degrees each, exact solid angles) of
    ``L_e V f cos dw`` with per-vertex cell visibility interpolated barycentrically; skipped where a
    bound on the contribution is below 1e-4 of the pixel's diffuse radiance, summed over 3 x 3 groups
    of cells far from the lobe's peak;
  * specular, background and the plane's black paper: stratified importance samples of the lobe per
    pixel, each with its own ray cast (exact visibility): a pilot of ``lobe_pilot`` samples, then 4x
    or 16x more where this part is a large share of the pixel, with the pilot's mean radiance as a
    control variate against the lobe's tabulated directional albedo.

- The mirror ball: the view ray is reflected and looks up what it hits (plane or environment), times
  the ball's reflectance; ball pixels are super-sampled ``ball_supersample``^2 times.
- IR: a point emitter (see :mod:`replay.synth.sensors`), one shadow ray per pixel.

:func:`reference_radiance` is an independent brute-force integrator (exact per-point visibility for
every sample, 16 times more samples in every part) used to measure the error of the fast one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appfusion.errors import AppFusionError

from . import materials as M
from .envmaps import Environment, hemisphere_cells
from .objects import ObjectModel

EPS_RAY = 1e-4  # m, ray origin offset along the geometric normal
LIGHTING_VERSION = 2  # bump when the precomputation changes (invalidates caches)

KIND_NONE, KIND_OBJECT, KIND_PLANE, KIND_BALL, KIND_SHEET = 0, 1, 2, 3, 4


@dataclass
class Quality:
    """Integration settings (recorded in ``scene.json``)."""

    q_up: int = 24                  # lat-long rows of the background quadrature above the horizon (4x columns)
    q_down: int = 24                # ... below the horizon (the plane's bounce light, its contact shadow and edge)
    emitter_cell_deg: float = 2.0   # emitter cell size
    lobe_pilot: int = 16            # stratified lobe samples per object pixel for the background (square)
    lobe_samples: int = 256         # at most this many where the background's share of the radiance is large
    spec_share: float = 0.03        # ... a pixel gets pilot * (share / spec_share)^2 samples (levels x4, x16)
    control_variate: bool = True    # extra lobe samples use the pilot's mean radiance as a control variate
    plane_fine_m: float = 0.005     # plane irradiance grid spacing near the centre
    plane_coarse_m: float = 0.04    # ... at the plane's edge
    ball_supersample: int = 4       # sub-pixels per axis on the mirror ball
    skip_rel: float = 1e-4          # emitter skipped below this fraction of the diffuse radiance
    coarse_block: int = 3           # far from a lobe's peak, emitter cells are summed in 3 x 3 groups
    coarse_far: float = 3.0         # ... where the half-vector angle exceeds this many group radii
    marker_rings: int = 4           # quadrature of each white circle (as a small area light)
    marker_sectors: int = 12

    def to_json(self) -> dict:
        return dict(self.__dict__)

    @classmethod
    def preset(cls, name: str) -> "Quality":
        """``"full"``: the defaults (render error below 0.5%); ``"test"``: coarse and fast (unit tests)."""
        if name == "full":
            return cls()
        if name == "test":
            return cls(q_up=12, q_down=12, emitter_cell_deg=4.0, plane_fine_m=0.01, plane_coarse_m=0.06,
                       lobe_pilot=4, lobe_samples=16, marker_rings=2, marker_sectors=6, ball_supersample=2)
        raise AppFusionError(f"unknown quality preset {name!r} (known: full, test)")


# -- analytic geometry ------------------------------------------------------------------------------

@dataclass
class SupportPlane:
    """Black paper on the table (z = 0) with four white circles (paper §4, §7).

    Circles are numbered 1 (+x, +y), 2 (+x, -y), 3 (-x, -y), 4 (-x, +y), centred at (+-side/2, +-side/2).
    Circle 1 is the printed *key* circle, larger (``key_radius_m``) so that the numbering, and with it
    the marker frame, is the same whichever side a pass starts from (a square of equal circles has a
    quarter-turn ambiguity).
    """

    half_size_m: float = 0.6
    albedo: float = 0.04
    ir_albedo: float = 0.05
    side_m: float = 0.30
    marker_radius_m: float = 0.025
    key_radius_m: float = 0.035
    marker_albedo: float = 0.85
    marker_ir_albedo: float = 0.80

    @property
    def marker_centres(self) -> np.ndarray:
        s = 0.5 * self.side_m
        return np.array([[s, s], [s, -s], [-s, -s], [-s, s]])

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Ray parameter of the plane hit (inf where missed) for rays o + t d, (N, 3) each."""
        oz = np.maximum(o[:, 2], 0.0)  # the world is above the table: origins on or below it start on it
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -oz / d[:, 2]
        x = o[:, :2] + t[:, None] * d[:, :2]
        ok = (d[:, 2] < 0) & (t >= 0) & np.all(np.abs(x) <= self.half_size_m, axis=1)
        return np.where(ok, t, np.inf)

    @property
    def marker_radii(self) -> np.ndarray:
        """Radius of circles 1..4 (circle 1 is the key circle), metres."""
        return np.array([self.key_radius_m, self.marker_radius_m, self.marker_radius_m, self.marker_radius_m])

    def marker_coverage(self, xy: np.ndarray, footprint_m=0.0) -> np.ndarray:
        """Fraction of a pixel footprint (radius ``footprint_m``) covered by white, (N,)."""
        out = np.zeros(len(xy))
        fw = np.broadcast_to(np.maximum(np.asarray(footprint_m, dtype=np.float64), 1e-5), (len(xy),))
        for c, R in zip(self.marker_centres, self.marker_radii):
            ax, ay = xy[:, 0] - c[0], xy[:, 1] - c[1]
            reach = R + fw
            near = np.nonzero((np.abs(ax) < reach) & (np.abs(ay) < reach))[0]
            if len(near):
                d = np.sqrt(ax[near] ** 2 + ay[near] ** 2)
                out[near] = np.maximum(out[near], np.clip((R - d) / (2 * fw[near]) + 0.5, 0.0, 1.0))
        return out

    def marker_points(self, n_r: int = 4, n_s: int = 12):
        """Quadrature points on the four circles: polar cells (n_r rings of equal width, n_s sectors).

        Returns points (4 n_r n_s, 3) on z = 0 and their exact areas (m^2)."""
        ph = (np.arange(n_s) + 0.5) * 2 * np.pi / n_s
        pts, area = [], []
        for c, R in zip(self.marker_centres, self.marker_radii):
            r = np.linspace(0, R, n_r + 1)
            rc = np.sqrt(0.5 * (r[:-1] ** 2 + r[1:] ** 2))
            dA = np.pi * (r[1:] ** 2 - r[:-1] ** 2) / n_s
            Rr, P = np.meshgrid(rc, ph, indexing="ij")
            pts.append(c[None] + np.stack([Rr * np.cos(P), Rr * np.sin(P)], -1).reshape(-1, 2))
            area.append(np.repeat(dA, n_s))
        pts = np.concatenate(pts)
        return np.concatenate([pts, np.zeros((len(pts), 1))], axis=1), np.concatenate(area)

    def albedo_at(self, xy, footprint_m=0.0) -> np.ndarray:
        c = self.marker_coverage(xy, footprint_m)
        return self.albedo + (self.marker_albedo - self.albedo) * c

    def ir_albedo_at(self, xy, footprint_m=0.0) -> np.ndarray:
        c = self.marker_coverage(xy, footprint_m)
        return self.ir_albedo + (self.marker_ir_albedo - self.ir_albedo) * c

    def to_json(self) -> dict:
        return {**self.__dict__, "marker_centres_m": self.marker_centres.tolist(),
                "numbering": "1 (+x,+y), 2 (+x,-y), 3 (-x,-y), 4 (-x,+y)"}


@dataclass
class MirrorBall:
    """A perfect mirror sphere (paper §4.3)."""

    centre_m: tuple = (0.0, 0.0, 0.035)
    radius_m: float = 0.035
    reflectance: float = 0.95

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        c = np.asarray(self.centre_m)
        oc = o - c
        b = np.einsum("ij,ij->i", oc, d)
        cc = np.einsum("ij,ij->i", oc, oc) - self.radius_m ** 2
        disc = b * b - cc
        sq = np.sqrt(np.maximum(disc, 0.0))
        t0, t1 = -b - sq, -b + sq
        t = np.where(t0 > 1e-7, t0, np.where(t1 > 1e-7, t1, np.inf))
        return np.where(disc >= 0, t, np.inf)

    def to_json(self) -> dict:
        return {"centre_m": list(self.centre_m), "radius_m": self.radius_m, "reflectance": self.reflectance}


@dataclass
class Sheet:
    """A big white Lambertian sheet, the plane y = 0 facing -y (IR calibration, paper §6)."""

    albedo: float = 0.8
    ir_albedo: float = 0.8
    half_size_m: float = 2.0
    centre_z_m: float = 0.5

    def intersect(self, o, d):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[:, 1] / d[:, 1]
        x = o + t[:, None] * d
        ok = (t > 0) & (np.abs(x[:, 0]) <= self.half_size_m) & (np.abs(x[:, 2] - self.centre_z_m) <= self.half_size_m)
        return np.where(ok, t, np.inf)

    def to_json(self) -> dict:
        return dict(self.__dict__)


@dataclass
class Hits:
    """Result of casting N rays."""

    t: np.ndarray
    kind: np.ndarray
    point: np.ndarray
    normal: np.ndarray      # shading normal (object: interpolated vertex normals)
    gnormal: np.ndarray     # geometric normal
    prim: np.ndarray        # object triangle id (-1 elsewhere)
    bary: np.ndarray        # (N, 3) barycentric weights of the triangle's vertices


# -- the scene ------------------------------------------------------------------------------------

class Scene:
    """Everything a ray can meet, plus the lighting.

    Parameters
    ----------
    env : Environment
    obj : ObjectModel, optional
    plane : SupportPlane, optional
    ball : MirrorBall, optional
    sheet : Sheet, optional
    quality : Quality
    """

    def __init__(self, env: Environment, obj: ObjectModel | None = None, plane: SupportPlane | None = None,
                 ball: MirrorBall | None = None, sheet: Sheet | None = None, quality: Quality | None = None):
        import open3d as o3d

        self.env, self.obj, self.plane, self.ball, self.sheet = env, obj, plane, ball, sheet
        self.quality = quality or Quality()
        self._rc = None
        if obj is not None:
            self._rc = o3d.t.geometry.RaycastingScene()
            self._rc.add_triangles(o3d.core.Tensor(obj.vertices.astype(np.float32)),
                                   o3d.core.Tensor(obj.faces.astype(np.uint32)))
            self._rs, self._al, self._code, self._irs = obj.materials.arrays()
        self._o3d = o3d
        self.lighting: Lighting | None = None

    # -- ray queries ---------------------------------------------------------------------------
    def _rays(self, o, d):
        return self._o3d.core.Tensor(np.concatenate([o, d], axis=1).astype(np.float32))

    def occluded(self, o: np.ndarray, d: np.ndarray, tfar: np.ndarray | float | None = None,
                 chunk: int = 2_000_000) -> np.ndarray:
        """True where the segment o + t d, 0 < t < tfar (inf by default), meets the object or the ball.

        The plane and the sheet are not tested (callers handle them analytically)."""
        n = len(o)
        out = np.zeros(n, dtype=bool)
        if n == 0:
            return out
        tf = np.full(n, np.inf) if tfar is None else np.broadcast_to(np.asarray(tfar, dtype=np.float64), (n,))
        if self._rc is not None:
            finite = np.isfinite(tf)
            for s in range(0, n, chunk):
                sl = slice(s, min(n, s + chunk))
                r = self._rays(o[sl], d[sl])
                if np.any(finite[sl]):
                    # Open3D's tfar is a scalar: cast and compare instead
                    th = self._rc.cast_rays(r)["t_hit"].numpy()
                    out[sl] = th < tf[sl]
                else:
                    out[sl] = self._rc.test_occlusions(r).numpy().astype(bool)
        if self.ball is not None:
            out |= self.ball.intersect(o, d) < tf
        return out

    def intersect(self, o: np.ndarray, d: np.ndarray) -> Hits:
        """Nearest hit of rays o + t d (N, 3); ``d`` unit."""
        n = len(o)
        t = np.full(n, np.inf)
        kind = np.zeros(n, dtype=np.int8)
        prim = np.full(n, -1, dtype=np.int64)
        uv = np.zeros((n, 2))
        gn = np.zeros((n, 3))
        if self._rc is not None:
            ans = self._rc.cast_rays(self._rays(o, d))
            th = ans["t_hit"].numpy().astype(np.float64)
            hit = np.isfinite(th)
            t[hit] = th[hit]
            kind[hit] = KIND_OBJECT
            prim[hit] = ans["primitive_ids"].numpy()[hit].astype(np.int64)
            uv[hit] = ans["primitive_uvs"].numpy()[hit]
            gn[hit] = ans["primitive_normals"].numpy()[hit]
        for geo, k in ((self.plane, KIND_PLANE), (self.ball, KIND_BALL), (self.sheet, KIND_SHEET)):
            if geo is None:
                continue
            tg = geo.intersect(o, d)
            closer = tg < t
            t[closer] = tg[closer]
            kind[closer] = k
            prim[closer] = -1
        p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        nrm = np.zeros((n, 3))
        bary = np.zeros((n, 3))
        m = kind == KIND_OBJECT
        if np.any(m):
            u, v = uv[m, 0], uv[m, 1]
            b = np.stack([1 - u - v, u, v], axis=1)
            bary[m] = b
            f = self.obj.faces[prim[m]]
            ns = np.einsum("nk,nkj->nj", b, self.obj.normals[f])
            nrm[m] = M.normalize(ns)
        m = kind == KIND_PLANE
        nrm[m] = gn[m] = [0.0, 0.0, 1.0]
        m = kind == KIND_SHEET
        nrm[m] = gn[m] = [0.0, -1.0, 0.0]
        m = kind == KIND_BALL
        if np.any(m):
            nb = (p[m] - np.asarray(self.ball.centre_m)) / self.ball.radius_m
            nrm[m] = gn[m] = nb
        return Hits(t, kind, p, nrm, gn, prim, bary)

    def cache_key(self) -> str:
        """Hash of everything the precomputed lighting depends on."""
        import hashlib
        import json

        h = hashlib.sha1(f"synth-lighting-v{LIGHTING_VERSION}".encode())
        if self.obj is not None:
            for a in (self.obj.vertices, self.obj.faces, self.obj.normals):
                h.update(np.ascontiguousarray(a).tobytes())
        doc = {"env": self.env.to_json(), "quality": self.quality.to_json(),
               "plane": None if self.plane is None else self.plane.to_json(),
               "ball": None if self.ball is None else self.ball.to_json(),
               "sheet": None if self.sheet is None else self.sheet.to_json()}
        h.update(json.dumps(doc, sort_keys=True, default=str).encode())
        return h.hexdigest()[:20]

    def ensure_lighting(self, progress=None, cache_dir=None) -> "Lighting":
        """The precomputed lighting, computed now or loaded from ``cache_dir`` (an npz per scene)."""
        if self.lighting is not None:
            return self.lighting
        path = None
        if cache_dir is not None:
            from pathlib import Path

            path = Path(cache_dir) / f"lighting-{self.cache_key()}.npz"
            if path.exists():
                try:
                    self.lighting = Lighting(self, progress=progress, arrays=dict(np.load(path)))
                    return self.lighting
                except Exception:  # a damaged cache file is recomputed
                    pass
        self.lighting = Lighting(self, progress=progress)
        if cache_dir is not None:
            self.save_lighting(cache_dir)
        return self.lighting

    def save_lighting(self, cache_dir) -> None:
        """Write the precomputed lighting into ``cache_dir`` (atomically; no-op if already there)."""
        import os
        from pathlib import Path

        path = Path(cache_dir) / f"lighting-{self.cache_key()}.npz"
        if self.lighting is None or path.exists():
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
        np.savez(tmp, **self.lighting.arrays())
        os.replace(tmp, path)


# -- precomputed lighting ------------------------------------------------------------------------

def _graded_nodes(half: float, fine: float, coarse: float, fine_half: float = 0.2) -> np.ndarray:
    """Grid nodes on [-half, half]: spacing ``fine`` for |s| <= fine_half, growing linearly to ``coarse``."""
    pos = [0.0]
    s = 0.0
    while s < half:
        h = fine if s < fine_half else fine + (coarse - fine) * (s - fine_half) / max(half - fine_half, 1e-9)
        s = min(half, s + h)
        pos.append(s)
    pos = np.array(pos)
    return np.concatenate([-pos[::-1], pos[1:]])


def _interp_grid(nodes_x, nodes_y, grid, xy):
    """Bilinear interpolation of grid (nx, ny, C) at points xy (N, 2) on a tensor grid (clamped)."""
    ix = np.clip(np.searchsorted(nodes_x, xy[:, 0]) - 1, 0, len(nodes_x) - 2)
    iy = np.clip(np.searchsorted(nodes_y, xy[:, 1]) - 1, 0, len(nodes_y) - 2)
    ax = np.clip((xy[:, 0] - nodes_x[ix]) / (nodes_x[ix + 1] - nodes_x[ix]), 0, 1)[:, None]
    ay = np.clip((xy[:, 1] - nodes_y[iy]) / (nodes_y[iy + 1] - nodes_y[iy]), 0, 1)[:, None]
    return ((grid[ix, iy] * (1 - ax) + grid[ix + 1, iy] * ax) * (1 - ay)
            + (grid[ix, iy + 1] * (1 - ax) + grid[ix + 1, iy + 1] * ax) * ay)


class Lighting:
    """Per-scene precomputation: plane irradiance grid, per-vertex irradiance and emitter-cell visibility.

    Attributes
    ----------
    q_dirs, q_dw, q_bg : background quadrature directions (K, 3), solid angles (K,), exact B (K, 3)
    e_dirs, e_dw, e_L, e_idx : emitter cells (see :meth:`Environment.emitter_cells`)
    plane_nodes : (x nodes, y nodes) of the plane irradiance grid
    plane_E : (nx, ny, 3) irradiance of the support plane (object/ball shadows included)
    vert_E : (V, 3) irradiance at each object vertex about its normal (shadows and plane bounce included)
    vert_vis : (V, K_e) uint8 visibility of each emitter cell from each vertex

    Notes
    -----
    Rays from a vertex are only cast where the object can be in the way: a vertex on the object's
    convex hull cannot see the object in any direction ``w`` with ``w . n_f > 0`` for the hull facet
    ``f`` it lies on (the ray leaves the hull at once and the hull is convex), so those directions are
    known to be free. Emitter cells more than ~6 degrees below a vertex's horizon are marked occluded
    without a ray (the surface itself hides them; they only matter for interpolation near the
    terminator).
    """

    PLANE_TEX_M = 0.002  # texel of the plane radiance texture used for bounce light

    def __init__(self, scene: Scene, progress=None, arrays: dict | None = None):
        import time

        t0 = time.perf_counter()
        self.scene = scene
        q = scene.quality
        env = scene.env
        self.q_dirs, self.q_dw = hemisphere_cells(q.q_up, q.q_down)
        self.q_bg = env.background_exact(self.q_dirs)
        self.e_dirs, self.e_dw, self.e_L, self.e_idx = env.emitter_cells(q.emitter_cell_deg)
        self._coarse_cells(q.coarse_block)
        self.m_pts = np.zeros((0, 3))
        self.m_dA = np.zeros(0)
        self.m_dL = np.zeros((0, 3))
        self.plane_nodes = None
        self.plane_E = None
        self.vert_E = None
        self.vert_vis = None
        self.stats: dict = {}
        self._progress = progress
        self.from_cache = arrays is not None
        if arrays is not None:
            if scene.plane is not None:
                nodes = arrays["plane_nodes"]
                self.plane_nodes = (nodes, nodes)
                self.plane_E = arrays["plane_E"]
                self._plane_texture()
            if scene.obj is not None:
                self.vert_E = arrays["vert_E"]
                ke = len(self.e_dw)
                self.vert_vis = np.unpackbits(arrays["vert_vis_bits"], axis=1, count=ke)
                self.vert_mvis = np.unpackbits(arrays["vert_mvis_bits"], axis=1, count=len(self.m_dA))
                self.vert_cvis = self.coarse_visibility(self.vert_vis).astype(np.float32)
        else:
            if scene.plane is not None:
                self._plane_irradiance()
            if scene.obj is not None:
                self._vertex_lighting()
        self.seconds = time.perf_counter() - t0

    def _coarse_cells(self, block: int):
        """Groups of block x block emitter cells for pixels far from the lobe's peak (see shade_object)."""
        g = self.scene.env.emitter_groups(self.scene.quality.emitter_cell_deg, block)
        self.e_group = g
        kc = int(g.max()) + 1 if len(g) else 0
        self.c_dw = np.bincount(g, weights=self.e_dw, minlength=kc)
        cd = np.stack([np.bincount(g, weights=self.e_dirs[:, c] * self.e_dw, minlength=kc) for c in range(3)], 1)
        self.c_dirs = cd / np.linalg.norm(cd, axis=1, keepdims=True)
        self.c_idx = np.zeros(kc, dtype=np.int64)
        self.c_idx[g] = self.e_idx
        self.c_L = np.zeros((kc, 3))
        self.c_L[g] = self.e_L
        # each group's angular size (the largest distance of its cells' directions from its centre)
        self.c_rad = np.zeros(kc)
        np.maximum.at(self.c_rad, g, np.arccos(np.clip(np.einsum("ij,ij->i", self.e_dirs, self.c_dirs[g]), -1, 1)))

    def coarse_visibility(self, vis_fine: np.ndarray) -> np.ndarray:
        """Solid-angle-weighted visibility of the coarse groups from fine cell visibility (..., K)."""
        from scipy.sparse import csr_matrix

        kc = len(self.c_dw)
        if kc == 0:
            return np.zeros(vis_fine.shape[:-1] + (0,), dtype=np.float64)
        G = csr_matrix((self.e_dw, (np.arange(len(self.e_dw)), self.e_group)), shape=(len(self.e_dw), kc))
        shp = vis_fine.shape
        out = (G.T @ vis_fine.reshape(-1, shp[-1]).T.astype(np.float64)).T / self.c_dw
        return out.reshape(shp[:-1] + (kc,))

    def arrays(self) -> dict:
        """What :meth:`Scene.ensure_lighting` caches."""
        out = {}
        if self.plane_E is not None:
            out.update(plane_nodes=self.plane_nodes[0], plane_E=self.plane_E)
        if self.vert_E is not None:
            out.update(vert_E=self.vert_E, vert_vis_bits=np.packbits(self.vert_vis.astype(bool), axis=1),
                       vert_mvis_bits=np.packbits(self.vert_mvis.astype(bool), axis=1))
        return out

    # -- irradiance of a z-up plane point (grid) ----------------------------------------------
    def _all_dirs(self, up_only: bool):
        d = np.concatenate([self.q_dirs, self.e_dirs])
        L = np.concatenate([self.q_bg, self.e_L])
        dw = np.concatenate([self.q_dw, self.e_dw])
        if up_only:
            m = d[:, 2] > 0
            d, L, dw = d[m], L[m], dw[m]
        return d, L, dw

    def irradiance_up(self, xy: np.ndarray, chunk: int = 512) -> np.ndarray:
        """Irradiance (N, 3) of plane points (x, y, 0) with normal +z, with object/ball shadows."""
        sc = self.scene
        d, L, dw = self._all_dirs(up_only=True)
        w = L * (d[:, 2] * dw)[:, None]  # (K, 3)
        E0 = w.sum(axis=0)
        out = np.tile(E0, (len(xy), 1))
        occluders = []
        if sc.obj is not None:
            occluders.append(sc.obj.bounding_sphere)
        if sc.ball is not None:
            occluders.append((np.asarray(sc.ball.centre_m, dtype=np.float64), sc.ball.radius_m))
        if not occluders:
            return out
        from scipy.spatial import cKDTree

        P = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
        tree = cKDTree(d)
        ii_all, jj_all = [], []
        for c, r in occluders:
            # candidate directions: inside the cone from each point around the occluder's bounding sphere
            v = c - P
            dist = np.linalg.norm(v, axis=1)
            ang = np.where(dist > r, np.arcsin(np.clip(r / np.maximum(dist, 1e-12), 0, 1)), np.pi)
            chord = 2 * np.sin(np.minimum(ang, np.pi / 2) / 2) + 1e-6
            chord = np.where(ang >= np.pi / 2, 2.0, chord)
            lists = tree.query_ball_point(v / dist[:, None], chord)
            lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
            if lens.sum() == 0:
                continue
            ii_all.append(np.repeat(np.arange(len(P)), lens))
            jj_all.append(np.concatenate([np.asarray(x, dtype=np.int64) for x in lists if len(x)]))
        if not ii_all:
            return out
        ii, jj = np.concatenate(ii_all), np.concatenate(jj_all)
        if len(occluders) > 1:
            key = np.unique(ii * len(d) + jj)
            ii, jj = key // len(d), key % len(d)
        self.stats["plane_rays"] = self.stats.get("plane_rays", 0) + len(ii)
        occ = sc.occluded(P[ii] + [0.0, 0.0, EPS_RAY], d[jj])
        if np.any(occ):
            for c in range(3):
                out[:, c] -= np.bincount(ii[occ], weights=w[jj[occ], c], minlength=len(P))
        return np.maximum(out, 0.0)

    def _plane_irradiance(self):
        pl = self.scene.plane
        q = self.scene.quality
        nodes = _graded_nodes(pl.half_size_m, q.plane_fine_m, q.plane_coarse_m)
        X, Y = np.meshgrid(nodes, nodes, indexing="ij")
        E = self.irradiance_up(np.stack([X.ravel(), Y.ravel()], axis=1))
        self.plane_nodes = (nodes, nodes)
        self.plane_E = E.reshape(len(nodes), len(nodes), 3)
        self._plane_texture()

    def _plane_texture(self):
        """Uniform-grid tables of the plane: the *black paper* radiance (the circles are integrated apart,
        as small area lights of radiance (rho_circle - rho_paper) / pi * E) and the circles' quadrature."""
        pl = self.scene.plane
        nodes = self.plane_nodes[0]
        h = self.PLANE_TEX_M
        n = int(round(2 * pl.half_size_m / h)) + 1
        self._tex_n = n
        c = np.linspace(-pl.half_size_m, pl.half_size_m, n)
        X, Y = np.meshgrid(c, c, indexing="ij")
        xy = np.stack([X.ravel(), Y.ravel()], axis=1)
        self._plane_L_tex = (pl.albedo / np.pi * self.plane_irradiance_at(xy)).reshape(n, n, 3)
        self._plane_L_tex_flat = self._plane_L_tex.reshape(n * n, 3).astype(np.float32)
        q = self.scene.quality
        self.m_pts, self.m_dA = pl.marker_points(q.marker_rings, q.marker_sectors)
        self.m_dL = (pl.marker_albedo - pl.albedo) / np.pi * self.plane_irradiance_at(self.m_pts[:, :2])
        self.stats["plane_grid"] = [len(nodes), len(nodes)]

    def plane_irradiance_at(self, xy: np.ndarray) -> np.ndarray:
        return _interp_grid(self.plane_nodes[0], self.plane_nodes[1], self.plane_E, xy)

    def plane_radiance(self, xy: np.ndarray, footprint_m=0.0) -> np.ndarray:
        """Radiance (N, 3) of the support plane at points xy (Lambertian: albedo / pi * E), anti-aliased
        over a pixel footprint of radius ``footprint_m``."""
        a = self.scene.plane.albedo_at(xy, footprint_m)
        return (a / np.pi)[:, None] * self.plane_irradiance_at(xy)

    def plane_radiance_tex(self, xy: np.ndarray) -> np.ndarray:
        """Radiance of the black paper (without the circles) from a 2 mm texture (bilinear)."""
        half = self.scene.plane.half_size_m
        n = self._tex_n
        f = (np.clip(xy, -half, half) + half) * ((n - 1) / (2 * half))
        i0 = np.clip(np.floor(f), 0, n - 2)
        a = (f - i0).astype(np.float32)
        base = i0[:, 0].astype(np.int64) * n + i0[:, 1].astype(np.int64)
        T = self._plane_L_tex_flat
        ax, ay = a[:, 0:1], a[:, 1:2]
        return ((T[base] * (1 - ax) + T[base + n] * ax) * (1 - ay)
                + (T[base + 1] * (1 - ax) + T[base + n + 1] * ax) * ay)

    # -- incident radiance along rays (background part: no emitters) ----------------------------
    def background_in(self, o: np.ndarray, d: np.ndarray, exact: bool = False, occ: np.ndarray | None = None,
                      bg: np.ndarray | None = None, markers: bool = False):
        """Incident radiance from the background and the plane bounce along rays (emitters excluded):
        0 if the object/ball blocks the ray, the plane's radiance if it hits the plane, else B(d).

        ``bg`` (N, 3), when given, is B(d) already evaluated. With ``markers=False`` the plane is black
        paper everywhere (the integrators add the circles apart); with ``True`` the circles are in."""
        sc = self.scene
        if occ is None:
            occ = sc.occluded(o, d)
        out = np.zeros((len(o), 3))
        free = ~occ
        if not np.any(free):
            return out
        o_, d_ = o[free], d[free]
        if bg is not None:
            L = bg[free].copy()
        else:
            L = sc.env.background_exact(d_) if exact else sc.env.background(d_)
        if sc.plane is not None:
            tp = sc.plane.intersect(o_, d_)
            hp = np.isfinite(tp)
            if np.any(hp):
                xy = o_[hp, :2] + tp[hp, None] * d_[hp, :2]
                L[hp] = self.plane_radiance(xy) if markers else self.plane_radiance_tex(xy)
        out[free] = L
        return out

    def emitter_visible(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """True where a ray towards an emitter cell is not blocked (object, ball, or the plane)."""
        vis = ~self.scene.occluded(o, d)
        if self.scene.plane is not None:
            vis &= ~np.isfinite(self.scene.plane.intersect(o, d))
        return vis

    # -- per-vertex precomputation -------------------------------------------------------------
    def _hull_normals(self) -> np.ndarray:
        """For each vertex, the normal of a convex-hull facet whose plane contains it (NaN if none)."""
        from scipy.spatial import ConvexHull

        obj = self.scene.obj
        v = obj.vertices
        out = np.full((len(v), 3), np.nan)
        try:
            hull = ConvexHull(v)
        except Exception:  # degenerate: treat every vertex as interior
            return out
        eq = hull.equations
        best = np.full(len(v), -np.inf)
        tol = 1e-7
        for s in range(0, len(v), 2048):
            vv, nn = v[s:s + 2048], obj.normals[s:s + 2048]
            dist = vv @ eq[:, :3].T + eq[:, 3]
            on = np.abs(dist) < tol
            align = np.where(on, nn @ eq[:, :3].T, -np.inf)
            j = np.argmax(align, axis=1)
            a = align[np.arange(len(vv)), j]
            ok = np.isfinite(a)
            blk = out[s:s + 2048]
            blk[ok] = eq[j[ok], :3]
            best[s:s + 2048] = a
        self.stats["hull_vertices"] = int(np.isfinite(out[:, 0]).sum())
        return out

    def _vertex_lighting(self, chunk: int = 1024):
        from appfusion.progress import progress as _progress

        obj = self.scene.obj
        V = len(obj.vertices)
        self.vert_E = np.zeros((V, 3))
        self.vert_vis = np.zeros((V, len(self.e_dw)), dtype=np.uint8)
        self.vert_mvis = np.zeros((V, len(self.m_dA)), dtype=np.uint8)
        hn = self._hull_normals()
        on_hull = np.isfinite(hn[:, 0])
        hn = np.where(on_hull[:, None], hn, 0.0)
        P = obj.vertices + EPS_RAY * obj.normals
        n_rays = 0
        it = range(0, V, chunk)
        if self._progress:
            it = _progress(it, total=(V + chunk - 1) // chunk, desc="light transport", enable=True)
        kq, ke = len(self.q_dw), len(self.e_dw)
        plane = self.scene.plane
        n32, h32 = obj.normals.astype(np.float32), hn.astype(np.float32)
        q32, e32, dw32 = self.q_dirs.astype(np.float32), self.e_dirs.astype(np.float32), self.q_dw.astype(np.float32)
        up = self.q_dirs[:, 2] >= 0
        qu, qd = np.nonzero(up)[0], np.nonzero(~up)[0]
        for s in it:
            sl = slice(s, min(V, s + chunk))
            p, n, h, onh = P[sl], obj.normals[sl], hn[sl], on_hull[sl]
            nv = len(p)
            # background quadrature over cells in the upper hemisphere of the normal
            cos = n32[sl] @ q32.T                                     # (nv, kq)
            need = cos > 0
            free = onh[:, None] & ((h32[sl] @ q32.T) > 1e-7)         # known unoccluded (convex hull)
            ii, jj = np.nonzero(need & ~free)
            occ = np.zeros((nv, kq), dtype=bool)
            if len(ii):
                occ[ii, jj] = self.scene.occluded(p[ii], self.q_dirs[jj])
            n_rays += len(ii)
            wgt = np.where(need & ~occ, cos, np.float32(0.0)) * dw32  # (nv, kq)
            E = (wgt[:, qu] @ self.q_bg[qu].astype(np.float32)).astype(np.float64)
            if plane is None:
                E += wgt[:, qd] @ self.q_bg[qd].astype(np.float32)
            else:
                wd = self.q_dirs[qd]                                  # downward directions
                t = np.maximum(p[:, 2:3], 0.0) / -wd[None, :, 2]      # (nv, kd)
                xy = p[:, None, :2] + t[..., None] * wd[None, :, :2]
                inside = np.all(np.abs(xy) <= plane.half_size_m, axis=-1)
                wq = wgt[:, qd]
                E += np.where(inside, np.float32(0.0), wq) @ self.q_bg[qd].astype(np.float32)
                a, b = np.nonzero(inside & (wq > 0))
                if len(a):
                    Lp = self.plane_radiance_tex(xy[a, b])
                    wv = wq[a, b]
                    E += np.stack([np.bincount(a, weights=Lp[:, c] * wv, minlength=nv) for c in range(3)], 1)
            # emitters: visibility of cells above (or just below) the horizon
            if ke:
                ce = n32[sl] @ e32.T
                cand = ce > -0.1
                freee = onh[:, None] & ((h32[sl] @ e32.T) > 1e-7)
                if plane is not None:
                    freee &= self.e_dirs[None, :, 2] >= 0
                i2, j2 = np.nonzero(cand & ~freee)
                vm = (cand & freee).astype(np.uint8)
                if len(i2):
                    vm[i2, j2] = self.emitter_visible(p[i2], self.e_dirs[j2])
                n_rays += len(i2)
                self.vert_vis[sl] = vm
                E += (np.maximum(ce, 0.0) * (self.e_dw.astype(np.float32) * vm)) @ self.e_L.astype(np.float32)
            # the white circles: small area lights on the plane
            km = len(self.m_dA)
            if km:
                v = self.m_pts[None, :, :] - p[:, None, :]                       # (nv, km, 3)
                dist = np.sqrt(np.einsum("ijk,ijk->ij", v, v))
                u = v / dist[..., None]
                cm = np.einsum("ijk,ik->ij", u, n)
                cand = cm > -0.1
                freem = onh[:, None] & (np.einsum("ijk,ik->ij", u, h) > 1e-9)
                i3, j3 = np.nonzero(cand & ~freem)
                mv = (cand & freem).astype(np.uint8)
                if len(i3):
                    mv[i3, j3] = ~self.scene.occluded(p[i3], u[i3, j3], dist[i3, j3] - 2 * EPS_RAY)
                n_rays += len(i3)
                self.vert_mvis[sl] = mv
                dOm = self.m_dA * np.maximum(p[:, 2:3], 0.0) / dist ** 3               # dA cos_x / d^2
                E += (np.maximum(cm, 0.0) * dOm * mv) @ self.m_dL
            self.vert_E[sl] = E
        self.stats["vertex_rays"] = n_rays
        self.vert_cvis = self.coarse_visibility(self.vert_vis).astype(np.float32)
        self.stats["vertex_pairs"] = int(V * (kq // 2 + ke))

    def interpolate(self, prim: np.ndarray, bary: np.ndarray, arr: np.ndarray) -> np.ndarray:
        """Barycentric interpolation of a per-vertex array over hit triangles."""
        f = self.scene.obj.faces[prim]
        return np.einsum("nk,nk...->n...", bary, arr[f])


# -- shading ------------------------------------------------------------------------------------

def _stratified(rng: np.random.Generator, n: int, m: int):
    """n sets of m stratified 2-D samples (m a square number): (n, m) u1, u2."""
    k = int(round(np.sqrt(m)))
    if k * k != m:
        raise AppFusionError(f"lobe_samples must be a square number, got {m}")
    i, j = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    u1 = (i.ravel()[None] + rng.random((n, m))) / k
    u2 = (j.ravel()[None] + rng.random((n, m))) / k
    return u1, u2


def shade_object(scene: Scene, hits: Hits, sel: np.ndarray, cam_centre: np.ndarray, rng: np.random.Generator,
                 lobe_samples: int | None = None, return_parts: bool = False):
    """RGB radiance of object hits seen from a camera (paper Eq. 2 with Eq. 1's BRDF, see module notes).

    Parameters
    ----------
    scene : Scene
        With an object; its lighting is precomputed on first use.
    hits : Hits
        Ray hits (e.g. of a camera's pixels).
    sel : (P,) int array
        Indices into ``hits`` of the object hits to shade.
    cam_centre : (3,) array
        Camera centre, metres (marker frame): the view direction of each point.
    rng : numpy Generator
        Jitter of the stratified lobe samples.
    lobe_samples : int, optional
        Cap on lobe samples per pixel (default ``scene.quality.lobe_samples``).
    return_parts : bool
        Also return the parts (diffuse, spec_emitters, spec_background, E, rho_d, lobe_samples).

    Returns
    -------
    (P, 3) ndarray
        Linear RGB radiance, in the environment's units.
    """
    lt = scene.ensure_lighting()
    obj = scene.obj
    q = scene.quality
    m_s = lobe_samples or q.lobe_samples
    prim, bary = hits.prim[sel], hits.bary[sel]
    p, n, ng = hits.point[sel], hits.normal[sel], hits.gnormal[sel]
    wo = M.normalize(cam_centre - p)
    # geometric normal facing the viewer side for ray offsets
    ng = np.where((np.einsum("ij,ij->i", ng, wo) < 0)[:, None], -ng, ng)
    rho_d = lt.interpolate(prim, bary, obj.rho_d)
    E = lt.interpolate(prim, bary, lt.vert_E)
    diffuse = rho_d / np.pi * E
    mat = obj.face_material[prim]
    spec_e = np.zeros_like(diffuse)
    spec_b = np.zeros_like(diffuse)
    n_samples = np.zeros(len(sel))
    pilot = q.lobe_pilot
    co = np.einsum("ij,ij->i", n, wo)
    r = M.reflect(wo, n)
    f_tri = obj.faces[prim]
    ref_lum = diffuse.mean(axis=1) + 1e-6
    for mi in np.unique(mat):
        mt = obj.materials[mi]
        if max(mt.rho_s) <= 0 or mt.lobe == "mirror":
            continue
        sm = np.nonzero(mat == mi)[0]
        rs = np.asarray(mt.rho_s)
        # --- emitters
        for ei, em in enumerate(scene.env.emitters):
            cells = np.nonzero(lt.e_idx == ei)[0]
            ccells = np.nonzero(lt.c_idx == ei)[0]
            ang = np.arccos(np.clip(r[sm] @ em.center_dir, -1, 1))
            th_min = np.maximum(ang - np.arccos(em.cone_cos), 0.0) / 2
            bound = (rs.max() * em.radiance.max() * em.solid_angle()
                     * M.lobe_fcos_bound(mt.lobe, mt.alpha, np.cos(th_min), co[sm]))
            need = bound > q.skip_rel * ref_lum[sm]
            # far from the lobe's peak the lobe is smooth over a group of cells: sum the groups instead
            far = th_min >= q.coarse_far * lt.c_rad[ccells].max()
            for sub, cl, D, dw, V in ((sm[need & ~far], cells, lt.e_dirs, lt.e_dw, lt.vert_vis),
                                      (sm[need & far], ccells, lt.c_dirs, lt.c_dw, lt.vert_cvis)):
                for s0 in range(0, len(sub), 2048):
                    ix = sub[s0:s0 + 2048]
                    vis = np.einsum("nk,nkj->nj", bary[ix], V[f_tri[ix]][:, :, cl].astype(np.float32))
                    Dc = D[cl]
                    nn = np.broadcast_to(n[ix, None, :], (len(ix), len(cl), 3))
                    ww = np.broadcast_to(wo[ix, None, :], nn.shape)
                    f = M.lobe_eval(mt.lobe, mt.alpha, np.broadcast_to(Dc[None], nn.shape), ww, nn)
                    c = np.maximum(n[ix] @ Dc.T, 0.0)
                    spec_e[ix] += (vis * f * c * dw[cl]).sum(axis=1)[:, None] * em.radiance * rs
        # --- the white circles (small area lights on the plane)
        if len(lt.m_dA):
            per = len(lt.m_dA) // 4
            for k in range(4):
                R = scene.plane.marker_radii[k]
                cols = np.arange(k * per, (k + 1) * per)
                c = np.r_[scene.plane.marker_centres[k], 0.0]
                v = c - p[sm]
                dist = np.sqrt(np.einsum("ij,ij->i", v, v))
                ang = np.arccos(np.clip(np.einsum("ij,ij->i", r[sm], v) / dist, -1, 1))
                rad = np.arcsin(np.clip(R / dist, 0, 1))
                th_min = np.maximum(ang - rad, 0.0) / 2
                omega = np.pi * R * R * np.maximum(p[sm, 2], 0) / np.maximum(dist, R) ** 3
                bound = (rs.max() * lt.m_dL[cols].max() * omega
                         * M.lobe_fcos_bound(mt.lobe, mt.alpha, np.cos(th_min), co[sm]))
                need = sm[bound > q.skip_rel * ref_lum[sm]]
                for s0 in range(0, len(need), 2048):
                    ix = need[s0:s0 + 2048]
                    vv = lt.m_pts[None, cols] - p[ix, None, :]
                    dd = np.sqrt(np.einsum("ijk,ijk->ij", vv, vv))
                    u = vv / dd[..., None]
                    vis = np.einsum("nk,nkj->nj", bary[ix], lt.vert_mvis[f_tri[ix]][:, :, cols].astype(np.float32))
                    nn = np.broadcast_to(n[ix, None, :], u.shape)
                    f = M.lobe_eval(mt.lobe, mt.alpha, u, np.broadcast_to(wo[ix, None, :], u.shape), nn)
                    cn = np.maximum(np.einsum("ijk,ik->ij", u, n[ix]), 0.0)
                    dOm = lt.m_dA[cols] * np.maximum(p[ix, 2:3], 0.0) / dd ** 3
                    spec_e[ix] += (vis * f * cn * dOm) @ lt.m_dL[cols] * rs
        # --- background + plane bounce: stratified lobe sampling with exact visibility. A pilot of
        # ``pilot`` samples per pixel, then pixels where this part is a large share of the radiance get
        # more (4x or 16x), so that its relative noise stays about uniform.
        o_sm = p[sm] + EPS_RAY * ng[sm]
        # a weak specular (matte) material needs only a small pilot: its share is ~rho_s of the pixel
        pilot_m = pilot if rs.max() >= 0.1 else max(4, pilot // 4)
        est, cnt = _lobe_background(lt, mt, o_sm, n[sm], wo[sm], rng, pilot_m)
        cv = None
        if q.control_variate:
            # the pilot's lobe-weighted mean radiance: a control variate independent of the later samples
            A = M.albedo_at(mt.lobe, mt.alpha, co[sm])
            cv = est / np.maximum(A, 1e-3)[:, None]
        if m_s > pilot:
            frac = est.mean(axis=1) * rs.mean() / (diffuse[sm].mean(axis=1) + spec_e[sm].mean(axis=1)
                                                  + est.mean(axis=1) * rs.mean() + 1e-9)
            want = np.minimum(m_s, pilot_m * np.maximum(1.0, (frac / q.spec_share) ** 2))
            for level in (4 * pilot, 16 * pilot):
                if level > m_s:
                    break
                more = np.nonzero(want >= level * 0.6)[0]
                if not len(more):
                    break
                add = level - int(cnt[more[0]])
                e2, c2 = _lobe_background(lt, mt, o_sm[more], n[sm[more]], wo[sm[more]], rng, add,
                                          None if cv is None else cv[more])
                est[more] = (est[more] * cnt[more, None] + e2 * c2[:, None]) / (cnt[more] + c2)[:, None]
                cnt[more] += c2
        spec_b[sm] = est * rs
        n_samples[sm] = cnt
    L = diffuse + spec_e + spec_b
    if return_parts:
        return L, {"diffuse": diffuse, "spec_emitters": spec_e, "spec_background": spec_b, "E": E, "rho_d": rho_d,
                   "lobe_samples": n_samples}
    return L


def _lobe_background(lt: "Lighting", mt, o: np.ndarray, n: np.ndarray, wo: np.ndarray, rng, m: int,
                     cv: np.ndarray | None = None):
    """Stratified lobe-sampling estimate (P, 3) of ``int L_background f cos dw`` (without rho_s) and the
    sample counts (P,).

    With a control variate ``cv`` (P, 3) (a radiance near the lobe's centre), the estimate is
    ``cv A(cos_o) + mean(w (L - cv))`` where ``A`` is the lobe's directional albedo from an accurate
    table: unbiased, and the variance from the lobe's shape (its cut at the horizon, the weights)
    is gone, leaving only that of ``L - cv``."""
    k = int(np.floor(np.sqrt(m)))
    m = k * k
    u1, u2 = _stratified(rng, len(o), m)
    nn = np.repeat(n, m, axis=0)
    ww = np.repeat(wo, m, axis=0)
    wi, wt = M.lobe_sample(mt.lobe, mt.alpha, ww, nn, u1.ravel(), u2.ravel())
    ok = wt > 0
    Lin = np.zeros((len(wi), 3))
    if np.any(ok):
        Lin[ok] = lt.background_in(np.repeat(o, m, axis=0)[ok], wi[ok])
    if cv is not None:
        Lin -= np.repeat(cv, m, axis=0)
    est = (Lin * wt[:, None]).reshape(len(o), m, 3).mean(axis=1)
    if cv is not None:
        est += cv * M.albedo_at(mt.lobe, mt.alpha, np.einsum("ij,ij->i", n, wo))[:, None]
    return est, np.full(len(o), m, dtype=np.float64)


def shade_simple(scene: Scene, o: np.ndarray, d: np.ndarray, hits: Hits | None = None,
                 footprint: np.ndarray | None = None) -> np.ndarray:
    """Radiance (N, 3) along rays (origins ``o``, unit directions ``d``, (N, 3)) that do not end on the
    object: environment, support plane (circles anti-aliased over ``footprint`` (N,) metres), sheet,
    mirror ball (the reflected ray is traced once more: plane with its circles, or the environment,
    times the ball's reflectance)."""
    lt = scene.ensure_lighting()
    if hits is None:
        hits = scene.intersect(o, d)
    out = np.zeros((len(o), 3))
    k = hits.kind
    m = k == KIND_NONE
    out[m] = scene.env.radiance(d[m])
    m = k == KIND_PLANE
    if np.any(m):
        fp = 0.0 if footprint is None else footprint[m]
        out[m] = lt.plane_radiance(hits.point[m, :2], fp)
    m = k == KIND_SHEET
    if np.any(m):
        out[m] = scene.sheet.albedo / np.pi * lt_sheet_irradiance(scene)
    m = k == KIND_BALL
    if np.any(m):
        nb = hits.normal[m]
        v = -d[m]
        rdir = M.reflect(v, nb)
        ro = hits.point[m] + EPS_RAY * nb
        Lb = lt.background_in(ro, rdir, markers=True)
        vis = ~scene.occluded(ro, rdir)
        if scene.plane is not None:
            vis &= ~np.isfinite(scene.plane.intersect(ro, rdir))
        Lb = Lb + vis[:, None] * scene.env.emitter_radiance(rdir)
        out[m] = scene.ball.reflectance * Lb
    return out


def lt_sheet_irradiance(scene: Scene) -> np.ndarray:
    """Irradiance of the calibration sheet (normal -y), unoccluded: quadrature over the environment."""
    lt = scene.ensure_lighting()
    if not hasattr(lt, "_sheet_E"):
        d, L, dw = lt._all_dirs(up_only=False)
        c = np.maximum(-d[:, 1], 0.0)
        lt._sheet_E = (L * (c * dw)[:, None]).sum(axis=0)
    return lt._sheet_E


# -- the brute-force reference -------------------------------------------------------------------

def reference_radiance(scene: Scene, points: np.ndarray, normals: np.ndarray, gnormals: np.ndarray,
                       wo: np.ndarray, rho_d: np.ndarray, mat: np.ndarray, factor: int = 16,
                       seed: int = 1234, return_parts: bool = False):
    """Brute-force radiance at surface points: every sample gets its own exact visibility ray.

    ``factor`` times more samples than the fast renderer in every part: the background quadrature on a
    lat-long grid ``sqrt(factor)`` times finer per axis, emitter cells ``sqrt(factor)`` times smaller,
    ``factor`` times more lobe samples. Intended for a few hundred points (error measurement).
    """
    q = scene.quality
    lt = scene.ensure_lighting()
    env = scene.env
    k = int(round(np.sqrt(factor)))
    qd, qdw = hemisphere_cells(q.q_up * k, q.q_down * k)
    qb = env.background_exact(qd)
    ed, edw, eL, eidx = env.emitter_cells(q.emitter_cell_deg / k)
    if scene.plane is not None:
        mpts, mdA = scene.plane.marker_points(q.marker_rings * k, q.marker_sectors * k)
        mdL = (scene.plane.marker_albedo - scene.plane.albedo) / np.pi * lt.plane_irradiance_at(mpts[:, :2])
    rng = np.random.default_rng(seed)
    out = np.zeros((len(points), 3))
    parts = {k: np.zeros((len(points), 3)) for k in ("diffuse", "spec_emitters", "spec_background")}
    obj = scene.obj
    for i in range(len(points)):
        p = points[i] + EPS_RAY * gnormals[i]
        n = normals[i]
        # diffuse: background + plane bounce
        cos = qd @ n
        s = cos > 0
        Lin = lt.background_in(np.repeat(p[None], s.sum(), 0), qd[s], exact=True)
        E = (Lin * (cos[s] * qdw[s])[:, None]).sum(axis=0)
        # emitters with exact visibility
        ce = ed @ n
        se = ce > 0
        vis = lt.emitter_visible(np.repeat(p[None], se.sum(), 0), ed[se])
        E += (eL[se] * (vis * ce[se] * edw[se])[:, None]).sum(axis=0)
        # white circles (fine quadrature, exact visibility)
        if scene.plane is not None:
            mv = mpts - p
            md = np.sqrt(np.einsum("ij,ij->i", mv, mv))
            mu = mv / md[:, None]
            mc = mu @ n
            ms = mc > 0
            mvis = ~scene.occluded(np.repeat(p[None], ms.sum(), 0), mu[ms], md[ms] - 2 * EPS_RAY)
            mdO = mdA[ms] * max(p[2], 0.0) / md[ms] ** 3
            E += (mdL[ms] * (mvis * mc[ms] * mdO)[:, None]).sum(axis=0)
        L = rho_d[i] / np.pi * E
        parts["diffuse"][i] = L
        mt = obj.materials[int(mat[i])]
        if max(mt.rho_s) > 0:
            rs = np.asarray(mt.rho_s)
            nn = np.broadcast_to(n, (se.sum(), 3))
            f = M.lobe_eval(mt.lobe, mt.alpha, ed[se], np.broadcast_to(wo[i], nn.shape), nn)
            se_ = (eL[se] * (vis * f * ce[se] * edw[se])[:, None]).sum(axis=0) * rs
            if scene.plane is not None and ms.any():
                fm = M.lobe_eval(mt.lobe, mt.alpha, mu[ms], np.broadcast_to(wo[i], (ms.sum(), 3)),
                                 np.broadcast_to(n, (ms.sum(), 3)))
                se_ = se_ + (mdL[ms] * (mvis * fm * mc[ms] * mdO)[:, None]).sum(axis=0) * rs
            parts["spec_emitters"][i] = se_
            L += se_
            m_s = q.lobe_samples * factor
            u1, u2 = _stratified(rng, 1, m_s)
            wi, wt = M.lobe_sample(mt.lobe, mt.alpha, np.broadcast_to(wo[i], (m_s, 3)), np.broadcast_to(n, (m_s, 3)),
                                   u1[0], u2[0])
            ok = wt > 0
            Lb = lt.background_in(np.repeat(p[None], ok.sum(), 0), wi[ok], exact=True)
            sb_ = (Lb * wt[ok, None]).sum(axis=0) / m_s * rs
            parts["spec_background"][i] = sb_
            L += sb_
        out[i] = L
    return (out, parts) if return_parts else out
