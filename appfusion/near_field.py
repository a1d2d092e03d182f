"""The support plane as near-field light: black paper and the four white circles (beyond paper §3).

The paper models the incident light as *distant* (§3): one environment map, captured at the mirror
ball's centre (§4.3), lights every point of the object. Below the horizon that map shows the support
plane as the ball sees it: the black paper around the ball, darkened by the ball's own shadow and
occlusion straight below it, and the four white circles about 9 degrees below the horizon. A point of
the object sees the plane from elsewhere: a side of a 15 cm bottle looks down at paper 5-20 cm away
(not shadowed by a ball) and at the circles 20-40 degrees below its horizon. Measured on the demo
session with every other input exact, this parallax left the diffuse term D off by -2.5 % near the
base and +1.6 % at mid-height, and the glossy paint's specular reflection of the plane ~0.002 (white
units) brighter than the map predicts — +7 % of the dark red channel of a blue paint (docs/rgb-pass.md §5c).

:class:`SupportPlaneLight` models what is known exactly about that plane: it is z = 0 in the marker
frame, the circles are where the printed layout puts them and their radiance is the reference white
of §4.2 (``circle_radiance``, 1 in the calibrated units of every RGB frame and of the environment
map), and the paper's radiance is read off the environment map itself (directions from the ball's
centre that hit paper clear of the circles and of the ball's shadow). Optionally the object's own
shadow on the plane (:meth:`SupportPlaneLight.with_object_shadow`, from the reconstructed mesh) scales
the plane's radiance. Within ``extent_m`` of the marker centre, a ray that leaves a surface point
downwards sees this plane instead of the map's lower hemisphere; beyond it (the plane's far part and
the room) the map is kept.

The RGB pass (§5.3) adds the resulting corrections to Eq. 5's terms:

    D_p = D(n_p) + dD_p,     dD_p = (1/pi) int_{lower} (L_plane(p, w) - L_env(w)) (n.w)+ dw
    S   = S(n, alpha, w_o) + dS,  dS = int_{lower} (L_plane(p, w) - L_env(w)) f(alpha; w, w_o) (n.w)+ dw

``dD`` once per point (octahedral quadrature of the paper plus exact small-patch integration of the
circles); ``dS`` per sample by stratified importance sampling of the Ward lobe (only for samples whose
lobe reaches below the horizon). Visibility from the point (the object occluding its own view of the
plane) is ignored, as everywhere in the paper.
"""

from __future__ import annotations

import math

import numpy as np

from . import octahedral as oc
from .brdf import local_frame, sample_ward, ward
from .errors import AppFusionError

__all__ = ["SupportPlaneLight", "paper_radiance_from_env"]


def _block_downsample(env: np.ndarray, n: int) -> np.ndarray:
    """(2, N, N, 3) map to (2, n, n, 3) by solid-angle-weighted block means (N a multiple of n), else
    by bilinear sampling at the coarse texel centres."""
    N = env.shape[1]
    if N == n:
        return env.astype(np.float64)
    if N % n == 0:
        f = N // n
        w = oc.sphere_solid_angles(N)[..., None]
        num = (env * w).reshape(2, n, f, n, f, 3).sum(axis=(2, 4))
        den = w.reshape(2, n, f, n, f, 1).sum(axis=(2, 4))
        return num / den
    return oc.sample_sphere_map(env.astype(np.float64), oc.sphere_directions(n))


def _circle_mask(xy: np.ndarray, centres: np.ndarray, radii: np.ndarray, grow: float = 1.0) -> np.ndarray:
    d2 = np.sum((xy[..., None, :] - centres[:, :2]) ** 2, axis=-1)
    return np.any(d2 <= (grow * radii) ** 2, axis=-1)


