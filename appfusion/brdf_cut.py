"""BRDF cut: specular-material clustering while scanning (paper §5.2).

Tree
----
A binary tree partitions the sampled points ``{p_i}`` on the 6-vector ``(p_i / s, n_i)`` (position scaled
by the object size ``s``, the diagonal of the points' bounding box, and the unit normal). A node is split
at the median of the coordinate with the largest spread (standard deviation) until it has fewer than
``2 * min_leaf`` points, so leaves hold ``min_leaf .. 2 min_leaf - 1`` points. Leaves are numbered depth
first, so every node covers a contiguous range of leaves ``[leaf_lo, leaf_hi)`` and its HBSAB is a
range sum of leaf HBSABs (cumulative sums for all nodes at once, ``np.add.reduceat`` for a cut).
Only the leaves store HBSABs (:class:`appfusion.hbsab.HBSAB`, one array for all leaves).

Reliability (paper: "enough samples and a sufficient coverage in a potential highlight region, based
on a synthetic BRDF of a broad highlight", after [LKG*03])
----------------------------------------------------------------------------------------------
A node is reliable when

1. its total weight ``sum w`` is at least ``min_total_weight``, and
2. the texels holding at least ``texel_min_weight`` cover at least ``min_coverage`` of the *highlight
   region's energy*: the highlight region is the set of texels carrying ``region_energy`` (90 %) of the
   energy of a broad retro-reflection Ward lobe (``alpha = broad_alpha = 0.3``; ``f cos(theta_h)`` times the
   texel's solid angle), i.e. the texels within ~25 degrees of the normal; coverage is the energy of
   the covered region texels over the region's energy.

Cut and clustering
------------------
The cut starts at the root; a node is replaced by its two children whenever at least one child is
reliable. The reliable cut nodes are clustered by k-means on their HBSABs. Two HBSABs are compared
over the texels both hold, after removing the diffuse part: the distance is the chi-square of the
texel differences about their weighted mean difference (the constant offset that best aligns them,
i.e. the difference of their diffuse components),

    chi2(i, c) = sum_t w_t (r_t - rbar)^2,   r_t = v_it - C_ct,   w_t = 1 / sigma_it^2,

with ``sigma_it^2 = c_i^2 v_it^2 / W_it`` the standard error of texel ``t`` of node ``i`` (``c_i`` the node's
median relative per-sample spread: the emitter's multiplicative noise). Centres are the weighted
means of their members' offset-aligned HBSABs. Unreliable cut nodes go to the centre with the least
``chi2 / (texels in common)``; when they share no texels with any centre, or the best centre is not
better than the second by ``assign_margin`` in chi-square, they take the label of the nearest reliable
cut node in ``(position / s, normal)``.

Choosing k (``k=None``)
-----------------------
k-means runs for ``k = 1 .. k_max`` (at most the number of reliable nodes) and ``k`` is the smallest
value for which either the clusters explain the nodes to within the noise (``chi2_k <= noise_ratio *
dof_k``, ``dof_k = sum_i (texels of i in common with its centre - 1)``) or one more cluster does not
reduce the chi-square *beyond the noise* by at least the factor ``split_gain``
(``(chi2_k - noise_ratio dof_k) / (chi2_{k+1} - noise_ratio dof_{k+1}) < split_gain``; a k + 1 within
the noise is always taken). So one material gives ``k = 1`` when the spread of its nodes is within
the noise, and a second material is only split off when it explains most of the excess spread. (Until
session 5 the test was ``chi2_k / chi2_{k+1} >= 1.25``. Synthetic two-material spheres give 1.59-1.63
and reach the noise at k = 2, an excess ratio of infinity; the demo bottle, whose spread is the sharp
peak across the paint's nodes rather than materials, gave 1.44 at chi2 / dof 15 -> 10.5 (excess ratio
1.49), and with the session-5 normals k = 2 came out of some runs as two mixed clusters, label
accuracy 0.58 end to end. ``split_gain`` was 2.0 until session 13: with sharper normals the
two-material capsule scans split at excess ratios of 2.07, 2.31 and 2.32 into the paint and a
scattered cluster with no lobe of its own (alpha 0.25-0.86), which the colour pass could not undo:
labels 0.70-0.91 end to end. At 3.0 the same scans take k = 1 and the colour pass splits the label
off (labels 0.977-0.980); the IR bench's two-material spheres, which reach the noise at k = 2,
still split: label accuracy 0.987.)

Refinements (beyond the paper)
------------------------------
*Leaf refinement*: after clustering, a leaf whose own HBSAB prefers another centre by at least
``leaf_margin`` in chi-square moves there (cut nodes may straddle a material boundary, their leaves
need not). *Interior-leaf fits*: a cluster's Ward fit uses only its interior leaves (the leaf's points
and its ``interior_k`` nearest leaves all carry the label) when these hold at least
``interior_min_fraction`` of its weight, since boundary leaves mix two lobes; failing that its pure
leaves (off the surface's rim, then with it), and only then every leaf it touches.

Output
------
:meth:`BRDFCut.result` gives per-point labels, the merged HBSAB of each cluster (the leaves' buffers
summed with the fraction of each leaf's area that has that label) and its Ward fit (alpha +- sigma,
``rho_s`` and ``rho_d`` in the IR band, :mod:`appfusion.ward_fit`). Labels stay stable from one call to
the next (new clusters are matched to the previous ones by shared area), and labels painted with
:meth:`BRDFCut.set_labels` override the clustering in every later result.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from . import octahedral as oc
from .brdf import ward_retro
from .errors import AppFusionError, EstimationError
from .hbsab import CH_SAT, CH_W, CH_WV, CH_WV2, DEFAULT_MAX_ANGLE_DEG, DEFAULT_N, HBSAB, half_vector_samples
from .points import check_oriented_points
from .ward_fit import ALPHA_MIN, RHO_S_MAX, WardFit, WardFitter, _is_pattern, one_blas_thread

__all__ = ["BRDFTree", "build_tree", "BRDFCut", "CutResult", "ClusterInfo", "highlight_region",
           "kmeans_hbsab"]


# -- tree ---------------------------------------------------------------------------------------

@dataclass
class BRDFTree:
    """Binary tree over points (paper §5.2, Fig. 5), nodes in depth-first (pre-)order, root = 0.

    Attributes
    ----------
    left, right, parent : (n_nodes,) int32
        Children (-1 for leaves) and parent (-1 for the root).
    leaf_lo, leaf_hi : (n_nodes,) int32
        The leaves under a node are ``leaf_lo .. leaf_hi - 1`` (depth-first leaf numbering).
    depth : (n_nodes,) int32
    leaf_node : (n_leaves,) int32
        Node id of each leaf.
    order : (N,) int64
        Point indices sorted by leaf; leaf ``j`` holds ``order[leaf_start[j]:leaf_start[j+1]]``.
    leaf_start : (n_leaves + 1,) int64
    point_leaf : (N,) int32
        Leaf of every point.
    size : float
        Object size used to scale positions (bounding-box diagonal), metres.
    """

    left: np.ndarray
    right: np.ndarray
    parent: np.ndarray
    leaf_lo: np.ndarray
    leaf_hi: np.ndarray
    depth: np.ndarray
    leaf_node: np.ndarray
    order: np.ndarray
    leaf_start: np.ndarray
    point_leaf: np.ndarray
    size: float

    @property
    def n_nodes(self) -> int:
        return len(self.left)

    @property
    def n_leaves(self) -> int:
        return len(self.leaf_node)

    @property
    def n_points(self) -> int:
        return len(self.point_leaf)

    def node_points(self, node: int) -> np.ndarray:
        """Indices of the points under ``node``."""
        return self.order[self.leaf_start[self.leaf_lo[node]]:self.leaf_start[self.leaf_hi[node]]]


def build_tree(positions: np.ndarray, normals: np.ndarray, min_leaf: int = 64,
               size: float | None = None, normal_weight: float = 1.0) -> BRDFTree:
    """Build the BRDF-cut tree over points (paper §5.2).

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        Points (metres) and unit normals.
    min_leaf : int
        Minimum points per leaf; a node with fewer than ``2 * min_leaf`` points is a leaf.
    size : float, optional
        Object size, metres (default: bounding-box diagonal).
    normal_weight : float
        Scale of the normal part of the split vector relative to the position part.

    Returns
    -------
    BRDFTree
    """
    P, Nn = check_oriented_points(positions, normals, "BRDF cut")
    min_leaf = int(min_leaf)
    if min_leaf < 1:
        raise AppFusionError(f"BRDF cut: min_leaf must be >= 1, got {min_leaf}")
    if size is None:
        size = float(np.linalg.norm(P.max(0) - P.min(0)))
    size = float(size) if size and size > 0 else 1.0
    X = np.hstack([(P - P.mean(0)) / size, Nn * float(normal_weight)])
    left, right, parent, depth, leaf_lo, is_leaf, leaf_node = [], [], [], [], [], [], []
    order_parts: list[np.ndarray] = []
    stack = [(np.arange(len(P)), -1, 0, 0)]          # (points, parent, which child, depth)
    while stack:
        idx, par, side, dep = stack.pop()
        nid = len(left)
        left.append(-1)
        right.append(-1)
        parent.append(par)
        depth.append(dep)
        leaf_lo.append(len(leaf_node))
        if par >= 0:
            (left if side == 0 else right)[par] = nid
        if len(idx) < 2 * min_leaf:
            is_leaf.append(True)
            leaf_node.append(nid)
            order_parts.append(idx)
            continue
        is_leaf.append(False)
        sub = X[idx]
        axis = int(np.argmax(sub.std(axis=0)))
        h = len(idx) // 2
        part = np.argpartition(sub[:, axis], h)
        stack.append((idx[part[h:]], nid, 1, dep + 1))   # right is popped after the left subtree
        stack.append((idx[part[:h]], nid, 0, dep + 1))
    n_nodes = len(left)
    left_a, right_a = np.array(left, np.int32), np.array(right, np.int32)
    lo = np.array(leaf_lo, np.int32)
    hi = lo + 1
    for nid in range(n_nodes - 1, -1, -1):             # children have larger ids (pre-order)
        if right_a[nid] >= 0:
            hi[nid] = hi[right_a[nid]]
    order = np.concatenate(order_parts).astype(np.int64)
    counts = np.array([len(o) for o in order_parts], np.int64)
    leaf_start = np.concatenate([[0], np.cumsum(counts)])
    point_leaf = np.empty(len(P), np.int32)
    point_leaf[order] = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
    return BRDFTree(left_a, right_a, np.array(parent, np.int32), lo, hi.astype(np.int32),
                    np.array(depth, np.int32), np.array(leaf_node, np.int32), order, leaf_start,
                    point_leaf, size)


# -- reliability ----------------------------------------------------------------------------------

def highlight_region(n: int, broad_alpha: float = 0.3, region_energy: float = 0.9) -> np.ndarray:
    """Energy of a broad synthetic highlight per texel, restricted to its core region, (N*N,).

    The energy of texel ``t`` is ``ward_retro(broad_alpha, cos h_t) cos h_t Omega_t`` (``Omega_t`` its solid
    angle); the region is the smallest set of texels holding ``region_energy`` of the total. Texels
    outside the region get 0. Used by the reliability test (paper §5.2, after [LKG*03]).
    """
    d = oc.hemi_directions(n).reshape(-1, 3)
    e = ward_retro(broad_alpha, d[:, 2]) * d[:, 2] * oc.hemi_solid_angles(n).reshape(-1)
    o = np.argsort(-e)
    c = np.cumsum(e[o]) / e.sum()
    m = int(np.searchsorted(c, region_energy)) + 1
    out = np.zeros_like(e)
    out[o[:m]] = e[o[:m]]
    return out


# -- clustering of HBSABs ----------------------------------------------------------------------

def _hbsab_features(data: np.ndarray, texel_min_weight: float):
    """Values, inverse-variance weights and masks of HBSAB sums (C, B, T) for clustering."""
    W = data[CH_W].astype(np.float64)
    ok = W >= texel_min_weight
    Wd = np.where(ok, W, 1.0)
    v = np.where(ok, data[CH_WV] / Wd, 0.0)
    var = np.where(ok, np.maximum(data[CH_WV2] / Wd - v * v, 0.0), 0.0)
    good = ok & (np.abs(v) > 0)
    rel = np.sort(np.where(good, var / np.maximum(v * v, 1e-300), np.inf), axis=1)   # row-wise median
    cnt = good.sum(axis=1)
    c2 = rel[np.arange(len(rel)), np.maximum(cnt - 1, 0) // 2]
    c2 = np.where((cnt > 0) & np.isfinite(c2) & (c2 > 0), c2, 0.25)
    vmax = np.max(np.abs(v), axis=1, keepdims=True)
    s2 = (c2[:, None] * v * v + (1e-2 * vmax) ** 2 + 1e-300) / Wd
    omega = np.where(ok, 1.0 / s2, 0.0)
    return v, omega, ok


def _chi2_matrix(X: np.ndarray, Om: np.ndarray, C: np.ndarray, MC: np.ndarray):
    """Offset-free weighted chi-square of every row of X against every centre: (n, k) arrays
    ``chi2`` and ``n_common`` (texels both have) and the best offsets ``delta`` (n, k)."""
    McT = MC.T.astype(np.float64)
    CM = (C * MC).T
    C2M = (C * C * MC).T
    OX = Om * X
    S0 = Om @ McT
    S1 = OX @ McT - Om @ CM
    S2 = (OX * X) @ McT - 2.0 * (OX @ CM) + Om @ C2M
    n_common = (Om > 0).astype(np.float64) @ McT
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(S0 > 0, S1 / np.where(S0 > 0, S0, 1.0), 0.0)
        chi2 = np.maximum(S2 - np.where(S0 > 0, S1 * delta, 0.0), 0.0)
    return chi2, n_common, delta


def kmeans_hbsab(X: np.ndarray, Om: np.ndarray, k: int, n_init: int = 4, max_iter: int = 50,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    """k-means of HBSAB rows under the offset-free chi-square distance (module docstring).

    Parameters
    ----------
    X : (n, T) array
        Texel values (1/sr), 0 where missing.
    Om : (n, T) array
        Inverse-variance weights, 0 where missing.
    k : int
        Clusters (clipped to the number of rows).
    n_init, max_iter, seed
        Restarts with k-means++ seeding, iterations per run, random seed.

    Returns
    -------
    labels : (n,) int64
    centres : (k', T) array, masks : (k', T) bool
        ``k' <= k`` (empty clusters are dropped, labels renumbered).
    chi2 : float
        Total chi-square of the rows about their centres.
    per_row : (n, 2) array
        Each row's chi-square and texels in common with its centre.
    """
    n, T = X.shape
    k = int(max(1, min(k, n)))
    present = Om > 0
    rng = np.random.default_rng(seed)
    best = None
    for run in range(n_init if k > 1 else 1):
        # k-means++ seeding on the chi-square distance per texel in common
        first = int(rng.integers(n))
        C = X[[first]].copy()
        MC = present[[first]].copy()
        while len(C) < k:
            chi2, nc, _ = _chi2_matrix(X, Om, C, MC)
            d = np.min(np.where(nc > 0, chi2 / np.maximum(nc, 1), np.inf), axis=1)
            d = np.where(np.isfinite(d), d, np.nanmax(np.where(np.isfinite(d), d, 0)) + 1.0)
            if d.sum() > 0:
                nxt = int(rng.choice(n, p=d / d.sum()))
            else:                                        # every row equals a centre already
                nxt = int(rng.integers(n))
            C = np.vstack([C, X[[nxt]]])
            MC = np.vstack([MC, present[[nxt]]])
        labels = np.full(n, -1)
        for _ in range(max_iter):
            chi2, nc, delta = _chi2_matrix(X, Om, C, MC)
            score = np.where(nc > 0, chi2 / np.maximum(nc, 1), np.inf)
            new = np.argmin(score, axis=1)
            if np.array_equal(new, labels):
                break
            labels = new
            own_delta = delta[np.arange(n), labels]
            C, MC = _weighted_centres(X, Om, labels, own_delta, len(C))
        chi2, nc, delta = _chi2_matrix(X, Om, C, MC)
        r = chi2[np.arange(n), labels]
        total = float(r.sum())
        if best is None or total < best[3] - 1e-9 * max(abs(total), 1.0):
            best = (labels.copy(), C.copy(), MC.copy(), total, np.stack([r, nc[np.arange(n), labels]], axis=1))
    labels, C, MC, total, per_row = best
    used = np.unique(labels)
    remap = np.full(len(C), -1)
    remap[used] = np.arange(len(used))
    return remap[labels], C[used], MC[used], total, per_row


def _is_needle(fit: WardFit) -> bool:
    """A Ward fit that ran to the needle bounds (rho_s at ``RHO_S_MAX`` or alpha at ``ALPHA_MIN``): it
    measured no lobe of its own. On a session-5 demo run (normals 0.33 degrees) a mixed cluster of the
    paint's and the label's boundary (40 % paint) fitted alpha 0.010 with rho_s below the bound and was
    kept as a material, which cost label accuracy 0.94 -> 0.79."""
    return fit.rho_s >= RHO_S_MAX * (1 - 1e-6) or fit.alpha <= ALPHA_MIN * (1 + 1e-6)


def _weighted_centres(X, Om, labels, own_delta, k):
    """Weighted means of the members' offset-aligned rows; (k, T) centres and masks."""
    L = np.zeros((k, len(X)))
    L[labels, np.arange(len(X))] = 1.0
    num = L @ (Om * (X - own_delta[:, None]))
    den = L @ Om
    MC = den > 0
    C = np.where(MC, num / np.where(MC, den, 1.0), 0.0)
    return C, MC


