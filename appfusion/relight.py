"""Relighting: render a captured object under any environment map from any view.

Solves the rendering equation (paper Eq. 2) with the captured reflectance of Eq. 1,

    L(w_o) = integral L_env(w) f_r(w, w_o) (n . w)+ V(w) dw,    f_r = rho_d / pi + rho_s f(alpha; w, w_o),

with the environment split, in the spirit of EnvyDepth (seed 003: an environment map turned into
lights), into compact very bright *emitters* and the smooth *rest*, ``L_env = sum_e L_e + L_rest``
(:class:`EnvSampler`), and each part integrated the way that suits it:

- an emitter (a connected set of texels far brighter than the map's mean: a sun) is an explicit light,
  a fitted constant-radiance disc where it is round (else its texels), integrated by a deterministic
  midpoint rule over cells of the disc, one shadow ray per cell and point:
  ``sum_k L_k f_r(w_k, w_o) (n . w_k)+ V(w_k) dw_k``;
- the rest by Monte Carlo with multiple importance sampling (balance heuristic) of two strategies, the
  map (texels chosen in proportion to luminance x solid angle) and the BRDF (cosine lobe for the diffuse
  part, for the specular part Ward's half-vector distribution or, for a GGX point, GGX's distribution
  of visible normals (:func:`sample_ggx`), chosen in proportion to their albedos),
  stratified per point; its diffuse part uses the rest's unshadowed irradiance ``E(n)`` (a table) as a
  control variate, so Monte Carlo only estimates what the occluders take away.

Why: the synthetic scanner's ``sunset`` sun (a disc of 1.5 degrees half-angle, radiance 3000) holds half
the map's energy in ~40 of its 131072 texels, and its glossy highlight (~50 times the diffuse radiance)
dominates the L2 norm of a relit image. Monte Carlo over the whole map left 7.3 % relative RMSE on the
demo's references with the *truth* reflectance and geometry; the split renderer leaves 1.2 % of which
0.45 % is its own noise at 64 samples (docs/performance.md, "Relighting accuracy").

Visibility V (self-shadowing) is traced against the object's own mesh with Open3D's RaycastingScene.
Unlike the capture passes, which ignore visibility as the paper does (§3), relighting can afford it.
The same model as the engine (:mod:`appfusion.brdf`): each point's specular lobe is the one its
cluster's model names (Ward, or GGX for the model ladder's third rung; :data:`appfusion.brdf.LOBES`).
"""

from __future__ import annotations

import numpy as np

from . import octahedral as oc
from .brdf import ggx_pdf, ggx_rows, lobe_rows, local_frame, sample_ggx, sample_ward, ward, ward_pdf
from .errors import AppFusionError
from .frame import REC709_LUMA, Intrinsics
from .result import ScanResult


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ REC709_LUMA


