"""BRDF cut (paper §5.2) and the IR pass glue: tree, reliability, cut, k-means, labels, scans."""

from __future__ import annotations

import numpy as np
import pytest

from appfusion import ir_synth as S
from appfusion.brdf_cut import BRDFCut, build_tree, highlight_region, kmeans_hbsab
from appfusion.errors import AppFusionError
from appfusion.hbsab import CH_W
from appfusion.ir_pass import IRPass


def _accuracy(labels, truth, areas=None):
    """Area-weighted fraction of correctly labelled points under the best label permutation."""
    from scipy.optimize import linear_sum_assignment

    a = np.ones(len(labels)) if areas is None else areas
    k = max(labels.max(), truth.max()) + 1
    M = np.zeros((k, k))
    np.add.at(M, (labels, truth), a)
    r, c = linear_sum_assignment(-M)
    return M[r, c].sum() / a.sum(), dict(zip(r, c))


# -- tree -----------------------------------------------------------------------------------------

def test_tree_partitions_points_depth_first():
    P, N = S.sphere_points(5000, radius=0.1)
    t = build_tree(P, N, min_leaf=40)
    sizes = np.diff(t.leaf_start)
    assert sizes.min() >= 40 and sizes.max() < 80
    assert sorted(t.order.tolist()) == list(range(5000))
    assert np.all(t.point_leaf[t.order] == np.repeat(np.arange(t.n_leaves), sizes))
    for node in range(t.n_nodes):                     # a node's leaves = its children's, contiguous
        L, R = t.left[node], t.right[node]
        if L >= 0:
            assert t.leaf_lo[node] == t.leaf_lo[L] and t.leaf_hi[L] == t.leaf_lo[R]
            assert t.leaf_hi[R] == t.leaf_hi[node] and t.parent[L] == node == t.parent[R]
            assert len(t.node_points(node)) == len(t.node_points(L)) + len(t.node_points(R))
        else:
            assert t.leaf_hi[node] - t.leaf_lo[node] == 1
    # leaves are compact in (position / size, normal): a leaf spans a small part of the sphere
    spread = [np.ptp(N[t.node_points(t.leaf_node[j])], axis=0).max() for j in range(t.n_leaves)]
    assert np.median(spread) < 0.5
    one = build_tree(P[:10], N[:10], min_leaf=64)      # fewer points than a leaf: the root
    assert one.n_nodes == 1 and one.n_leaves == 1


def test_tree_input_errors():
    P, N = S.sphere_points(100)
    with pytest.raises(AppFusionError, match="normals of shape"):
        build_tree(P, N[:5])
    N2 = N.copy()
    N2[7] = 0
    with pytest.raises(AppFusionError, match="point 7 has a zero normal"):
        build_tree(P, N2)
    P2 = P.copy()
    P2[3, 1] = np.nan
    with pytest.raises(AppFusionError, match="point 3"):
        build_tree(P2, N)


# -- reliability and the cut ------------------------------------------------------------------------

def test_highlight_region_and_reliability():
    reg = highlight_region(32)
    d = np.array([0.0, 0.0, 1.0])
    from appfusion import octahedral as oc

    th = np.degrees(np.arccos(oc.hemi_directions(32).reshape(-1, 3) @ d))
    assert th[reg > 0].max() < 35 and th[reg > 0].min() < 3      # a disc around the normal
    P, N = S.sphere_points(2000, radius=0.1)
    cut = BRDFCut(P, N, n=32, min_leaf=50, min_total_weight=100)
    rel, total, cov = cut.node_reliability()
    assert not rel.any() and np.all(total == 0)
    assert cut.cut().tolist() == [0]                  # nothing reliable: the cut is the root
    # samples covering the whole highlight region in leaf 0's points only
    pts = cut.tree.node_points(cut.tree.leaf_node[0])
    h = oc.hemi_directions(32).reshape(-1, 3)[reg > 0]
    h = np.repeat(h, 3, axis=0)
    cut.add_samples(np.resize(pts, len(h)), h, h, np.ones(len(h)))
    rel, total, cov = cut.node_reliability()
    assert cov[cut.tree.leaf_node[0]] == pytest.approx(1.0)
    assert rel[0] and rel[cut.tree.leaf_node[0]]
    nodes = cut.cut(rel)
    lo, hi = cut.tree.leaf_lo[nodes], cut.tree.leaf_hi[nodes]
    assert lo[0] == 0 and np.all(lo[1:] == hi[:-1]) and hi[-1] == cut.tree.n_leaves   # a partition
    assert cut.tree.leaf_node[0] in nodes             # refined down to the reliable leaf