# -- results -------------------------------------------------------------------------------------

@dataclass
class ClusterInfo:
    """One specular material found by the BRDF cut.

    Attributes
    ----------
    label : int
    n_points : int
    area : float
        Sum of the point areas (or the point count without areas).
    hbsab : HBSAB
        Merged HBSAB of the cluster (one buffer).
    fit : WardFit or None
        Ward fit of the merged HBSAB, None when it could not be fitted (see ``status``).
    status : str
        ``"fitted"`` or why not (``"insufficient data: ..."``).
    fits : dict
        ``lobe -> WardFit``: the fit of every lobe tried (``BRDFCut(lobes=...)``); ``fit`` is the one
        :func:`appfusion.ward_fit.choose_lobe` kept, and ``fit.lobe`` names it.
    """

    label: int
    n_points: int
    area: float
    hbsab: HBSAB
    fit: WardFit | None
    status: str
    fits: dict = field(default_factory=dict)

    @property
    def alpha(self) -> float | None:
        return None if self.fit is None else self.fit.alpha

    @property
    def alpha_sigma(self) -> float | None:
        return None if self.fit is None else self.fit.alpha_sigma

    @property
    def rho_s_ir(self) -> float | None:
        return None if self.fit is None else self.fit.rho_s

    @property
    def rho_d_ir(self) -> float | None:
        return None if self.fit is None else self.fit.rho_d


