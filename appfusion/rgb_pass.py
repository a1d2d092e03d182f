"""The RGB pass (paper §5.3): per-point diffuse albedo rho_d and per-cluster specular albedo rho_s.

Each calibrated (white-balanced, linear) RGB pixel ``L`` registered to a sampled point ``p_i`` of
normal ``n_i`` in cluster ``c`` (Ward roughness ``alpha_c`` from the IR pass) obeys Eq. 5,

    L = rho_d,i D(n_i) + rho_s,c S(n_i, alpha_c, w_o),

with ``D`` and ``S`` from :mod:`appfusion.diffuse_term` and :mod:`appfusion.double_product` and
``w_o`` the unit direction from the point to the RGB camera's centre.

rho_d (Eq. 6)
    ``rho_d,i = min_j L_ij / D_ij`` over the samples of the point; as in the paper a low percentile
    (default the 10th) replaces the minimum, read from a fixed-size histogram per point and channel:
    ``bins`` (default 64) log-spaced bins over ``ratio_range`` (default 1/64 .. 2, 7.9 % per bin),
    uint16 counts (all halved when one would overflow), values outside the range counted in the end
    bins. Each bin also keeps the running mean of its samples' position inside it (uint8, stochastic
    rounding), and the percentile is interpolated inside the bin where the cumulative count crosses
    it, as if the bin's samples were spread uniformly around that mean (see
    :func:`histogram_percentile`). On the synthetic sphere this halves the quantisation error
    (median rho_d error 2.8 % -> 1.9 % with ~9 samples per point; a 512-bin histogram gives 2.1 %).
    Memory: ``3 * bins * 3`` bytes per point (576 B), whatever the number of frames.

Joint least squares (``estimator="lsq"``, the default)
    Eq. 6's low percentile is biased by sensor noise: with samples scattered by sigma around the
    truth, the 10th percentile sits ~1.3 sigma low (the synthetic Kinect's 8-bit RGB scatters by ~5 %,
    so rho_d came out 7 % low even with every other input exact). The default estimator solves Eq. 5 in
    the least-squares sense over all samples instead -- rho_d per point and rho_s per cluster jointly
    -- from two more running sums per point (``sum S``, ``sum L``); see :meth:`RGBPass._lsq`. Same
    constant memory, unbiased under zero-mean noise. ``estimator="percentile"`` keeps the paper's
    Eq. 6 + 8.

rho_s (Eq. 8), constant memory and live
    ``rho_s = sum S (L - D rho_d) / sum S^2`` over the samples of a cluster needs rho_d fixed. Rather
    than a second sweep over the frames, each point keeps the running sums ``sum S^2``, ``sum S L``
    and ``sum S D`` per channel (9 float64). Because rho_d,i is constant per point,

        sum_j S_ij (L_ij - D_ij rho_d,i) = sum_j S_ij L_ij - rho_d,i sum_j S_ij D_ij,

    so :meth:`RGBPass.result` forms the exact numerator of Eq. 8 with the *final* rho_d at any time
    (the GUI can show rho_s live), and no sample is ever stored.

Samples
    Registration (``registration=``): ``"points"`` (default) projects every point into the depth
    image, keeps it where the measured depth agrees within ``depth_tol`` and it faces the camera, then
    projects it into the RGB camera (``depth_to_rgb``) and reads the image there (``rgb_sampling``:
    the nearest pixel, the default, or bilinear between the four around it) -- one sample per
    visible point and frame. ``"pixels"`` is the paper's
    wording: every depth pixel goes to its nearest point with :func:`appfusion.points.register_pixels`
    (a grid look-up, nearest up to a cell of ``max_dist / 2``), is transformed into the RGB camera and
    read there, and the pixels of one point in one frame (same ``w_o``) are averaged into one sample.
    On a synthetic sphere like that of ``tests/test_rgb_pass.py`` (1500 points, 7 mm apart, sharp
    highlights about one point wide) the grid's off-by-one-cell matches biased rho_s of the sharp
    material by -10 %, against < 1 % with ``"points"``; with the paper's ~1 mm point spacing the two
    should agree (not measured). A sample
    is skipped when it is dark (max channel < ``dark``), saturated (any channel of any of its pixels
    >= ``saturated``), grazing (``n.w_o < min_cos``), outside the RGB image, or
    the point's ``D`` is below ``d_min`` times the largest D of the scene. Nothing produces NaN.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .brdf import LOBES
from .diffuse_term import envmap_check
from .double_product import DoubleProductTables
from .envmap import effective_alpha
from .errors import AppFusionError
from .frame import Intrinsics, invert_pose
from .normal_refine import tangent_frames
from .points import check_oriented_points, interior_mask, interior_or_all

__all__ = ["RGBPass", "RGBResult", "histogram_percentile"]


@dataclass
class RGBResult:
    """What the RGB pass estimates.

    Attributes
    ----------
    rho_d : (P, 3) float32
        Diffuse albedo per point (linear RGB). Points without a sample get their cluster's median
        (0 when the cluster has no observed point); see ``observed``.
    rho_s : (C, 3) float32
        Specular albedo per cluster (linear RGB, >= 0; 0 for a cluster without specular samples).
    counts : (P,) int64
        Samples (point-frames) that entered each point's histogram.
    observed : (P,) bool
        ``counts > 0``.
    cluster_samples : (C,) int64
        Samples per cluster.
    s2 : (C, 3) float64
        ``sum S^2`` per cluster (the denominator of Eq. 8: how well rho_s is determined).
    notes : list of str
        Warnings (clusters without samples, ...).
    model : list of str
        Per cluster, the rung of the model ladder chosen by held-out error (``"lsq"`` estimator):
        ``"diffuse"`` (rho_s = 0) or the cluster's lobe (``"ward"``, or ``"ggx"`` where the IR pass
        found a GGX lobe, :mod:`appfusion.ward_fit`); the cluster's lobe for every cluster with the
        percentile estimator.
    heldout_rss : (C, 2) float64
        Held-out residual sum of squares per cluster of the diffuse-only and of the Ward model.
    heldout_z : (C,) float64
        The held-out improvement of Ward over diffuse only in standard errors of its mean (the
        ladder keeps Ward from ``ladder_z`` on).
    rho_s_ward : (C, 3) float64
        The Ward rung's rho_s (the pooled slope of Eq. 5, clamped at 0) also for the clusters the
        ladder made diffuse: what the data would say of their lobe ("lsq" estimator only).
    rho_s_sigma : (C, 3) float64 or None
        Standard error of the Ward rung's rho_s ("lsq" estimator only; None otherwise): a sandwich
        estimate over blocks of points (:meth:`RGBPass.rho_s_standard_error`), so that points sharing
        pixels and texture count once.
    """

    rho_d: np.ndarray
    rho_s: np.ndarray
    counts: np.ndarray
    observed: np.ndarray
    cluster_samples: np.ndarray
    s2: np.ndarray
    notes: list = field(default_factory=list)
    model: list = field(default_factory=list)
    heldout_rss: np.ndarray | None = None
    rho_s_ward: np.ndarray | None = None
    heldout_z: np.ndarray | None = None
    rho_s_sigma: np.ndarray | None = None


def histogram_percentile(hist: np.ndarray, lo: float, width: float, pct: float,
                         bin_mean: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Percentile of per-row histograms over log-spaced bins, interpolated inside the bin.

    Parameters
    ----------
    hist : (..., B) integer array
        Counts; bin ``b`` covers ``[lo + b width, lo + (b + 1) width)`` in natural-log units.
    lo, width : float
        Lower edge and width of the bins, ln units.
    pct : float
        Percentile in (0, 100).
    bin_mean : (..., B) uint8 array, optional
        Mean position of each bin's samples inside the bin, in 1/255 of its width. Without it the
        samples are taken as uniform over the bin; with it, as uniform over the widest interval
        centred on their mean that fits in the bin (``[mu - s, mu + s]``, ``s = min(mu, 1 - mu)``), which
        places a tight cluster of samples where it is rather than anywhere in the bin.

    Returns
    -------
    value : (...) float64
        ``exp`` of the interpolated log value; 0 where a row is empty.
    total : (...) int64
        Counts per row.
    """
    h = np.asarray(hist)
    cum = np.cumsum(h, axis=-1, dtype=np.int64)
    total = cum[..., -1]
    q = np.maximum(total * (pct / 100.0), 1e-9)
    b = np.argmax(cum >= q[..., None], axis=-1)                 # first bin reaching the rank
    cb = np.take_along_axis(cum, b[..., None], axis=-1)[..., 0]
    hb = np.take_along_axis(h, b[..., None], axis=-1)[..., 0].astype(np.float64)
    f = np.clip((q - (cb - hb)) / np.maximum(hb, 1.0), 0.0, 1.0)
    if bin_mean is not None:
        mu = np.take_along_axis(np.asarray(bin_mean), b[..., None], axis=-1)[..., 0] / 255.0
        f = mu + np.minimum(mu, 1.0 - mu) * (2.0 * f - 1.0)
    val = np.exp(lo + (b + f) * width)
    return np.where(total > 0, val, 0.0), total


def _voxel_pool(positions: np.ndarray, labels: np.ndarray, values: np.ndarray, h: float) -> np.ndarray:
    """Sums of ``values`` (P, K) over the points of the same label in the 3 x 3 x 3 voxels (side ``h``,
    metres) around each point, interpolated trilinearly between the voxel centres around the point
    (so that decisions taken on them do not follow the voxel grid); (P, K).

    One ``np.add.at`` over the occupied voxels, then each occupied voxel's 27-neighbour sum, then
    each point's 8 surrounding voxel centres (weights of empty ones dropped and the rest renormalised).
    """
    x = np.asarray(positions, np.float64) / h
    key = np.floor(x).astype(np.int64)
    lo = key.min(axis=0) - 2
    key -= lo
    dims = key.max(axis=0) + 3
    lab = np.asarray(labels, np.int64)

    def flat_of(k):                                         # one integer per (label, voxel)
        return ((lab * dims[0] + k[:, 0]) * dims[1] + k[:, 1]) * dims[2] + k[:, 2]

    flat = flat_of(key)
    uniq, inv = np.unique(flat, return_inverse=True)
    sums = np.zeros((len(uniq), values.shape[1]))
    np.add.at(sums, inv.reshape(-1), values)
    pooled = np.zeros_like(sums)                           # each occupied voxel's 27-neighbour sum
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                f = uniq + (dx * dims[1] + dy) * dims[2] + dz
                j = np.minimum(np.searchsorted(uniq, f), len(uniq) - 1)
                ok = uniq[j] == f
                pooled[ok] += sums[j[ok]]
    # trilinear between the centres of the 8 voxels around the point (same label only)
    u = x - lo - 0.5                                        # in units of voxel centres
    base = np.floor(u).astype(np.int64)
    fr = u - base
    out = np.zeros((len(x), values.shape[1]))
    wsum = np.zeros(len(x))
    for cx in (0, 1):
        for cy in (0, 1):
            for cz in (0, 1):
                kk = base + np.array([cx, cy, cz])
                f = flat_of(kk)
                j = np.minimum(np.searchsorted(uniq, f), len(uniq) - 1)
                ok = uniq[j] == f
                w = (np.where(cx, fr[:, 0], 1 - fr[:, 0]) * np.where(cy, fr[:, 1], 1 - fr[:, 1])
                     * np.where(cz, fr[:, 2], 1 - fr[:, 2]))
                w = np.where(ok, w, 0.0)
                out[ok] += w[ok, None] * pooled[j[ok]]
                wsum += w
    own = np.searchsorted(uniq, flat)                       # a point always has its own voxel
    fallback = wsum <= 1e-12
    out[fallback] = pooled[own[fallback]]
    return np.where(fallback[:, None], out, out / np.maximum(wsum, 1e-12)[:, None])