def test_kmeans_offset_free_distance():
    """Rows that differ by a constant (their diffuse part) are one cluster; a different lobe is not."""
    rng = np.random.default_rng(0)
    T = 200
    base = np.exp(-np.linspace(0, 5, T))
    other = np.exp(-np.linspace(0, 15, T))
    X = np.vstack([base + rng.uniform(0, 1, (30, 1)), other + rng.uniform(0, 1, (20, 1))])
    X += rng.normal(0, 0.01, X.shape)
    Om = np.full(X.shape, 1e4)
    Om[rng.random(X.shape) < 0.3] = 0                # missing texels
    lab, C, MC, chi2, per = kmeans_hbsab(X, Om, 2, seed=1)
    assert len(set(lab[:30])) == 1 and len(set(lab[30:])) == 1 and lab[0] != lab[30]
    lab1, *_ = kmeans_hbsab(X[:30], Om[:30], 3, seed=1)
    assert len(lab1) == 30


# -- scans through the IR pass ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def two_material_scan():
    sc, P, N, truth = S.two_material_sphere(seed=3, n_points=20000)
    ip = IRPass(P, N, sc.profile(), min_leaf=32)
    poses = S.orbit_poses(sc.center, 0.5, per_ring=16, seed=3)
    S.scan(ip, sc, poses)
    return sc, ip, truth, poses


def test_two_materials_labels_and_alphas(two_material_scan):
    sc, ip, truth, _ = two_material_scan
    res = ip.result()
    assert res.k_auto and res.k == 2, res.chi2_by_k
    acc, mapping = _accuracy(res.labels, truth)
    assert acc >= 0.95, acc
    for lab, mat in mapping.items():
        a_true = sc.materials[mat].alpha
        fit = res.clusters[lab].fit
        assert fit is not None and abs(fit.alpha / a_true - 1) <= 0.05, (a_true, fit)
        assert 0 < fit.alpha_sigma < 0.05 * a_true
        assert abs(res.clusters[lab].rho_d_ir - sc.materials[mat].rho_d) < 0.05
    np.testing.assert_array_equal(res.alphas(), [c.fit.alpha for c in res.clusters])
    assert res.fitted.all() and np.all(np.isfinite(res.alpha_sigmas()))
    # a forced k gives the same partition
    res2 = ip.result(k=2)
    assert _accuracy(res2.labels, truth)[0] >= 0.95