@dataclass
class CutResult:
    """Clustering of a point set by the BRDF cut (paper §5.2).

    Attributes
    ----------
    labels : (N,) int32
        Cluster of every point, ``0 .. k-1``.
    clusters : list of ClusterInfo
        One per label.
    k : int
        Number of clusters.
    k_auto : bool
        True if ``k`` was chosen automatically.
    cut_nodes : (m,) int32
        Tree nodes of the cut (depth-first order).
    cut_reliable : (m,) bool
        Which cut nodes passed the reliability test.
    chi2_by_k : dict
        ``k -> (chi2, dof)`` of the k-means runs (automatic k).
    notes : list of str
        Anything the caller should know (k reduced, no reliable node yet, ...).
    """

    labels: np.ndarray
    clusters: list[ClusterInfo]
    k: int
    k_auto: bool
    cut_nodes: np.ndarray
    cut_reliable: np.ndarray
    chi2_by_k: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    @property
    def fitted(self) -> np.ndarray:
        """(k,) bool: clusters with a Ward fit."""
        return np.array([c.fit is not None for c in self.clusters], bool)

    def alphas(self, fallback: float = 0.3) -> np.ndarray:
        """(k,) roughness per cluster; ``fallback`` where a cluster has no fit yet."""
        return np.array([fallback if c.fit is None else c.fit.alpha for c in self.clusters])

    def alpha_sigmas(self, fallback: float = 1.0) -> np.ndarray:
        """(k,) 1-sigma uncertainty of alpha; ``fallback`` where a cluster has no fit yet."""
        return np.array([fallback if c.fit is None else c.fit.alpha_sigma for c in self.clusters])


