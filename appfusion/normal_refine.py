"""Specular normal refinement: glossy points' normals moved to where their highlights say (beyond the paper).

The TSDF of §4.1 rounds any curvature sharper than about a voxel (3 mm): on the scanner's pepper
the rim of the stem's dimple comes out with normals 3-8 degrees off (99th percentile 7.6 deg, median
0.93). Shading with a sharp lobe (alpha 0.07: about 2 degrees of normal) puts each highlight on the
wrong row of pixels there: relit under a sunset, 99 % of the pepper's error sat in 1 % of its pixels,
and the truth's normals at the same points took its relit error from 0.37 to 0.13. The RGB frames
see those highlights too (the capture's own lights), so they say where the normals are.

:class:`NormalRefiner` sweeps the RGB frames once more after the RGB pass (§5.3) has settled rho_d,
rho_s and alpha. Each point of a glossy cluster gets ``K`` candidate normals: its own, and rings of
``n_ring`` normals tilted by each of ``radii_deg``. Per point and candidate it keeps the sums of
Eq. 5's residual with rho_d profiled out,

    r_jk = L_j - rho_s S(n_k, w_o,j)           RSS_k = sum_j |r_jk|^2 - |sum_j r_jk|^2 / n

(per channel; ``rho_d D(n_k)`` is the one constant of a point's samples, so any error of rho_d or
of D, the plane's near field included, leaves the comparison alone, and a point's diffuse shading
moves nothing). A candidate replaces the normal when its RSS is lower than the current normal's by
more than ``z^2`` times the point's own residual variance per sample (the best candidate's
``RSS / (3 n - 4)``) and by more than half of it (``min_gain``): where no highlight was seen, every candidate explains the samples alike and
the normal stays. The point's rho_d is then solved again with the new S and D. Rounds with halved
radii (``rounds``, the pipeline's sweeps) refine the step; constant memory: ``4 K`` floats per
point refined.
"""

from __future__ import annotations

import math
import time

import numpy as np

from .errors import AppFusionError


def tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (P, 3) each, orthogonal to unit ``normals`` (P, 3) and to each other."""
    n = np.asarray(normals, np.float64)
    a = np.where(np.abs(n[:, 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    t = np.cross(n, a)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(n, t)


def candidate_normals(normals: np.ndarray, radii_deg=(1.5, 3.0), n_ring: int = 6) -> np.ndarray:
    """Candidate normals (P, K, 3) around unit ``normals`` (P, 3): the normal itself (k = 0), then
    ``n_ring`` normals tilted by each radius (degrees), the rings turned half a step against each
    other; ``K = 1 + n_ring * len(radii_deg)``."""
    n = np.asarray(normals, np.float64)
    t, b = tangent_frames(n)
    out = [n]
    for i, r in enumerate(radii_deg):
        rr = math.radians(float(r))
        for j in range(n_ring):
            ph = 2 * math.pi * (j + 0.5 * (i % 2)) / n_ring
            out.append(n * math.cos(rr) + (t * math.cos(ph) + b * math.sin(ph)) * math.sin(rr))
    c = np.stack(out, axis=1)
    return (c / np.linalg.norm(c, axis=2, keepdims=True)).astype(np.float32)


def highlight_range_map(envmap: np.ndarray, cone_rad: float, n: int = 32) -> np.ndarray:
    """Per direction of a coarse (2, n, n) octahedral grid, the range (max - min, per channel) of the
    environment's radiance, averaged over coarse texels (about 4.5 degrees at n = 32: what a sharp lobe
    sees of it), within ``cone_rad`` of that direction (plus a texel): how much S can change when the
    mirror direction moves inside the cone, times the lobe's albedo. Shape (2, n, n, 3)."""
    from . import octahedral as oc

    env = np.asarray(envmap, np.float32)
    N = env.shape[1]
    if N % n == 0:                                            # texel blocks -> coarse texels
        b = N // n
        coarse_vals = env.reshape(2, n, b, n, b, 3).mean(axis=(2, 4)).reshape(-1, 3)
    else:
        coarse_vals = oc.sample_sphere_map(env, oc.sphere_directions(n)).reshape(-1, 3).astype(np.float32)
    d = oc.sphere_directions(n).reshape(-1, 3).astype(np.float32)
    cos_c = math.cos(min(math.pi, cone_rad + math.sqrt(4 * math.pi / (2 * n * n))))
    inside = (d @ d.T) >= cos_c                                # (2 n^2, 2 n^2): 4 MB at n = 32
    out = np.zeros((len(d), 3), np.float32)
    for c in range(3):
        v = coarse_vals[:, c][None, :]
        out[:, c] = np.where(inside, v, -np.inf).max(axis=1) - np.where(inside, v, np.inf).min(axis=1)
    return out.reshape(2, n, n, 3)