def paper_radiance_from_env(env: np.ndarray, ball_centre, centres: np.ndarray, radii: np.ndarray,
                            ball_radius: float | None = None) -> np.ndarray:
    """Radiance (3,) of the black paper, read from the lower hemisphere of an environment map.

    Parameters
    ----------
    env : (2, N, N, 3) ndarray
        Environment map captured at the mirror ball (marker frame, white units).
    ball_centre : (3,) array_like
        The ball's centre, metres (marker frame); its height above the plane sets where each
        direction hits the paper.
    centres : (4, 3) ndarray; radii : (4,) ndarray
        The white circles (metres).
    ball_radius : float, optional
        Default: the centre's height (a ball resting on the plane).

    Returns
    -------
    (3,) ndarray
        Per-channel median over texels whose ray from the ball's centre hits paper 1.5-25 ball radii
        from the contact point (clear of the ball's own shadow and contact occlusion) and clear of the
        circles (twice their radius).
    """
    c = np.asarray(ball_centre, np.float64)
    if c.shape != (3,) or not np.isfinite(c).all() or c[2] <= 0:
        raise AppFusionError(f"paper radiance: the ball's centre must be above the plane, got {ball_centre}")
    r = float(ball_radius if ball_radius is not None else c[2])
    n = env.shape[1]
    d = oc.sphere_directions(n)[1].reshape(-1, 3)
    L = np.asarray(env[1], np.float64).reshape(-1, 3)
    t = c[2] / np.maximum(-d[:, 2], 1e-9)
    xy = c[:2] + t[:, None] * d[:, :2]
    rho = np.linalg.norm(xy - c[:2], axis=1)
    ok = (d[:, 2] < -0.05) & (rho > 1.5 * r) & (rho < 25 * r) & ~_circle_mask(xy, centres, radii, 2.0)
    ok &= np.isfinite(L).all(axis=1)
    if ok.sum() < 8:
        raise AppFusionError("paper radiance: the environment map shows too little of the support plane "
                             "(fewer than 8 texels of paper around the ball)")
    return np.median(L[ok], axis=0)