# -- the cut ------------------------------------------------------------------------------------

class BRDFCut:
    """Leaf HBSABs of a BRDF-cut tree, the reliability test, the cut, k-means and the labels.

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        Sampled surface points (world frame, metres) and unit normals.
    n : int
        HBSAB texels per side (default 32).
    min_leaf : int
        Minimum points per tree leaf (default 64).
    max_angle_deg : float
        Grazing cut-off of the HBSAB updates, degrees.
    areas : (N,) array, optional
        Surface area of every point (for area-weighted merging); default 1 each.
    k : int, optional
        Number of clusters; None chooses it (module docstring).
    k_max : int
        Largest k tried when choosing automatically.
    min_total_weight, texel_min_weight, min_coverage, broad_alpha, region_energy
        Reliability test (module docstring).
    noise_ratio, split_gain
        Automatic k (module docstring).
    assign_margin : float
        Chi-square margin for assigning unreliable nodes by their HBSAB.
    leaf_margin : float or None
        Chi-square margin by which a leaf's own HBSAB must prefer another centre to leave its cut
        node's cluster (None: no leaf refinement).
    interior_k, interior_min_fraction
        The Ward fit of a cluster uses its interior leaves (a leaf whose points and ``interior_k``
        nearest leaves all carry the cluster's label) when they hold at least
        ``interior_min_fraction`` of its weight; boundary leaves mix two materials' lobes. Failing
        that, its pure leaves (every point carries the label) off the rim, then with it, when they
        hold that fraction; else every leaf carrying the label. (A band-shaped cluster in a coarse
        tree may have no interior leaf: the 320 x 240 bench scan's label, 128 leaves, 33 on the rim.
        All its leaves, seam leaves with the paint's sharp highlight included, fitted alpha 0.051 for
        0.35; its pure leaves 0.42.)
    rim : (N,) bool array, optional
        Points at the surface's open boundary (where the object box cut the fused surface off the
        support plane, :func:`appfusion.geometry_pass.open_boundary_points`): leaves holding one are
        not interior either. There the fused normals are worst and depth pixels of the plane can
        register to the object's lowest points; on the demo's matte label (Ward 0.35, a lobe 5 %
        above its diffuse level) leaving the rim's leaves out of the fit lowers its reduced
        chi-square from 5.9 to 4.6 (seed 1: 4.6 to 3.9).
    merge_alpha_rel, merge_rho_rel : float
        Automatic k: clusters whose fitted alpha and rho_s agree within these relative tolerances are
        merged (:meth:`_merge_alike`).
    emitter : None, "flat" or (k, theta, shift)
        The emitter's intensity distribution (IR profile, §6): the Ward fits then model clipped
        highlight texels instead of leaving them out (:func:`appfusion.ward_fit.fit_ward`).
    fit_min_weight : float
        Texel weight threshold of the Ward fits.
    diffuse : {"min", "fit"}
        Diffuse handling of the Ward fits (:func:`appfusion.ward_fit.fit_ward`).
    lobes : tuple of str
        The lobes each cluster's fit tries (:class:`appfusion.ward_fit.WardFitter`): ``("ward",)``
        (default, the paper's) or ``("ward", "ggx")``, the model ladder's GGX rung, where a cluster's
        ``fit.lobe`` says which :func:`appfusion.ward_fit.choose_lobe` kept. Every fit tries them
        (the progressive ones too: on the stored ggx-sphere and demo scans a cluster's two fits took
        1.6-1.9x the Ward fit's time, +0.04-0.1 s per cluster and call; :mod:`appfusion.ward_fit`).
        The clusters' merge test (:meth:`_merge_alike`) compares their Ward fits.
    dtype : numpy dtype
        Storage type of the leaf HBSABs (float32 default).
    seed : int
        Seed of the k-means restarts.
    """

    def __init__(self, positions, normals, n: int = DEFAULT_N, min_leaf: int = 64,
                 max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG, areas=None, k: int | None = None,
                 k_max: int = 6, min_total_weight: float = 200.0, texel_min_weight: float = 2.0,
                 min_coverage: float = 0.5, broad_alpha: float = 0.3, region_energy: float = 0.9,
                 noise_ratio: float = 1.0, split_gain: float = 3.0, assign_margin: float = 4.0,
                 fit_min_weight: float = 1.0, diffuse: str = "fit", dtype=np.float32, seed: int = 0,
                 size: float | None = None, leaf_margin: float | None = 9.0, interior_k: int = 6,
                 interior_min_fraction: float = 0.3, emitter=None, merge_alpha_rel: float = 0.25,
                 merge_rho_rel: float = 0.35, rim=None, lobes: tuple = ("ward",)):
        P, Nn = check_oriented_points(positions, normals, "BRDF cut")
        self.positions, self.normals = P, Nn
        self.tree = build_tree(P, Nn, min_leaf=min_leaf, size=size)
        self._rim_leaf = None
        if rim is not None:
            rim = np.asarray(rim)
            if rim.shape != (len(P),) or rim.dtype != bool:
                raise AppFusionError(f"BRDF cut: rim must be one bool per point ({len(P)}), got an array of "
                                     f"shape {rim.shape} and dtype {rim.dtype}")
            self._rim_leaf = np.bincount(self.tree.point_leaf, rim.astype(np.float64), self.tree.n_leaves) > 0
        self.leaves = HBSAB(self.tree.n_leaves, n=n, max_angle_deg=max_angle_deg, dtype=dtype)
        if areas is None:
            self.areas = np.ones(len(P))
        else:
            self.areas = np.asarray(areas, dtype=np.float64).reshape(-1)
            if len(self.areas) != len(P) or not np.all(np.isfinite(self.areas)) or np.any(self.areas < 0):
                raise AppFusionError(f"BRDF cut: areas must be {len(P)} finite non-negative values")
        if k is not None and int(k) < 1:
            raise AppFusionError(f"BRDF cut: k must be >= 1 or None (automatic), got {k}")
        self.k = None if k is None else int(k)
        self.k_max = max(1, int(k_max))
        self.min_total_weight = float(min_total_weight)
        self.texel_min_weight = float(texel_min_weight)
        self.min_coverage = float(min_coverage)
        self.region = highlight_region(self.leaves.n, broad_alpha, region_energy)
        self.noise_ratio = float(noise_ratio)
        self.split_gain = float(split_gain)
        self.assign_margin = float(assign_margin)
        self.leaf_margin = None if leaf_margin is None else float(leaf_margin)
        self.interior_k = int(interior_k)
        self.interior_min_fraction = float(interior_min_fraction)
        self.fit_min_weight = float(fit_min_weight)
        self.diffuse = diffuse
        self.emitter = emitter
        self.lobes = tuple(lobes)
        WardFitter(lobes=self.lobes)                 # checks the names now, not at the first fit
        self.merge_alpha_rel = float(merge_alpha_rel)
        self.clip_sum, self.clip_n = 0.0, 0        # saturated samples' values (the sensor's clip level)
        self.merge_rho_rel = float(merge_rho_rel)
        self.seed = int(seed)
        self.overrides = np.full(len(P), -1, np.int32)
        self._prev_labels: np.ndarray | None = None
        self._fitters: dict[int, WardFitter] = {}
        feat = np.hstack([(P - P.mean(0)) / self.tree.size, Nn])
        lens = np.diff(self.tree.leaf_start).astype(np.float64)
        self._leaf_feat_sum = np.add.reduceat(feat[self.tree.order], self.tree.leaf_start[:-1], axis=0)
        self._leaf_count = lens

    # -- data in ------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return self.leaves.n

    @property
    def nbytes(self) -> int:
        """State memory (leaf HBSABs, tree, labels), bytes; independent of the frames added."""
        t = self.tree
        tree_b = sum(a.nbytes for a in (t.left, t.right, t.parent, t.leaf_lo, t.leaf_hi, t.depth,
                                        t.leaf_node, t.order, t.leaf_start, t.point_leaf))
        return int(self.leaves.nbytes + tree_b + self.overrides.nbytes)

    def add_samples(self, point_idx: np.ndarray, wi: np.ndarray, wo: np.ndarray, value: np.ndarray,
                    weight: np.ndarray | None = None) -> int:
        """Add IR samples of points (local-frame directions) to their leaves' HBSABs (Eq. 3).

        Returns the number of samples used (grazing ones are discarded).
        """
        pidx = np.asarray(point_idx, dtype=np.int64).reshape(-1)
        if pidx.size and (pidx.min() < 0 or pidx.max() >= self.tree.n_points):
            raise AppFusionError(f"BRDF cut: point index out of range 0..{self.tree.n_points - 1}")
        s = half_vector_samples(wi, wo, value, self.n, self.leaves.max_angle_deg, weight)
        leaf = self.tree.point_leaf[pidx[s.keep]].astype(np.int64)
        self.leaves.add(leaf * (self.n * self.n) + s.texel, s.channels)
        return len(s.keep)

    # -- reliability and the cut ----------------------------------------------------------------
    def node_reliability(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Reliability of every node: (reliable (n_nodes,) bool, total weight, highlight coverage)."""
        t = self.tree
        W = self.leaves.data[CH_W]
        cum = np.zeros((t.n_leaves + 1, W.shape[1]))
        np.cumsum(W, axis=0, dtype=np.float64, out=cum[1:])
        NW = cum[t.leaf_hi] - cum[t.leaf_lo]                 # (n_nodes, T)
        total = NW.sum(axis=1)
        covered = NW >= self.texel_min_weight * (1 - 1e-9)
        reg = self.region
        coverage = (covered @ reg) / reg.sum()
        reliable = (total >= self.min_total_weight) & (coverage >= self.min_coverage)
        return reliable, total, coverage

    def cut(self, reliable: np.ndarray | None = None) -> np.ndarray:
        """Nodes of the BRDF cut, sorted depth-first: start at the root, replace a node by its two
        children whenever one of them is reliable (paper §5.2)."""
        t = self.tree
        if reliable is None:
            reliable = self.node_reliability()[0]
        out = []
        front = np.array([0], np.int64)
        while len(front):
            L, R = t.left[front], t.right[front]
            internal = L >= 0
            expand = internal.copy()
            expand[internal] = reliable[L[internal]] | reliable[R[internal]]
            out.append(front[~expand])
            front = np.concatenate([L[expand], R[expand]]).astype(np.int64)
        nodes = np.concatenate(out)
        return nodes[np.argsort(t.leaf_lo[nodes])].astype(np.int32)

    # -- manual refinement -------------------------------------------------------------------
    def set_labels(self, point_idx, label: int) -> None:
        """Paint points with a cluster label (manual refinement, paper §5.2); persists across
        re-clustering until :meth:`clear_labels`. ``label`` may exceed the current k (a new cluster)."""
        label = int(label)
        if label < 0:
            raise AppFusionError(f"BRDF cut: painted label must be >= 0, got {label}")
        idx = np.asarray(point_idx, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= len(self.overrides)):
            raise AppFusionError(f"BRDF cut: painted point index out of range 0..{len(self.overrides) - 1}")
        self.overrides[idx] = label

    def fit_clusters(self, labels) -> list[ClusterInfo]:
        """Ward fits (§5.1) of the clusters of a given labelling, e.g. once the colour pass has split
        off a material the IR showed no highlight of (``appfusion.rgb_pass``): its points then stop
        diluting the lobe of the cluster they were in. Leaves as in :meth:`result` (merged HBSAB of
        each label, interior leaves fitted); fresh fitters, so the clusters of :meth:`result` keep
        their warm starts.

        Parameters
        ----------
        labels : (N,) int array, one label >= 0 per point

        Returns
        -------
        list of :class:`ClusterInfo`, one per label ``0..labels.max()``.
        """
        lab = np.asarray(labels)
        if lab.shape != (len(self.overrides),) or not np.issubdtype(lab.dtype, np.integer) or (lab.size and lab.min() < 0):
            raise AppFusionError(f"BRDF cut: fit_clusters needs one label >= 0 per point ({len(self.overrides)}), "
                                 f"got an array of shape {lab.shape} and dtype {lab.dtype}")
        kept = self._fitters
        self._fitters = {}
        try:
            with one_blas_thread():
                return self._clusters(lab.astype(np.int64), int(lab.max()) + 1 if lab.size else 1, True)
        finally:
            self._fitters = kept

    def clear_labels(self, point_idx=None) -> None:
        """Remove painted labels (all, or of ``point_idx``)."""
        if point_idx is None:
            self.overrides[:] = -1
        else:
            self.overrides[np.asarray(point_idx, dtype=np.int64)] = -1

    # -- clustering ----------------------------------------------------------------------------
    def _choose_k(self, X, Om, chi2_by_k):
        """Automatic k (module docstring): grow k while the clusters leave more than the noise and one
        more cluster reduces the chi-square in excess of the noise by at least ``split_gain``."""
        k_hi = min(self.k_max, len(X))
        runs = {}

        def run(kk):
            if kk not in runs:
                lab, C, MC, chi2, per = kmeans_hbsab(X, Om, kk, seed=self.seed)
                dof = float(np.sum(np.maximum(per[:, 1] - 1, 0)))
                runs[kk] = (lab, C, MC, chi2, dof)
                chi2_by_k[kk] = (chi2, dof)
            return runs[kk]

        kk = 1
        while True:
            lab, C, MC, chi2, dof = run(kk)
            if kk >= k_hi or len(C) < kk or chi2 <= self.noise_ratio * max(dof, 1.0):
                break
            nxt = run(kk + 1)
            excess, excess_next = chi2 - self.noise_ratio * dof, nxt[3] - self.noise_ratio * nxt[4]
            if len(nxt[1]) <= kk or not (excess_next <= 0 or excess / excess_next >= self.split_gain):
                break
            kk += 1
        return runs[kk][:3]

    def result(self, k: int | None = None, fit: bool = True) -> CutResult:
        with one_blas_thread():
            return self._result(k, fit)

    def _result(self, k, fit) -> CutResult:
        """Cut, cluster, label and fit (paper §5.2); see the module docstring.

        Parameters
        ----------
        k : int, optional
            Overrides the constructor's ``k`` for this call (None: the constructor's; automatic if
            that is None too).
        fit : bool
            Fit a Ward lobe to every cluster's merged HBSAB (warm-started from the last call).

        Returns
        -------
        CutResult
        """
        t = self.tree
        k = self.k if k is None else int(k)
        notes: list[str] = []
        reliable, total, coverage = self.node_reliability()
        nodes = self.cut(reliable)
        rel = reliable[nodes]
        sums = self._clustering_sums(np.add.reduceat(self.leaves.data[[CH_W, CH_WV, CH_WV2, CH_SAT]],
                                                     t.leaf_lo[nodes], axis=1, dtype=np.float64))
        X, Om, _ = _hbsab_features(sums, self.texel_min_weight)
        cols = np.flatnonzero(Om.any(axis=0))                 # texels some node holds
        X, Om = X[:, cols], Om[:, cols]
        node_label = np.zeros(len(nodes), np.int64)
        chi2_by_k: dict = {}
        n_rel = int(rel.sum())
        if n_rel == 0:
            notes.append("no reliable BRDF-cut node yet (too few samples or too little highlight coverage): "
                         "one cluster")
            k_eff = 1
        else:
            Xr, Omr = X[rel], Om[rel]
            if k is None:
                lab, C, MC = self._choose_k(Xr, Omr, chi2_by_k)
            else:
                if k > n_rel:
                    notes.append(f"k = {k} requested but only {n_rel} reliable cut node(s): k reduced")
                lab, C, MC, chi2, per = kmeans_hbsab(Xr, Omr, min(k, n_rel), seed=self.seed)
                if len(C) < min(k, n_rel):
                    notes.append(f"only {len(C)} distinct cluster(s) in the data")
            k_eff = len(C)
            node_label[rel] = lab
            unrel = np.flatnonzero(~rel)
            if len(unrel):
                node_label[unrel] = self._assign_unreliable(nodes, rel, unrel, X, Om, C, MC, lab)
        # per-leaf labels (refined where a leaf's own data decide), then per-point labels
        leaf_label = np.repeat(node_label, t.leaf_hi[nodes] - t.leaf_lo[nodes])
        if n_rel and k_eff > 1 and self.leaf_margin is not None:
            leaf_label = self._refine_leaves(leaf_label, cols, C, MC)
        labels = leaf_label[t.point_leaf].astype(np.int32)
        labels = self._stabilise(labels, k_eff)
        painted = self.overrides >= 0
        if painted.any():
            labels[painted] = self.overrides[painted]
        k_out = int(max(k_eff, labels.max() + 1 if len(labels) else 1))
        clusters = self._clusters(labels, k_out, fit)
        if k is None and fit and not painted.any():
            labels, clusters, merged = self._merge_alike(labels, clusters)
            if merged:
                k_out = len(clusters)
                notes.append(f"automatic k: {merged} cluster(s) merged into others with the same fitted lobe")
        self._prev_labels = labels.copy()
        return CutResult(labels=labels, clusters=clusters, k=k_out, k_auto=k is None, cut_nodes=nodes,
                         cut_reliable=rel, chi2_by_k=chi2_by_k, notes=notes)

    def _merge_alike(self, labels, clusters):
        """Automatic k, second check: k-means splits noisy real data (texture, normal noise) beyond
        what the chi-square expects, so clusters whose fitted Ward lobes agree -- alpha within
        ``merge_alpha_rel`` relative (or 3 combined sigma) and rho_s within ``merge_rho_rel`` (or 3
        combined sigma) -- are one
        material and are merged (largest first), then refitted. A cluster whose fit ran to the needle
        bound (``rho_s`` at ``ward_fit.RHO_S_MAX`` or alpha at ``ALPHA_MIN``: clipped peaks that any sharp
        enough lobe explains)
        measured no lobe of its own either and joins the largest cluster with a proper fit.
        Returns labels, clusters, merges."""
        merged = 0
        while len(clusters) > 1:
            # a cluster whose chosen lobe is GGX compares by its Ward fit: a GGX and a Ward alpha are
            # not comparable
            fits = [(c.label, c.fit if c.fit.lobe == "ward" else c.fits.get("ward", c.fit))
                    for c in clusters if c.fit is not None]
            needle = [a for a, f in fits if _is_needle(f)]
            sound = [c for c in clusters if c.fit is not None and c.label not in needle]
            pair = None
            if needle and sound:
                keep = max(sound, key=lambda c: c.area).label
                pair = (min(keep, needle[0]), max(keep, needle[0]))
            for i in range(len(fits) if pair is None else 0):
                for j in range(i + 1, len(fits)):
                    (a, fa), (b, fb) = fits[i], fits[j]
                    if fa.at_bound or fb.at_bound:              # no lobe measured: nothing to compare
                        continue
                    da = abs(fa.alpha - fb.alpha)
                    tol = max(self.merge_alpha_rel * 0.5 * (fa.alpha + fb.alpha),
                              3.0 * float(np.hypot(fa.alpha_sigma, fb.alpha_sigma)))
                    ds = abs(fa.rho_s - fb.rho_s)
                    tol_s = max(self.merge_rho_rel * 0.5 * (fa.rho_s + fb.rho_s),
                                3.0 * float(np.hypot(fa.rho_s_sigma, fb.rho_s_sigma)))
                    if da <= tol and ds <= tol_s:
                        pair = (a, b)
                        break
                if pair:
                    break
            if pair is None:
                break
            a, b = pair
            labels = np.where(labels == b, a, labels)
            labels = np.where(labels > b, labels - 1, labels).astype(np.int32)
            self._fitters = {}
            self._prev_labels = None
            clusters = self._clusters(labels, len(clusters) - 1, True)
            merged += 1
        return labels, clusters, merged

    def _clustering_sums(self, d: np.ndarray) -> np.ndarray:
        """``W, WV, WV2`` (3, B, T) that k-means compares, from ``W, WV, WV2, WSAT`` sums.

        With the emitter's pattern divided out (``emitter[0] == "pattern"``) the IR pass keeps clipped
        samples out of the texel means (:mod:`appfusion.ward_fit`), so a node whose highlight clipped
        throughout has no peak texels and looks matte. For clustering, clipped samples count at the
        mean clip level instead, as they did before the pattern map: on a two-material scan (seed 1)
        the means alone gave two clusters of half paint, half label, one of them alpha 0.62.
        """
        if _is_pattern(self.emitter) and self.clip_n:
            c = self.clip_sum / self.clip_n
            W, WV, WV2, SAT = d
            return np.stack([W + SAT, WV + c * SAT, WV2 + c * c * SAT])
        return d[:3]

    def _refine_leaves(self, leaf_label, cols, C, MC):
        """Move a leaf to another centre when its own HBSAB is closer to it by ``leaf_margin`` in
        chi-square (the cut's nodes straddle material boundaries; their leaves need not)."""
        d = self._clustering_sums(self.leaves.data[[CH_W, CH_WV, CH_WV2, CH_SAT]][:, :, cols].astype(np.float64))
        XL, OmL, _ = _hbsab_features(d, self.texel_min_weight)
        chi2, nc, _ = _chi2_matrix(XL, OmL, C, MC)
        chi2 = np.where(nc > 0, chi2, np.inf)
        idx = np.arange(len(leaf_label))
        best = np.argmin(chi2, axis=1)
        cur = chi2[idx, leaf_label]
        with np.errstate(invalid="ignore"):
            switch = np.isfinite(cur) & (cur - chi2[idx, best] >= self.leaf_margin)
        out = leaf_label.copy()
        out[switch] = best[switch]
        return out

    def _assign_unreliable(self, nodes, rel, unrel, X, Om, C, MC, rel_labels):
        chi2, nc, _ = _chi2_matrix(X[unrel], Om[unrel], C, MC)
        score = np.where(nc > 0, chi2 / np.maximum(nc, 1), np.inf)
        order = np.sort(np.where(np.isfinite(score), chi2, np.inf), axis=1)
        best = np.argmin(score, axis=1)
        decided = np.isfinite(score[np.arange(len(unrel)), best])
        if C.shape[0] > 1:
            with np.errstate(invalid="ignore"):
                decided &= (order[:, 1] - order[:, 0]) >= self.assign_margin
        out = best.copy()
        if not decided.all():
            # nearest reliable cut node in (position / size, normal)
            t = self.tree
            lo, hi = t.leaf_lo[nodes], t.leaf_hi[nodes]
            cs = np.vstack([np.zeros((1, 6)), np.cumsum(self._leaf_feat_sum, axis=0)])
            cn = np.concatenate([[0.0], np.cumsum(self._leaf_count)])
            cent = (cs[hi] - cs[lo]) / (cn[hi] - cn[lo])[:, None]
            tree = cKDTree(cent[rel])
            _, j = tree.query(cent[unrel[~decided]])
            out[~decided] = rel_labels[np.asarray(j)]
        return out

    def _stabilise(self, labels: np.ndarray, k: int) -> np.ndarray:
        """Renumber clusters to match the previous result's labels by shared area (Hungarian)."""
        prev = self._prev_labels
        if prev is None or k <= 1:
            return labels
        keep = prev < k
        ov = np.zeros((k, k))
        np.add.at(ov, (labels[keep], prev[keep]), self.areas[keep])
        r, c = linear_sum_assignment(-ov)
        mapping = np.empty(k, np.int64)
        mapping[r] = c
        return mapping[labels].astype(np.int32)

    def _pure_leaves(self, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per leaf (n_leaves,): the smallest label of its points, whether they all share it (pure),
        and whether it is pure and holds no point of the surface's open boundary (``rim``)."""
        t = self.tree
        lo = np.minimum.reduceat(labels[t.order], t.leaf_start[:-1])
        hi = np.maximum.reduceat(labels[t.order], t.leaf_start[:-1])
        pure = lo == hi
        rim = self._rim_leaf if self._rim_leaf is not None else np.zeros(t.n_leaves, bool)
        return lo, pure, pure & ~rim

    def _interior_leaves(self, labels: np.ndarray) -> np.ndarray:
        """(n_leaves,) bool: leaves whose points share one label, as do their ``interior_k`` nearest
        leaves in ``(position / size, normal)``, and that hold no point of the surface's open
        boundary (``rim``). Leaves at a material boundary mix two lobes; the clusters' Ward fits leave
        them out (labels are unaffected)."""
        t = self.tree
        lo, pure, inside = self._pure_leaves(labels)
        if self.interior_k <= 0 or t.n_leaves <= 1:
            return inside
        cent = self._leaf_feat_sum / self._leaf_count[:, None]
        kk = min(self.interior_k + 1, t.n_leaves)
        _, nb = cKDTree(cent).query(cent, k=kk)
        nb = np.asarray(nb).reshape(t.n_leaves, -1)
        same = (lo[nb] == lo[:, None]) & pure[nb]
        return inside & same.all(axis=1)                      # (a rim leaf's neighbours stay interior)

    def _clusters(self, labels, k, fit) -> list[ClusterInfo]:
        t = self.tree
        F = np.zeros((k, t.n_leaves))
        np.add.at(F, (labels, t.point_leaf), self.areas)
        leaf_area = np.bincount(t.point_leaf, self.areas, t.n_leaves)
        Fn = F / np.where(leaf_area > 0, leaf_area, 1.0)[None]
        merged = self.leaves.merge(Fn)
        rungs = []
        if fit:
            _, pure, inside = self._pure_leaves(labels)
            rungs = [self.leaves.merge(Fn * m[None]) for m in (self._interior_leaves(labels), inside, pure)]
        out = []
        counts = np.bincount(labels, minlength=k)
        for c in range(k):
            hb = merged[c]
            wf, status = None, "not fitted"
            if fit:
                # fit the interior leaves when they hold enough of the cluster's data; else the leaves
                # of this label alone, off the rim, then with it; else every leaf carrying the label
                use = hb
                for rung in rungs:
                    if rung[c].total_weight()[0] >= self.interior_min_fraction * hb.total_weight()[0]:
                        use = rung[c]
                        break
                fitter = self._fitters.setdefault(c, WardFitter(self.fit_min_weight, self.diffuse,
                                                                         emitter=self.emitter, lobes=self.lobes))
                fitter.clip = self.clip_sum / self.clip_n if self.clip_n else None
                try:
                    wf = fitter.fit(use)
                    status = "fitted"
                except EstimationError as e:
                    status = f"insufficient data: {e}"
            fits = {} if wf is None else dict(self._fitters[c].fits)
            out.append(ClusterInfo(label=c, n_points=int(counts[c]), area=float(F[c].sum()), hbsab=hb,
                                   fit=wf, status=status, fits=fits))
        return out