class EnvSampler:
    """An environment map split into explicit emitters plus a rest importance-sampled by luminance.

    ``env = rest + emitters`` texel by texel. Emitters: the texels brighter than ``emitter_ratio`` times
    the map's mean luminance, in 8-connected sets per octahedral face, each grown by ``grow`` texels
    (the anti-aliased fringe); inside such a region the rest keeps ``min(env, fill)``, ``fill`` the
    per-channel median of the ring of texels around it (the sky behind the sun), and the emitter takes
    the excess. A round emitter is then replaced by a *disc* of constant radiance with the same energy
    ``E = sum L dw``, centred at its luminance-weighted mean direction, of solid angle ``E / L_peak``
    (a blur keeps the energy and, for a disc wider than the blur, the plateau ``L_peak``): the map's
    texels smear a sharp sun over about a texel more (the lat-long raster, the resampling), which shows
    in a sharp glossy highlight (2.7 % error in a grazing highlight of the demo, 0.7 % with the disc).
    For the ``sunset`` map at 2 x 256^2 the fit gives a radius of 1.502 degrees (truth 1.5), radiance
    2997 (truth 3000) and the direction within 0.007 degrees.

    Parameters
    ----------
    env : (2, N, N, 3) array_like
        Octahedral environment map (:mod:`appfusion.octahedral`), linear RGB radiance (any units, >= 0).
    emitter_ratio : float
        Seeds of emitters: texels whose luminance exceeds ``emitter_ratio`` times the map's mean
        luminance (``sum L dw / 4 pi``). The default 50 picks the ``sunset`` sun (~3000x the mean)
        and leaves the office's ceiling panels (~16x, 0.12 sr each, smooth enough for Monte Carlo)
        to the rest. ``np.inf`` disables the split.
    grow : int
        Texels by which each set of seed texels is grown.
    max_texels : int
        Budget of emitter texels: emitters are taken in order of energy while they fit; the others
        stay in the rest.
    disc : bool
        Fit discs to round emitters (ratio of the principal second moments below 1.5, total second
        moment below ``r^2``, twice that of a disc of radius ``r``); False keeps every emitter's texels.

    Attributes
    ----------
    env : (2, N, N, 3) float64
        The full map.
    rest : (2, N, N, 3) float64
        The map less its emitters.
    em_dirs : (K, 3) float64, em_omega : (K,) float64, em_radiance : (K, 3) float64, em_id : (K,) int64
        Emitter texels: centre direction, solid angle (sr), radiance ``env - rest`` and emitter index.
    emitters : list of dict
        Per emitter: ``texels``, ``solid_angle_sr`` (of its texels), ``energy`` ((3,) ``sum L dw``),
        ``direction`` (unit), ``energy_fraction`` (of the whole map's luminance energy), ``model``
        ("disc" or "texels"); a disc also has ``radius_rad`` and ``disc_radiance`` (3,).
    p, cdf : (2 N^2,) float64
        Texel probabilities of the rest's sampling (luminance x solid angle).
    rest_black : bool
        The rest has no energy (a map of emitters only): no Monte Carlo at all.
    """

    def __init__(self, env: np.ndarray, emitter_ratio: float = 50.0, grow: int = 2, max_texels: int = 1024,
                 disc: bool = True):
        env = np.asarray(env, np.float64)
        if env.ndim != 4 or env.shape[0] != 2 or env.shape[1] != env.shape[2] or env.shape[3] != 3:
            raise AppFusionError(f"environment map must have shape (2, N, N, 3), got {env.shape}")
        if not np.all(np.isfinite(env)) or np.any(env < 0):
            raise AppFusionError("environment map has negative or non-finite radiance")
        self.env = env
        self.n = env.shape[1]
        self.omega = oc.sphere_solid_angles(self.n).ravel()
        lum = np.maximum(_luminance(env.reshape(-1, 3)), 0)
        total = float((lum * self.omega).sum())
        if total <= 0:
            raise AppFusionError("environment map is black: nothing to light the object with")
        self.rest, ids = self._split(env, lum.reshape(2, self.n, self.n), total, emitter_ratio, grow, max_texels)
        sel = np.nonzero(ids.ravel() >= 0)[0]
        self.em_index = sel
        self.em_dirs = oc.sphere_directions(self.n).reshape(-1, 3)[sel]
        self.em_omega = self.omega[sel]
        self.em_radiance = (env - self.rest).reshape(-1, 3)[sel]
        self.em_id = ids.ravel()[sel]
        self.emitters = []
        for e in range(int(ids.max()) + 1 if len(sel) else 0):
            k = self.em_id == e
            self.emitters.append(self._fit(self.em_dirs[k], self.em_omega[k], self.em_radiance[k], total, disc))
        self._sub_cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        w = np.maximum(_luminance(self.rest.reshape(-1, 3)), 0) * self.omega
        rest_total = float(w.sum())
        self.rest_black = rest_total <= 0
        # a black rest (the map is emitters only) contributes nothing; any valid pdf then does
        self.p = w / rest_total if not self.rest_black else self.omega / self.omega.sum()
        self.cdf = np.cumsum(self.p)
        self.cdf[-1] = 1.0

    @staticmethod
    def _fit(d, om, L, total, disc):
        """Describe one emitter from its texels (directions (k, 3), solid angles (k,), radiance (k, 3))
        and fit a disc to it where it is round (see the class notes); ``total``: the map's luminance
        energy."""
        lum = np.maximum(_luminance(L), 0)
        en = (L * om[:, None]).sum(0)
        wl = lum * om
        c = (d * wl[:, None]).sum(0)
        c = c / max(np.linalg.norm(c), 1e-300)
        out = {"texels": int(len(om)), "solid_angle_sr": float(om.sum()), "energy": en, "direction": c,
               "energy_fraction": float(_luminance(en) / total), "model": "texels"}
        peak = float(lum.max()) if len(lum) else 0.0
        if not disc or peak <= 0 or wl.sum() <= 0:
            return out
        # the disc: solid angle = energy / plateau radiance (a blur keeps the energy and, for a disc
        # wider than the blur, the plateau), radius from the solid angle
        omega = float(_luminance(en)) / peak
        r = float(np.arccos(np.clip(1 - omega / (2 * np.pi), -1, 1)))
        t = np.cross(c, [0.0, 0.0, 1.0] if abs(c[2]) < 0.9 else [1.0, 0.0, 0.0])
        t /= np.linalg.norm(t)
        b = np.cross(c, t)
        xy = np.stack([d @ t, d @ b], -1)
        cov = (xy[:, :, None] * xy[:, None, :] * wl[:, None, None]).sum(0) / wl.sum()
        ev = np.linalg.eigvalsh(cov)
        # round (ratio of the second moments' principal values; a disc has 1) and compact (the second
        # moment of a disc of radius r is r^2 / 4 per axis: a blurred disc has 1.2-1.5 times r^2 / 2 in
        # all, a ring or scattered texels far more)
        if ev[0] > 0 and ev[1] / ev[0] < 1.5 and ev.sum() < r * r:
            out.update(model="disc", radius_rad=r, disc_radiance=en / omega, tangent=t, bitangent=b)
        return out

    @staticmethod
    def _split(env, lum, total, ratio, grow, max_texels):
        """The rest map and the emitter index of every texel (-1: none), see the class notes."""
        from scipy import ndimage

        n = env.shape[1]
        rest = env.copy()
        ids = np.full((2, n, n), -1, np.int64)
        if not np.isfinite(ratio):
            return rest, ids
        omega = oc.sphere_solid_angles(n)
        hot = lum > ratio * total / (4 * np.pi)
        cands = []
        eight = np.ones((3, 3), bool)
        for f in range(2):
            lab, k = ndimage.label(hot[f], structure=eight)
            for c in range(1, k + 1):
                region = ndimage.binary_dilation(lab == c, structure=eight, iterations=max(grow, 0))
                ring = ndimage.binary_dilation(region, structure=eight) & ~region & ~hot[f]
                cands.append((float((lum[f] * omega[f])[region].sum()), f, region, ring))
        used = 0
        for _, f, region, ring in sorted(cands, key=lambda c: -c[0]):
            region = region & (ids[f] < 0)
            cnt = int(region.sum())
            if cnt == 0 or used + cnt > max_texels:
                continue
            fill = np.median(rest[f][ring], axis=0) if ring.any() else np.zeros(3)
            rest[f][region] = np.minimum(rest[f][region], fill)
            ids[f][region] = int(ids.max()) + 1
            used += cnt
        return rest, ids

    def sample(self, u: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Importance-sample the rest: directions (M, 3) and their solid-angle pdf (M,) (1/sr) for
        uniforms ``u`` (M,) in [0, 1) (texel by the CDF of ``p``, then uniform in the texel's (u, v))."""
        idx = np.minimum(np.searchsorted(self.cdf, u, side="right"), len(self.cdf) - 1)
        n = self.n
        face, rem = np.divmod(idx, n * n)
        row, col = np.divmod(rem, n)
        jit = rng.random((len(u), 2))
        uv = np.stack([(col + jit[:, 0]) * 2.0 / n - 1, (row + jit[:, 1]) * 2.0 / n - 1], axis=1)
        d = oc.sphere_decode(face, uv)
        return d, self.pdf(d)

    def pdf(self, d: np.ndarray) -> np.ndarray:
        """Solid-angle pdf (1/sr) of drawing direction ``d`` (..., 3) with :meth:`sample`.

        Within a texel the sample is uniform in (u, v), so the density is the texel probability times
        the local Jacobian dA/domega = 2 |p|^3 over the texel's (u, v) area (2/N)^2.
        """
        i = oc.sphere_texel_index(d, self.n)
        face, uv = oc.sphere_encode(d)
        x, y = 0.5 * (uv[..., 0] + uv[..., 1]), 0.5 * (uv[..., 0] - uv[..., 1])
        z = 1.0 - np.abs(x) - np.abs(y)
        jac = 2.0 * (x * x + y * y + z * z) ** 1.5  # du dv per steradian
        return self.p[i] * jac / (2.0 / self.n) ** 2

    def radiance(self, d: np.ndarray) -> np.ndarray:
        """Radiance of the full map in directions ``d`` (..., 3), bilinear, (..., 3)."""
        return oc.sample_sphere_map(self.env, d)

    def rest_radiance(self, d: np.ndarray) -> np.ndarray:
        """Radiance of the rest (the map less its emitters) in directions ``d`` (..., 3), bilinear, (..., 3)."""
        return oc.sample_sphere_map(self.rest, d)

    def emitter_samples(self, s: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Midpoint quadrature of the emitters at refinement ``s`` (1 for lobes wider than a texel).

        A texel emitter: ``s`` x ``s`` cells per texel (exact Jacobian ``d omega = du dv / (2 |p|^3)``
        at the cell centres, renormalised so that a texel's cells sum to its solid angle), radiance
        piecewise constant per texel. A disc of radius ``r``: ``nr = max(3, ceil(s r / h))`` rings of
        equal width (``h`` the texel angle) x ``4 nr`` sectors, cell centres at the rings' mid solid
        angle, exact cell solid angles ``2 pi (cos r0 - cos r1) / (4 nr)``, constant radiance.

        Returns
        -------
        dirs : (K, 3) unit directions of the cell centres
        domega : (K,) solid angles (sr)
        radiance : (K, 3) emitter radiance of each cell
        """
        s = max(int(s), 1)
        if s not in self._sub_cache:
            n = self.n
            dirs, dws, Ls = [np.zeros((0, 3))], [np.zeros(0)], [np.zeros((0, 3))]
            tex = np.isin(self.em_id, [i for i, e in enumerate(self.emitters) if e["model"] == "texels"])
            if tex.any():
                face, rem = np.divmod(self.em_index[tex], n * n)
                row, col = np.divmod(rem, n)
                o = (np.arange(s) + 0.5) / s
                ou, ov = [a.ravel() for a in np.meshgrid(o, o)]
                uv = np.stack([(col[:, None] + ou) * 2.0 / n - 1, (row[:, None] + ov) * 2.0 / n - 1], -1)
                d = oc.sphere_decode(np.repeat(face[:, None], s * s, 1), uv)
                x, y = 0.5 * (uv[..., 0] + uv[..., 1]), 0.5 * (uv[..., 0] - uv[..., 1])
                z = 1.0 - np.abs(x) - np.abs(y)
                w = (x * x + y * y + z * z) ** -1.5
                dirs.append(d.reshape(-1, 3))
                dws.append((self.em_omega[tex][:, None] * w / w.sum(1, keepdims=True)).ravel())
                Ls.append(np.repeat(self.em_radiance[tex], s * s, axis=0))
            h = self.texel_angle()
            for e in self.emitters:
                if e["model"] != "disc":
                    continue
                r = e["radius_rad"]
                nr = max(3, int(np.ceil(s * r / h)))
                ns = 4 * nr
                edges = np.linspace(0.0, r, nr + 1)
                dw_ring = 2 * np.pi * (np.cos(edges[:-1]) - np.cos(edges[1:])) / ns
                rc = np.arccos(0.5 * (np.cos(edges[:-1]) + np.cos(edges[1:])))
                ph = (np.arange(ns) + 0.5) * 2 * np.pi / ns
                Rr, P = np.meshgrid(rc, ph, indexing="ij")
                d = (np.cos(Rr)[..., None] * e["direction"] + np.sin(Rr)[..., None]
                     * (np.cos(P)[..., None] * e["tangent"] + np.sin(P)[..., None] * e["bitangent"]))
                dirs.append(d.reshape(-1, 3))
                dws.append(np.repeat(dw_ring, ns))
                Ls.append(np.broadcast_to(e["disc_radiance"], (nr * ns, 3)))
            self._sub_cache[s] = (np.concatenate(dirs), np.concatenate(dws), np.concatenate(Ls))
        return self._sub_cache[s]

    def irradiance_rest(self, normals: np.ndarray) -> np.ndarray:
        """Unshadowed irradiance of the rest, ``E(n) = integral L_rest(w) (n . w)+ dw``, (..., 3).

        From a table over normals computed once by summing the rest map, box-averaged to at most
        2 x 64^2 texels, against the clamped cosine, on a latitude-longitude grid of nodes (65 polar
        angles from pole to pole x 128 azimuths), bilinear between nodes. ``E`` is the map convolved
        with a cosine, smooth in both angles; the table's error is ~1e-3 relative (tests). The control
        variate of the diffuse Monte Carlo part (:func:`_rest_light`).
        """
        nt, nph = 65, 128
        if getattr(self, "_E_table", None) is None:
            n = self.n
            f = max(1, n // 64)
            while n % f:
                f -= 1
            m = n // f
            om = self.omega.reshape(2, m, f, m, f)
            Lw = (self.rest.reshape(2, m, f, m, f, 3) * om[..., None]).sum(axis=(2, 4)).reshape(-1, 3)
            d = oc.sphere_directions(m).reshape(-1, 3)
            th = np.linspace(0.0, np.pi, nt)
            ph = np.arange(nph) * (2 * np.pi / nph)
            T, P = np.meshgrid(th, ph, indexing="ij")
            nrm = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
            E = np.zeros((len(nrm), 3))
            for a in range(0, len(nrm), 512):
                E[a:a + 512] = np.maximum(nrm[a:a + 512] @ d.T, 0.0) @ Lw
            self._E_table = E
        nrm = np.asarray(normals, np.float64)
        r = np.maximum(np.linalg.norm(nrm, axis=-1), 1e-300)
        fy = np.arccos(np.clip(nrm[..., 2] / r, -1.0, 1.0)) * ((nt - 1) / np.pi)
        fx = np.mod(np.arctan2(nrm[..., 1], nrm[..., 0]), 2 * np.pi) * (nph / (2 * np.pi))
        y0 = np.clip(np.floor(fy).astype(np.int64), 0, nt - 2)
        x0 = np.floor(fx).astype(np.int64) % nph
        x1 = (x0 + 1) % nph
        ay, ax = np.clip(fy - y0, 0, 1)[..., None], np.clip(fx - np.floor(fx), 0, 1)[..., None]
        T = self._E_table
        r0, r1 = y0 * nph, (y0 + 1) * nph
        return ((T[r0 + x0] * (1 - ax) + T[r0 + x1] * ax) * (1 - ay)
                + (T[r1 + x0] * (1 - ax) + T[r1 + x1] * ax) * ay)

    def texel_angle(self) -> float:
        """Typical angular size of a texel (rad): the square root of the mean texel solid angle."""
        return float(np.sqrt(4 * np.pi / (2 * self.n * self.n)))


#: GGX's half-vector lobe at half maximum is this fraction of Ward's at the same alpha
#: (``tan theta_h = sqrt(sqrt(2) - 1) alpha`` against ``sqrt(ln 2) alpha``): the emitters' cell
#: refinement of a GGX point uses ``0.773 alpha`` as its width (:func:`_emitter_light`)
GGX_CORE_TO_WARD = float(np.sqrt(np.sqrt(2.0) - 1.0) / np.sqrt(np.log(2.0)))
#: the BRDF strategies of GGX points in :func:`_rest_light` (``ggx_proposal``): "vndf" (:func:`sample_ggx`,
#: the default) or "ward" (Ward's half-vector proposal with its own pdf: also unbiased, noisier; kept
#: for comparison)
GGX_PROPOSALS = ("vndf", "ward")


def shade_points(positions, normals, wo, rho_d, rho_s, alpha, env: np.ndarray | EnvSampler,
                 spp: int = 256, scene=None, seed: int = 0, chunk: int = 4096, lobe=None,
                 ggx_proposal: str = "vndf") -> np.ndarray:
    """Outgoing radiance (linear RGB) at surface points towards ``wo`` (paper Eq. 2 with Eq. 1).

    ``L(w_o) = sum_k L_k f_r(w_k, w_o) (n . w_k)+ V(w_k) dw_k + integral L_rest f_r (n . w)+ V dw``
    (paper Eq. 2; ``f_r`` of Eq. 1). The emitters of :class:`EnvSampler` by a deterministic midpoint
    rule (:meth:`EnvSampler.emitter_samples` at refinement ``s = ceil(4 h / (sqrt(2) alpha))``, 1 to 4,
    ``h`` the texel angle, so that the Ward lobe's incident-direction width ``sqrt(2) alpha`` spans
    about four cells; a GGX point takes ``GGX_CORE_TO_WARD alpha`` for ``alpha``, its core being that
    much narrower; ``s = 1`` for matte points), one shadow ray per cell; the rest by MIS Monte Carlo
    (:func:`_rest_light`). A point seen from below its shading normal's horizon (``n . w_o <= 0``: an
    interpolated normal at a silhouette) gets no specular term, as in the synthetic scanner's renderer.

    Parameters
    ----------
    positions, normals, wo : (M, 3) ndarray
        Points (world, metres), unit normals, unit directions towards the viewer. Normals are
        renormalised; rows with a non-finite entry or a zero normal / view direction give 0.
    rho_d, rho_s : (M, 3) ndarray; alpha : (M,) ndarray
        Reflectance of each point (paper Eq. 1): diffuse albedo, specular intensity, roughness of
        the point's lobe (clamped to >= 1e-3).
    env : (2, N, N, 3) ndarray or EnvSampler
        Environment radiance in the same world frame (an array is split with the default settings).
    spp : int
        Samples per point per strategy for the rest (total 2 x spp); 0 leaves only the emitters.
    scene : open3d.t.geometry.RaycastingScene, optional
        Occluders for visibility; no shadows when None.
    seed : int
        Seed of the Monte Carlo part (the emitters' part is deterministic).
    chunk : int
        Points per vectorised batch (memory).
    lobe : None, str or (M,) array_like of str
        Specular lobe of each point, "ward" or "ggx" (:data:`appfusion.brdf.LOBES`; "diffuse" counts
        as "ward", its ``rho_s`` being 0): :func:`appfusion.brdf.ward` or :func:`appfusion.brdf.ggx`,
        sampled by Ward's half vector or GGX's visible normals (:func:`sample_ggx`). None: all Ward
        (the same numbers as without GGX support).
    ggx_proposal : {"vndf", "ward"}
        The BRDF strategy of GGX points (:data:`GGX_PROPOSALS`): their visible normals (default) or,
        for comparison, Ward's half-vector proposal with its own pdf (unbiased, noisier: variance x12
        at alpha 0.05, x1.9 at 0.15).

    Returns
    -------
    (M, 3) float32
        Radiance in the environment map's units.
    """
    sampler = env if isinstance(env, EnvSampler) else EnvSampler(env)
    rng = np.random.default_rng(seed)
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    M = len(positions)
    normals = np.asarray(normals, np.float64).reshape(M, 3)
    wo = np.asarray(wo, np.float64).reshape(M, 3)
    rho_d = np.asarray(rho_d, np.float64).reshape(M, 3)
    rho_s = np.asarray(rho_s, np.float64).reshape(M, 3)
    alpha = np.asarray(alpha, np.float64).reshape(M)
    is_ggx = ggx_rows(lobe, M)
    if ggx_proposal not in GGX_PROPOSALS:
        raise AppFusionError(f"shade_points: ggx_proposal must be one of {', '.join(GGX_PROPOSALS)}, got {ggx_proposal!r}")
    out = np.zeros((M, 3))
    if M == 0:
        return out.astype(np.float32)
    nn, nw = np.linalg.norm(normals, axis=1), np.linalg.norm(wo, axis=1)
    good = (np.isfinite(np.concatenate([positions, normals, wo, rho_d, rho_s, alpha[:, None]], 1)).all(1)
            & (nn > 1e-12) & (nw > 1e-12))
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = np.where(good[:, None], normals / nn[:, None], [0.0, 0.0, 1.0])
        wo = np.where(good[:, None], wo / nw[:, None], [0.0, 0.0, 1.0])
    positions = np.where(good[:, None], positions, 0.0)
    rho_d = np.where(good[:, None], rho_d, 0.0)
    rho_s = np.where(good[:, None], rho_s, 0.0)
    alpha = np.where(good, np.maximum(alpha, 1e-3), 1.0)
    for s in range(0, M, chunk):
        sl = slice(s, min(s + chunk, M))
        p, n, v = positions[sl], normals[sl], wo[sl]
        rd, rs, al = rho_d[sl], rho_s[sl], alpha[sl]
        g = None if is_ggx is None else (is_ggx[sl] if is_ggx[sl].any() else None)
        F = local_frame(n)
        wo_l = np.einsum("mij,mj->mi", F, v)
        # seen from below the shading normal's horizon (an interpolated normal at a silhouette): no
        # specular term, as Ward's lobe (and the reference renderer) has none there; diffuse stays
        rs = np.where((wo_l[:, 2] > 1e-6)[:, None], rs, 0.0)
        wo_l[:, 2] = np.maximum(wo_l[:, 2], 1e-4)
        wo_l /= np.linalg.norm(wo_l, axis=1, keepdims=True)
        total = np.zeros((len(p), 3))
        if len(sampler.emitters):
            total += _emitter_light(sampler, p, n, F, wo_l, rd, rs, al, scene, g=g)
        if spp > 0 and not sampler.rest_black:
            total += _rest_light(sampler, p, n, F, wo_l, rd, rs, al, scene, spp, rng, g=g,
                                 vndf=ggx_proposal == "vndf")
        out[sl] = total
    out[~good] = 0.0
    return out.astype(np.float32)


def _occluded(scene, org: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Open3D occlusion test of rays (R, 3) + (R, 3) (origins already offset), (R,) bool."""
    import open3d as o3d

    if len(org) == 0:
        return np.zeros(0, bool)
    rays = np.concatenate([org, dirs], -1).astype(np.float32)
    return scene.test_occlusions(o3d.core.Tensor(rays), tnear=1e-4).numpy().astype(bool)


def _emitter_light(sampler: EnvSampler, p, n, F, wo_l, rd, rs, al, scene, budget: int = 1 << 21,
                   g: np.ndarray | None = None) -> np.ndarray:
    """Explicit emitters: ``sum_k L_k f_r(w_k, w_o) (n . w_k)+ V(w_k) dw_k`` per point, (m, 3).

    Points are grouped by the cell subdivision ``s`` their lobe needs (see :func:`shade_points`);
    matte points (``rho_s = 0``) use one cell per texel. ``g`` (m,) bool: the GGX points (None: none).
    """
    m = len(p)
    out = np.zeros((m, 3))
    glossy = rs.mean(1) > 0
    h = sampler.texel_angle()
    width = al if g is None else np.where(g, GGX_CORE_TO_WARD * al, al)
    s_pt = np.where(glossy, np.ceil(4 * h / (np.sqrt(2) * width)), 1).clip(1, 4).astype(int)
    for s in np.unique(s_pt):
        D, dw, Le = sampler.emitter_samples(int(s))
        K = len(D)
        idx = np.nonzero(s_pt == s)[0]
        step = max(1, budget // max(K, 1))
        for b in range(0, len(idx), step):
            ix = idx[b:b + step]
            wi_l = np.einsum("mij,kj->mki", F[ix], D)  # (mb, K, 3)
            cos_i = wi_l[..., 2]
            lit = cos_i > 1e-6
            f_spec = lobe_rows(al[ix, None], wi_l, np.broadcast_to(wo_l[ix, None, :], wi_l.shape),
                                None if g is None else g[ix])
            w = np.where(lit, cos_i, 0.0) * dw  # (mb, K)
            if scene is not None:
                pi, ki = np.nonzero(lit)
                occ = _occluded(scene, p[ix][pi] + 1e-4 * n[ix][pi], D[ki])
                w[pi[occ], ki[occ]] = 0.0
            # diffuse: rho_d / pi * sum_k L_k w_k; specular: rho_s * sum_k L_k f_k w_k
            out[ix] = rd[ix] / np.pi * (w @ Le) + rs[ix] * ((w * f_spec) @ Le)
    return out


def _rest_light(sampler: EnvSampler, p, n, F, wo_l, rd, rs, al, scene, spp, rng,
                g: np.ndarray | None = None, vndf: bool = True) -> np.ndarray:
    """MIS Monte Carlo of ``integral L_rest f_r (n . w)+ V dw`` per point, (m, 3).

    Balance heuristic over the map's and the BRDF's strategies, ``spp`` samples each: a sample ``w``
    has the weight ``g(w) = (n . w)+ / (spp (pdf_map(w) + pdf_brdf(w)))`` and both strategies' sums
    add up. The BRDF strategy draws from the cosine lobe or the specular lobe (Ward's half vector;
    GGX's visible normals for the points ``g`` (m,) bool, None: none; Ward's half vector for them too
    with ``vndf=False``), ``pdf_brdf`` their mixture. Specular: ``rho_s sum L f g V``. Diffuse, with the unshadowed irradiance as a control
    variate: ``rho_d / pi (E(n) - sum L g (1 - V))`` (:meth:`EnvSampler.irradiance_rest`), exact where
    nothing is occluded, noisy only in what the occluders take away.
    """
    m = len(p)
    # probability of choosing the Ward lobe within the BRDF strategy, from the albedo ratio
    wd, ws = rd.mean(1), rs.mean(1)
    q_spec = np.where(ws > 0, ws / np.maximum(wd + ws, 1e-12), 0.0)
    # --- strategy A: environment samples; strategy B: BRDF samples
    # stratified (Latin hypercube) uniforms per point: each of the spp samples of a point falls in
    # its own 1/spp slice of every dimension, which cuts the variance of the env map's bright spots
    dA, _ = sampler.sample(_stratified(rng, m, spp).reshape(-1), rng)
    dA = dA.reshape(m, spp, 3)
    u = np.stack([_stratified(rng, m, spp) for _ in range(3)], -1)
    choose_spec = u[..., 0] < q_spec[:, None]
    cos_dir = np.stack(_cosine(u[..., 1], u[..., 2]), -1)
    spec_dir, _, _ = sample_ward(al[:, None], wo_l[:, None, :], u[..., 1], u[..., 2])
    gi = np.zeros(0, np.int64) if g is None else np.flatnonzero(g)
    vndf = vndf and len(gi) > 0
    if vndf:
        # the same stratified uniforms, GGX's visible normals
        spec_dir[gi] = sample_ggx(al[gi, None], wo_l[gi, None, :], u[gi, :, 1], u[gi, :, 2])[0]
    wiB_l = np.where(choose_spec[..., None], spec_dir, cos_dir)
    dB = np.einsum("mji,msj->msi", F, wiB_l)
    wiA_l = np.einsum("mij,msj->msi", F, dA)
    diff = np.zeros((m, 3))  # sum of L cos / (spp (pdf_a + pdf_b)) over the occluded samples
    spec = np.zeros((m, 3))  # sum of L f cos / (...) over the visible samples
    for wi_l, wi in ((wiA_l, dA), (wiB_l, dB)):
        cos_i = wi_l[..., 2]
        ok = cos_i > 1e-6
        f_spec = lobe_rows(al[:, None], wi_l, np.broadcast_to(wo_l[:, None, :], wi_l.shape), g)
        pdf_s = ward_pdf(al[:, None], wi_l, wo_l[:, None, :])
        if vndf:
            pdf_s[gi] = ggx_pdf(al[gi, None], wi_l[gi], wo_l[gi, None, :])
        pdf_b = (1 - q_spec[:, None]) * np.maximum(cos_i, 0) / np.pi + q_spec[:, None] * pdf_s
        pdf_a = sampler.pdf(wi)
        w = np.where(ok, cos_i, 0.0) / np.maximum(spp * (pdf_a + pdf_b), 1e-30)
        L = sampler.rest_radiance(wi)
        vis = np.ones(ok.shape, bool)
        if scene is not None:
            pi, si = np.nonzero(ok)
            occ = _occluded(scene, p[pi] + 1e-4 * n[pi], wi[pi, si])
            vis[pi[occ], si[occ]] = False
        spec += np.einsum("ms,msc->mc", w * f_spec * vis, L)
        diff += np.einsum("ms,msc->mc", w * ~vis, L)
    # diffuse with the unshadowed irradiance as control variate: E(n) exactly, less the Monte Carlo
    # estimate of what the occluders take away (zero noise where nothing is occluded)
    E = np.maximum(sampler.irradiance_rest(n) - diff, 0.0)
    return rd / np.pi * E + rs * spec


def _stratified(rng: np.random.Generator, m: int, spp: int) -> np.ndarray:
    """(m, spp) uniforms, one in each interval [k/spp, (k+1)/spp) per row, in random order."""
    perm = np.argsort(rng.random((m, spp)), axis=1)
    return (perm + rng.random((m, spp))) / spp


def _cosine(u1, u2):
    r = np.sqrt(u1)
    phi = 2 * np.pi * u2
    return r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1 - u1, 0))


def render_view(result: ScanResult, env: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray,
                spp: int = 256, shadows: bool = True, seed: int = 0, normal_field=None,
                crease_deg: float | None = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """Render the captured object under ``env`` seen by a pinhole camera.

    Parameters
    ----------
    result : ScanResult
        Must carry a mesh.
    env : (2, N, N, 3) ndarray
        Environment radiance in the marker frame.
    intrinsics : Intrinsics
    pose : (4, 4) ndarray
        Camera-to-world pose of the rendering camera (OpenCV axes).
    normal_field : appfusion.points.NormalField, optional
        The result's points as a normal field (built here if not given; pass one to render several
        views of the same result).
    crease_deg : float or None
        Hits on a triangle whose vertex normals differ by more than this (degrees) are shaded with
        the nearest point's normal, not an interpolation across the crease. None: always
        interpolate. Vase (session 17; truth mesh, truth normals at our points): relit 0.279 ->
        0.127 in the view that sees the lid's edge; no triangle of the capsules or spheres qualifies.

    Returns
    -------
    image : (H, W, 3) float32 linear radiance (0 where the object is not hit)
    mask : (H, W) bool, pixels that see the object
    """
    import open3d as o3d
    from .export import transfer_to_vertices
    from .points import interpolate_mls

    V, Fc = np.asarray(result.mesh_vertices, np.float32), np.asarray(result.mesh_faces, np.int32)
    if len(Fc) == 0:
        raise AppFusionError("relighting needs a mesh: export the scan first (appfusion scan writes one)")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(Fc.astype(np.uint32)))
    H, W = intrinsics.height, intrinsics.width
    dirs_cam = intrinsics.rays().reshape(-1, 3).astype(np.float64)
    dirs = dirs_cam @ pose[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    org = np.broadcast_to(pose[:3, 3], dirs.shape)
    rays = np.concatenate([org, dirs], 1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy()
    mask = np.isfinite(t)
    img = np.zeros((H * W, 3), np.float32)
    if mask.any():
        prim = hit["primitive_ids"].numpy()[mask]
        bu, bv = hit["primitive_uvs"].numpy()[mask].T
        bary = np.stack([1 - bu - bv, bu, bv], 1)
        # the shading normal: at each mesh vertex the nearest sampled point's normal tilted by the
        # normal's gradient to the vertex (points.NormalField), interpolated over the hit triangle.
        # Demo: vertex normals 0.34 degrees off the truth against 0.41 by inverse distance over 4
        # points (whose centroid is not the vertex); relit 0.199 -> 0.190. Tilting at each hit instead
        # gave the same on the scan, but 0.031 instead of 0.026 on the truth oracle (docs/performance.md)
        if normal_field is None:
            from .points import NormalField

            normal_field = NormalField(result.positions, result.normals)
        vn = normal_field(V)
        n = np.einsum("mk,mki->mi", bary, vn[Fc[prim]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        pos = org[mask] + dirs[mask] * t[mask][:, None]
        if crease_deg is not None:
            # a hit triangle whose vertices' normals differ by more than crease_deg straddles a
            # crease (points.sharpen_creases): interpolating across it would light a band of normals
            # the surface does not have, so such hits take their nearest point's normal
            tv = vn[Fc[prim]]
            c = np.minimum(np.minimum(np.einsum("mc,mc->m", tv[:, 0], tv[:, 1]), np.einsum("mc,mc->m", tv[:, 1], tv[:, 2])),
                           np.einsum("mc,mc->m", tv[:, 0], tv[:, 2]))
            cr = c < np.cos(np.radians(crease_deg))
            if cr.any():
                n[cr] = normal_field.nearest(pos[cr])
        # rho_d at the hit from the sampled points around it: the points are ~10x denser than the
        # mesh's vertices, and interpolating per-vertex rho_d over the triangles blurred the label's
        # stripes and the material seam (demo: error off the highlights 0.124 -> 0.104 in one view).
        # A linear moving-least-squares fit over 6 points (points.interpolate_mls) rather than inverse
        # distance over 4, which flattens a texture's gradients (session 33: matte 10k-point scan
        # 0.0554 -> 0.0497, demo 0.0307 -> 0.0299)
        rd = interpolate_mls(result.positions, result.normals, np.asarray(result.rho_d), pos,
                             tree=normal_field.tree)
        # per-point cluster parameters taken at the nearest sampled point (no blending across clusters)
        lab = transfer_to_vertices(result.positions, np.asarray(result.labels), pos, nearest=True)
        wo = -dirs[mask]
        # orient the shading normal to the side of the surface the camera sees: the side of the hit
        # triangle's geometric normal turned towards the viewer (robust to the mesh's winding and to
        # the points' normal orientation). Not "n . wo > 0": at a silhouette an interpolated normal
        # may face slightly away from the viewer and flipping it would light the inside
        ng = hit["primitive_normals"].numpy()[mask].astype(np.float64)
        ng = np.where(np.sum(ng * wo, 1, keepdims=True) < 0, -ng, ng)
        n = np.where(np.sum(n * ng, 1, keepdims=True) < 0, -n, n)
        lobes = _cluster_lobes(result)
        img[mask] = shade_points(pos, n, wo, rd, result.rho_s[lab], result.alpha[lab], env, spp=spp,
                                 scene=scene if shadows else None, seed=seed,
                                 lobe=lobes[lab] if (lobes == "ggx").any() else None)
    return img.reshape(H, W, 3), mask.reshape(H, W)


def _cluster_lobes(result) -> np.ndarray:
    """(C,) str, each cluster's specular lobe from ``result.model``: "ggx" where the model says so,
    else "ward" (a "diffuse" cluster has ``rho_s = 0``; a missing or short ``model`` list counts as
    Ward)."""
    C = len(np.asarray(result.alpha))
    model = list(getattr(result, "model", None) or [])
    return np.array(["ggx" if i < len(model) and str(model[i]) == "ggx" else "ward" for i in range(C)])