def denoise_rho_d(positions: np.ndarray, rho_d: np.ndarray, stderr: np.ndarray, labels: np.ndarray,
                  k: int = 32, z: float = 2.5, max_dist: float = 0.008) -> np.ndarray:
    """Noise-aware, edge-preserving smoothing of per-point rho_d (a sigma filter; beyond the paper).

    Each point's rho_d becomes the inverse-variance weighted mean over itself and those of its ``k``
    nearest points of the same cluster within ``max_dist`` whose rho_d agrees with its own within ``z`` combined standard
    errors in every channel, ``|rho_q - rho_p| <= z sqrt(se_p^2 + se_q^2)`` (Lee's sigma filter with
    a known noise level per point). Where a point's samples are few, its neighbours' evidence is
    pooled; a texture edge whose step is large against the noise is not crossed, and a point
    measured much better than its neighbours (small ``se``) keeps nearly its own value. Eq. 6 / 5
    estimate each point alone, so its error is its own samples' noise: on `bench --quick`'s small
    scan (12-24 samples a point) the blue paint's red rho_d (0.05) scattered by 11.5 % per point,
    about its standard error (docs/rgb-pass.md §5g).

    Parameters
    ----------
    positions : (P, 3) array
        Points, metres.
    rho_d : (P, 3) array
        Per-point diffuse albedo.
    stderr : (P, 3) array
        Its standard error per point and channel (:meth:`RGBPass.rho_d_stderr`); points with a
        non-finite one are neither changed nor used.
    labels : (P,) int array
        Clusters: a point pools only its own cluster's.
    k : int
        Neighbours considered (the point itself included).
    z : float
        Agreement threshold in standard errors.
    max_dist : float
        Farthest neighbour pooled, metres (default 8 mm). A scan's points lie 1-3 mm apart, so its
        ``k`` nearest are within a few mm (the 32nd: 2 mm on the demo, 6 mm on `bench --quick`'s
        10k-point scan). On a sparse set the truth varies over a neighbourhood by less than the
        acceptance band but more than the noise: on `bench`'s 1200-point sphere (8 mm between
        neighbours, 26 mm to the 32nd) pooling cost 0.72 -> 0.76 % of median error, within 8 mm
        0.74 %.

    Returns
    -------
    (P, 3) float64 array
    """
    from scipy.spatial import cKDTree

    P = np.asarray(positions, np.float64)
    rd = np.asarray(rho_d, np.float64)
    se = np.asarray(stderr, np.float64)
    lab = np.asarray(labels)
    if rd.shape != (len(P), 3) or se.shape != rd.shape or lab.shape != (len(P),):
        raise AppFusionError(f"denoise_rho_d: need positions (P, 3), rho_d and stderr (P, 3), labels (P,); got "
                             f"{P.shape}, {rd.shape}, {se.shape}, {lab.shape}")
    if not (int(k) >= 1 and z > 0 and max_dist > 0):
        raise AppFusionError(f"denoise_rho_d: need k >= 1, z > 0 and max_dist > 0, got k={k}, z={z}, max_dist={max_dist}")
    ok = np.isfinite(se).all(axis=1) & np.isfinite(rd).all(axis=1)
    idx = np.flatnonzero(ok)
    out = rd.copy()
    kk = min(int(k), len(idx))
    if kk < 2:
        return out
    # a sentinel row (index len(idx)) stands for the neighbours beyond max_dist: weight 0, no label
    se = np.r_[np.maximum(se[idx], 1e-9), np.full((1, 3), np.inf)]
    r = np.r_[rd[idx], np.zeros((1, 3))]
    li = np.r_[lab[idx].astype(np.int64), -1]
    _, nb = cKDTree(P[idx]).query(P[idx], kk, distance_upper_bound=float(max_dist))
    out_i = np.empty((len(idx), 3))
    step = max(1, 2_000_000 // (kk * 3))                   # bounded temporaries: ~50 MB a block
    for a in range(0, len(idx), step):
        b = slice(a, min(a + step, len(idx)))
        nq = nb[b]
        sq, rq = se[nq], r[nq]                              # (m, k, 3)
        agree = (np.abs(rq - r[b, None]) <= z * np.sqrt(sq * sq + se[b, None] ** 2)).all(axis=2)
        agree &= li[nq] == li[b, None]
        w = agree[..., None] / (sq * sq)
        out_i[b] = (w * rq).sum(axis=1) / w.sum(axis=1)    # the point itself always agrees
    out[idx] = out_i
    return out


def clipped_mean_factor(zero_fraction) -> np.ndarray:
    """Ratio of the true mean to the observed mean of Gaussian samples clipped at 0, from the
    fraction of samples that read 0 (docs/rgb-pass.md §5h).

    A sensor whose noise is clipped at black reads ``Y = max(X, 0)``, ``X ~ N(mu, sigma^2)``, so
    ``E[Y] = sigma (t Phi(t) + phi(t))`` with ``t = mu / sigma``, while ``P(Y = 0) = Phi(-t)``. The
    zero fraction gives ``t`` without knowing ``sigma``, and ``mu = E[Y] t / (t Phi(t) + phi(t))``.
    1 where nothing was clipped, 0 from half the samples at 0 on (the median is black).

    Parameters
    ----------
    zero_fraction : array_like
        Fraction of samples at 0, in [0, 1].

    Returns
    -------
    ndarray of float64, the same shape, in [0, 1].
    """
    from scipy.special import ndtr, ndtri

    f = np.clip(np.asarray(zero_fraction, np.float64), 0.0, 1.0)
    t = -ndtri(np.clip(f, 1e-12, 0.5))
    h1 = t * ndtr(t) + np.exp(-0.5 * t * t) / math.sqrt(2 * math.pi)
    out = np.where(f >= 0.5, 0.0, t / np.maximum(h1, 1e-300))
    return np.where(f <= 0, 1.0, np.clip(out, 0.0, 1.0))


def _chromaticity(rho_d: np.ndarray) -> np.ndarray:
    """``rho_d / sum rho_d`` per point (P, 3): a colour without its brightness."""
    rd = np.asarray(rho_d, np.float64)
    return rd / np.maximum(rd.sum(axis=1, keepdims=True), 1e-9)


def colour_regions(positions: np.ndarray, rho_d: np.ndarray, tol: float = 0.1, span: float = 0.5,
                   k: int = 9, min_tol: float = 0.0125) -> np.ndarray:
    """Connected regions of one colour on the sampled surface (beyond the paper; used by
    :meth:`RGBPass.reassign_by_model` where the BRDF evidence of single points is too weak).

    Two points are linked when they are among each other's ``k - 1`` nearest neighbours, closer than
    four times the median nearest-neighbour spacing, and their rho_d chromaticities
    (``rho_d / sum rho_d``) differ by at most ``tol`` (L1); a region is a connected component of
    those links. A chain of small steps could link two colours through a soft gradient (a seam's
    blended footprints), so a region whose chromaticity spans more than ``span`` (the summed 2-98 %
    ranges of its three channels) is cut again with half the tolerance, down to ``min_tol`` (below
    that its points stay regions of one). The bulk of a region therefore never spans two colours
    further apart than ``span`` (a thin fringe of blended points, under 2 % of it, can hang on): the
    demo's blue paint and cream label (0.94) never share one; the label's brown stripes and its cream
    (0.37) do, as they should (one material).

    Parameters
    ----------
    positions : (P, 3) array
        Point positions, metres.
    rho_d : (P, 3) array
        Diffuse albedo per point (its colour).
    tol, span, min_tol : float
        Chromaticity tolerances (L1 of ``rho_d / sum rho_d``; a point's own noise is ~0.02).
    k : int
        Neighbours considered per point (itself included).

    Returns
    -------
    (P,) int array of region numbers, 0 .. n_regions - 1.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    P = np.asarray(positions, np.float64)
    n = len(P)
    region = np.arange(n, dtype=np.int64)
    if n < 2:
        return region
    chrom = _chromaticity(rho_d)
    kk = min(int(k), n)
    dd, nb = cKDTree(P).query(P, k=kk)
    reach = 4.0 * float(np.median(dd[:, 1]))
    near = dd[:, 1:] < reach
    cdiff = np.abs(chrom[nb[:, 1:]] - chrom[:, None]).sum(axis=-1)
    todo = [(np.arange(n), float(tol))]
    nxt = 0
    while todo:
        idx, t = todo.pop()
        if t < min_tol:
            region[idx] = nxt + np.arange(len(idx))
            nxt += len(idx)
            continue
        inside = np.zeros(n, bool)
        inside[idx] = True
        loc = np.full(n, -1, np.int64)
        loc[idx] = np.arange(len(idx))
        ok = near[idx] & (cdiff[idx] <= t) & inside[nb[idx, 1:]]
        i = np.repeat(np.arange(len(idx)), kk - 1)[ok.ravel()]
        j = loc[nb[idx, 1:].ravel()[ok.ravel()]]
        g = coo_matrix((np.ones(len(i)), (i, j)), shape=(len(idx), len(idx)))
        nc, comp = connected_components(g, directed=False)
        order = np.argsort(comp, kind="stable")
        bounds = np.searchsorted(comp[order], np.arange(nc + 1))
        for c in range(nc):
            members = idx[order[bounds[c]:bounds[c + 1]]]
            if len(members) > 2:
                lo, hi = np.percentile(chrom[members], [2, 98], axis=0)
                if float((hi - lo).sum()) > span:
                    todo.append((members, t / 2))
                    continue
            region[members] = nxt
            nxt += 1
    return region


def _choose_by_evidence(rss: np.ndarray, var: np.ndarray, cands: np.ndarray, movable: np.ndarray,
                        positions: np.ndarray, rho_d: np.ndarray, min_z: float, radius: float,
                        colour_tol: float = 0.1, regions: np.ndarray | None = None,
                        own: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Cluster per point from pooled model residuals, colour where they do not decide
    (:meth:`RGBPass.reassign_by_model`).

    Parameters
    ----------
    rss, var : (P, K) arrays
        Pooled RSS of each candidate model, and the variance of its lobe's share of it.
    cands : (K,) int array
        The candidates' cluster numbers.
    movable : (P,) bool array
        Points that may take any candidate (others: the result there is the best candidate but unused).
    positions : (P, 3) array
    rho_d : (P, 3) array
        The points' diffuse albedo (their colour).
    min_z : float
        Gap between the best and second-best RSS, in standard errors, below which colour decides.
    radius : float
        Metres: how far a weak point looks for confident neighbours (its 32 nearest).
    colour_tol : float
        Largest L1 distance of rho_d chromaticities (``rho_d / sum rho_d``) that counts as the same
        colour (the demo's blue paint and cream label: 0.94; the label's brown stripes and cream: 0.37;
        a point's own noise ~0.02).
    regions : (P,) int array, optional
        Colour regions (:func:`colour_regions`). A weak point first takes the best model of its
        region, the points' own residuals ``own`` summed over the region's movable points, where that
        sum decides (a gap of at least ``min_z`` standard errors).
    own : ((P, K), (P, K)) arrays, optional
        The points' own (unpooled) residuals and variances, for ``regions``.

    Returns
    -------
    (P,) int array of cluster numbers: the best model's; for a weak point its colour region's best
    model where the region decides, else the cluster of its confident neighbour with the closest
    rho_d chromaticity if that is the same colour, else the best model's.
    """
    order = np.argsort(rss, axis=1, kind="stable")
    rows = np.arange(len(rss))
    best, second = order[:, 0], order[:, 1]
    gap = rss[rows, second] - rss[rows, best]
    z = gap / np.sqrt(np.maximum(var[rows, best] + var[rows, second], 1e-300))
    choice = np.asarray(cands)[best]
    low = z < float(min_z)
    weak = movable & low
    strong = np.flatnonzero(movable & ~low)
    out = choice.copy()
    if weak.any() and regions is not None and own is not None:
        reg = np.asarray(regions, np.int64)
        nr = int(reg.max()) + 1 if len(reg) else 0
        R = np.zeros((nr, rss.shape[1]))
        V = np.zeros((nr, rss.shape[1]))
        np.add.at(R, reg[movable], np.asarray(own[0], np.float64)[movable])
        np.add.at(V, reg[movable], np.asarray(own[1], np.float64)[movable])
        ro = np.argsort(R, axis=1, kind="stable")
        rr = np.arange(nr)
        rz = (R[rr, ro[:, 1]] - R[rr, ro[:, 0]]) / np.sqrt(np.maximum(V[rr, ro[:, 0]] + V[rr, ro[:, 1]], 1e-300))
        decided = weak & (rz[reg] >= float(min_z))
        out[decided] = np.asarray(cands)[ro[reg[decided], 0]]
        weak = weak & ~decided
    if not weak.any() or len(strong) == 0:
        return out
    chrom = _chromaticity(rho_d)
    wi = np.flatnonzero(weak)
    dd, nb = cKDTree(positions[strong]).query(positions[wi], k=min(32, len(strong)), distance_upper_bound=float(radius))
    dd, nb = dd.reshape(len(wi), -1), nb.reshape(len(wi), -1)
    ok = np.isfinite(dd)
    nbi = strong[np.where(ok, nb, 0)]
    cd = np.where(ok, np.abs(chrom[nbi] - chrom[wi][:, None]).sum(axis=-1), np.inf)
    j = np.argmin(cd, axis=1)
    has = cd[np.arange(len(wi)), j] <= float(colour_tol)          # a neighbour of the same colour
    pick = nbi[np.arange(len(wi)), j]
    out[wi[has]] = choice[pick[has]]
    return out


def _normal_order(normals: np.ndarray) -> np.ndarray:
    """Permutation sorting unit normals (P, 3) along a Morton (Z-order) curve of their octahedral
    coordinates (face, then 10 + 10 bits)."""
    from . import octahedral as octa

    face, uv = octa.sphere_encode(normals)
    q = np.clip(((uv + 1.0) * 512).astype(np.int64), 0, 1023)

    def spread(x):
        x = (x | (x << 8)) & 0x00FF00FF
        x = (x | (x << 4)) & 0x0F0F0F0F
        x = (x | (x << 2)) & 0x33333333
        return (x | (x << 1)) & 0x55555555

    code = (face << 20) | (spread(q[:, 1]) << 1) | spread(q[:, 0])
    return np.argsort(code, kind="stable")


def _lobe_names(names, n: int, what: str) -> np.ndarray:
    """(n,) lobe names (``"<U8"``) from ``names`` (default all Ward); anything but ``n`` names among
    :data:`appfusion.brdf.LOBES` is one AppFusionError naming ``what``."""
    lob = np.array(["ward"] * n if names is None else [str(x) for x in np.asarray(names).reshape(-1)], dtype="<U8")
    if lob.shape != (n,) or not np.isin(lob, LOBES).all():
        raise AppFusionError(f"RGBPass: {what} must be {n} name(s) among {', '.join(LOBES)}, got {lob.tolist()}")
    return lob


#: the six distinct products X_i X_j of the footprint's three terms, in the order of RGBPass's sums
_FP_I = np.array([0, 0, 0, 1, 1, 2])
_FP_J = np.array([0, 1, 2, 1, 2, 2])


def _ward_only(lobe) -> bool:
    """True when ``lobe`` (a name or an array of names) names only Ward lobes."""
    return lobe == "ward" if isinstance(lobe, str) else bool((np.asarray(lobe) == "ward").all())


class RGBPass:
    """Streaming estimator of rho_d (per point) and rho_s (per cluster), paper §5.3.

    GGX lobes (``lobes``) take at least ``NEAR_FIELD_GGX_MIN_SAMPLES`` (16) lobe samples for the
    support plane's ``dS`` (:meth:`near_field_dS`).

    Parameters
    ----------
    positions, normals : (P, 3) array
        Sampled surface points (world / marker frame, metres) and their unit normals.
    labels : (P,) int array
        Cluster of each point, in ``[0, C)``.
    alphas : (C,) array
        Roughness of each cluster's lobe (IR pass).
    envmap : (2, N, N, 3) array
        Environment radiance in the world frame (lighting pass), ``appfusion.octahedral`` layout.
    tables : DoubleProductTables, optional
        Prebuilt tables of the same environment; built for the clusters' alphas when omitted.
    bins : int
        Histogram bins per point and channel.
    ratio_range : (float, float)
        Range of ``L / D`` the bins span (log-spaced).
    percentile : float
        Percentile of ``L / D`` taken as rho_d (paper: 10th).
    estimator : {"lsq", "percentile"}
        ``"percentile"``: the paper's Eq. 6 (a low percentile of ``L / D`` per point) then Eq. 8.
        ``"lsq"`` (default): the joint least-squares solution of Eq. 5 over all samples, rho_d per point
        and rho_s per cluster, from per-point running sums (see :meth:`result`); the percentile stays
        the fallback for points with fewer than ``min_lsq_samples`` samples. The percentile is biased
        low by sensor noise (about -1.3 sigma at the 10th: -7 % on the synthetic Kinect's RGB, whose
        samples scatter by ~5 %); the least-squares mean is not.
    min_lsq_samples : int
        Samples a point needs before its least-squares rho_d replaces the percentile (default 3).
    lobes : (C,) sequence of str, optional
        Each cluster's specular lobe, one of :data:`appfusion.brdf.LOBES` (default all ``"ward"``, the
        paper's); ``"ggx"`` is the model ladder's third rung, chosen by the IR pass's fit. S is read
        from the double-product tables of each point's own lobe and alpha.
    specular : (C,) bool array, optional
        Clusters that may have a specular lobe (default all). A cluster the IR pass found diffuse
        (model ladder's first rung) gets ``S = 0``: no double-product table is built for its alpha
        and its samples skip the S look-up; its rho_s is 0.
    ladder_margin, ladder_z, ladder_margin_z : float
        Model ladder (``"lsq"``): a cluster keeps its Ward lobe only if that lowers the held-out
        residual sum of squares by more than the fraction ``ladder_margin`` (default 0.2 %) with an
        improvement of at least ``ladder_margin_z`` standard errors of the mean per-point improvement
        (default 3), or by at least ``ladder_z`` standard errors whatever the fraction (default 5);
        otherwise it is diffuse (rho_s = 0). See :meth:`_lsq`.
    interior_m : float
        rho_s and the ladder use only the points farther than this from any point of another
        cluster (metres, default 5 mm), where their cluster has enough of them: along a material
        seam a point's pixels and its label mix both materials. 0: every point.
    dark, saturated : float
        Linear-RGB thresholds of the skipped samples.
    min_cos : float
        Smallest ``n . w_o`` used (default cos 75 degrees).
    d_min : float
        Points whose D (any channel) is below ``d_min`` times the scene's largest D are not sampled.
    max_dist : float, optional
        Registration distance, metres (default: :func:`appfusion.points.register_pixels`'s).
    registration : {"pixels", "points"}
        ``"pixels"`` (paper): every depth pixel to its nearest point (:func:`appfusion.points.register_pixels`),
        the pixels of a point averaged. ``"points"``: every point projected into the depth image, kept
        where the depth there agrees within ``depth_tol`` (visible) and it faces the camera; one RGB
        sample per point, read where the point projects (``rgb_sampling``).
    depth_tol : float
        Visibility tolerance of ``"points"`` registration, metres.
    rgb_sampling : {"bilinear", "nearest"}
        How a sample reads the RGB image where its point projects: the nearest pixel (up to half a
        pixel off; default) or bilinear between the four pixels around it, a low-pass that read
        sharp highlights ~1 % lower and blurred a 320 x 240 scan's colour seam (docs/rgb-pass.md §6).
    table_kwargs : dict, optional
        Passed to :class:`~appfusion.double_product.DoubleProductTables`.
    near_field : appfusion.near_field.SupportPlaneLight, optional
        The support plane as near-field light: its corrections are added to D (once per point) and
        to S (per sample whose lobe reaches below the horizon); None keeps the paper's distant light.
    diffuse_tau : float or None
        rho_d of ``estimator="lsq"`` weights each sample by ``1 / (1 + (S / (tau D))^2)`` (means over
        RGB; views without a highlight count most, as Eq. 6 intends); None: the unweighted least
        squares. rho_s is the unweighted pooled slope either way.
    near_field_samples : int
        Ward lobe samples per RGB sample for the near-field ``dS``.
    compare_alphas : sequence of float, optional
        Lobes every point is also measured against (:meth:`reassign_by_model`): per point and alpha,
        the running sums of S, S^2, S L and of the diffuse weighting with the S of that alpha (for the
        points whose own lobe is another one; 128 bytes per point and alpha).
    compare_lobes : sequence of str, optional
        The lobe of each compare alpha (``"ward"`` or ``"ggx"``; default all Ward): a GGX cluster's
        lobe is measured on the other points with its own shape, so that points can move to and from it.
    map_blur_var : float
        Blur variance per axis (rad^2) the environment map carries (a captured map's
        ``meta["blur_var_rad2"]``, :func:`appfusion.envmap.map_blur_var`). S is read against the map at
        the effective roughness :func:`appfusion.envmap.effective_alpha` of each lobe, so that a sharp
        lobe does not see the lights widened twice (demo, alpha 0.06: rho_s +1.9 % without). 0: the
        lobes' own alphas. The support plane's ``dS`` keeps the lobe's alpha (the plane is modelled,
        not blurred).
    clip_correction, clip_pool_k : bool, int
        Least-squares rho_d (``"lsq"``) corrects each point's means of L for the sensor noise clipped
        at black in dark channels (:func:`clipped_mean_factor`), from the fraction of samples that
        read exactly 0 over the point and its nearest points of the same cluster within 8 mm
        (``clip_pool_k`` in all, default 32; docs/rgb-pass.md §5h). Without it a channel a noise
        width or two above black reads high.
    se_block_m : float
        Side (m) of the blocks of points whose slope terms :meth:`rho_s_standard_error` takes as
        independent (default 4 mm: a few pixels on the object at 1 m; docs/rgb-pass.md §5i).
    s_replicate : int
        With the near field on, the support plane's ``dS`` is a Monte Carlo estimate, and its noise
        in the regressor S of Eq. 5 dilutes the pooled slope (errors in variables: ``rho_s`` times
        ``var S_true / (var S_true + var noise)``, within points). A second, independent estimate
        ``S_b`` with this many lobe samples is kept per sample (two more sums per point and channel,
        ``sum S_b`` and ``sum S S_b``), and rho_s's denominator is the within-point covariance of the
        two estimates, whose noises are independent: an instrumental variable, unbiased for any
        sample count (:meth:`_lsq`; docs/rgb-pass.md §5k). 0 (default): the plain slope. Ignored
        without the near field (S is then exact). It costs a second ``dS`` per sample: a scan asks
        for it in its offline re-sweeps only (``ScanConfig.rho_s_replicate``), where the update
        rate does not matter (with it the live sweep's near-field update rate fell from ~30 to 19
        frames/s).
    footprint : bool
        Model the pixel footprint's blur of the print in rho_s's regression (default False;
        :meth:`_lsq`, docs/rgb-pass.md §5l). A sample reads the albedo averaged over its pixel's
        footprint on the surface, whose size and shape change with the view; where the print is
        curved in albedo (a stripe, a block's edge) the average changes with the view too, and the
        part of that change that goes with S lands in the slope: on the demo's label (truth 0.03)
        the darkest quarter of the points read -0.06 and the brightest +0.09. To second order the
        blur adds ``c/2 D tr(H Sigma)`` to a sample, ``H`` the Hessian of rho_d along the surface
        (fitted to the neighbours' rho_d, :meth:`_footprint_projector`), ``Sigma = d^2 (I + t t^T /
        cos^2)`` the footprint's shape in the point's tangent frame (``d`` the camera's distance,
        ``t`` the view's tangential part, ``cos`` its cosine with the normal) and ``c`` the
        footprint's variance per axis at 1 m (a pixel box and the nearest-pixel offset give ``(1/6) /
        f^2``; fitted, so that optics and demosaicing count too). Per-point sums of Sigma's three terms, their products and their
        products with S and L (27 numbers per point) let ``c`` be fitted with rho_s, one value for all
        clusters and channels (:attr:`footprint_c`). A scan asks for it in its offline re-sweeps
        (``ScanConfig.rho_s_footprint``).
    """

    #: lobe samples of the support plane's dS for a GGX lobe, at least (:meth:`near_field_dS`)
    NEAR_FIELD_GGX_MIN_SAMPLES = 16

    def __init__(self, positions, normals, labels, alphas, envmap, *, tables: DoubleProductTables | None = None,
                 bins: int = 64, ratio_range: tuple[float, float] = (1 / 64, 2.0), percentile: float = 10.0,
                 estimator: str = "lsq", min_lsq_samples: int = 3, ladder_margin: float = 0.002,
                 ladder_z: float = 5.0, ladder_margin_z: float = 3.0, interior_m: float = 0.005,
                 specular=None, lobes=None,
                 dark: float = 0.01, saturated: float = 0.98, min_cos: float = math.cos(math.radians(75)),
                 d_min: float = 0.01, max_dist: float | None = None, registration: str = "points",
                 depth_tol: float = 0.01, table_kwargs: dict | None = None, near_field=None,
                 diffuse_tau: float | None = 0.25, near_field_samples: int = 4, compare_alphas=None,
                 compare_lobes=None, rgb_sampling: str = "nearest",
                 map_blur_var: float = 0.0, clip_correction: bool = True, clip_pool_k: int = 32,
                 se_block_m: float = 0.004, s_replicate: int = 0, footprint: bool = False):
        P, N = check_oriented_points(positions, normals, "RGBPass")
        lab = np.asarray(labels)
        if lab.shape != (len(P),) or not np.issubdtype(lab.dtype, np.integer):
            raise AppFusionError(f"RGBPass: labels must be ({len(P)},) integers, got {lab.shape} {lab.dtype}")
        al = np.atleast_1d(np.asarray(alphas, dtype=np.float64))
        if al.ndim != 1 or not np.isfinite(al).all() or (al <= 0).any():
            raise AppFusionError(f"RGBPass: alphas must be positive finite roughnesses per cluster, got {al}")
        if lab.min() < 0 or lab.max() >= len(al):
            raise AppFusionError(f"RGBPass: labels must lie in [0, {len(al)}) (one alpha per cluster), "
                                 f"got [{int(lab.min())}, {int(lab.max())}]")
        if estimator not in ("lsq", "percentile"):
            raise AppFusionError(f"RGBPass: estimator must be 'lsq' or 'percentile', got {estimator!r}")
        if registration not in ("pixels", "points"):
            raise AppFusionError(f"RGBPass: registration must be 'pixels' or 'points', got {registration!r}")
        if rgb_sampling not in ("bilinear", "nearest"):
            raise AppFusionError(f"RGBPass: rgb_sampling must be 'bilinear' or 'nearest', got {rgb_sampling!r}")
        self.rgb_sampling = rgb_sampling
        if bins < 4 or not (0 < ratio_range[0] < ratio_range[1]) or not 0 < percentile < 100:
            raise AppFusionError(f"RGBPass: need bins >= 4, 0 < ratio_range[0] < ratio_range[1], 0 < percentile < 100; "
                                 f"got {bins}, {ratio_range}, {percentile}")
        env = envmap_check(envmap, "RGBPass envmap")
        # Points are kept internally in the order of a Morton code of their normals, so that the
        # samples of a frame read neighbouring rows of the S tables (cache locality); public indices
        # and results are in the caller's order (self._rank maps caller -> internal).
        order = _normal_order(N)
        self._order = order
        self._rank = np.empty_like(order)
        self._rank[order] = np.arange(len(order))
        P, N, lab = P[order], N[order], lab[order]
        self.positions = np.ascontiguousarray(P, dtype=np.float32)
        self.normals = np.ascontiguousarray(N, dtype=np.float32)
        self._ndotp = np.einsum("ij,ij->i", self.normals, self.positions)
        self.labels = lab.astype(np.int64)
        self.alphas = al
        self.n_clusters = len(al)
        t0 = time.perf_counter()
        spec = np.ones(len(al), bool) if specular is None else np.asarray(specular, bool).reshape(-1)
        if spec.shape != al.shape:
            raise AppFusionError(f"RGBPass: specular must be {len(al)} flags (one per cluster), got {spec.shape}")
        self.specular = spec
        self._spec_point = spec[self.labels]
        lob = _lobe_names(lobes, len(al), "lobes (one per cluster)")
        self.lobes = lob
        self.point_lobe = lob[self.labels]                      # (P,) the lobe of each point's S sums
        spec_cl = np.unique(self.labels[self._spec_point])
        used = {lb: np.unique(al[spec_cl[lob[spec_cl] == lb]]) for lb in LOBES}
        cmp_al = np.zeros(0) if compare_alphas is None else np.asarray(compare_alphas, np.float64).reshape(-1)
        if not (np.isfinite(cmp_al).all() and (cmp_al > 0).all()):
            raise AppFusionError(f"RGBPass: compare_alphas must be positive finite roughnesses, got {cmp_al}")
        self.compare_alphas = cmp_al
        cmp_lb = _lobe_names(compare_lobes, len(cmp_al), "compare_lobes (one per compare alpha)")
        self.compare_lobes = cmp_lb
        for lb in LOBES:
            used[lb] = np.unique(np.r_[used[lb], cmp_al[cmp_lb == lb]])
        if not (np.isfinite(map_blur_var) and map_blur_var >= 0):
            raise AppFusionError(f"RGBPass: map_blur_var must be a finite variance >= 0 (rad^2), got {map_blur_var}")
        self.map_blur_var = float(map_blur_var)
        used = {lb: np.unique(self._map_alpha(a)) for lb, a in used.items()}
        #: the (lobe, alpha) of every S table this pass reads (DoubleProductTables.keep_only)
        self.table_keys = {(lb, float(a)) for lb, a_lb in used.items() for a in a_lb}
        if tables is None:
            tables = DoubleProductTables(env, used["ward"], **(table_kwargs or {}))
        else:
            for a in used["ward"]:
                tables.add_alpha(float(a))
        for lb, a_lb in used.items():
            if lb != "ward":
                for a in a_lb:
                    tables.add_alpha(float(a), lobe=lb)
        self.tables = tables
        self.table_seconds = time.perf_counter() - t0
        self.D = tables.D(N).astype(np.float32)                      # (P, 3), fixed per point
        # the support plane as near-field light (appfusion.near_field): D and S see the paper and the
        # circles from each point instead of from the mirror ball
        self.near_field = near_field
        self.near_field_samples = int(near_field_samples)
        if not (isinstance(s_replicate, (int, np.integer)) and 0 <= int(s_replicate) <= 256):
            raise AppFusionError(f"RGBPass: s_replicate must be an integer in [0, 256] (lobe samples of the "
                                 f"second dS estimate; 0: none), got {s_replicate!r}")
        self.s_replicate = int(s_replicate)
        if near_field is not None:
            t1 = time.perf_counter()
            self.D = np.maximum(self.D + near_field.delta_D(P, N), 0.0).astype(np.float32)
            self.near_field_seconds = time.perf_counter() - t1
        dmax = float(self.D.max()) if self.D.size else 0.0
        self.lit = (self.D.min(axis=1) > d_min * dmax) if dmax > 0 else np.zeros(len(P), bool)
        self.point_alpha = al[self.labels]
        self.bins = int(bins)
        self.log_lo = math.log(ratio_range[0])
        self.log_width = (math.log(ratio_range[1]) - self.log_lo) / self.bins
        self.percentile = float(percentile)
        self.estimator = estimator
        self.ladder_margin = float(ladder_margin)
        self.ladder_z = float(ladder_z)
        self.ladder_margin_z = float(ladder_margin_z)
        self.interior_m = float(interior_m)
        self._interior_key = None
        self.heldout_z = None
        self.model: list = [str(x) for x in lob]
        self.heldout_rss = None
        self.rho_s_ward = None
        self.rho_s_sigma = None
        if not (np.isfinite(se_block_m) and se_block_m > 0):
            raise AppFusionError(f"RGBPass: se_block_m must be a positive length (m), got {se_block_m}")
        self.se_block_m = float(se_block_m)
        self._se_voxel = None                                     # voxel number of each point (cached)
        self.min_lsq_samples = max(1, int(min_lsq_samples))
        self.dark, self.saturated, self.min_cos = float(dark), float(saturated), float(min_cos)
        self.max_dist = max_dist
        self.registration = registration
        self.depth_tol = float(depth_tol)
        n = len(P)
        self.hist = np.zeros((n, 3, self.bins), np.uint16)
        self.bin_mean = np.zeros((n, 3, self.bins), np.uint8)       # mean position in the bin, /255
        self._rng = np.random.default_rng(0)
        self.counts = np.zeros(n, np.int64)
        # samples whose channel read exactly 0 (noise clipped at black), per point and channel
        self.zeros = np.zeros((n, 3), np.int32)
        self.clip_correction = bool(clip_correction)
        self.clip_pool_k = max(1, int(clip_pool_k))
        self._clip_nbr = None
        # the per-point sums, (n, 3) each, are views of one (n, 8, 3) array, so that a frame gathers
        # and scatters a point's 24 sums at once (one cache-friendly row, not eight scattered ones):
        # sum S^2, SL, SD, S, L, L^2, and the diffuse weighting's sum wL, wS. sum S and sum L: with D
        # fixed per point, these are every moment the least squares of Eq. 5 needs; sum L^2 gives the
        # model ladder's held-out residuals
        self._sums = np.zeros((n, 8, 3))
        (self.sum_s2, self.sum_sl, self.sum_sd, self.sum_s, self.sum_l, self.sum_l2,
         self.sum_wl, self.sum_ws) = (self._sums[:, j] for j in range(8))
        # diffuse weighting of rho_d (lsq): sum w, sum w L, sum w S with w = 1 / (1 + (S / (tau D))^2)
        if diffuse_tau is not None and not diffuse_tau > 0:
            raise AppFusionError(f"RGBPass: diffuse_tau must be > 0 or None, got {diffuse_tau}")
        self.diffuse_tau = None if diffuse_tau is None else float(diffuse_tau)
        self.sum_w = np.zeros(n)
        # the instrumental variable of rho_s (s_replicate): sum S_b and sum S S_b per point and channel,
        # S_b a second estimate of S whose Monte Carlo noise is independent of S's; own_s: the point's
        # S sums are those of its own lobe, and so belong with these two and with the footprint's
        # sums of X S (reassign_by_model swaps in a compare lobe's S sums, which have neither: such a
        # point's denominator is its V_SS and it has no footprint term)
        self._rep = np.zeros((n, 2, 3))
        self.sum_sb, self.sum_ssb = self._rep[:, 0], self._rep[:, 1]
        self.own_s = np.ones(n, bool)
        # the pixel footprint's terms (footprint): per point, sum X (3), the 6 distinct sums X_i X_j,
        # sum X_i S_c and sum X_i L_c (9 each), X = Sigma's (11, 12, 22) terms in the point's tangent
        # frame (t1, t2); rows of one (n, 27) array, gathered and scattered at once
        if not isinstance(footprint, (bool, np.bool_)):
            raise AppFusionError(f"RGBPass: footprint must be True or False, got {footprint!r}")
        self.footprint = bool(footprint)
        self.footprint_c = None
        self.rho_s_unblurred = None
        self._fp_proj = None
        if self.footprint:
            self._fp = np.zeros((n, 27))
            self._fp_t1, self._fp_t2 = (t.astype(np.float32) for t in tangent_frames(self.normals))
        else:
            self._fp = np.zeros((0, 27))
        # the same S sums with each compare alpha's S (reassign_by_model), for the points whose own
        # lobe differs (the others' own sums are those): (alpha, point, channel); sum w (alpha, point)
        m = len(self.compare_alphas)
        self.cmp_s, self.cmp_s2, self.cmp_sl, self.cmp_wl, self.cmp_ws = (np.zeros((m, n, 3)) for _ in range(5))
        self.cmp_w = np.zeros((m, n))
        self.frames = 0
        self.stats = {"samples": 0, "skipped_dark": 0, "skipped_saturated": 0, "skipped_grazing": 0,
                      "skipped_unlit": 0, "register_s": 0.0, "update_s": 0.0}

    @property
    def nbytes(self) -> int:
        """Bytes of the per-point state (histograms and sums), excluding the tables."""
        return int(self.hist.nbytes + self.bin_mean.nbytes + self.counts.nbytes + self.zeros.nbytes + 8 * self.sum_s2.nbytes
                   + self.sum_w.nbytes + self.D.nbytes + 5 * self.cmp_s.nbytes + self.cmp_w.nbytes
                   + self._rep.nbytes + self.own_s.nbytes + self._fp.nbytes)

    # -- per-frame --------------------------------------------------------------------------
    def add_frame(self, rgb_linear: np.ndarray, depth: np.ndarray, rgb_intrinsics: Intrinsics,
                  depth_intrinsics: Intrinsics, pose: np.ndarray, depth_to_rgb: np.ndarray) -> int:
        """Register one depth + RGB frame and update the estimators.

        Parameters
        ----------
        rgb_linear : (H, W, 3) float array
            Calibrated linear RGB (``Frame.rgb_linear()`` after white balance), in [0, 1].
        depth : (h, w) float array
            Depth image, metres, NaN invalid.
        rgb_intrinsics, depth_intrinsics : Intrinsics
            Of the two images.
        pose : (4, 4) array
            Camera-to-world pose of the depth camera (world = marker frame).
        depth_to_rgb : (4, 4) array
            Depth-camera to RGB-camera transform.

        Returns
        -------
        int
            Samples (point-frames) used.
        """
        from .points import register_pixels

        rgb = np.asarray(rgb_linear)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[:2] != rgb_intrinsics.shape:
            raise AppFusionError(f"RGBPass.add_frame: rgb image of shape {rgb.shape} does not match the RGB "
                                 f"intrinsics ({rgb_intrinsics.height}x{rgb_intrinsics.width}x3)")
        if not np.issubdtype(rgb.dtype, np.floating):
            raise AppFusionError(f"RGBPass.add_frame: rgb must be linear float (Frame.rgb_linear()), got {rgb.dtype}")
        depth = np.asarray(depth)
        if depth.shape != depth_intrinsics.shape:
            raise AppFusionError(f"RGBPass.add_frame: depth image of shape {depth.shape} does not match the depth "
                                 f"intrinsics ({depth_intrinsics.height}x{depth_intrinsics.width})")
        T = np.asarray(pose, dtype=np.float64)
        E = np.asarray(depth_to_rgb, dtype=np.float64)
        for name, M in (("pose", T), ("depth_to_rgb", E)):
            if M.shape != (4, 4) or not np.isfinite(M).all():
                raise AppFusionError(f"RGBPass.add_frame: {name} must be a finite 4x4 matrix, got shape {M.shape}")
        t0 = time.perf_counter()
        if self.registration == "pixels":
            pix, pts = register_pixels(self.positions, self.normals, depth, depth_intrinsics, T, self.max_dist)
            Xd = self._backproject(depth, depth_intrinsics, pix)
        else:
            pts, Xd = self._project_points(depth, depth_intrinsics, T)
        t1 = time.perf_counter()
        self.stats["register_s"] += t1 - t0
        used = self._update(rgb, pts, Xd, rgb_intrinsics, T, E)
        self.stats["update_s"] += time.perf_counter() - t1
        self.frames += 1
        return used

    def _project_points(self, depth, K: Intrinsics, T) -> tuple[np.ndarray, tuple]:
        """Visible points by projection: internal point indices and their depth-camera coordinates."""
        cam = T[:3, 3].astype(np.float32)
        idx = np.flatnonzero(self.normals @ cam > self._ndotp)               # facing the camera
        Ti = invert_pose(T)
        R = Ti[:3, :3].astype(np.float32)
        t = Ti[:3, 3].astype(np.float32)
        X = self.positions[idx] @ R.T + t
        z = X[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = np.float32(1.0) / z
            u = np.rint(np.float32(K.fx) * X[:, 0] * iz + np.float32(K.cx))
            v = np.rint(np.float32(K.fy) * X[:, 1] * iz + np.float32(K.cy))
        ok = (z > 1e-3) & (u >= 0) & (u <= K.width - 1) & (v >= 0) & (v <= K.height - 1)
        sel = np.flatnonzero(ok)
        pix = v[sel].astype(np.int64) * K.width + u[sel].astype(np.int64)
        vis = np.abs(depth.reshape(-1)[pix] - z[sel]) <= self.depth_tol       # NaN depth -> not visible
        sel = sel[vis]
        return idx[sel], (X[sel, 0], X[sel, 1], z[sel])

    @staticmethod
    def _backproject(depth, K: Intrinsics, pix) -> tuple:
        z = depth.reshape(-1)[pix].astype(np.float32)
        u = (pix % K.width).astype(np.float32)
        v = (pix // K.width).astype(np.float32)
        return ((u - np.float32(K.cx)) * (z / np.float32(K.fx)), (v - np.float32(K.cy)) * (z / np.float32(K.fy)), z)

    def _update(self, rgb, pts, Xd, Ki: Intrinsics, T, E) -> int:
        pts, col, C = self._lookup_rgb(rgb, pts, Xd, Ki, T, E)
        if len(pts) == 0:
            return 0
        if self.registration == "points":                    # one pixel per point already: _add skips
            return self._add(pts, col, C, np.zeros(len(pts), bool), unique=True)   # clipped / NaN ones
        c0, c1, c2 = col[:, 0], col[:, 1], col[:, 2]            # channel-wise: reductions along the
        sat = np.maximum(np.maximum(c0, c1), c2) >= self.saturated   # short axis are ~3x slower
        bad_in = ~np.isfinite(c0 + c1 + c2)
        if bad_in.any():                                        # NaN pixels in the image: treat as saturated
            sat |= bad_in
            col = np.where(bad_in[:, None], 0.0, col)
        # one sample per point and frame: mean of its pixels; saturated if any pixel is
        n = len(self.positions)
        cnt = np.bincount(pts, minlength=n)
        p = np.flatnonzero(cnt)
        k = cnt[p].astype(np.float32)
        L = np.stack([np.bincount(pts, weights=col[:, c], minlength=n)[p] for c in range(3)], axis=1) / k[:, None]
        satp = np.bincount(pts, weights=sat.astype(np.float64), minlength=n)[p] > 0
        return self._add(p, L, C, satp, unique=True)

    def _lookup_rgb(self, rgb, pts, Xd, Ki: Intrinsics, T, E) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The RGB pixel of each registered sample: internal point indices ``pts`` (k,) and their
        depth-camera coordinates ``Xd`` -> (points kept (m,), their RGB (m, 3), RGB camera centre in
        the world (3,)); samples that fall outside the RGB image are dropped."""
        C = (T @ invert_pose(E))[:3, 3]                      # RGB camera centre, world
        if len(pts) == 0:
            return pts, np.zeros((0, 3), np.float32), C
        H, W = rgb.shape[:2]
        # depth-camera point -> RGB camera -> RGB pixel
        x, y, z = Xd
        R = E[:3, :3].astype(np.float32)
        t = E[:3, 3].astype(np.float32)
        xr = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
        yr = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
        zr = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            ur = np.float32(Ki.fx) * xr / zr + np.float32(Ki.cx)
            vr = np.float32(Ki.fy) * yr / zr + np.float32(Ki.cy)
        ok = (zr > 1e-3) & (ur >= -0.5) & (ur < W - 0.5) & (vr >= -0.5) & (vr < H - 0.5)
        if not ok.all():
            pts, ur, vr = pts[ok], ur[ok], vr[ok]
        flat = rgb.reshape(-1, 3)
        if self.rgb_sampling == "nearest" or W < 2 or H < 2:
            ui = np.clip(np.rint(ur).astype(np.int64), 0, W - 1)
            vi = np.clip(np.rint(vr).astype(np.int64), 0, H - 1)
            return pts, flat.take(vi * W + ui, axis=0), C
        # bilinear between the four pixel centres around the projection (clamped at the border); a
        # NaN pixel among them makes the sample NaN, which _add skips
        u0 = np.clip(np.floor(ur).astype(np.int64), 0, W - 2)
        v0 = np.clip(np.floor(vr).astype(np.int64), 0, H - 2)
        au = np.clip(ur - u0, 0.0, 1.0).astype(np.float32)[:, None]
        av = np.clip(vr - v0, 0.0, 1.0).astype(np.float32)[:, None]
        i = v0 * W + u0
        top = flat.take(i, axis=0).astype(np.float32)
        top += (flat.take(i + 1, axis=0) - top) * au
        bot = flat.take(i + W, axis=0).astype(np.float32)
        bot += (flat.take(i + W + 1, axis=0) - bot) * au
        top += (bot - top) * av
        return pts, top, C

    def add_samples(self, point_idx: np.ndarray, L: np.ndarray, camera_center: np.ndarray,
                    saturated: np.ndarray | None = None) -> int:
        """Add registered samples directly (a front end that registers pixels itself).

        Parameters
        ----------
        point_idx : (k,) int array
            Points (indices into the arrays given to the constructor); may repeat.
        L : (k, 3) array
            Calibrated linear RGB of each sample.
        camera_center : (3,) or (k, 3) array
            RGB camera centre(s), world frame (``w_o`` points from the point to it).
        saturated : (k,) bool array, optional
            Samples known to be clipped (besides any channel >= the threshold).

        Returns
        -------
        int
            Samples used (the others were dark, saturated, grazing, or of unlit points).
        """
        p = np.asarray(point_idx).reshape(-1)
        if not np.issubdtype(p.dtype, np.integer):
            raise AppFusionError(f"RGBPass.add_samples: point indices must be integers, got {p.dtype}")
        L = np.asarray(L, dtype=np.float32).reshape(-1, 3)
        if len(L) != len(p):
            raise AppFusionError(f"RGBPass.add_samples: {len(p)} point indices but {len(L)} RGB samples")
        if len(p) and (p.min() < 0 or p.max() >= len(self.positions)):
            raise AppFusionError(f"RGBPass.add_samples: point index out of range [0, {len(self.positions)})")
        Cc = np.asarray(camera_center, dtype=np.float64)
        if Cc.shape not in ((3,), (len(p), 3)) or not np.isfinite(Cc).all():
            raise AppFusionError(f"RGBPass.add_samples: camera_center must be a finite (3,) or ({len(p)}, 3) array")
        sat = np.zeros(len(p), bool) if saturated is None else np.asarray(saturated, bool).reshape(-1)
        if len(sat) != len(p):
            raise AppFusionError(f"RGBPass.add_samples: {len(sat)} saturation flags for {len(p)} samples")
        return self._add(self._rank[p.astype(np.int64)], L, Cc, sat, unique=False)

    def _add(self, p: np.ndarray, L: np.ndarray, C: np.ndarray, sat: np.ndarray, unique: bool) -> int:
        """Core update on internal point indices ``p`` (k,), RGB ``L`` (k, 3), camera centre(s) ``C``."""
        if len(p) == 0:
            return 0
        L = np.asarray(L, dtype=np.float32)
        finite = np.isfinite(L[:, 0] + L[:, 1] + L[:, 2])        # any NaN / inf channel (3x faster than .all(1))
        if not finite.all():                                  # NaN/inf pixels: skipped like clipped ones
            sat = sat | ~finite
            L = np.where(finite[:, None], L, np.float32(0.0))
        Lmax = np.maximum(np.maximum(L[:, 0], L[:, 1]), L[:, 2])
        sat = sat | (Lmax >= self.saturated)
        # np.take rather than fancy indexing: 2-4x faster on (N, 3) rows
        wo = np.asarray(C, dtype=np.float32) - self.positions.take(p, axis=0)
        dist = np.sqrt(np.einsum("ij,ij->i", wo, wo))
        near = ~(dist > 1e-6)                                 # camera at the point: no view direction
        wo *= (np.float32(1.0) / np.where(near, np.float32(1.0), dist))[:, None]
        nrm = self.normals.take(p, axis=0)
        cos_o = np.einsum("ij,ij->i", nrm, wo)
        dark = Lmax < self.dark
        graz = (cos_o < self.min_cos) | near
        unlit = ~self.lit[p]
        keep = ~(dark | sat | graz | unlit)
        st = self.stats
        st["skipped_saturated"] += int(np.count_nonzero(sat))
        st["skipped_dark"] += int(np.count_nonzero(dark & ~sat))
        st["skipped_grazing"] += int(np.count_nonzero(graz & ~dark & ~sat))
        st["skipped_unlit"] += int(np.count_nonzero(unlit & ~graz & ~dark & ~sat))
        k = np.flatnonzero(keep)
        if len(k) == 0:
            return 0
        if len(k) < len(p):
            p, L, wo, nrm = (x.take(k, axis=0) for x in (p, L, wo, nrm))
            if self.footprint:
                dist, cos_o = dist.take(k), cos_o.take(k)
        X = self._footprint_terms(p, wo, dist, cos_o) if self.footprint else None
        sp = self._spec_point[p]
        seed = self.frames * 7919 + st["samples"]
        rep = self.replicating
        if sp.all():                                          # (k, 3) float32 each; Sb None unless rep
            S, Sb = self._lobe_S(p, nrm, wo, self.point_alpha[p], seed, self.point_lobe[p], replicate=rep)
        else:                                                 # diffuse-only clusters: S = 0, no table
            S = np.zeros((len(p), 3), np.float32)
            Sb = np.zeros((len(p), 3), np.float32) if rep else None
            if sp.any():
                q = p[sp]
                S[sp], Sq = self._lobe_S(q, nrm[sp], wo[sp], self.point_alpha[q], seed, self.point_lobe[q],
                                         replicate=rep)
                if rep:
                    Sb[sp] = Sq
        Sc = self._compare_S(p, nrm, wo, sp, seed=seed + 1)
        if unique:
            self._accumulate(p, L, S, Sc, Sb, X)
        else:                                                 # repeated points: rounds of distinct ones
            rest = np.arange(len(p))
            while len(rest):
                _, first = np.unique(p[rest], return_index=True)
                take = rest[first]
                self._accumulate(p[take], L[take], S[take], [(m[take], Sm[take]) for m, Sm in Sc],
                                 None if Sb is None else Sb[take], None if X is None else X[take])
                rest = np.delete(rest, first)
        st["samples"] += len(p)
        return int(len(p))

    def _map_alpha(self, alpha):
        """The roughness S is read against the map with (:func:`appfusion.envmap.effective_alpha`)."""
        if self.map_blur_var <= 0:
            return alpha
        return effective_alpha(alpha, self.map_blur_var)

    def table_S(self, nrm, wo, alpha_eff, lobe="ward") -> np.ndarray:
        """The tables' S (k, 3) float32 at normals and views (k, 3), effective roughness ``alpha_eff``
        (:meth:`_map_alpha`) and lobe names ``lobe`` (str or (k,))."""
        if _ward_only(lobe):
            return self.tables.S(nrm, wo, alpha_eff)
        return self.tables.S(nrm, wo, alpha_eff, lobe=lobe)

    @property
    def replicating(self) -> bool:
        """Samples get a second ``dS`` estimate (:attr:`s_replicate`): only S's near-field part is
        Monte Carlo, so only with the near field on."""
        return self.near_field is not None and self.s_replicate > 0

    #: added to a sample's seed for its second ``dS`` estimate (:attr:`s_replicate`): a prime far
    #: beyond any pass's sample count, so that the two estimates never share random numbers
    REPLICATE_SEED = 15485863

    def _lobe_S(self, p, nrm, wo, alpha, seed: int, lobe="ward", replicate: bool = False):
        """``(S, S_b)``: S (k, 3) float32 of samples of internal points ``p`` with normals, views (k, 3),
        roughness ``alpha`` (k,) and lobe names ``lobe`` (str or (k,)): the double product (§5.3), plus
        the support plane's ``dS`` (clamped at 0) when the near field is on; ``S_b`` with ``replicate``
        (only where :attr:`replicating`) the same with a second, independent ``dS`` of
        :attr:`s_replicate` lobe samples (the instrumental variable of :meth:`_lsq`), else None."""
        T = self.table_S(nrm, wo, self._map_alpha(alpha), lobe)
        if self.near_field is None:
            return T, None
        pos = self.positions.take(p, axis=0)
        S = np.maximum(T + self.near_field_dS(pos, nrm, wo, alpha, lobe, seed), 0.0).astype(np.float32)
        if not replicate:
            return S, None
        dSb = self.near_field_dS(pos, nrm, wo, alpha, lobe, seed + self.REPLICATE_SEED, n_samples=self.s_replicate)
        return S, np.maximum(T + dSb, 0.0).astype(np.float32)

    def near_field_dS(self, pos, nrm, wo, alpha, lobe, seed: int, n_samples: int | None = None) -> np.ndarray:
        """The support plane's ``dS`` (k, 3) (:meth:`appfusion.near_field.SupportPlaneLight.delta_S`) with
        ``near_field_samples`` lobe samples, and at least :attr:`NEAR_FIELD_GGX_MIN_SAMPLES` for GGX
        lobes: a GGX tail sees far more of the plane than a Ward lobe of the same alpha, and with 4
        samples its ``dS`` scattered by twice its size (Ward: half), which the regression of L on S
        reads as a weaker lobe -- the ggx-sphere's underside (normals towards the paper) split off as
        "less specular" (labels 0.87); with 16, none did (session 36). ``n_samples``: instead of
        ``near_field_samples`` (the second estimate of :attr:`s_replicate`)."""
        ns = self.near_field_samples if n_samples is None else int(n_samples)
        if _ward_only(lobe):
            return self.near_field.delta_S(pos, nrm, wo, alpha, n_samples=ns, seed=seed)
        lb = np.broadcast_to(np.asarray(lobe), (len(pos),))
        g = lb == "ggx"
        al = np.broadcast_to(np.asarray(alpha, np.float64), (len(pos),))
        out = np.zeros((len(pos), 3))
        if (~g).any():
            out[~g] = self.near_field.delta_S(pos[~g], nrm[~g], wo[~g], al[~g], n_samples=ns, seed=seed)
        out[g] = self.near_field.delta_S(pos[g], nrm[g], wo[g], al[g], seed=seed + 1, lobe="ggx",
                                         n_samples=max(ns, self.NEAR_FIELD_GGX_MIN_SAMPLES))
        return out

    def _compare_S(self, p, nrm, wo, sp, seed: int) -> list:
        """Per compare alpha: (need (k,) bool, S (k, 3) float32) for the samples of points whose own
        lobe is another one (or none); S is 0 where not needed."""
        out = []
        for m, (a, lb) in enumerate(zip(self.compare_alphas, self.compare_lobes)):
            need = ~(sp & np.isclose(self.point_alpha[p], a, rtol=1e-6, atol=0.0) & (self.point_lobe[p] == lb))
            Sm = np.zeros((len(p), 3), np.float32)
            i = np.flatnonzero(need)
            if len(i):
                Sm[i] = self._lobe_S(p[i], nrm[i], wo[i], np.full(len(i), a), seed + 104729 * (m + 1), lobe=str(lb))[0]
            out.append((need, Sm))
        return out

    def _diffuse_weight(self, S: np.ndarray, Dp: np.ndarray) -> np.ndarray:
        """``w = 1 / (1 + (S / (tau D))^2)`` of the diffuse-weighted rho_d (means over RGB), (k,)."""
        # channel sums, not .mean(axis=1) (3x slower on (k, 3)); the 1/3s cancel
        s = S[:, 0] + S[:, 1]
        s += S[:, 2]
        d = Dp[:, 0] + Dp[:, 1]
        d += Dp[:, 2]
        np.maximum(d, np.float32(3e-12), out=d)
        x = (s / d).astype(np.float64)
        x *= 1.0 / self.diffuse_tau
        x *= x
        x += 1.0
        return np.divide(1.0, x, out=x)

    def _accumulate(self, p: np.ndarray, L: np.ndarray, S: np.ndarray, Sc: list = (),
                    Sb: np.ndarray | None = None, X: np.ndarray | None = None) -> None:
        """Histogram, bin-mean and Eq. 8 sum updates for distinct internal points ``p``; ``Sc`` as
        :meth:`_compare_S` returns it, for the same samples; ``Sb`` (k, 3): the second estimate of S
        (:attr:`s_replicate`), or None; ``X`` (k, 3): the footprint's terms (:attr:`footprint`), or None."""
        Dp = self.D.take(p, axis=0)
        # rho_d histograms: log(L / D) per channel into the point's bins, plus the running mean of the
        # samples' position inside their bin (uint8, stochastic rounding keeps it unbiased)
        x = (np.log(np.maximum(L, np.float32(1e-12)) / Dp) - np.float32(self.log_lo)) * np.float32(1.0 / self.log_width)
        np.clip(x, 0.0, self.bins - 1e-3, out=x)
        b = x.astype(np.int64)
        fr = x - b
        fi = (p[:, None] * 3 + np.arange(3)) * self.bins + b
        flat_h = self.hist.reshape(-1)
        flat_m = self.bin_mean.reshape(-1)
        h = flat_h[fi]                                         # one gather; (p, channel) distinct
        h += 1
        flat_h[fi] = h
        n_new = h.astype(np.float32)
        m_old = flat_m[fi].astype(np.float32) * np.float32(1 / 255)
        m_new = m_old + (fr - m_old) / n_new
        flat_m[fi] = np.clip(m_new * 255 + self._rng.random(m_new.shape, dtype=np.float32), 0, 255).astype(np.uint8)
        top = np.iinfo(np.uint16).max - 1024
        full = h >= top
        if full.any():
            fp = np.unique(p[full.any(axis=1)])
            self.hist[fp] = (self.hist[fp] + 1) // 2          # keep the shape (and the bin means), halve counts
        self.counts[p] += 1
        self.zeros[p] += L <= 0
        weighted = self.diffuse_tau is not None
        u = np.empty((len(p), 8 if weighted else 6, 3))      # this frame's terms, in self._sums's order
        np.multiply(S, S, out=u[:, 0])
        np.multiply(S, L, out=u[:, 1])
        np.multiply(S, Dp, out=u[:, 2])
        u[:, 3] = S
        u[:, 4] = L
        np.multiply(L, L, out=u[:, 5])
        if weighted:
            w = self._diffuse_weight(S, Dp)
            self.sum_w[p] += w
            np.multiply(w[:, None], L, out=u[:, 6])
            np.multiply(w[:, None], S, out=u[:, 7])
            u += self._sums.take(p, axis=0)                  # distinct p: gather, add, scatter
            self._sums[p] = u
        else:
            self._sums[p, :6] += u
        if X is not None:
            f = np.empty((len(p), 27))
            f[:, 0:3] = X
            f[:, 3:9] = X[:, _FP_I] * X[:, _FP_J]
            f[:, 9:18] = (X[:, :, None] * S[:, None, :]).reshape(-1, 9)
            f[:, 18:27] = (X[:, :, None] * L[:, None, :]).reshape(-1, 9)
            f += self._fp.take(p, axis=0)
            self._fp[p] = f
        if Sb is not None:
            r = np.empty((len(p), 2, 3))
            r[:, 0] = Sb
            np.multiply(S, Sb, out=r[:, 1])
            r += self._rep.take(p, axis=0)
            self._rep[p] = r
        for m, (need, Sm) in enumerate(Sc):
            q, Lq, Sq = p[need], L[need], Sm[need]
            self.cmp_s[m, q] += Sq
            self.cmp_s2[m, q] += Sq * Sq
            self.cmp_sl[m, q] += Sq * Lq
            if self.diffuse_tau is not None:
                w = self._diffuse_weight(Sq, Dp[need])
                self.cmp_w[m, q] += w
                self.cmp_wl[m, q] += w[:, None] * Lq
                self.cmp_ws[m, q] += w[:, None] * Sq

    def _footprint_terms(self, p: np.ndarray, wo: np.ndarray, dist: np.ndarray, cos_o: np.ndarray) -> np.ndarray:
        """The pixel footprint's shape on the surface for samples of internal points ``p`` (:attr:`footprint`):
        ``X = d^2 (1 + a^2 / cos^2, a b / cos^2, 1 + b^2 / cos^2)`` (k, 3), the (11, 12, 22) terms of
        ``Sigma = d^2 (I + t t^T / cos^2)`` in the point's tangent frame, ``t = (a, b)`` the view's
        tangential part (``w_o . t1``, ``w_o . t2``), ``cos = n . w_o``, ``d`` the camera's distance
        (m). A pixel of angular size ``1 / f`` covers ``d / f`` head-on and ``d / (f cos)`` along
        ``t``; ``Sigma`` times the camera's constant (:attr:`footprint_c`) is the footprint's
        covariance (m^2)."""
        a = np.einsum("ij,ij->i", wo, self._fp_t1.take(p, axis=0)).astype(np.float64)
        b = np.einsum("ij,ij->i", wo, self._fp_t2.take(p, axis=0)).astype(np.float64)
        d2 = dist.astype(np.float64) ** 2
        ic2 = 1.0 / np.maximum(cos_o.astype(np.float64), 1e-3) ** 2
        return np.stack([d2 * (1 + a * a * ic2), d2 * a * b * ic2, d2 * (1 + b * b * ic2)], axis=1)

    #: nearest points (the point itself included) whose rho_d the footprint's curvature is fitted to
    FOOTPRINT_NEIGHBOURS = 24

    def _footprint_projector(self) -> tuple[np.ndarray, np.ndarray]:
        """Per point, the linear map (3, k) from its k nearest points' rho_d to half its Hessian terms
        ``(h11 / 2, h12, h22 / 2)`` in its tangent frame: the least-squares quadric ``a + b x + c y + (h11
        x^2 + 2 h12 x y + h22 y^2) / 2`` over the neighbours of its own cluster (coordinates along t1,
        t2 scaled by the neighbourhood's radius); zero where fewer than 10 of them share its cluster.
        Returns it (n, 3, k) and the neighbours (n, k). The map is cached per labelling, the
        neighbours (which do not depend on it) once."""
        key = self._labels_key()
        if self._fp_proj is not None and self._fp_proj[0] == key:
            return self._fp_proj[1], self._fp_proj[2]
        P = self.positions.astype(np.float64)
        n = len(P)
        k = min(self.FOOTPRINT_NEIGHBOURS, n)
        nb = self._fp_proj[2] if self._fp_proj is not None else None       # positions only: kept
        if nb is None:
            nb = np.asarray(cKDTree(P).query(P, k=k)[1], np.int64).reshape(n, k)
        proj = np.zeros((n, 3, k), np.float32)
        for lo in range(0, n, 8192):
            sl = slice(lo, min(lo + 8192, n))
            q = nb[sl]
            Q = P[q] - P[sl, None]
            x = np.einsum("pki,pi->pk", Q, self._fp_t1[sl].astype(np.float64))
            y = np.einsum("pki,pi->pk", Q, self._fp_t2[sl].astype(np.float64))
            r = np.maximum(np.sqrt(x * x + y * y).max(axis=1), 1e-9)[:, None]
            xs, ys = x / r, y / r
            A = np.stack([np.ones_like(xs), xs, ys, xs * xs, xs * ys, ys * ys], axis=-1)     # (p, k, 6)
            w = (self.labels[q] == self.labels[sl, None]).astype(np.float64)
            M = np.einsum("pk,pki,pkj->pij", w, A, A) + 1e-9 * np.eye(6)
            R = np.linalg.solve(M, np.transpose(A * w[:, :, None], (0, 2, 1)))         # (p, 6, k)
            # coefficients of x^2, xy, y^2 in scaled coordinates -> (h11 / 2, h12, h22 / 2) in metres
            R = R[:, 3:6] / (r * r)[:, :, None]
            R[w.sum(axis=1) < 10] = 0.0
            proj[sl] = R
        self._fp_proj = (key, proj, nb)
        return proj, nb

    def _footprint_moments(self, use: np.ndarray, nn: np.ndarray, rho_s: np.ndarray):
        """Within-point moments of the footprint's regressor ``G = D (h11 X11 + 2 h12 X12 + h22 X22) / 2``
        per point and channel (:attr:`footprint`): ``C_GS``, ``C_GL`` and ``V_GG`` (n, 3), 0 where the
        point is not used or its S sums are a compare lobe's (:attr:`own_s`). ``H`` is fitted to the
        points' rho_d ``(mean L - rho_s mean S) / D`` with ``rho_s`` (C, 3) (the plain slope); a
        neighbour with too few samples counts with the point's own rho_d."""
        proj, nb = self._footprint_projector()
        D = np.maximum(self.D.astype(np.float64), 1e-12)
        rd = (self.sum_l - np.maximum(rho_s, 0.0)[self.labels] * self.sum_s) / nn / D
        rd = np.where(use[:, None], rd, 0.0)
        # a neighbour without samples (not seen, or too few) takes the point's own rho_d: no
        # curvature is made up where nothing was measured
        rn = np.where(use[nb][:, :, None], rd[nb], rd[:, None, :])
        hv = np.einsum("pjk,pkc->pjc", proj, rn) * D[:, None, :]                 # (n, 3 terms, 3 channels)
        f = self._fp
        x = f[:, 0:3]
        xx = np.empty((len(f), 3, 3))
        xx[:, _FP_I, _FP_J] = f[:, 3:9]
        xx[:, _FP_J, _FP_I] = f[:, 3:9]
        nk = nn[:, :, None]
        v_xx = xx - x[:, :, None] * x[:, None, :] / nk                          # (n, 3, 3)
        c_xs = f[:, 9:18].reshape(-1, 3, 3) - x[:, :, None] * self.sum_s[:, None, :] / nk   # (n, term, channel)
        c_xl = f[:, 18:27].reshape(-1, 3, 3) - x[:, :, None] * self.sum_l[:, None, :] / nk
        ok = (use & self.own_s)[:, None]
        c_gs = np.where(ok, np.einsum("pjc,pjc->pc", hv, c_xs), 0.0)
        c_gl = np.where(ok, np.einsum("pjc,pjc->pc", hv, c_xl), 0.0)
        v_gg = np.where(ok, np.maximum(np.einsum("pjc,pjk,pkc->pc", hv, v_xx, hv), 0.0), 0.0)
        return c_gs, c_gl, v_gg

    # -- results ------------------------------------------------------------------------------
    def rho_d(self) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) rho_d from the histograms (0 where unobserved) and (P,) sample counts, internal order."""
        val, _ = histogram_percentile(self.hist, self.log_lo, self.log_width, self.percentile, self.bin_mean)
        return val, self.counts.copy()

    def rho_d_stderr(self, rho_s: np.ndarray | None = None) -> np.ndarray:
        """Standard error of each point's least-squares rho_d, (P, 3), caller order: ``sqrt(s^2 / n) / D``
        with ``s^2 = (V_LL - 2 rho_s C_SL + rho_s^2 V_SS) / (n - 1)``, the per-sample variance of the
        residual of Eq. 5 under its cluster's ``rho_s`` (``rho_s`` (C, 3), default the current result's;
        0 for a diffuse cluster). The diffuse weighting is ignored (it can only lower the error: a
        conservative value). inf where a point has fewer than ``max(min_lsq_samples, 3)`` samples."""
        if rho_s is None:
            rho_s = self.result().rho_s
        rs = np.asarray(rho_s, np.float64)[self.labels]
        use, n, c_sl, v_ss, v_ll = self._within_point_moments(max(self.min_lsq_samples, 3))
        s2 = np.maximum(v_ll - 2 * rs * c_sl + rs * rs * v_ss, 0.0) / np.maximum(n - 1, 1)
        se = np.sqrt(s2 / n) / np.maximum(self.D.astype(np.float64), 1e-12)
        se = np.where(use[:, None], se, np.inf)
        return se[self._rank]

    def _within_point_moments(self, min_samples: int):
        """Per point and channel, over its samples: ``use`` (at least ``min_samples``), the sample count
        ``n`` (1 where unused), and the centred moments ``C_SL = sum SL - sum S sum L / n``,
        ``V_SS`` and ``V_LL`` (likewise; variances clamped at 0 against rounding), 0 where unused."""
        use = self.counts >= min_samples
        u = use[:, None]
        n = np.where(u, self.counts.astype(np.float64)[:, None], 1.0)
        c_sl = np.where(u, self.sum_sl - self.sum_s * self.sum_l / n, 0.0)
        v_ss = np.where(u, np.maximum(self.sum_s2 - self.sum_s * self.sum_s / n, 0.0), 0.0)
        v_ll = np.where(u, np.maximum(self.sum_l2 - self.sum_l * self.sum_l / n, 0.0), 0.0)
        return use, n, c_sl, v_ss, v_ll

    def _labels_key(self) -> bytes:
        """A digest of the current labelling, the key of what is cached per labelling."""
        return hashlib.blake2b(self.labels.tobytes(), digest_size=16).digest()

    def _interior(self, use: np.ndarray) -> np.ndarray:
        """Points that enter rho_s and the model ladder: usable and farther than ``interior_m`` from
        every point of another cluster, per cluster where at least a quarter of its usable points are
        (else all its usable points). Cached per labelling."""
        lab = self.labels
        key = (self._labels_key(), self.interior_m)
        if self._interior_key != key:
            self._interior_far, self._interior_key = interior_mask(self.positions, lab, self.interior_m), key
        return interior_or_all(self._interior_far, lab, use)

    def _lsq(self, rd_pct: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint least squares of Eq. 5: rho_d per point, rho_s per cluster, from the running sums.

        Minimising ``sum_p sum_j (L_pj - D_p rho_d,p - S_pj rho_s,c)^2`` (``D`` is fixed per point)
        gives, for a given rho_s, ``rho_d,p = (mean_j L_pj - rho_s mean_j S_pj) / D_p``; put back, rho_s
        is the pooled within-point regression slope of L on S,

            rho_s,c = sum_p (sum SL - sum S sum L / n) / sum_p (sum S^2 - (sum S)^2 / n),

        so only the variation of S over a point's views separates specular from diffuse. rho_s is
        clamped at 0 (and rho_d re-solved); points with fewer than ``min_lsq_samples`` samples keep
        their percentile rho_d and enter neither sum. The slope pools only a cluster's interior points
        (:meth:`_interior`): on the demo the label's points within 5 mm of the paint raised its slope
        from 0.027 to 0.041 (truth 0.03), the paint's did not move.

        With the near field's Monte Carlo ``dS`` in S, the denominator is the within-point
        covariance of S with its second estimate ``S_b`` (:attr:`s_replicate`), ``sum S S_b - sum S
        sum S_b / n``, instead of ``V_SS``: the noise of S inflates ``V_SS`` by its own variance and
        so dilutes the slope, but not the covariance of two independent estimates
        (:meth:`_replicate_moment`, :attr:`IV_MIN_RATIO`). The model ladder scores the plain slope (the best predictor of L
        from the noisy S), and rho_d uses the instrumental rho_s.
        """
        C = self.n_clusters
        lab = self.labels
        use, nn, cov, var, vll = self._within_point_moments(self.min_lsq_samples)
        inner = self._interior(use)
        li = lab[inner]
        num = np.stack([np.bincount(li, weights=cov[inner, c], minlength=C) for c in range(3)], axis=1)
        den = den_plain = np.stack([np.bincount(li, weights=var[inner, c], minlength=C) for c in range(3)], axis=1)
        var_iv = var
        if self.replicating:
            # the summed V_SSb, kept within [IV_MIN_RATIO, 1] times the plain denominator
            var_iv = self._replicate_moment(use, nn, var)
            den_iv = np.stack([np.bincount(li, weights=var_iv[inner, c], minlength=C) for c in range(3)], axis=1)
            den = np.clip(den_iv, self.IV_MIN_RATIO * den, den)
        scale = np.maximum(den.max(), 1e-300)
        ok = den > 1e-12 * scale
        cov_s = cov
        if self.footprint and inner.any():
            cov_s, num = self._footprint_fit(inner, use, nn, cov, num, den, den_plain, ok)
        rho_s = np.maximum(np.where(ok, num / np.where(ok, den, 1.0), 0.0), 0.0)
        # model ladder (issue #11, after seed 002): diffuse only, or diffuse + Ward, per cluster, chosen
        # by held-out error. The points are split in two halves; rho_s fitted on one half is scored on
        # the other with each point's rho_d refitted to its own samples, whose residual is then the
        # within-point variance  RSS_p(rho_s) = V_LL - 2 rho_s C_SL + rho_s^2 V_SS  (rho_s = 0: diffuse).
        # Ward is kept where it lowers the held-out RSS by more than ladder_margin (a fraction), or where
        # the held-out points' improvement RSS_p(0) - RSS_p(rho_s) is positive by ladder_z standard
        # errors of its mean: the demo's label (truth rho_s 0.03 under 7-9 % shot noise) lowers its RSS
        # by only 0.02 %, but at z = 14. The z alone misses glossy clusters whose improvement sits in
        # a few highlight points (a test's sphere: -40 % of the RSS at z = 4.8). The margin alone kept a
        # false lobe on few data (session 26: the matte scene at 12 frames of 320 x 240 lowered its
        # RSS by 0.5 % at z = 2.1 with rho_s 0.007, 0.004, 0.004), so it also asks for ladder_margin_z.
        half = (np.arange(len(lab)) % 2).astype(bool)
        rss = np.zeros((C, 2))
        g_sum, g_sq, g_n = np.zeros(C), np.zeros(C), np.zeros(C)
        for h in (False, True):
            fit_m, test_m = inner & (half == h), inner & (half != h)
            nu = np.stack([np.bincount(lab[fit_m], weights=cov[fit_m, c], minlength=C) for c in range(3)], 1)
            de = np.stack([np.bincount(lab[fit_m], weights=var[fit_m, c], minlength=C) for c in range(3)], 1)
            rs_h = np.maximum(np.where(de > 0, nu / np.where(de > 0, de, 1.0), 0.0), 0.0)
            lt = lab[test_m]
            r_d = vll[test_m].sum(1)
            r_w = (vll[test_m] - 2 * rs_h[lt] * cov[test_m] + rs_h[lt] ** 2 * var[test_m]).sum(1)
            rss[:, 0] += np.bincount(lt, weights=r_d, minlength=C)
            rss[:, 1] += np.bincount(lt, weights=r_w, minlength=C)
            g = r_d - r_w
            g_sum += np.bincount(lt, weights=g, minlength=C)
            g_sq += np.bincount(lt, weights=g * g, minlength=C)
            g_n += np.bincount(lt, minlength=C)
        mean = g_sum / np.maximum(g_n, 1)
        sd = np.sqrt(np.maximum(g_sq / np.maximum(g_n, 1) - mean ** 2, 0.0))
        z = np.where(g_n > 1, mean / np.maximum(sd / np.sqrt(np.maximum(g_n, 1)), 1e-300), 0.0)
        self.model = [str(self.lobes[c]) if (self.specular[c] and ok[c].any() and rss[c, 1] < rss[c, 0]
                                 and ((rss[c, 1] < (1 - self.ladder_margin) * rss[c, 0] and z[c] >= self.ladder_margin_z)
                                      or z[c] >= self.ladder_z))
                      else "diffuse"
                      for c in range(C)]
        self.heldout_rss = rss
        self.heldout_z = z
        self.rho_s_ward = rho_s
        self.rho_s_sigma = self.rho_s_standard_error(inner, cov_s, var_iv, num, den)
        rho_s = np.where(np.array([m != "diffuse" for m in self.model])[:, None], rho_s, 0.0)
        D = np.maximum(self.D.astype(np.float64), 1e-12)
        rd = (self.sum_l - rho_s[lab] * self.sum_s) / nn / D
        if self.diffuse_tau is not None:
            # the same least squares with each sample weighted by how diffuse it is (w = 1 for S << D):
            # errors of S (normals, alpha, lighting) enter rho_d through rho_s S, most where S is large
            sw = self.sum_w[:, None]
            rd_w = (self.sum_wl - rho_s[lab] * self.sum_ws) / np.maximum(sw, 1e-300) / D
            rd = np.where(sw > 1e-6, rd_w, rd)
        if self.clip_correction:
            # noise clipped at black: the diffuse level, what is left once the specular term is taken
            # out, times the point's clipped_mean_factor (1: nothing clipped)
            rd = rd * self._clip_factor()
        rd = np.where(use[:, None], np.maximum(rd, 0.0), rd_pct)
        return rd, rho_s, den

    def _footprint_fit(self, inner, use, nn, cov, num, den, den_plain, ok):
        """rho_s's regression with the pixel footprint's term (:attr:`footprint`): within points,
        ``L = D rho_d + rho_s S + c G``, ``rho_s`` per cluster and channel and ``c`` one constant of
        the camera. Per cluster and channel the normal equations are ``den rho_s + b c = num`` with
        ``b = sum C_GS``, and for ``c``, summed over them all, ``sum (b rho_s) + sum V_GG c = sum
        C_GL`` (``den`` the slope's denominator, the instrumental one where :attr:`replicating`: G
        carries no Monte Carlo noise); eliminating rho_s, ``c = (sum C_GL - sum b num / den) / (sum
        V_GG - sum b^2 / den)``, kept >= 0 (a footprint only averages). One ``c`` for all clusters:
        fitted per cluster, the demo's paint read 0.48 mm at 1 m and its label 0.56 (0.55 together),
        and a cluster with little curved print (a plain paint) has little to fit it with.
        ``den_plain``: the plain denominator (sum V_SS), whose slope fits the rho_d that ``H`` is read
        from. Returns the points' slope covariances and the clusters' numerators with ``c G`` taken out;
        sets :attr:`footprint_c` (float) and :attr:`rho_s_unblurred` (the slope without the term)."""
        C = self.n_clusters
        lab = self.labels
        pos = den_plain > 0
        rs0 = np.where(pos, num / np.where(pos, den_plain, 1.0), 0.0)          # the plain slope, for rho_d's H
        c_gs, c_gl, v_gg = self._footprint_moments(use, nn, rs0)
        li = lab[inner]
        b, y, g = (np.stack([np.bincount(li, weights=m[inner, ch], minlength=C) for ch in range(3)], 1)
                   for m in (c_gs, c_gl, v_gg))
        safe = np.where(ok, den, 1.0)
        top = y.sum() - np.where(ok, b * num / safe, 0.0).sum()
        bot = g.sum() - np.where(ok, b * b / safe, 0.0).sum()
        c = max(top / bot, 0.0) if bot > 1e-12 * max(g.sum(), 1e-300) else 0.0
        self.footprint_c = float(c)
        self.rho_s_unblurred = np.maximum(np.where(ok, num / safe, 0.0), 0.0)
        return cov - c * c_gs, num - c * b

    def _replicate_moment(self, use: np.ndarray, nn: np.ndarray, var: np.ndarray) -> np.ndarray:
        """Per point and channel, the within-point covariance of S and its second estimate,
        ``V_SSb = sum S S_b - sum S sum S_b / n`` (not clamped: its sum over points is what counts),
        where the point has the replicate sums (:attr:`own_s`); ``V_SS`` (``var``) elsewhere, and 0
        where the point is not used. Only while :attr:`replicating`."""
        v_ab = self.sum_ssb - self.sum_s * self.sum_sb / nn
        return np.where(use[:, None] & self.own_s[:, None], v_ab, var)

    #: the instrumental denominator is kept within [IV_MIN_RATIO, 1] times the plain one: a cluster
    #: whose S varies within its points by less than its Monte Carlo noise (a diffuse-looking lobe,
    #: few samples) cannot be corrected by more than 1 / IV_MIN_RATIO, and the correction never
    #: lowers the slope (the covariance of two independent noisy estimates exceeds neither's variance
    #: but by chance)
    IV_MIN_RATIO = 0.25

    def rho_s_standard_error(self, inner: np.ndarray, cov: np.ndarray, var: np.ndarray, num: np.ndarray,
                             den: np.ndarray) -> np.ndarray:
        """Standard error (C, 3) of the pooled slope ``rho_s = num / den`` of :meth:`_lsq`.

        The slope is a ratio of sums over points, ``sum_p C_SL,p / sum_p V_SS,p``; to first order its
        error is ``sum_p e_p / den`` with ``e_p = C_SL,p - rho_s V_SS,p``. The points are not
        independent: ~7 share a pixel on the demo (100k points, 1.6 mm pixels on the object), and a
        pixel's footprint mixes the texture around it. So the ``e_p`` are summed per block of points
        (cubes of side ``se_block_m``, per cluster) and the blocks taken as independent (a sandwich,
        or cluster-robust, estimate): ``sigma = sqrt(sum_b (sum_{p in b} e_p)^2) / den``. On the demo's
        label, 4 mm blocks predict 0.0025-0.0028 per channel where the points alone would say
        0.0012-0.0014; six captures of the same radiance with different sensor noise spread by
        0.0019-0.0028 (``docs/rgb-pass.md`` §5i). Constant memory: it reads the running sums only.
        """
        C = self.n_clusters
        sigma = np.full((C, 3), np.nan)
        ok = den > 0
        if not inner.any():
            return sigma
        if self._se_voxel is None:
            v = np.floor(self.positions.astype(np.float64) / self.se_block_m).astype(np.int64)
            self._se_voxel = np.unique(v, axis=0, return_inverse=True)[1].reshape(-1)   # 0..n_voxels-1
        lab = self.labels[inner]
        r = np.where(ok, num / np.where(ok, den, 1.0), 0.0)
        e = cov[inner] - r[lab] * var[inner]
        key = self._se_voxel[inner] * C + lab
        _, blk = np.unique(key, return_inverse=True)
        blk = blk.reshape(-1)
        blk_lab = np.zeros(int(blk.max()) + 1, np.int64)
        blk_lab[blk] = lab
        for ch in range(3):
            eb = np.bincount(blk, weights=e[:, ch])
            sq = np.bincount(blk_lab, weights=eb * eb, minlength=C)
            sigma[:, ch] = np.where(ok[:, ch], np.sqrt(sq) / np.where(ok[:, ch], den[:, ch], 1.0), np.nan)
        return sigma

    def _clip_factor(self) -> np.ndarray:
        """:func:`clipped_mean_factor` (P, 3) of each point's samples: the fraction that read 0, pooled
        over the point and its ``clip_pool_k - 1`` nearest points of the same cluster within 8 mm
        (cached per labelling). It scales the diffuse level ``D rho_d`` (the mean of L less the
        specular term): the samples near black are the clipped ones, a highlight sample is never 0
        and is taken out whole by ``rho_s S``, though it dilutes the fraction (under-correcting
        where the lobe varies)."""
        if not self.zeros.any():
            return np.ones_like(self.sum_l)
        key = self._labels_key()
        if self._clip_nbr is None or self._clip_nbr[0] != key:
            k = min(self.clip_pool_k, len(self.positions))
            dist, idx = cKDTree(self.positions).query(self.positions, k=k, distance_upper_bound=0.008)
            idx = np.asarray(idx).reshape(len(self.positions), k)
            ok = np.isfinite(np.asarray(dist).reshape(idx.shape))
            idx = np.where(ok, idx, 0)
            ok &= self.labels[idx] == self.labels[:, None]
            self._clip_nbr = (key, idx, ok)
        _, idx, ok = self._clip_nbr
        z = (self.zeros[idx] * ok[:, :, None]).sum(axis=1).astype(np.float64)
        n = (self.counts[idx] * ok).sum(axis=1).astype(np.float64)
        return clipped_mean_factor(z / np.maximum(n, 1.0)[:, None])

    def split_by_specular(self, ratio: float = 0.5, pool_m: float = 0.008, min_fraction: float = 0.08,
                          min_samples: int = 3, min_lobe_sd: float = 0.001) -> list[tuple[int, int, int]]:
        """Split off the part of a cluster whose colour shows much less specular reflection.

        The IR pass clusters on the IR highlights it saw (§5.2); a material whose highlight the IR
        never showed (a matte label next to a glossy paint, seen only from above its own height)
        ends up in a glossy cluster. The RGB samples see the environment's lights from every view,
        so the specular scale can be measured locally: for each point, the pooled within-point
        regression slope of L on S over its neighbourhood (the per-point slope of :meth:`_lsq`,
        pooled because one point's views vary S too little): the points of the same cluster in the
        3 x 3 x 3 cube of voxels of side ``max(pool_m, 2 x point spacing)`` around it (a 2.4 cm cube
        by default). Points of cluster ``c`` whose local slope is below ``ratio`` times the cluster's
        rho_s by more than three standard errors (from the neighbourhood's residuals) form a
        new, diffuse cluster when they hold at least ``min_fraction`` of the cluster's points: no
        data measured its roughness (the IR showed no highlight, and S was taken with the glossy
        cluster's alpha), so a lobe with a borrowed alpha would be a guess -- on the demo it put sharp
        sun highlights on the matte label when relit. Its rho_d is then ``mean L / D``. The per-point
        sums do not depend on the labels, so nothing is recomputed.

        Neighbourhoods of 48 nearest points (2.3 mm at the demo's 100k points) left the slope so noisy
        that the demo's label accuracy stayed 0.68; the 2.4 cm cube gives 0.81 on the same sums
        (docs/rgb-pass.md §5d). ``ratio`` was 0.35 until the normals improved (session 5): on the same
        sums 0.35 / 0.5 / 0.6 / 0.7 gave label accuracy 0.911 / 0.936 / 0.936 / 0.924 on the demo and
        0.886 / 0.931 / 0.941 on the seed-1 bottle; the one-material sphere splits at none of them.

        A neighbourhood whose views vary the cluster's own lobe term ``rho_s S`` by less than
        ``min_lobe_sd`` (its standard deviation per sample and channel, white-balanced units) says
        nothing about the lobe, however small its standard error: there an error of S of a few
        thousandths (the map, the support plane's model, a texture edge) decides the slope. The
        vase's underside (normals facing the paper, sd 0.0003 at the median) was split off as
        diffuse without it; the demo's label keeps 85 % of its split points (docs/rgb-pass.md §5d).

        Returns
        -------
        list of (cluster, new cluster, points moved)
        """
        from .points import mean_spacing

        if self.estimator != "lsq" or not self.counts.any():
            return []
        if not pool_m > 0:
            raise AppFusionError(f"split_by_specular: pool_m must be > 0, got {pool_m}")
        use, _, c_sl, v_ss, v_ll = self._within_point_moments(min_samples)
        dof_p = np.where(use, 3.0 * (self.counts - 1), 0.0)
        h = max(float(pool_m), 2.0 * mean_spacing(self.positions)) if len(self.positions) > 8 else float(pool_m)
        vals = np.stack([c_sl.sum(1), v_ss.sum(1), v_ll.sum(1), dof_p], axis=1)
        num, den, vll, dof = _voxel_pool(self.positions, self.labels, vals, h).T
        local = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
        # its standard error from the neighbourhood's residual: only a slope *significantly* below
        # the cluster's counts (views that never caught a highlight say nothing about one)
        rss = np.maximum(vll - np.nan_to_num(local) * num, 0.0)
        dof = np.maximum(dof - 1.0, 1.0)
        se = np.sqrt(rss / dof / np.where(den > 0, den, np.inf))
        rs = self.result().rho_s.mean(axis=1)
        # the cluster's lobe term's spread per sample and channel: den sums V_SS over 3 channels, dof 3 (n - 1)
        s_sd = np.sqrt(np.maximum(den, 0.0) / np.maximum(dof, 1.0))
        out = []
        for c in range(self.n_clusters):
            m = self.labels == c
            if not self.specular[c] or rs[c] <= 0 or m.sum() < 2:
                continue
            low = m & np.isfinite(local) & (local + 3.0 * se < ratio * rs[c]) & (rs[c] * s_sd >= min_lobe_sd)
            if low.sum() < min_fraction * m.sum() or (m & ~low).sum() < min_fraction * m.sum():
                continue
            new = self.n_clusters
            self.labels = np.where(low, new, self.labels)
            self.alphas = np.r_[self.alphas, self.alphas[c]]
            self.lobes = np.append(self.lobes, self.lobes[c])
            self.specular = np.r_[self.specular, False]
            self.model = list(self.model) + ["diffuse"]
            self._spec_point = self.specular[self.labels]
            self.n_clusters += 1
            out.append((c, new, int(low.sum())))
        return out

    def merge_alike(self, alpha_rel: float = 0.3, rho_rel: float = 0.25) -> list[tuple[int, int]]:
        """Merge clusters that are one material by every measurement: alpha (IR) within ``alpha_rel``
        and rho_s (RGB, mean over channels) within ``rho_rel`` of their means. The merged cluster's
        alpha is the point-weighted mean; each point keeps the S sums of its own alpha. Returns the
        (kept, removed) pairs, in the cluster numbering at the time of each merge."""
        out = []
        while self.n_clusters > 1:
            rs = self.result().rho_s.mean(axis=1)
            cnt = np.bincount(self.labels, minlength=self.n_clusters)
            pair = None
            for i in range(self.n_clusters):
                for j in range(i + 1, self.n_clusters):
                    if (cnt[i] == 0 or cnt[j] == 0 or self.specular[i] != self.specular[j]
                            or self.lobes[i] != self.lobes[j]):
                        continue
                    a, b = self.alphas[i], self.alphas[j]
                    if abs(a - b) > alpha_rel * 0.5 * (a + b):
                        continue
                    if abs(rs[i] - rs[j]) > rho_rel * max(0.5 * (rs[i] + rs[j]), 1e-6):
                        continue
                    pair = (i, j)
                    break
                if pair:
                    break
            if pair is None:
                break
            i, j = pair
            self.alphas = self.alphas.copy()
            self.alphas[i] = (cnt[i] * self.alphas[i] + cnt[j] * self.alphas[j]) / (cnt[i] + cnt[j])
            self.alphas = np.delete(self.alphas, j)
            self.lobes = np.delete(self.lobes, j)
            self.specular = np.delete(self.specular, j)
            self.model = [m for c, m in enumerate(self.model) if c != j]
            lab = np.where(self.labels == j, i, self.labels)
            self.labels = np.where(lab > j, lab - 1, lab)
            self._spec_point = self.specular[self.labels]
            self.n_clusters -= 1
            out.append((i, j))
        return out

    def reassign_by_model(self, pool_m: float = 0.008, min_samples: int = 3, min_z: float = 3.0,
                          colour_radius_m: float = 0.02, weak_lobe: float = 0.002,
                          colour_regions_on: bool = True) -> int:
        """Move each point to the cluster whose Eq. 5 model explains its neighbourhood's colour best.

        After the colour split (:meth:`split_by_specular`) and the IR refit, each cluster has its own
        lobe (or none, by the model ladder). A point's residual under cluster ``c``'s model with its
        rho_d refitted to its own samples is the within-point ``RSS_c = V_LL - 2 rho_s,c C_SL,c +
        rho_s,c^2 V_SS,c`` (over RGB; ``C``, ``V`` with the S of ``alpha_c``: the point's own sums where
        that is its lobe, else the ``compare_alphas`` sums), ``V_LL`` for a diffuse cluster. The
        residuals are pooled over the 3 x 3 x 3 voxels of side ``max(pool_m, 2 x spacing)`` around the
        point, over *all* points there (the split pooled within one cluster), and the point goes to the
        lowest: the maximum-likelihood choice between the fitted models, without the split's
        three-standard-error margin (which guarded a new cluster that had no model yet).

        Where the evidence is weak, colour decides. A lobe's share of a point's RSS difference,
        ``2 rho_s C_SL - rho_s^2 V_SS``, has a standard error of about ``2 rho_s s sqrt(V_SS)`` under the
        other model (``s^2`` the point's per-sample variance, ``V_LL / (n - 1)``, per channel); pooled like the RSS,
        the gap between the best and the second-best model counts in those errors (``z``). A point whose
        views never put a highlight where the models differ has ``z`` near 0, and argmin alone took the
        first cluster: on the demo a patch of the label at the bottom (0-3 cm) went to the paint. A
        point with ``z < min_z`` takes the cluster of the point among its 32 nearest confident
        neighbours (``z >= min_z``, within ``colour_radius_m``) whose rho_d has the closest
        chromaticity, if that is the same colour (:func:`_choose_by_evidence`): a material's colour is
        the weaker evidence, used only where the BRDF gives none. Before that, with
        ``colour_regions_on``, a weak point takes the best model of its colour region
        (:func:`colour_regions`), the points' own residuals summed over the region, where that sum is
        ``min_z`` standard errors apart: a band of the label that no view showed a highlight on is
        decided by the rest of its band. `bench --quick`'s small scan (40 frames at 320 x 240, 99 % of
        its points weak): labels 0.876 -> 0.991, the label's alpha 0.416 -> 0.345 (truth 0.35); the demo
        0.974 -> 0.994 (docs/rgb-pass.md §5d).

        Candidates are the diffuse clusters and those whose lobe (alpha and shape) is among
        ``compare_alphas`` / ``compare_lobes``; a cluster whose lobe is not, but lowers its held-out
        residual by less than ``weak_lobe`` (a fraction), competes with its diffuse fit; points of other
        clusters stay. A moved point's S sums become those of its new lobe (the compare
        sums); a point moved into a diffuse cluster keeps its own (rho_s 0 leaves S out of rho_d but
        for the diffuse weighting). On the demo's second sweep: label accuracy 0.947 -> 0.959
        (docs/rgb-pass.md §5e). Returns the number of points moved.
        """
        from .points import mean_spacing

        if self.estimator != "lsq" or not len(self.compare_alphas) or not self.counts.any():
            return 0
        if not pool_m > 0:
            raise AppFusionError(f"reassign_by_model: pool_m must be > 0, got {pool_m}")
        res = self.result()                                   # the model ladder's rungs and rho_s
        lab = self.labels
        use, n, _, _, vll = self._within_point_moments(min_samples)
        s2 = np.where(use[:, None], vll / np.maximum(n - 1, 1), 0.0)     # per-sample variance, (P, 3)
        vll = vll.sum(axis=1)
        cands, rss, var, lobe = [], [], [], {}
        for c in range(self.n_clusters):
            if not (lab == c).any():
                continue
            rs_c = np.asarray(res.rho_s[c], np.float64)
            hit = np.flatnonzero(np.isclose(self.compare_alphas, self.alphas[c], rtol=1e-6, atol=0.0)
                                 & (self.compare_lobes == self.lobes[c]))
            as_diffuse = res.model[c] == "diffuse" or rs_c.max() <= 0
            if not as_diffuse and len(hit) == 0:
                # its lobe was not measured on the other points. A lobe that explains almost none of
                # its colour (held-out RSS within weak_lobe of diffuse only: the demo's label, 0.02 %)
                # competes as the diffuse fit it nearly is; a stronger one keeps its points
                hr = self.heldout_rss
                if not (hr is not None and hr[c, 0] > 0 and hr[c, 0] - hr[c, 1] < weak_lobe * hr[c, 0]):
                    continue
                as_diffuse = True
            if as_diffuse:
                cands.append(c)
                rss.append(vll)
                var.append(np.zeros_like(vll))
                continue
            m = int(hit[0])
            own = (self._spec_point & np.isclose(self.point_alpha, self.alphas[c], rtol=1e-6, atol=0.0)
                   & (self.point_lobe == self.lobes[c]))[:, None]
            s = np.where(own, self.sum_s, self.cmp_s[m])
            s2 = np.where(own, self.sum_s2, self.cmp_s2[m])
            sl = np.where(own, self.sum_sl, self.cmp_sl[m])
            c_sl = np.where(use[:, None], sl - s * self.sum_l / n, 0.0)
            v_ss = np.where(use[:, None], np.maximum(s2 - s * s / n, 0.0), 0.0)
            cands.append(c)
            rss.append(vll - (2 * rs_c * c_sl - rs_c * rs_c * v_ss).sum(axis=1))
            var.append(4.0 * (rs_c * rs_c * s2 * v_ss).sum(axis=1))
            lobe[c] = (m, own[:, 0])
        if len(cands) < 2:
            return 0
        k = len(cands)
        h = max(float(pool_m), 2.0 * mean_spacing(self.positions)) if len(self.positions) > 8 else float(pool_m)
        vals = np.column_stack([np.where(use[:, None], np.stack(rss + var, axis=1), 0.0), use.astype(np.float64)])
        pooled = _voxel_pool(self.positions, np.zeros(len(lab), np.int64), vals, h)
        movable = np.isin(lab, cands) & (pooled[:, -1] > 0)
        rd = np.empty((len(lab), 3))
        rd[self._rank] = np.asarray(res.rho_d, np.float64)             # caller's order -> internal
        regions = colour_regions(self.positions, rd) if colour_regions_on else None
        choice = _choose_by_evidence(pooled[:, :k], pooled[:, k:2 * k], np.asarray(cands), movable,
                                     self.positions, rd, min_z, colour_radius_m, regions=regions,
                                     own=(vals[:, :k], vals[:, k:2 * k]))
        new = np.where(movable, choice, lab)
        moved = new != lab
        for c, (m, own) in lobe.items():
            q = moved & (new == c) & ~own
            self.sum_s[q], self.sum_s2[q], self.sum_sl[q] = self.cmp_s[m, q], self.cmp_s2[m, q], self.cmp_sl[m, q]
            self.sum_sd[q] = self.cmp_s[m, q] * self.D[q]
            self.sum_w[q], self.sum_wl[q], self.sum_ws[q] = self.cmp_w[m, q], self.cmp_wl[m, q], self.cmp_ws[m, q]
            self.own_s[q] = False                             # no replicate / footprint sums of the compare lobe's S
        self.labels = new.astype(np.int64)
        self._spec_point = self.specular[self.labels]
        self.point_alpha = self.alphas[self.labels]
        self.point_lobe = self.lobes[self.labels]
        return int(moved.sum())

    def labels_caller_order(self) -> np.ndarray:
        """Current cluster labels in the caller's point order."""
        return self.labels[self._rank].astype(np.int32)

    def result(self) -> RGBResult:
        """Current estimates (cheap: can be called after every frame for live display)."""
        rd, counts = self.rho_d()
        observed = counts > 0
        C = self.n_clusters
        notes = []
        lab = self.labels
        csamp = np.bincount(lab, weights=counts, minlength=C).astype(np.int64)
        if self.estimator == "lsq":
            rd, rho_s, den = self._lsq(rd)
            ok = den > 1e-12 * np.maximum(den.max(), 1e-300)
        else:
            # Eq. 8 with the final rho_d: sum S (L - D rho_d) = sum SL - rho_d sum SD
            num = np.stack([np.bincount(lab, weights=self.sum_sl[:, c] - rd[:, c] * self.sum_sd[:, c], minlength=C)
                            for c in range(3)], axis=1)
            den = np.stack([np.bincount(lab, weights=self.sum_s2[:, c], minlength=C) for c in range(3)], axis=1)
            scale = np.maximum(den.max(), 1e-300)
            ok = den > 1e-12 * scale
            rho_s = np.where(ok, num / np.where(ok, den, 1.0), 0.0)
            rho_s = np.maximum(rho_s, 0.0)
        for c in range(C):
            if csamp[c] == 0:
                notes.append(f"cluster {c}: no RGB samples; rho_s = 0 and its points' rho_d = 0")
            elif not ok[c].all():
                notes.append(f"cluster {c}: no specular signal (sum S^2 ~ 0); rho_s = 0")
        # unobserved points: their cluster's median rho_d
        out = rd.copy()
        if not observed.all():
            for c in np.unique(lab[~observed]):
                m = (lab == c) & observed
                out[(lab == c) & ~observed] = np.median(rd[m], axis=0) if m.any() else 0.0
        r = self._rank                                        # back to the caller's point order
        model = list(self.model) if self.estimator == "lsq" else [str(x) for x in self.lobes]
        return RGBResult(out[r].astype(np.float32), rho_s.astype(np.float32), counts[r], observed[r], csamp,
                         den, notes, model=model, heldout_rss=self.heldout_rss,
                         rho_s_ward=self.rho_s_ward if self.estimator == "lsq" else None,
                         heldout_z=self.heldout_z if self.estimator == "lsq" else None,
                         rho_s_sigma=self.rho_s_sigma if self.estimator == "lsq" else None)