def test_a_needle_fit_is_no_material_of_its_own(two_material_scan):
    """Automatic k: a cluster whose Ward fit ran to the rho_s or the lower alpha bound (a needle lobe:
    clipped peaks that any sharp enough lobe meets) joins the largest properly fitted cluster; real
    lobes stay."""
    import dataclasses

    from appfusion.ward_fit import ALPHA_MIN, RHO_S_MAX

    sc, ip, truth, _ = two_material_scan
    res = ip.result()
    assert res.k == 2
    cut = ip.cut
    clusters = list(res.clusters)
    small = min(clusters, key=lambda c: c.area)
    clusters[small.label] = dataclasses.replace(
        small, fit=dataclasses.replace(small.fit, alpha=0.016, rho_s=RHO_S_MAX, at_bound=True))
    labels, merged_clusters, merged = cut._merge_alike(res.labels.copy(), clusters)
    assert merged == 1 and len(merged_clusters) == 1 and np.all(labels == 0)
    # the other needle bound: alpha at ALPHA_MIN with an ordinary rho_s (a mixed boundary cluster)
    clusters = list(res.clusters)
    clusters[small.label] = dataclasses.replace(
        small, fit=dataclasses.replace(small.fit, alpha=ALPHA_MIN, rho_s=0.3, at_bound=True))
    cut._fitters, cut._prev_labels = {}, None
    labels, merged_clusters, merged = cut._merge_alike(res.labels.copy(), clusters)
    assert merged == 1 and len(merged_clusters) == 1 and np.all(labels == 0)
    # two proper, different lobes are left apart
    labels2, kept, merged2 = cut._merge_alike(res.labels.copy(), list(res.clusters))
    assert merged2 == 0 and len(kept) == 2
    cut._fitters, cut._prev_labels = {}, None


def test_painted_labels_persist_and_labels_are_stable(two_material_scan):
    sc, ip, truth, poses = two_material_scan
    r1 = ip.result()
    painted = np.arange(0, 20000, 97)
    ip.set_labels(painted, 1)
    try:
        r2 = ip.result()
        assert np.all(r2.labels[painted] == 1)
        unpainted = np.setdiff1d(np.arange(20000), painted)
        assert np.array_equal(r1.labels[unpainted], r2.labels[unpainted])     # same numbering
        ip.set_labels([5], 4)                          # a new cluster, painted only
        r3 = ip.result()
        assert r3.k == 5 and r3.labels[5] == 4 and r3.clusters[4].n_points == 1
        assert all(np.isfinite(c.alpha) for c in r3.clusters if c.fit is not None)
        with pytest.raises(AppFusionError, match="painted"):
            ip.set_labels([1], -2)
    finally:
        ip.cut.clear_labels()
    assert np.array_equal(ip.result().labels, r1.labels)


def test_fit_clusters_of_given_labels(two_material_scan):
    """The lobes of an outside labelling (the colour pass's split): the true materials' labels fit
    their own alphas, one label over both materials fits neither; the clusters of result() keep
    their fitters."""
    sc, ip, truth, _ = two_material_scan
    before = {c: f for c, f in ip.cut._fitters.items()}
    infos = ip.fit_clusters(truth.astype(np.int32))
    assert [c.label for c in infos] == [0, 1]
    for c in infos:
        assert c.fit is not None and abs(c.fit.alpha / sc.materials[c.label].alpha - 1) <= 0.05, c.fit
    mixed = ip.fit_clusters(np.zeros(len(truth), np.int32))
    assert len(mixed) == 1
    a = mixed[0].fit.alpha if mixed[0].fit is not None else None
    assert a is None or all(abs(a / m.alpha - 1) > 0.05 for m in sc.materials)
    assert ip.cut._fitters == before
    with pytest.raises(AppFusionError, match="one label"):
        ip.fit_clusters(truth[:10])
    with pytest.raises(AppFusionError, match="one label"):
        ip.fit_clusters(-np.ones(len(truth), np.int32))


def test_state_size_is_independent_of_frames(two_material_scan):
    sc, ip, truth, poses = two_material_scan
    a = IRPass(ip.cut.positions, ip.cut.normals, sc.profile(), min_leaf=32)
    S.scan(a, sc, poses[:3])
    b = IRPass(ip.cut.positions, ip.cut.normals, sc.profile(), min_leaf=32)
    S.scan(b, sc, poses[:3] * 10)
    assert b.stats["used"] == pytest.approx(10 * a.stats["used"], rel=0.01)
    assert a.nbytes == b.nbytes
    assert b.cut.leaves.data[CH_W].sum() == pytest.approx(10 * a.cut.leaves.data[CH_W].sum(), rel=1e-3)