class SupportPlaneLight:
    """The marker plane z = 0 as a near-field light (see the module notes).

    Parameters
    ----------
    env : (2, N, N, 3) ndarray
        The environment map (marker frame, white units) the distant model uses.
    centres : (K, 3) ndarray
        White circle centres on the plane, metres.
    radii : (K,) ndarray
        Their radii, metres.
    paper : (3,) array_like
        Radiance of the black paper (white units), e.g. :func:`paper_radiance_from_env`.
    circle_radiance : float or (3,) array_like
        Radiance of the circles (the reference white of §4.2: 1).
    extent_m : float
        Radius around the marker centre within which the plane model replaces the map.
    n_quad : int
        Side of the octahedral quadrature square of ``dD`` (lower hemisphere, ``n_quad^2`` directions).
    """

    def __init__(self, env, centres, radii, paper, circle_radiance=1.0, extent_m: float = 0.45,
                 n_quad: int = 16):
        env = np.asarray(env)
        if env.ndim != 4 or env.shape[0] != 2 or env.shape[1] != env.shape[2] or env.shape[3] != 3:
            raise AppFusionError(f"SupportPlaneLight: environment map must be (2, N, N, 3), got {env.shape}")
        self.env = np.asarray(env, np.float32)
        self.centres = np.asarray(centres, np.float64).reshape(-1, 3)
        self.radii = np.asarray(radii, np.float64).reshape(-1)
        if len(self.radii) != len(self.centres) or (self.radii <= 0).any():
            raise AppFusionError("SupportPlaneLight: one positive radius per circle centre is needed")
        self.paper = np.asarray(paper, np.float64).reshape(3)
        self.circle = np.broadcast_to(np.asarray(circle_radiance, np.float64), (3,)).copy()
        if not (np.isfinite(self.paper).all() and (self.paper >= 0).all() and np.isfinite(self.circle).all()):
            raise AppFusionError(f"SupportPlaneLight: paper / circle radiance must be finite and >= 0, got "
                                 f"{self.paper}, {self.circle}")
        self.extent = float(extent_m)
        self.n_quad = int(n_quad)
        self._env_coarse = _block_downsample(self.env, self.n_quad)                 # (2, n_quad, n_quad, 3)
        self._env_q = self._env_coarse[1].reshape(-1, 3)                             # lower face
        self._dir_q = oc.sphere_directions(self.n_quad)[1].reshape(-1, 3)
        self._om_q = oc.sphere_solid_angles(self.n_quad)[1].reshape(-1)
        self.shadow = None            # (nodes, grid) of the object's shadow factor on the plane
        self._circle_pts = self._circle_patches()

    @classmethod
    def from_scan(cls, env, marker_centres, marker_radii, ball_centre, ball_radius=None, **kw) -> "SupportPlaneLight":
        """The plane of a scan: paper radiance from the map as seen from the ball (:func:`paper_radiance_from_env`)."""
        paper = paper_radiance_from_env(np.asarray(env), ball_centre, np.asarray(marker_centres, float),
                                        np.asarray(marker_radii, float), ball_radius)
        return cls(env, marker_centres, marker_radii, paper, **kw)

    # -- the plane's radiance --------------------------------------------------------------------
    def with_object_shadow(self, vertices, faces, half_m: float | None = None, step_m: float = 0.005,
                           n_dirs: int = 192) -> "SupportPlaneLight":
        """Scale the plane's radiance by the object's shadow (its mesh, marker frame).

        The factor at a plane point is its irradiance from the map's upper hemisphere with the object
        as occluder over the unoccluded one: the ``n_dirs`` directions of most energy are ray-cast
        against the mesh (Open3D ``RaycastingScene``), the rest count as visible. Tabulated on a grid of
        ``step_m`` over ``[-half_m, half_m]^2`` (default: ``extent_m``), bilinear in between.
        """
        import open3d as o3d

        V = np.asarray(vertices, np.float32)
        F = np.asarray(faces, np.int64)
        if len(F) == 0 or len(V) == 0:
            return self
        half = float(half_m if half_m is not None else self.extent)
        nodes = np.arange(-half, half + 0.5 * step_m, step_m)
        gx, gy = np.meshgrid(nodes, nodes, indexing="ij")
        pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, 1e-4)], axis=1)
        up_d = oc.sphere_directions(self.n_quad)[0].reshape(-1, 3)
        up_L = self._env_coarse[0].reshape(-1, 3).mean(axis=1)
        w = np.maximum(up_L, 0) * np.maximum(up_d[:, 2], 0) * oc.sphere_solid_angles(self.n_quad)[0].reshape(-1)
        total = w.sum()
        if total <= 0:
            return self
        top = np.argsort(-w)[:n_dirs]
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F.astype(np.uint32)))
        occ_w = np.zeros(len(pts))
        for s in range(0, len(top), 32):
            dd = up_d[top[s:s + 32]]
            rays = np.concatenate([np.repeat(pts, len(dd), 0), np.tile(dd, (len(pts), 1))], 1).astype(np.float32)
            occ = scene.test_occlusions(o3d.core.Tensor(rays)).numpy().reshape(len(pts), len(dd))
            occ_w += occ @ w[top[s:s + 32]]
        factor = np.clip(1.0 - occ_w / total, 0.0, 1.0).reshape(gx.shape)
        self.shadow = (nodes, factor)
        return self

    def _shadow_at(self, xy: np.ndarray) -> np.ndarray:
        if self.shadow is None:
            return np.ones(len(xy))
        nodes, g = self.shadow
        h = nodes[1] - nodes[0]
        fx = (xy[:, 0] - nodes[0]) / h
        fy = (xy[:, 1] - nodes[0]) / h
        m = len(nodes)
        inside = (fx >= 0) & (fx <= m - 1) & (fy >= 0) & (fy <= m - 1)
        x0 = np.clip(np.floor(fx).astype(np.int64), 0, m - 2)
        y0 = np.clip(np.floor(fy).astype(np.int64), 0, m - 2)
        ax, ay = np.clip(fx - x0, 0, 1), np.clip(fy - y0, 0, 1)
        v = (g[x0, y0] * (1 - ax) * (1 - ay) + g[x0 + 1, y0] * ax * (1 - ay)
             + g[x0, y0 + 1] * (1 - ax) * ay + g[x0 + 1, y0 + 1] * ax * ay)
        return np.where(inside, v, 1.0)

    def plane_radiance(self, xy: np.ndarray) -> np.ndarray:
        """Radiance (M, 3) of plane points ``xy`` (M, 2): circle or paper, times the object's shadow."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        base = np.where(_circle_mask(xy, self.centres, self.radii)[:, None], self.circle, self.paper)
        return base * self._shadow_at(xy)[:, None]

    def delta_radiance(self, points: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """``L_plane - L_env`` (M, 3) along rays from ``points`` (M, 3) in unit ``dirs`` (M, 3): non-zero
        only for rays that hit the plane within ``extent_m`` of the marker centre."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        d = np.asarray(dirs, np.float64).reshape(-1, 3)
        out = np.zeros((len(p), 3))
        down = (d[:, 2] < -1e-6) & (p[:, 2] > 0)
        if not down.any():
            return out
        i = np.flatnonzero(down)
        t = -p[i, 2] / d[i, 2]
        xy = p[i, :2] + t[:, None] * d[i, :2]
        near = np.sum(xy * xy, axis=1) <= self.extent ** 2
        i, xy = i[near], xy[near]
        out[i] = self.plane_radiance(xy) - oc.sample_sphere_map(self.env, d[i])
        return out

    # -- corrections to Eq. 5 ----------------------------------------------------------------------
    def _circle_patches(self, n_r: int = 3, n_s: int = 12):
        """Area patches of every circle: centres (K * n_r * n_s, 3) and areas."""
        pts, area = [], []
        for c, r in zip(self.centres, self.radii):
            edges = np.linspace(0, r, n_r + 1)
            for a, b in zip(edges[:-1], edges[1:]):
                rm = 0.5 * (a + b)
                ph = (np.arange(n_s) + 0.5) * 2 * np.pi / n_s
                pts.append(np.stack([c[0] + rm * np.cos(ph), c[1] + rm * np.sin(ph), np.zeros(n_s)], 1))
                area.append(np.full(n_s, np.pi * (b * b - a * a) / n_s))
        return np.concatenate(pts), np.concatenate(area)

    def delta_D(self, points: np.ndarray, normals: np.ndarray, chunk: int = 2048) -> np.ndarray:
        """``dD`` (P, 3) of points (P, 3) with unit normals (P, 3), white units (module notes).

        The paper part is an octahedral quadrature of the lower hemisphere (``n_quad^2`` directions)
        of ``paper * shadow - L_env``; the circles add ``(L_circle - paper * shadow) cos_p cos_c / r^2 dA``
        over small patches (exact in the limit of small patches, no aliasing of a 5-degree disc).
        """
        P = np.asarray(points, np.float64).reshape(-1, 3)
        N = np.asarray(normals, np.float64).reshape(-1, 3)
        out = np.zeros((len(P), 3))
        dq, om, Lq = self._dir_q, self._om_q, self._env_q
        cp, ca = self._circle_pts
        shadow_c = self._shadow_at(cp[:, :2])
        for s in range(0, len(P), chunk):
            p, n = P[s:s + chunk], N[s:s + chunk]
            m = len(p)
            above = p[:, 2] > 0
            cos = np.maximum(n @ dq.T, 0.0)                                    # (m, Q)
            t = p[:, 2:3] / np.maximum(-dq[:, 2], 1e-9)[None, :]                # (m, Q)
            hx = p[:, 0:1] + t * dq[None, :, 0]
            hy = p[:, 1:2] + t * dq[None, :, 1]
            near = (hx * hx + hy * hy <= self.extent ** 2) & above[:, None]
            sh = self._shadow_at(np.stack([hx.ravel(), hy.ravel()], 1)).reshape(m, -1) if self.shadow is not None \
                else np.ones_like(hx)
            wq = np.where(near, cos * om[None, :], 0.0)                           # (m, Q)
            paper_part = (wq * sh) @ np.ones(len(dq))                            # (m,)
            out[s:s + chunk] = (paper_part[:, None] * self.paper[None, :] - wq @ Lq) / np.pi
            # circles: small patches, radiance above the paper's
            v = cp[None, :, :] - p[:, None, :]                                   # (m, C, 3)
            r2 = np.sum(v * v, axis=-1)
            r = np.sqrt(r2)
            cos_p = np.maximum(np.einsum("mci,mi->mc", v, n) / r, 0.0)
            cos_c = np.maximum(p[:, 2:3] / r, 0.0)
            g = cos_p * cos_c * ca[None, :] / r2 / np.pi                          # (m, C)
            dL = (self.circle - self.paper)[None, :] * shadow_c[:, None]          # (C, 3)
            out[s:s + chunk] += np.where(above[:, None], g @ dL, 0.0)
        return out

    def delta_S(self, points: np.ndarray, normals: np.ndarray, wo: np.ndarray, alpha, n_samples: int = 16,
                seed: int = 0, n_samples_circle: int = 16) -> np.ndarray:
        """``dS`` (M, 3): the lobe's view of the plane minus its view of the map's lower hemisphere.

        Parameters
        ----------
        points, normals, wo : (M, 3) ndarray
            Sample points (marker frame, m), unit normals, unit directions to the camera.
        alpha : float or (M,) ndarray
            Ward roughness per sample.
        n_samples : int
            Lobe samples per sample: a stratified sqrt(n) x sqrt(n) pattern of Ward half-vector
            sampling, rotated at random per sample (unbiased; the noise averages over a point's
            views and a cluster's points like the sensor's).
        n_samples_circle : int
            Lobe samples for the samples whose lobe may reach a white circle (the mirror ray within
            the circle's angular radius plus three lobe widths of its centre). A circle is 20 times
            brighter than the paper and a few degrees wide: with 4 samples a lobe hit it with one
            sample or none, and that noise in S diluted the colour pass's regression of L on S (a
            glossy sphere's equator read a specular slope of 0.09 for 0.28 and half of it was split
            off as matte; 0.19 with 16 samples, 0.25 with 64, at 153 and 254 ms per demo frame
            against 127 with 4).

        Only samples whose mirror direction lies within ~4 lobe widths of the horizon or below get a
        correction; the others are 0.
        """
        p = np.asarray(points, np.float64).reshape(-1, 3)
        n = np.asarray(normals, np.float64).reshape(-1, 3)
        v = np.asarray(wo, np.float64).reshape(-1, 3)
        al = np.broadcast_to(np.asarray(alpha, np.float64), (len(p),))
        out = np.zeros((len(p), 3))
        if len(p) == 0:
            return out
        cos_o = np.sum(n * v, axis=1)
        r = 2 * cos_o[:, None] * n - v
        width = np.minimum(4 * np.arctan(al), np.pi / 2)
        reach = np.sin(width)
        i = np.flatnonzero((r[:, 2] < reach) & (cos_o > 1e-3) & (p[:, 2] > 0))
        if len(i) == 0:
            return out
        # which lobes may see a circle: the mirror ray within the circle's angular radius plus three
        # lobe widths of the direction to its centre
        to_c = self.centres[None, :, :] - p[i, None, :]                      # (m, C, 3)
        dist = np.linalg.norm(to_c, axis=-1)
        cos_c = np.einsum("mci,mi->mc", to_c, r[i]) / np.maximum(dist, 1e-9)
        ang = np.arccos(np.clip(cos_c, -1.0, 1.0))
        near = np.any(ang <= self.radii[None, :] / np.maximum(dist, 1e-9) + 3.0 * np.arctan(al[i])[:, None] + 0.02,
                      axis=1)
        rng = np.random.default_rng(seed)
        self._delta_S_mc(p, n, v, al, i[~near], n_samples, rng, out)
        self._delta_S_mc(p, n, v, al, i[near], max(n_samples, n_samples_circle), rng, out)
        return out

    def _delta_S_mc(self, p, n, v, al, idx, n_samples, rng, out) -> None:
        """Stratified Ward lobe sampling of ``dS`` for the samples ``idx`` (written into ``out``)."""
        if len(idx) == 0:
            return
        k = max(int(round(math.sqrt(n_samples))), 1)
        g = (np.arange(k) + 0.5) / k
        u1, u2 = np.meshgrid(g, g, indexing="ij")
        u1, u2 = u1.ravel(), u2.ravel()                                         # (K,)
        chunk = max(4096 * 4 // len(u1), 64)                                 # ~16k lobe rays at a time
        for s in range(0, len(idx), chunk):
            j = idx[s:s + chunk]
            m = len(j)
            a = al[j][:, None]
            F = local_frame(n[j])
            vl = np.einsum("mij,mj->mi", F, v[j])
            uu1 = (u1[None, :] + rng.random((m, 1)) / k) % 1.0
            uu2 = (u2[None, :] + rng.random((m, 1))) % 1.0
            vlk = np.broadcast_to(vl[:, None, :], (m, len(u1), 3))
            wi, vh, pdf = sample_ward(a, vlk, uu1, uu2)                            # (m, K, 3), (m, K), (m, K)
            ci = wi[..., 2]
            f = ward(a, wi, vlk)
            wgt = np.where((ci > 0) & (vh > 0), f * ci / np.maximum(pdf, 1e-300), 0.0)
            wi_w = np.einsum("mji,mkj->mki", F, wi)
            dL = self.delta_radiance(np.repeat(p[j], len(u1), 0), wi_w.reshape(-1, 3)).reshape(m, len(u1), 3)
            out[j] = np.einsum("mk,mkc->mc", wgt, dL) / len(u1)