class NormalRefiner:
    """One sweep of specular normal refinement over an :class:`~appfusion.rgb_pass.RGBPass`'s points.

    Parameters
    ----------
    rgb : appfusion.rgb_pass.RGBPass
        The finished RGB pass: its points, clusters, lobes, tables, near field and registration are used.
    rho_s : (C, 3) array
        Specular albedo per cluster (the pass's result; 0 for a diffuse cluster, whose points are
        not refined).
    normals : (P, 3) array, optional
        Normals to start from, caller order (default: the pass's).
    radii_deg : sequence of float
        Tilts of the candidate rings, degrees.
    n_ring : int
        Candidates per ring.
    z : float
        Significance of a move, in standard deviations of the point's residual (see the module).
    min_samples : int
        Samples a point needs to be moved.
    screen : float or None
        Refine only the points whose relative residual variance in the pass, ``RSS / (n |mean L|^2)``
        with their current normal, is over ``screen`` times the median of the glossy points': where
        the highlights fit already, no candidate can fit significantly better, and the sweep costs
        ``K`` S look-ups per sample (demo: ...). None: every glossy point.
    min_gain : float
        A move must also explain this fraction of the point's residual (``RSS_0 - RSS_best >
        min_gain RSS_0``): a model error (the tables' S, the map, rho_s) leaves every point some
        residual a neighbouring normal explains a little better, and with little noise that little
        is significant. A sphere whose normals were half tilted by 3 degrees (1 % noise): the tilted
        ones' best candidates explained a median 80 % of their residual, the right ones' 0.6 %
        (90th percentile 44 %).
    only : (P,) bool array, optional
        Consider only these points (caller order), e.g. the ones a previous round moved.
    max_alpha : float
        Clusters with a rougher lobe are not refined: a highlight pins the normal only to about the
        lobe's width (alpha 0.35: 20 degrees).
    eps : float
        A sample is looked up at every candidate only where the highlights could change it:
        ``rho_s`` times the lobe-blurred map's radiance range within ``2 * max tilt`` of its mirror
        direction (:func:`highlight_range_map`) at least ``eps`` times its radiance (any channel);
        elsewhere every candidate gets the current normal's S. 0: every sample at every candidate.
    """

    def __init__(self, rgb, rho_s, normals=None, *, radii_deg=(1.5, 3.0), n_ring: int = 6, z: float = 4.0,
                 min_samples: int = 8, screen: float | None = None, only=None, min_gain: float = 0.0,
                 max_alpha: float = 0.2, eps: float = 0.1, fit: str = "shape"):
        self.rgb = rgb
        rs = np.asarray(rho_s, np.float64)
        if rs.ndim != 2 or rs.shape[1] != 3 or len(rs) < rgb.n_clusters or not np.isfinite(rs).all():
            raise AppFusionError(f"NormalRefiner: rho_s must be finite ({rgb.n_clusters}, 3), got {rs.shape}")
        self.rho_s = np.maximum(rs, 0.0)
        if not (np.isfinite(z) and z > 0) or n_ring < 3 or not len(radii_deg) or min(radii_deg) <= 0:
            raise AppFusionError(f"NormalRefiner: need z > 0, n_ring >= 3 and positive radii; got {z}, {n_ring}, "
                                 f"{radii_deg}")
        N0 = rgb.normals if normals is None else np.asarray(normals, np.float32)
        if N0.shape != rgb.normals.shape or not np.isfinite(N0).all():
            raise AppFusionError(f"NormalRefiner: normals must be finite {rgb.normals.shape}, got {N0.shape}")
        if normals is not None:
            N0 = N0[rgb._order]
        glossy = (self.rho_s[rgb.labels].max(axis=1) > 0) & (rgb.point_alpha <= max_alpha)
        glossy &= rgb._spec_point & rgb.lit & (rgb.counts >= min_samples)
        if only is not None:
            o = np.asarray(only, bool).reshape(-1)
            if o.shape != (len(glossy),):
                raise AppFusionError(f"NormalRefiner: only must be ({len(glossy)},) flags, got {o.shape}")
            glossy &= o[rgb._order]
        self.screened = int(np.count_nonzero(glossy))
        if screen is not None and glossy.any():
            use, n, c_sl, v_ss, v_ll = rgb._within_point_moments(2)
            rs_p = self.rho_s[rgb.labels]
            rss = (v_ll - 2 * rs_p * c_sl + rs_p ** 2 * v_ss).sum(axis=1)
            mean_l2 = ((rgb.sum_l / n) ** 2).sum(axis=1)
            rel = rss / (n[:, 0] * np.maximum(mean_l2, 1e-12))
            glossy &= rel > float(screen) * np.median(rel[glossy])
        self.sel = np.flatnonzero(glossy)                     # internal indices of the refined points
        self._slot = np.full(len(rgb.positions), -1, np.int64)
        self._slot[self.sel] = np.arange(len(self.sel))
        if not 0 <= min_gain < 1:
            raise AppFusionError(f"NormalRefiner: min_gain must be in [0, 1), got {min_gain}")
        if fit not in ("shape", "fixed"):
            raise AppFusionError(f"NormalRefiner: fit must be 'shape' or 'fixed', got {fit!r}")
        self.fit = fit
        self.z, self.min_samples, self.min_gain = float(z), int(min_samples), float(min_gain)
        self.radii_deg = tuple(float(r) for r in radii_deg)
        self.N0 = N0
        self.cand = candidate_normals(N0[self.sel], self.radii_deg, n_ring)      # (Q, K, 3)
        Q, K = self.cand.shape[:2]
        self.K = K
        self.alpha_eff = rgb._map_alpha(rgb.point_alpha[self.sel])
        self.lobe = rgb.point_lobe[self.sel]                   # each refined point's lobe (brdf.LOBES)
        # D of each candidate: the tables' distant light, plus the pass's near-field part at the normal
        D0 = rgb.D[self.sel].astype(np.float64)
        Dt = rgb.tables.D(self.cand.reshape(-1, 3)).reshape(Q, K, 3).astype(np.float64)
        self.Dc = np.maximum(Dt + (D0 - Dt[:, 0])[:, None, :], 1e-9)
        # where a sample's S can change across the candidates: one range map per lobe
        self.eps = float(eps)
        self._range_n = 32
        self._range = None if self.eps <= 0 else highlight_range_map(
            rgb.tables.env, 2 * math.radians(max(self.radii_deg)), self._range_n).reshape(-1, 3)
        self.stats = {"samples": 0, "full": 0}
        self.n = np.zeros(Q, np.int64)
        self.sum_r = np.zeros((Q, K, 3))
        self.sum_r2 = np.zeros((Q, K))
        # the highlight's shape: per candidate, the regression of y = sum_c L_c on the predicted
        # specular x_k = sum_c rho_s,c S_k,c with a free slope (see rss(shape=True))
        self.sum_x = np.zeros((Q, K))
        self.sum_xx = np.zeros((Q, K))
        self.sum_xy = np.zeros((Q, K))
        self.sum_y = np.zeros(Q)
        self.sum_yy = np.zeros(Q)
        # rho_d of the chosen candidate as the pass solves it (diffuse-weighted, RGBPass diffuse_tau)
        self.tau = rgb.diffuse_tau
        self.sum_w = np.zeros((Q, K))
        self.sum_wr = np.zeros((Q, K, 3))
        self.seconds = 0.0

    @property
    def nbytes(self) -> int:
        return int(self.cand.nbytes + self.Dc.nbytes + self.sum_r.nbytes + self.sum_r2.nbytes + self.n.nbytes
                   + self.sum_w.nbytes + self.sum_wr.nbytes)

    def add_frame(self, rgb_linear, depth, rgb_intrinsics, depth_intrinsics, pose, depth_to_rgb) -> int:
        """Register one frame as :meth:`appfusion.rgb_pass.RGBPass.add_frame` does and add its samples
        of the refined points; returns the samples used."""
        t0 = time.perf_counter()
        g = self.rgb
        rgb = np.asarray(rgb_linear)
        T = np.asarray(pose, np.float64)
        E = np.asarray(depth_to_rgb, np.float64)
        pts, Xd = g._project_points(np.asarray(depth), depth_intrinsics, T)
        keep = self._slot[pts] >= 0
        pts, Xd = pts[keep], tuple(x[keep] for x in Xd)
        pts, L, C = g._lookup_rgb(rgb, pts, Xd, rgb_intrinsics, T, E)
        used = self._add(pts, L, C)
        self.seconds += time.perf_counter() - t0
        return used

    def add_samples(self, point_idx, L, camera_center) -> int:
        """Add registered samples directly: points ``point_idx`` (k,) (caller order, distinct), their
        calibrated linear RGB ``L`` (k, 3) and the RGB camera centre (3,); returns the samples used."""
        p = np.asarray(point_idx).reshape(-1).astype(np.int64)
        L = np.asarray(L, np.float32).reshape(-1, 3)
        if len(L) != len(p) or (len(p) and (p.min() < 0 or p.max() >= len(self._slot))):
            raise AppFusionError(f"NormalRefiner.add_samples: {len(p)} point indices in [0, {len(self._slot)}) "
                                 f"and as many RGB samples needed, got {len(L)}")
        if len(np.unique(p)) != len(p):
            raise AppFusionError("NormalRefiner.add_samples: one sample per point and call")
        pts = self.rgb._rank[p]
        keep = self._slot[pts] >= 0
        return self._add(pts[keep], L[keep], np.asarray(camera_center, np.float64).reshape(3))

    def _add(self, pts, L, C) -> int:
        """Samples of internal points ``pts`` (distinct), RGB ``L`` (k, 3), camera centre ``C``."""
        g = self.rgb
        if len(pts) == 0:
            return 0
        L = np.asarray(L, np.float32)
        Lmax = np.max(L, axis=1)
        wo = np.asarray(C, np.float32) - g.positions[pts]
        wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), np.float32(1e-9))
        q = self._slot[pts]
        cos_o = np.einsum("ij,ij->i", self.N0[pts], wo)
        ok = np.isfinite(Lmax) & (Lmax >= g.dark) & (cos_o >= g.min_cos)
        if not ok.all():
            pts, L, wo, q, Lmax = pts[ok], L[ok], wo[ok], q[ok], Lmax[ok]
        m = len(pts)
        if m == 0:
            return 0
        K = self.K
        n0 = self.N0[pts]
        ae = self.alpha_eff[q]
        rs = self.rho_s[g.labels[pts]]
        lb = self.lobe[q]
        S0 = g.table_S(n0, wo, ae, lb)
        full = np.ones(m, bool)
        if self._range is not None:
            from .octahedral import sphere_texel_index

            r0 = 2 * np.einsum("ij,ij->i", n0, wo)[:, None] * n0 - wo
            rng = self._range[sphere_texel_index(r0, self._range_n)]
            full = (rs * rng).max(axis=1) >= self.eps * Lmax
        S = np.repeat(S0[:, None, :], K, axis=1)
        f = np.flatnonzero(full)
        if len(f):
            # candidate-major: each of the K look-ups reads the tables in the points' (normal-sorted)
            # order, as the pass does
            nk = self.cand[q[f], 1:].transpose(1, 0, 2).reshape(-1, 3)
            Sk = g.table_S(nk, np.tile(wo[f], (K - 1, 1)), np.tile(ae[f], K - 1), np.tile(lb[f], K - 1))
            S[f, 1:] = Sk.reshape(K - 1, len(f), 3).transpose(1, 0, 2)
        self.stats["samples"] += m
        self.stats["full"] += len(f)
        if g.near_field is not None:                          # the plane's dS at the current normal, for all
            dS = g.near_field_dS(g.positions[pts], n0, wo, g.point_alpha[pts], lb, seed=7 * g.frames + m)
            S = np.maximum(S + dS[:, None, :], 0.0)
        r = L[:, None, :] - rs[:, None, :] * S                                # (m, K, 3)
        self.n[q] += 1                                        # one sample per point and frame
        self.sum_r[q] += r
        self.sum_r2[q] += np.einsum("ikc,ikc->ik", r, r)
        x = np.einsum("ikc,ic->ik", S, rs)
        y = L.sum(axis=1, dtype=np.float64)
        self.sum_x[q] += x
        self.sum_xx[q] += x * x
        self.sum_xy[q] += x * y[:, None]
        self.sum_y[q] += y
        self.sum_yy[q] += y * y
        if self.tau is not None:                              # w = 1 / (1 + (S / (tau D))^2), RGB means
            x = (S.sum(axis=2) / np.maximum(self.Dc[q].sum(axis=2), 3e-12)) / self.tau
            w = 1.0 / (1.0 + x * x)
            self.sum_w[q] += w
            self.sum_wr[q] += w[..., None] * r
        return m

    def rss(self, shape: bool | None = None) -> np.ndarray:
        """(Q, K) residual sums of squares per refined point and candidate, rho_d profiled out.

        ``shape`` (default: the refiner's ``fit == "shape"``): of ``sum_c L_c`` regressed on the
        candidate's predicted highlight ``sum_c rho_s,c S_k,c`` with a free slope >= 0 and intercept,
        so that a candidate wins by putting the highlights where the samples show them, not by
        moving a highlight the map draws too bright or too sharp out of the observed views; else of
        Eq. 5 with the exported rho_s."""
        n = np.maximum(self.n, 1).astype(np.float64)
        if not (self.fit == "shape" if shape is None else shape):
            return self.sum_r2 - np.einsum("ikc,ikc->ik", self.sum_r, self.sum_r) / n[:, None]
        nn = n[:, None]
        v_yy = np.maximum(self.sum_yy - self.sum_y ** 2 / n, 0.0)[:, None]
        v_xx = np.maximum(self.sum_xx - self.sum_x ** 2 / nn, 0.0)
        c_xy = self.sum_xy - self.sum_x * self.sum_y[:, None] / nn
        expl = np.where((c_xy > 0) & (v_xx > 1e-12 * np.maximum(v_yy, 1e-30)), c_xy ** 2 / np.maximum(v_xx, 1e-30), 0.0)
        return np.maximum(v_yy - expl, 0.0)

    def result(self) -> tuple[np.ndarray, np.ndarray, dict]:
        """Refined normals (P, 3) and the refitted ``rho_d`` factor, both in the caller's order, and stats.

        Returns
        -------
        normals : (P, 3) float32
            The moved points' best candidates, the others' normals as given.
        rho_d : (P, 3) float64
            ``(mean L - rho_s mean S) / D`` at the chosen normal for the moved points, the means
            weighted as the pass weights them (``diffuse_tau``); D from the pass's tables plus its
            near-field correction at the old normal; NaN elsewhere (keep yours).
        stats : dict
            ``points`` refined, ``moved``, ``median_move_deg`` of the moved, ``seconds``.

        Also sets :attr:`rho_d_factor` (P, 3): for the moved points, the refitted rho_d at the chosen
        normal over the one at the point's own normal (candidate 0), both from this sweep's samples,
        so that the sample noise cancels; NaN elsewhere. A caller whose rho_d went through
        corrections the refiner does not make (pooling with neighbours, noise clipped at black)
        scales it by this factor rather than replacing it.
        """
        g = self.rgb
        rss = self.rss()
        best = np.argmin(rss, axis=1)
        Q = len(self.sel)
        rb = rss[np.arange(Q), best]
        dof = np.maximum((self.n - 3) if self.fit == "shape" else (3 * self.n - 4), 1)
        gain = rss[:, 0] - rb
        move = ((best > 0) & (self.n >= self.min_samples) & (gain > self.z ** 2 * np.maximum(rb, 0) / dof)
                & (gain > self.min_gain * rss[:, 0]))
        N = self.N0.copy()
        qi = np.flatnonzero(move)
        newn = self.cand[qi, best[qi]]
        N[self.sel[qi]] = newn
        rho_d = np.full((len(N), 3), np.nan)
        factor = np.full((len(N), 3), np.nan)
        if len(qi):
            rd_best, rd_own = self._refit_rho_d(qi, best[qi]), self._refit_rho_d(qi, 0)
            rho_d[self.sel[qi]] = rd_best
            ok = rd_own > 1e-6
            factor[self.sel[qi]] = np.where(ok, rd_best / np.where(ok, rd_own, 1.0), np.nan)
        ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", newn, self.N0[self.sel[qi]]), -1, 1)))
        stats = {"points": int(Q), "moved": int(len(qi)), "median_move_deg": float(np.median(ang)) if len(qi) else 0.0,
                 "gain_pct": np.percentile(gain[qi] / np.maximum(rss[qi, 0], 1e-30), [10, 50, 90]).round(3).tolist()
                 if len(qi) else [],
                 "seconds": self.seconds, "samples": self.stats["samples"],
                 "full_fraction": self.stats["full"] / max(self.stats["samples"], 1)}
        out_n = np.empty_like(N)
        out_n[g._order] = N
        out_r = np.empty_like(rho_d)
        out_r[g._order] = rho_d
        self.rho_d_factor = np.empty_like(factor)
        self.rho_d_factor[g._order] = factor                # the caller's order, as rho_d
        return out_n, out_r, stats

    def _refit_rho_d(self, qi: np.ndarray, k) -> np.ndarray:
        """``(mean L - rho_s mean S) / D`` (q, 3) of refined points ``qi`` at candidate(s) ``k``, the means
        weighted as the pass weights them (``diffuse_tau``)."""
        if self.tau is not None:
            mean_r = self.sum_wr[qi, k] / np.maximum(self.sum_w[qi, k], 1e-12)[:, None]
        else:
            mean_r = self.sum_r[qi, k] / self.n[qi, None]
        return mean_r / self.Dc[qi, k]
