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
circles; it does not depend on the lobe); ``dS`` per sample by stratified importance sampling of the
sample's lobe, Ward (half vector, Walter 2005) or GGX (visible normals, Heitz 2018; the model ladder's
third rung), only for samples whose lobe reaches below the horizon, plus uniform samples of the white
circles a broad lobe may reach, combined with the lobe's by multiple importance sampling. Visibility from the point (the object occluding its own view of the
plane) is ignored, as everywhere in the paper.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np

from . import octahedral as oc
from .brdf import COS_EPS, ggx_d, ggx_g1, ggx_half, ggx_rows, lobe_rows, local_frame, sample_ggx, sample_ward
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

    #: a lobe (2 atan(alpha), radians) narrower than this times a circle's angular radius keeps lobe
    #: sampling alone for it; broader ones add area samples of the disc (:meth:`delta_S`). The same
    #: rule for GGX, whose core (half maximum) is 0.77 times Ward's at the same alpha and whose tail
    #: the lobe samples cover anyway (the choice moves noise, never the mean)
    MIS_LOBE_TO_DISC = 1.5
    #: GGX's half-vector tangent (in units of alpha) beyond which exp(-4) = 1.8 % of its ``D cos``
    #: mass lies (``tan^2 = alpha^2 (e^4 - 1)``), as for Ward at ``tan = 2 alpha``: a GGX sample gets a
    #: correction where its mirror ray is within ``2 atan(7.32 alpha)`` of the horizon or below
    #: (Ward: ``4 atan(alpha)``). Far wider than Ward's: the long tail is why GGX is a rung
    GGX_TAIL = float(np.sqrt(np.expm1(4.0)))

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
        self._env_lower4 = self._four_texels(self.env[1])                           # (12, N^2) float32
        self._circle_cells = self._circle_grid()

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

    @staticmethod
    def _four_texels(face: np.ndarray) -> np.ndarray:
        """(12, N^2) table of a face (N, N, 3): for texel (y, x), rows 3c..3c+2 hold the RGB of its
        bilinear corner c = (y, x), (y, x + 1), (y + 1, x), (y + 1, x + 1), clamped to the face (one
        gather per bilinear look-up)."""
        N = face.shape[0]
        i = np.arange(N)
        i1 = np.minimum(i + 1, N - 1)
        c = [face[np.ix_(ys, xs)] for ys in (i, i1) for xs in (i, i1)]
        return np.ascontiguousarray(np.stack(c).reshape(4, N * N, 3).transpose(0, 2, 1).reshape(12, N * N),
                                    dtype=np.float32)

    def _circle_grid(self) -> tuple[float, int, np.ndarray]:
        """Cell side ``h`` (m), cells per side ``m`` and flags (m * m,) of the cells over
        ``[-extent, extent]^2`` that may overlap a circle (centre within radius + half a cell diagonal)."""
        m = int(min(max(2 * self.extent / (0.5 * self.radii.min()), 1), 512))
        h = 2 * self.extent / m
        c = (np.arange(m) + 0.5) * h - self.extent
        gx, gy = np.meshgrid(c, c, indexing="ij")
        xy = np.stack([gx.ravel(), gy.ravel()], 1)
        flags = _circle_mask(xy, self.centres, self.radii + 0.75 * h)
        return h, m, flags

    def delta_D(self, points: np.ndarray, normals: np.ndarray, chunk: int = 2048) -> np.ndarray:
        """``dD`` (P, 3) of points (P, 3) with unit normals (P, 3), white units (module notes).

        The paper part is an octahedral quadrature of the lower hemisphere (``n_quad^2`` directions)
        of ``paper * shadow - L_env``; the circles add ``(L_circle - paper * shadow) cos_p cos_c / r^2 dA``
        over small patches (exact in the limit of small patches, no aliasing of a 5-degree disc).
        """
        P = np.asarray(points, np.float64).reshape(-1, 3)
        N = np.asarray(normals, np.float64).reshape(-1, 3)
        # the scan asks twice for the same points (the RGB pass and its second sweep): 4-5 s each on
        # the demo's 100k points, so the last answer is kept, keyed by the inputs' bytes
        key = hashlib.blake2b(P.tobytes() + N.tobytes(), digest_size=16).digest()
        cached = getattr(self, "_delta_D_last", None)
        if cached is not None and cached[0] == key:
            return cached[1].copy()
        # one BLAS thread: OpenBLAS's second thread halved nothing here (bench sphere, 100k points:
        # 1.2 s either way) but burnt the other core meanwhile, and spun ~0.1 s after it
        from .fusion import blas_threads

        with blas_threads(1):
            out = self._delta_D(P, N, chunk)
        self._delta_D_last = (key, out.copy())
        return out

    def _delta_D(self, P: np.ndarray, N: np.ndarray, chunk: int) -> np.ndarray:
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
                seed: int = 0, n_samples_circle: int = 16, circle_samples: int = 4,
                reference: bool = False, lobe=None) -> np.ndarray:
        """``dS`` (M, 3): the lobe's view of the plane minus its view of the map's lower hemisphere.

        Parameters
        ----------
        points, normals, wo : (M, 3) ndarray
            Sample points (marker frame, m), unit normals, unit directions to the camera.
        alpha : float or (M,) ndarray
            Roughness of each sample's lobe.
        n_samples : int
            Lobe samples per sample: a stratified sqrt(n) x sqrt(n) pattern of Ward half-vector
            sampling (GGX: of its visible normals, weight ``G1(w_i)``), rotated at random per sample
            (unbiased; the noise averages over a point's views and a cluster's points like the sensor's).
        circle_samples : int
            Area samples of each white circle a lobe may reach (the mirror ray within the circle's
            angular radius plus three lobe widths of its centre), combined with the lobe samples by
            multiple importance sampling (power heuristic, Veach 1997 §9.2). A circle is 20 times
            brighter than the paper and a few degrees wide: 4 lobe samples hit it with one sample or
            none, and that noise in S diluted the colour pass's regression of L on S (a glossy
            sphere's equator read a specular slope of 0.09 for 0.28). Uniform points of the disc see
            it every time; the combination is unbiased for any count, and with 4 lobe + 4 area samples
            its noise is below that of the earlier 16 lobe samples (docs/rgb-pass.md §5c).
        n_samples_circle : int
            With ``circle_samples=0``: the lobe samples of the lobes that may reach a circle instead
            (the earlier scheme; 16 gave that equator 0.19, 64 gave 0.25).
        reference : bool
            Run the original per-ray implementation (:meth:`_delta_S_mc_reference`, the
            ``circle_samples=0`` scheme). With ``circle_samples=0`` the fast path draws the same random
            numbers and agrees with it to float32 rounding (tests).
        lobe : None, str or (M,) array_like of str
            Each sample's specular lobe, "ward" or "ggx" (:data:`appfusion.brdf.LOBES`; "diffuse"
            counts as "ward"). None: all Ward (the same numbers as without GGX support).

        Only samples whose mirror direction lies within ~4 lobe widths of the horizon or below get a
        correction (Ward: ``4 atan(alpha)``; GGX: ``2 atan(GGX_TAIL alpha)``, its long tail); the
        others are 0.

        Returns
        -------
        (M, 3) ndarray
            ``dS`` in white units (radiance x 1/sr x sr), to add to Eq. 5's ``S`` (paper §5.3).
        """
        p = np.asarray(points, np.float64).reshape(-1, 3)
        n = np.asarray(normals, np.float64).reshape(-1, 3)
        v = np.asarray(wo, np.float64).reshape(-1, 3)
        al = np.broadcast_to(np.asarray(alpha, np.float64), (len(p),))
        gx = ggx_rows(lobe, len(p), "delta_S")                             # (M,) bool or None
        out = np.zeros((len(p), 3))
        if len(p) == 0:
            return out
        cos_o = n[:, 0] * v[:, 0] + n[:, 1] * v[:, 1] + n[:, 2] * v[:, 2]
        rz = 2 * cos_o * n[:, 2] - v[:, 2]                                   # mirror ray's z
        atan_a = np.arctan(al.astype(np.float32))
        reach = np.sin(np.minimum(4 * atan_a, np.float32(np.pi / 2)))
        if gx is not None:
            tail = 2 * np.arctan(np.float32(self.GGX_TAIL) * al.astype(np.float32))
            reach = np.where(gx, np.sin(np.minimum(tail, np.float32(np.pi / 2))), reach)
        i = np.flatnonzero((rz < reach) & (cos_o > 1e-3) & (p[:, 2] > 0))
        if len(i) == 0:
            return out
        # which lobes may see a circle: the mirror ray within the circle's angular radius plus three
        # lobe widths of the direction to its centre
        f32 = np.float32
        px, py, pz = (p[i, c].astype(f32) for c in range(3))
        co2 = 2 * cos_o[i]
        rx, ry, rz = ((co2 * n[i, c] - v[i, c]).astype(f32) for c in range(3))     # mirror rays (m,)
        w3 = 3 * atan_a[i] + f32(0.02)
        if gx is not None:
            # a GGX lobe's tail reaches a circle from far off: rare lobe rays that hit one (20 times the
            # paper) made dS heavy-tailed (a glossy sphere's underside split off as "less specular" by the
            # regression dilution), so GGX lobes area-sample every circle within their tail's reach
            w3 = np.where(gx[i], np.minimum(tail[i], f32(np.pi)) + f32(0.02), w3).astype(f32)
        near_c = np.empty((len(self.radii), len(i)), bool)                  # (C, m)
        sharp_c = np.empty((len(self.radii), len(i)), bool)                 # lobe narrower than the disc
        lobe = 2 * atan_a[i]                                                 # ~ the lobe's angular radius
        for c, (cen, rad) in enumerate(zip(self.centres.astype(f32), self.radii.astype(f32))):
            dx, dy, dz = cen[0] - px, cen[1] - py, cen[2] - pz
            dist = np.maximum(np.sqrt(dx * dx + dy * dy + dz * dz), f32(1e-9))
            cos_c = (dx * rx + dy * ry + dz * rz) / dist
            # angle to the centre <= rad / dist + w3, as cosines (arccos is decreasing; 5x cheaper)
            near_c[c] = cos_c >= np.cos(np.minimum(rad / dist + w3, f32(np.pi)))
            sharp_c[c] = lobe < self.MIS_LOBE_TO_DISC * rad / dist
        rng = np.random.default_rng(seed)
        if not (reference or circle_samples <= 0):
            # lobes narrower than a disc they may reach keep the lobe samples alone (n_samples_circle);
            # the others sample their discs too
            sharp = (near_c & sharp_c).any(axis=0)
            near_c[:, sharp] = False
            self._delta_S_mc(p, n, v, al, i[sharp], max(n_samples, n_samples_circle), rng, out, ggx=gx)
            i = i[~sharp]
            near_c = near_c[:, ~sharp]
        if reference or circle_samples <= 0:
            near = near_c.any(axis=0)
            self._delta_S_mc(p, n, v, al, i[~near], n_samples, rng, out, reference, ggx=gx)
            self._delta_S_mc(p, n, v, al, i[near], max(n_samples, n_samples_circle), rng, out, reference, ggx=gx)
            return out
        k = max(int(round(math.sqrt(n_samples))), 1)
        k2 = max(int(round(math.sqrt(circle_samples))), 1)
        bits = np.zeros(len(i), np.int64)                                     # (m,) circles with area samples
        for c in range(len(near_c)):
            bits |= near_c[c].astype(np.int64) << c
        self._delta_S_mc(p, n, v, al, i, k * k, rng, out, mis=(bits, k2 * k2), ggx=gx)
        pc, ps = np.nonzero(near_c)                                           # (circle, sample) pairs
        if len(ps):
            s = i[ps]
            ru, rw = self._rotations(rng, len(s), k2 * k2)
            args = [np.take(x, s, axis=0) for x in (p, n, v, al)]
            gs = None if gx is None else gx[s]
            if gs is None or not gs.any():
                dS = self._circle_mc(*args, pc, k2, ru, rw, k * k)
            else:
                dS = np.empty((len(s), 3))
                for sel, lb in ((~gs, False), (gs, True)):
                    if sel.any():
                        dS[sel] = self._circle_mc(*(x[sel] for x in args), pc[sel], k2, ru[sel], rw[sel], k * k,
                                                  ggx=lb)
            for c in range(3):
                out[:, c] += np.bincount(s, weights=dS[:, c], minlength=len(p))
        return out

    @staticmethod
    def _rotations(rng, count: int, n_rays: int) -> tuple[np.ndarray, np.ndarray]:
        """The per-sample random shifts (count,) of the stratified pattern: ``r1`` (of the ``tan^2``
        strata, scaled by 1/k) and ``r2`` (of the azimuth), drawn in chunks of ~16k lobe rays."""
        r1, r2 = np.empty(count), np.empty(count)
        chunk = max(4096 * 4 // n_rays, 64)
        for s in range(0, count, chunk):
            m = min(chunk, count - s)
            r1[s:s + m] = rng.random(m)
            r2[s:s + m] = rng.random(m)
        return r1, r2

    def _delta_S_mc(self, p, n, v, al, idx, n_samples, rng, out, reference: bool = False, mis=None,
                    ggx=None) -> None:
        """Stratified lobe sampling of ``dS`` for the samples ``idx`` (written into ``out``).

        ``k = round(sqrt(n_samples))``; sample ``m`` takes the ``k x k`` half vectors
        ``u1 = (i + 0.5 + r1_m) / k mod 1``, ``u2 = (j + 0.5) / k + r2_m mod 1`` of Walter's Ward
        sampling (``tan^2 theta_h = -alpha^2 log u1``, ``phi_h = 2 pi u2``), reflects ``w_o`` about them
        and averages ``(L_plane - L_env)(w_i) f cos_i / pdf`` (white units). ``reference=True`` runs the
        original per-ray implementation (:meth:`_delta_S_mc_reference`) on the same shifts. ``mis``:
        ``(bits, n2)``, per sample of ``idx`` the circles (bit c) that also get ``n2`` area samples
        (:meth:`_circle_mc`); a ray that hits one of them weighs the circle's excess over the paper by
        the power heuristic ``(k^2 p_lobe)^2 / ((k^2 p_lobe)^2 + (n2 p_area)^2)``. ``ggx``: (M,) bool
        over all samples (None: none), the samples whose lobe is GGX: the same ``(u1, u2)`` strata
        drive its visible-normal sampling (:meth:`_lobe_mc_ggx`).
        """
        if len(idx) == 0:
            return
        k = max(int(round(math.sqrt(n_samples))), 1)
        r1, r2 = self._rotations(rng, len(idx), k * k)
        if reference:
            self._delta_S_mc_reference(p, n, v, al, idx, k, r1, r2, out, ggx)
            return
        chunk = max(32768 // (k * k), 64)                                     # ~32k lobe rays at a time
        P, N, V, A = (np.take(x, idx, axis=0) for x in (p, n, v, al))
        G = None if ggx is None else ggx[idx]
        for s in range(0, len(idx), chunk):
            c = slice(s, s + chunk)
            mj = None if mis is None else (mis[0][c], mis[1])
            if G is None or not G[c].any():
                out[idx[c]] = self._lobe_mc(P[c], N[c], V[c], A[c], k, r1[c], r2[c], mj)
                continue
            gc = G[c]
            for sel, est in ((~gc, self._lobe_mc), (gc, self._lobe_mc_ggx)):
                if sel.any():
                    ms = None if mj is None else (mj[0][sel], mj[1])
                    out[idx[c][sel]] = est(P[c][sel], N[c][sel], V[c][sel], A[c][sel], k, r1[c][sel], r2[c][sel], ms)

    def _mis_excess(self, mis, smp, hit, hc, exc, t, p, K, p_lobe_of):
        """The lobe rays' share of a circle's excess that the circle's area samples carry instead.

        ``mis = (bits, n2)`` as in :meth:`_delta_S_mc`; ``hit`` (h,) the rays (of the flat ray arrays)
        that hit circle ``hc`` at distance ``t`` with excess radiance ``exc`` (3, h); ``smp`` the sample of
        each ray; ``K`` lobe rays per sample and ``p_lobe_of(hit, hs)`` the lobe pdf of those rays. For
        the rays whose circle is area-sampled: their indices and ``(1 - w_lobe) exc`` (3, u) with the power
        heuristic ``w_lobe = (K p_lobe)^2 / ((K p_lobe)^2 + (n2 p_area)^2)`` (Veach 1997 §9.2); None if none."""
        bits, n2 = mis
        hs = smp[hit]
        use = (bits[hs] >> hc) & 1 == 1
        if not use.any():
            return None
        hit, hs, hc, exc = hit[use], hs[use], hc[use], exc[:, use]
        p_lobe = p_lobe_of(hit, hs)
        p_area = t[hit].astype(np.float64) ** 3 / (np.pi * self.radii[hc] ** 2 * p[hs, 2])
        w_lobe = (K * p_lobe) ** 2 / ((K * p_lobe) ** 2 + (n2 * p_area) ** 2)
        return hit, (1.0 - w_lobe) * exc

    def _lobe_mc(self, p, n, v, a, k, r1, r2, mis=None) -> np.ndarray:
        """The ``k x k`` stratified lobe estimate of ``dS`` (m, 3), white units, for samples with points
        ``p`` (m, 3, m above the plane), unit normals ``n`` and views ``v`` (m, 3, ``n.v > 1e-3``),
        Ward ``a`` (m,) and pattern shifts ``r1``, ``r2`` (m,); ``mis`` as in :meth:`_delta_S_mc`.

        The estimator of :meth:`_delta_S_mc_reference`, per ray without the BRDF calls: ``log``,
        ``sqrt`` run on a sample's k distinct ``u1`` and ``cos``/``sin`` on its k azimuths; ray (i, j)'s
        half vector is ``h = sin(theta_i) e_j + cos(theta_i) n`` with ``e_j`` the world azimuth vector,
        so ``w_o.h``, ``cos_i = 2 (w_o.h) cos(theta_h) - cos_o`` and ``w_i.z`` are two products each; the
        weight ``f cos_i / pdf`` of Walter's half-vector sampling is ``cos_h^3 (w_o.h) sqrt(cos_i /
        cos_o)`` (the lobe's exponential cancels); only rays with ``cos_i > 0`` that go down
        (``w_i.z < -1e-6``) meet the plane and the map. Arrays are (k, m), (k, k, m) and (C, Q): the
        sample (or ray) index last, so numpy's inner loops run over it; float32 per ray.
        """
        m = len(p)
        K = k * k
        f32 = np.float32
        g = (np.arange(k) + 0.5)[:, None] / k
        u1 = g + r1[None, :] / k                                                 # (k, m), in [0, 2)
        u1 -= u1 >= 1.0                                                          # mod 1 (exact)
        tan2 = -(a * a)[None, :] * np.log(np.maximum(u1, 1e-12))
        ch = 1.0 / np.sqrt(1.0 + tan2)                                          # cos theta_h (k, m)
        sh = np.sqrt(np.maximum(1.0 - ch * ch, 0.0))
        # the rest per sample in float32 (SIMD cos / sin; the rays are float32 anyway):
        # cos / sin of phi_j = 2 pi (j + 0.5) / k + 2 pi r2 by the angle sum (one cos, sin per sample)
        phi0 = (2 * np.pi * r2).astype(f32)
        c0, s0 = np.cos(phi0), np.sin(phi0)
        cg, sg_ = np.cos(2 * np.pi * g).astype(f32), np.sin(2 * np.pi * g).astype(f32)   # (k, 1)
        cp, sp = cg * c0 - sg_ * s0, sg_ * c0 + cg * s0                           # (k, m)
        # the normal's tangent frame (t, b) of brdf.local_frame (Duff et al. 2017), componentwise (m,)
        n32, v32 = n.astype(f32), v.astype(f32)
        nx, ny, nz = n32[:, 0], n32[:, 1], n32[:, 2]
        vx, vy, vz = v32[:, 0], v32[:, 1], v32[:, 2]
        sg = np.where(nz >= 0, f32(1.0), f32(-1.0))
        aa = f32(-1.0) / (sg + nz)
        bb = nx * ny * aa
        tx, ty, tz = 1 + sg * nx * nx * aa, sg * bb, -sg * nx
        bx, by, bz = bb, sg + ny * ny * aa, -ny
        co32 = nx * vx + ny * vy + nz * vz
        # azimuth vectors e_j = cos(phi_j) t + sin(phi_j) b, world, per component (k, m)
        ex = cp * tx + sp * bx
        ey = cp * ty + sp * by
        ez = cp * tz + sp * bz
        ev = cp * (tx * vx + ty * vy + tz * vz) + sp * (bx * vx + by * vy + bz * vz)   # e_j . w_o
        sh32, ch32 = sh.astype(f32), ch.astype(f32)
        # ray (i, j): axis 0 = i (theta_h), axis 1 = j (azimuth), axis 2 = sample
        oh = sh32[:, None, :] * ev[None, :, :]
        oh += (ch32 * co32)[:, None, :]                                          # w_o . h (k, k, m)
        ci = oh * (2 * ch32)[:, None, :]
        ci -= co32                                                              # w_i . n
        wz = sh32[:, None, :] * ez[None, :, :]
        wz += (ch32 * nz)[:, None, :]                                            # h.z, world
        wz *= 2 * oh
        wz -= vz                                                                # w_i.z, world
        q = np.flatnonzero((ci > COS_EPS) & (wz < -1e-6))
        if len(q) == 0:
            return np.zeros((m, 3))
        smp = q % m
        ij = q // m
        si = (ij // k) * m + smp                                                  # (i, sample)
        sj = (ij % k) * m + smp                                                   # (j, sample)
        oh, ci, wz = oh.reshape(-1).take(q), ci.reshape(-1).take(q), wz.reshape(-1).take(q)
        shq, chq = sh32.reshape(-1).take(si), ch32.reshape(-1).take(si)
        per = np.take(np.stack([p[:, 0].astype(f32), p[:, 1].astype(f32), p[:, 2].astype(f32), vx, vy, nx, ny,
                                co32]), smp, axis=1)                              # (8, Q)
        wx = 2 * oh * (shq * ex.reshape(-1).take(sj) + chq * per[5]) - per[3]
        wy = 2 * oh * (shq * ey.reshape(-1).take(sj) + chq * per[6]) - per[4]
        wgt = chq * chq * chq * oh * np.sqrt(ci / per[7])
        dL, hit, hc, exc, t = self._delta_radiance_down(per[0], per[1], per[2], wx, wy, wz)   # (3, Q), hits
        if mis is not None and len(hit):
            # Walter's pdf of the ray; its exp(-tan^2 theta_h / a^2) is u1
            got = self._mis_excess(mis, smp, hit, hc, exc, t, p, K, lambda hit, hs: u1.reshape(-1)[si[hit]] / (
                4 * np.pi * a[hs] * a[hs] * chq[hit].astype(np.float64) ** 3 * oh[hit].astype(np.float64)))
            if got is not None:
                dL[:, got[0]] -= got[1].astype(f32)
        out = np.empty((m, 3))
        for c in range(3):
            out[:, c] = np.bincount(smp, weights=wgt * dL[c], minlength=m)
        return out / K

    def _lobe_mc_ggx(self, p, n, v, a, k, r1, r2, mis=None) -> np.ndarray:
        """The ``k x k`` stratified estimate of ``dS`` (m, 3), white units, for GGX samples (arguments
        as :meth:`_lobe_mc`, ``a`` the GGX roughness): ray (i, j) draws GGX's visible normals
        (:func:`appfusion.brdf.sample_ggx`) at ``u1 = (i + 0.5 + r1) / k mod 1``, ``u2 = (j + 0.5) / k
        + r2 mod 1`` and weighs ``(L_plane - L_env)(w_i)`` by ``f cos_i / pdf = G1(w_i)``; rays with
        ``cos_i > 0`` that go down meet the plane. ``mis`` as in :meth:`_delta_S_mc`, with the lobe's
        density ``G1(w_o) D(h) / (4 cos_o)``. Float64, arrays (m, k^2) (GGX clusters are the few).
        """
        m = len(p)
        K = k * k
        g = (np.arange(k) + 0.5) / k
        u1 = g[None, :, None] + r1[:, None, None] / k                             # (m, k, 1): i
        u1 -= u1 >= 1.0
        u2 = g[None, None, :] + r2[:, None, None]                                  # (m, 1, k): j
        u2 -= u2 >= 1.0
        u1, u2 = (np.broadcast_to(x, (m, k, k)).reshape(m, K) for x in (u1, u2))
        F = local_frame(n)
        vl = np.einsum("mij,mj->mi", F, v)
        wi_l, _, pdf = sample_ggx(a[:, None], vl[:, None, :], u1, u2)           # (m, K, 3), (m, K)
        ci = wi_l[..., 2]
        wz = np.einsum("mj,mkj->mk", F[:, :, 2], wi_l)                           # w_i.z, world
        q = np.flatnonzero((ci > COS_EPS) & (wz < -1e-6))
        if len(q) == 0:
            return np.zeros((m, 3))
        smp = q // K
        wl = wi_l.reshape(-1, 3)[q]
        wx = np.einsum("qj,qj->q", F[smp, :, 0], wl)
        wy = np.einsum("qj,qj->q", F[smp, :, 1], wl)
        wgt = ggx_g1(a[smp], ci.reshape(-1)[q])
        dL, hit, hc, exc, t = self._delta_radiance_down(p[smp, 0], p[smp, 1], p[smp, 2], wx, wy,
                                                        wz.reshape(-1)[q])
        dL = dL.astype(np.float64)
        if mis is not None and len(hit):
            got = self._mis_excess(mis, smp, hit, hc, exc, t, p, K, lambda hit, hs: pdf.reshape(-1)[q[hit]])
            if got is not None:
                dL[:, got[0]] -= got[1]
        out = np.empty((m, 3))
        for c in range(3):
            out[:, c] = np.bincount(smp, weights=wgt * dL[c], minlength=m)
        return out / K

    def _circle_mc(self, p, n, v, a, c, k2, ru, rw, n_lobe, ggx: bool = False) -> np.ndarray:
        """Area samples of circle ``c`` (P,) for samples (points ``p``, normals ``n``, views ``v``:
        (P, 3); Ward ``a`` (P,)): the circle's excess over the paper, ``int_disc (L_circle - L_paper)
        shadow f cos_i cos_c / r^2 dA`` (white units, (P, 3)), by ``k2 x k2`` stratified uniform points
        of the disc (``rho = R sqrt(u)``, ``psi = 2 pi w``; ``u`` shifted by ``ru / k2``, ``w`` by ``rw``),
        each weighed against the ``n_lobe`` lobe samples by the power heuristic, ``f cos_i a_a / (a_l^2 +
        a_a^2)`` with ``a_l = n_lobe p_lobe``, ``a_a = k2^2 p_area``: ``p_area = r^3 / (A p_z)`` per steradian, ``p_lobe`` Walter's Ward pdf. Points of
        the disc beyond ``extent_m`` add nothing (the map is kept there). Arrays (k2, k2, P), float32
        per area sample (the estimate is summed in float64). ``ggx``: the samples' lobe is GGX (``a``
        its roughness): ``f`` is :func:`appfusion.brdf.ggx_half`, ``p_lobe`` the visible-normal density
        ``G1(w_o) D(h) / (4 cos_o)`` of :meth:`_lobe_mc_ggx`."""
        P = len(p)
        n2 = k2 * k2
        f32 = np.float32
        g = (np.arange(k2) + 0.5)[:, None] / k2
        uu = g + ru[None, :] / k2
        uu -= uu >= 1.0
        ww = g + rw[None, :]
        ww -= ww >= 1.0
        R = self.radii[c]
        rho = (R * np.sqrt(uu)).astype(f32)                                    # (k2, P)
        psi = (2 * np.pi * ww).astype(f32)
        x = (self.centres[c, 0].astype(f32) + rho[:, None, :] * np.cos(psi)[None, :, :]).reshape(n2, P)
        y = (self.centres[c, 1].astype(f32) + rho[:, None, :] * np.sin(psi)[None, :, :]).reshape(n2, P)
        p, n, v, a = p.astype(f32), n.astype(f32), v.astype(f32), a.astype(f32)
        nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
        vx, vy, vz = v[:, 0], v[:, 1], v[:, 2]
        dx, dy, dz = x - p[:, 0], y - p[:, 1], -p[:, 2]
        r = np.sqrt(dx * dx + dy * dy + dz * dz)
        wx, wy, wz = dx / r, dy / r, dz / r
        ci = nx * wx + ny * wy + nz * wz
        co = nx * vx + ny * vy + nz * vz
        hx, hy, hz = wx + vx, wy + vy, wz + vz
        hn = np.sqrt(hx * hx + hy * hy + hz * hz)
        ch = (nx * hx + ny * hy + nz * hz) / hn
        oh = (vx * hx + vy * hy + vz * hz) / hn
        ok = (ci > COS_EPS) & (ch > COS_EPS) & (oh > 0) & (x * x + y * y <= f32(self.extent ** 2))
        chs = np.where(ok, ch, f32(1.0))
        if ggx:
            ci_ = np.where(ok, ci, f32(1.0)).astype(np.float64)
            co_ = co.astype(np.float64)
            f_cos = np.where(ok, ggx_half(a, chs, ci_, co_) * ci_, 0.0)                  # f cos_i (1/sr)
            p_lobe = ggx_g1(a, co_) * ggx_d(a, chs) / (4.0 * co_)
        else:
            a2 = a * a
            c2 = chs * chs
            E = np.exp(-(1.0 - c2) / (c2 * a2))
            f_cos = E / (f32(4 * np.pi) * a2) * np.sqrt(np.where(ok, ci, f32(0.0)) / co)   # f cos_i (1/sr)
            p_lobe = E / (f32(4 * np.pi) * a2 * c2 * chs * np.where(ok, oh, f32(1.0)))
        p_area = r * r * r / (f32(np.pi * R * R) * p[:, 2])
        a_l, a_a = f32(n_lobe) * p_lobe, f32(n2) * p_area
        w = np.where(ok, f_cos * a_a / (a_l * a_l + a_a * a_a), f32(0.0))          # (n2, P)
        if self.shadow is not None:
            w = w * self._shadow_at(np.stack([x.ravel(), y.ravel()], 1)).reshape(n2, P)
        return w.sum(axis=0, dtype=np.float64)[:, None] * (self.circle - self.paper)[None, :]

    def _delta_radiance_down(self, px, py, pz, wx, wy, wz):
        """:meth:`delta_radiance` (3, Q), float32, for rays known to go down (``wz < -1e-6``) from points
        ``(px, py, pz)`` (Q,) above the plane. Circles are tested exactly only on the rays whose hit
        point lies in a cell of :attr:`_circle_cells` that may overlap one; the map is read on its
        lower face only (bilinear, as :func:`appfusion.octahedral.sample_sphere_map`, from its
        four-texel table).

        Also returns the rays that hit a circle: their indices (H,), circle (H,), the circle's excess
        over the paper there ``(L_circle - L_paper) shadow`` (3, H), and every ray's length to the
        plane ``t`` (Q,), metres."""
        t = -pz / wz
        x = px + t * wx
        y = py + t * wy
        out = np.zeros((3, len(t)), np.float32)
        none = np.zeros(0, np.int64)
        i = np.flatnonzero(x * x + y * y <= np.float32(self.extent ** 2))
        if len(i) == 0:
            return out, none, none, np.zeros((3, 0)), t
        x, y, dx, dy, dz = x[i], y[i], wx[i], wy[i], wz[i]
        h, m_c, cells = self._circle_cells
        cx = np.clip(((x + np.float32(self.extent)) * np.float32(1.0 / h)).astype(np.int64), 0, m_c - 1)
        cy = np.clip(((y + np.float32(self.extent)) * np.float32(1.0 / h)).astype(np.int64), 0, m_c - 1)
        cand = np.flatnonzero(cells[cx * m_c + cy])
        hit, hc = none, none
        if len(cand):
            xy_c = np.stack([x[cand], y[cand]], 1).astype(np.float64)
            inside = np.sum((xy_c[:, None, :] - self.centres[None, :, :2]) ** 2, axis=-1) <= self.radii ** 2
            on = inside.any(axis=1)
            hit, hc = cand[on], np.argmax(inside[on], axis=1)                   # (H,) rows of i, circle
        ex = (self.circle - self.paper)[:, None]
        if self.shadow is None:
            plane = np.broadcast_to(self.paper.astype(np.float32)[:, None], (3, len(i)))
            exc = np.broadcast_to(ex, (3, len(hit)))
        else:
            sh = self._shadow_at(np.stack([x, y], 1).astype(np.float64))
            plane = (self.paper[:, None] * sh).astype(np.float32)
            exc = ex * sh[hit]
        if len(hit):
            plane = plane.copy()
            plane[:, hit] += exc.astype(np.float32)
        N = self.env.shape[1]
        s = np.abs(dx) + np.abs(dy) - dz
        ux, uy = dx / s, dy / s
        fx = (ux + uy + 1.0) * np.float32(0.5 * N) - np.float32(0.5)
        fy = (ux - uy + 1.0) * np.float32(0.5 * N) - np.float32(0.5)
        x0 = np.clip(np.floor(fx).astype(np.int64), 0, N - 1)
        y0 = np.clip(np.floor(fy).astype(np.int64), 0, N - 1)
        ax = np.clip(fx - x0, 0.0, 1.0)
        ay = np.clip(fy - y0, 0.0, 1.0)
        c4 = np.take(self._env_lower4, y0 * N + x0, axis=1)                      # (12, Q'): corner, channel
        top = c4[0:3] + (c4[3:6] - c4[0:3]) * ax
        bot = c4[6:9] + (c4[9:12] - c4[6:9]) * ax
        out[:, i] = plane - (top + (bot - top) * ay)
        return out, i[hit], hc, exc, t

    def _delta_S_mc_reference(self, p, n, v, al, idx, k, r1, r2, out, ggx=None) -> None:
        """The original per-ray implementation of :meth:`_delta_S_mc` (sample_ward, ward, delta_radiance
        on every ray; for the samples ``ggx`` (M,) bool, sample_ggx and ggx), kept as the reference the
        tests hold the fast path to."""
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
            uu1 = (u1[None, :] + r1[s:s + chunk, None] / k) % 1.0
            uu2 = (u2[None, :] + r2[s:s + chunk, None]) % 1.0
            vlk = np.broadcast_to(vl[:, None, :], (m, len(u1), 3))
            wi, vh, pdf = sample_ward(a, vlk, uu1, uu2)                            # (m, K, 3), (m, K), (m, K)
            gj = None if ggx is None else ggx[j]
            if gj is not None and gj.any():
                wi[gj], vh[gj], pdf[gj] = sample_ggx(a[gj], vlk[gj], uu1[gj], uu2[gj])
            ci = wi[..., 2]
            f = lobe_rows(a, wi, vlk, gj)
            wgt = np.where((ci > 0) & (vh > 0), f * ci / np.maximum(pdf, 1e-300), 0.0)
            wi_w = np.einsum("mji,mkj->mki", F, wi)
            dL = self.delta_radiance(np.repeat(p[j], len(u1), 0), wi_w.reshape(-1, 3)).reshape(m, len(u1), 3)
            out[j] = np.einsum("mk,mkc->mc", wgt, dL) / len(u1)