def test_one_material_sphere_gives_one_cluster():
    sc, P, N, truth = S.two_material_sphere(seed=5, n_points=12000, one_material=True)
    ip = IRPass(P, N, sc.profile(), min_leaf=32)
    S.scan(ip, sc, S.orbit_poses(sc.center, 0.5, per_ring=12, seed=5))
    res = ip.result()
    assert res.k == 1 and res.k_auto, res.chi2_by_k
    assert np.all(res.labels == 0)
    assert abs(res.clusters[0].alpha / sc.materials[0].alpha - 1) < 0.05


def test_ir_pass_input_errors():
    sc, P, N, truth = S.two_material_sphere(seed=5, n_points=500, one_material=True)
    ip = IRPass(P, N, sc.profile(), min_leaf=32)
    K = sc.intrinsics
    with pytest.raises(AppFusionError, match="same size"):
        ip.add_frame(np.zeros((10, 10)), np.zeros(K.shape), K, np.eye(4))
    with pytest.raises(AppFusionError, match="pose"):
        ip.add_frame(np.zeros(K.shape), np.zeros(K.shape), K, np.eye(3))
    with pytest.raises(AppFusionError, match="point indices"):
        ip.add_samples(np.zeros(3, int), np.zeros((2, 3)), (0, 0, 1), (0, 0, 1), np.zeros(3))
    assert ip.add_frame(np.zeros(K.shape), np.full(K.shape, np.nan), K, np.eye(4)) == 0


def test_ir_pass_takes_frames():
    from appfusion.frame import Frame

    sc, P, N, truth = S.two_material_sphere(seed=6, n_points=2000, one_material=True)
    ip = IRPass(P, N, sc.profile(), min_leaf=32)
    T = S.orbit_poses(sc.center, 0.5, per_ring=1, elevations_deg=(30,))[0]
    ir, depth = sc.render(T)
    f = Frame(0, 0.0, depth=depth, ir=ir, depth_intrinsics=sc.intrinsics, pose=T, pass_name="geometry")
    n = ip.add(f)
    assert n > 1000 and ip.stats["used"] == n
    assert ip.add(f.replace(ir=None)) == 0
    with pytest.raises(AppFusionError, match="no camera pose"):
        ip.add(f.replace(pose=None))


def test_pattern_mode_clusters_with_clipped_samples_at_the_clip_level():
    """With the emitter pattern divided out, clipped samples are out of the texel means; k-means
    compares texels with them counted at the mean clip level (a node clipped throughout must not
    look matte)."""
    rng = np.random.default_rng(0)
    P = rng.normal(size=(200, 3))
    N = P / np.linalg.norm(P, axis=1, keepdims=True)
    cut = BRDFCut(P, N, min_leaf=50, emitter=("pattern", 1.6, 0.355, 0.431))
    d = np.zeros((4, 2, 3))
    d[0] = [[2.0, 0.0, 1.0], [1.0, 1.0, 1.0]]          # W (unclipped)
    d[1] = d[0] * 0.5                                   # WV: unclipped mean 0.5
    d[2] = d[0] * 0.25
    d[3] = [[0.0, 4.0, 1.0], [0.0, 0.0, 0.0]]          # WSAT
    assert np.array_equal(cut._clustering_sums(d), d[:3])          # no clip level yet
    cut.clip_sum, cut.clip_n = 30.0, 10                 # mean clip level 3
    W, WV, WV2 = cut._clustering_sums(d)
    assert W[0].tolist() == [2.0, 4.0, 2.0] and WV[0].tolist() == [1.0, 12.0, 3.5]
    assert WV2[0, 1] == pytest.approx(36.0) and np.array_equal(W[1], d[0, 1])
    plain = BRDFCut(P, N, min_leaf=50, emitter=(1.6, 0.355, 0.431))
    plain.clip_sum, plain.clip_n = 30.0, 10
    assert np.array_equal(plain._clustering_sums(d), d[:3])


def test_samples_take_the_normal_at_their_own_place_on_the_surface():
    """Pixels register to the nearest of sparse points: on a sphere with 3000 points a pixel's normal
    differs from its point's by ~1.3 degrees, which widened the Ward lobe fitted from them (alpha
    +3.4 %). With the normal's gradient each sample is tilted to its own place (`normal_gradient`)."""
    sc, P, N, truth = S.two_material_sphere(seed=5, n_points=3000, one_material=True)
    poses = S.orbit_poses(sc.center, 0.5, per_ring=12, seed=5)
    a_true = sc.materials[0].alpha
    err = {}
    for g in (False, True):
        ip = IRPass(P, N, sc.profile(), min_leaf=32, normal_gradient=g)
        S.scan(ip, sc, poses)
        err[g] = ip.result(k=1).clusters[0].fit.alpha / a_true - 1
    assert err[False] > 0.02 and abs(err[True]) < 0.01, err


def test_rim_leaves_stay_out_of_the_fits(two_material_scan):
    """Leaves holding a point of the surface's open boundary (``rim``) are not interior: the clusters'
    Ward fits leave them out, the labels do not change; a rim of the wrong shape is named."""
    sc, ip, truth, _ = two_material_scan
    P = ip.cut.positions
    rim = P[:, 2] < np.percentile(P[:, 2], 10)                     # a band of the sphere
    cut = BRDFCut(P, ip.cut.normals, min_leaf=32, rim=rim)
    lab = truth.astype(np.int64)
    inner = cut._interior_leaves(lab)
    plain = BRDFCut(P, ip.cut.normals, min_leaf=32)._interior_leaves(lab)
    rim_leaf = np.bincount(cut.tree.point_leaf, rim.astype(float), cut.tree.n_leaves) > 0
    assert rim_leaf.any() and not inner[rim_leaf].any()
    np.testing.assert_array_equal(inner[~rim_leaf], plain[~rim_leaf])
    with pytest.raises(AppFusionError, match="rim must be one bool per point"):
        BRDFCut(P, ip.cut.normals, rim=rim[:10])
    with pytest.raises(AppFusionError, match="rim must be one bool per point"):
        BRDFCut(P, ip.cut.normals, rim=rim.astype(int))


def test_a_cluster_without_interior_leaves_fits_its_pure_leaves(two_material_scan, monkeypatch):
    """When a cluster's interior leaves hold too little of its weight (a band-shaped material in a
    coarse tree), its Ward fit takes the leaves whose points all carry its label, not every leaf it
    touches: the boundary leaves mix the other material's lobe in."""
    from appfusion.ward_fit import WardFitter

    sc, ip, truth, _ = two_material_scan
    cut = ip.cut
    lab = truth.astype(np.int64)
    seen = []
    fit = WardFitter.fit

    def spy(self, hb, *a, **k):
        seen.append(float(hb.total_weight()[0]))
        return fit(self, hb, *a, **k)

    monkeypatch.setattr(WardFitter, "fit", spy)
    monkeypatch.setattr(cut, "interior_k", cut.tree.n_leaves)        # no leaf is interior now
    assert not cut._interior_leaves(lab).any()
    infos = cut.fit_clusters(lab)
    _, pure, inside = cut._pure_leaves(lab)
    assert pure.any() and not np.array_equal(pure, np.ones_like(pure))
    F = np.zeros((2, cut.tree.n_leaves))
    np.add.at(F, (lab, cut.tree.point_leaf), cut.areas)
    Fn = F / np.bincount(cut.tree.point_leaf, cut.areas, cut.tree.n_leaves)[None]
    for c in infos:
        want = cut.leaves.merge(Fn * inside[None])[c.label].total_weight()[0]
        assert seen[c.label] == pytest.approx(want)                    # the pure leaves' data
        assert seen[c.label] < c.hbsab.total_weight()[0]
        assert abs(c.fit.alpha / sc.materials[c.label].alpha - 1) <= 0.05, c.fit
