"""D(n) and S(n, alpha, w_o) tables of the RGB pass (paper §5.3) against brute-force quadrature of Eq. 4.

The references come from :mod:`appfusion.rgb_synth` (direct sums over the environment's texels with an
independent Ward implementation), never from the wavelet code.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from appfusion import octahedral as octa
from appfusion.brdf import ggx, ward
from appfusion.diffuse_term import DiffuseTable, NodeGrid, diffuse_exact, envmap_check
from appfusion.double_product import (CapSquare, DoubleProductTables, SparseCoeffs, default_cap, ggx_kernel_slices,
                                      haar2, ihaar2, kernel_slices, mirror_params, signed_frames, ward_kernel_slices)
from appfusion.errors import AppFusionError
from appfusion.rgb_synth import brute_force_S, synthetic_envmap, ward_reference


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def sample_set(n: int, seed: int, alphas):
    """Random (n, w_o, alpha): normals not pointing into the plane, cameras above the plane,
    n.w_o >= 0.2 (view angles up to 78 degrees)."""
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n, 3))
    nrm[:, 2] = np.abs(nrm[:, 2]) * 1.5 - 0.3 * np.linalg.norm(nrm[:, :2], axis=1)
    nrm = _unit(nrm)
    wo = np.empty_like(nrm)
    for i in range(n):
        while True:
            c = _unit(rng.normal(size=3))
            if c[2] > 0.05 and c @ nrm[i] > 0.2:
                wo[i] = c
                break
    return nrm, wo, rng.choice(np.asarray(alphas), size=n)


def rel_rms(est, ref):
    return float(np.sqrt(((est - ref) ** 2).sum() / (ref ** 2).sum()))


# -- building blocks -------------------------------------------------------------------------------

def test_haar_is_orthonormal_and_invertible():
    x = np.random.default_rng(0).normal(size=(4, 32, 32, 3))
    c = haar2(x)
    assert c.shape == x.shape
    np.testing.assert_allclose((c ** 2).sum(axis=(1, 2)), (x ** 2).sum(axis=(1, 2)), rtol=1e-12)   # Parseval
    np.testing.assert_allclose(ihaar2(c), x, atol=1e-12)
    y = np.random.default_rng(1).normal(size=(4, 32, 32, 3))
    np.testing.assert_allclose((haar2(y) * c).sum(axis=(1, 2)), (x * y).sum(axis=(1, 2)), rtol=1e-10)


def test_sparse_coeffs_keep_the_largest_and_quantise():
    rng = np.random.default_rng(2)
    c = rng.normal(size=(5, 256, 3)) * rng.uniform(0.1, 10, size=(5, 1, 1))
    sp = SparseCoeffs.from_dense(c, 40)
    assert sp.idx.dtype == np.uint16 and sp.q.dtype == np.int16 and sp.idx.shape == (5, 40)
    mag = np.abs(c).sum(-1)
    for b in range(5):
        kept = set(sp.idx[b].tolist())
        assert kept == set(np.argsort(-mag[b])[:40].tolist())
    d = sp.dense()
    kept_mask = d.any(axis=-1)
    err = np.abs(d - c)[kept_mask.nonzero()]
    assert err.max() <= np.abs(c).max() / 32767 * 0.51 * 1.0001        # int16 rounding, per-vector scale
    assert sp.nbytes == sp.idx.nbytes + sp.q.nbytes + sp.scale.nbytes


def test_node_grid_interpolates_exactly_at_nodes_and_within_faces():
    g = NodeGrid(9)
    d = g.directions.reshape(-1, 3)
    idx, w, face = g.lookup(d)
    np.testing.assert_allclose(w.sum(-1), 1.0)
    # a node is reproduced: its own weight is 1 (or it sits on a shared edge)
    got = (w[..., None] * d[idx]).sum(1)
    np.testing.assert_allclose(_unit(got), d, atol=1e-12)
    # random directions: all 4 corners on the direction's face, weights in [0, 1]
    q = _unit(np.random.default_rng(3).normal(size=(1000, 3)))
    idx, w, face = g.lookup(q)
    assert ((idx // 81) == face[:, None]).all() and (w >= 0).all() and (w <= 1).all()
    with pytest.raises(AppFusionError):
        NodeGrid(2)


def test_signed_frames_are_orthonormal_and_smooth_on_each_face():
    rng = np.random.default_rng(4)
    d = _unit(rng.normal(size=(500, 3)))
    s = np.where(d[:, 2] >= 0, 1.0, -1.0)
    F = signed_frames(d, s)
    np.testing.assert_allclose(F @ F.transpose(0, 2, 1), np.broadcast_to(np.eye(3), F.shape), atol=1e-12)
    np.testing.assert_allclose(F[:, 2], d)
    np.testing.assert_allclose(np.linalg.det(F), 1.0, atol=1e-12)
    # the +1 branch is smooth across the equator (used by face 0 up to its border)
    e = _unit(np.array([[1.0, 0.3, 1e-9], [1.0, 0.3, -1e-9]]))
    Fe = signed_frames(e, 1.0)
    assert np.abs(Fe[0] - Fe[1]).max() < 1e-6


def test_cap_square_solid_angles():
    for cap in (0.4, 1.0, math.pi / 2, 2.0):
        sq = CapSquare(16, cap, sub=4)
        np.testing.assert_allclose(sq.solid_angles.sum(), 2 * math.pi * (1 - math.cos(cap)), rtol=2e-3)
        ang = np.arccos(np.clip(sq.directions[..., 2], -1, 1))
        assert ang.max() < cap
    np.testing.assert_allclose(CapSquare(16, math.pi / 2, 8).solid_angles, octa.hemi_solid_angles(16, 8), rtol=1e-9)
    with pytest.raises(AppFusionError):
        CapSquare(12, 1.0)


def test_kernel_slice_is_the_ward_lobe_times_cosine():
    sq = CapSquare(16, 1.2, sub=1)
    th, be, a = 0.7, 2.1, 0.15
    K = ward_kernel_slices(a, sq, np.array([th]), np.array([be]))[0, 0]
    n = np.array([math.sin(th) * math.cos(be), math.sin(th) * math.sin(be), math.cos(th)])
    wo = 2 * math.cos(th) * n - np.array([0, 0, 1.0])
    w = sq.directions.reshape(-1, 3)
    ref = ward(a, w, np.broadcast_to(wo, w.shape), np.broadcast_to(n, w.shape)) * np.maximum(w @ n, 0)
    np.testing.assert_allclose(K.ravel() / math.sqrt(math.cos(th)), ref, rtol=1e-9, atol=1e-12)


def test_mirror_params():
    rng = np.random.default_rng(5)
    n = _unit(rng.normal(size=(100, 3)))
    wo = _unit(n + rng.normal(size=(100, 3)) * 0.5)
    r, co, beta = mirror_params(n, wo)
    np.testing.assert_allclose(np.einsum("ij,ij->i", r, n), co, atol=1e-12)       # mirror: same angle
    np.testing.assert_allclose(np.linalg.norm(np.cross(n, r + wo), axis=1), 0, atol=1e-12)
    F = signed_frames(r, np.where(r[:, 2] >= 0, 1.0, -1.0))
    nl = np.stack([np.cos(beta) * np.sqrt(1 - co ** 2), np.sin(beta) * np.sqrt(1 - co ** 2), co], 1)
    np.testing.assert_allclose(np.einsum("pji,pj->pi", F, nl), n, atol=1e-9)


# -- D -----------------------------------------------------------------------------------------------

def test_diffuse_table_matches_exact_quadrature():
    env = synthetic_envmap(64, seed=3)
    T = DiffuseTable(env, m=65)
    n = _unit(np.random.default_rng(6).normal(size=(2000, 3)))
    ref = diffuse_exact(env, n)
    got = T(n)
    rel = np.abs(got - ref) / ref
    assert np.median(rel) < 1e-3
    assert (np.abs(got - ref).max(1) / ref.max()).max() < 0.01
    # a constant environment of radiance 1: D = 1 for every normal (upper or lower face)
    one = np.ones((2, 16, 16, 3), np.float32)
    np.testing.assert_allclose(DiffuseTable(one, m=9)(n), 1.0, rtol=5e-3)


def test_envmap_check_rejects_bad_maps():
    with pytest.raises(AppFusionError, match="shape"):
        envmap_check(np.zeros((16, 32, 3)))
    bad = np.ones((2, 8, 8, 3), np.float32)
    bad[1, 2, 3, 0] = np.nan
    with pytest.raises(AppFusionError, match="NaN"):
        envmap_check(bad, "the map")
    bad[1, 2, 3, 0] = -1
    with pytest.raises(AppFusionError, match="non-negative"):
        envmap_check(bad)


# -- S -------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_tables():
    env = synthetic_envmap(32, seed=1)
    t0 = time.process_time()
    T = DoubleProductTables(env, [0.12, 0.3], r_res=lambda a: 49 if a < 0.2 else 33, d_res=33)
    return env, T, time.process_time() - t0


def test_S_small_map_against_brute_force(small_tables):
    env, T, _ = small_tables
    n, wo, al = sample_set(250, 7, [0.12, 0.3])
    ref = brute_force_S(env, n, al, wo)
    got = T.S(n, wo, al)
    assert got.dtype == np.float32 and np.isfinite(got).all()
    assert rel_rms(got, ref) < 0.02                                   # (coarser r grid than the default)
    assert abs(got.sum() / ref.sum() - 1) < 0.005                     # no bias
    assert T.valid(n, wo).all()


def test_S_scales_with_the_environment_and_is_zero_when_grazing(small_tables):
    env, T, _ = small_tables
    n, wo, al = sample_set(40, 8, [0.12])
    bright = DoubleProductTables(env * 1e5, [0.12], r_res=49, d_res=9)     # float16 table would overflow unscaled
    np.testing.assert_allclose(bright.S(n, wo, 0.12), 1e5 * T.S(n, wo, 0.12), rtol=2e-3)
    graz = _unit(np.cross(n, [0.3, 0.1, 0.9]))                        # w_o in the tangent plane
    assert (T.S(n, graz, 0.12) == 0).all() and not T.valid(n, graz).any()
    assert (T.S(n, -wo, 0.12) == 0).all()                             # from below the surface


def test_S_alpha_interpolation_between_close_alphas():
    env = synthetic_envmap(32, seed=1)
    T = DoubleProductTables(env, [0.2, 0.22], r_res=33, d_res=9)
    n, wo, _ = sample_set(150, 9, [0.21])
    a = 0.21
    got, ref = T.S(n, wo, a), brute_force_S(env, n, a, wo)
    at_node = rel_rms(T.S(n, wo, 0.2), brute_force_S(env, n, 0.2, wo))
    assert rel_rms(got, ref) < at_node + 0.01                          # log-alpha blend of close lobes
    with pytest.raises(AppFusionError, match="outside"):
        T.S(n, wo, 0.5)


def test_lighting_truncation_trades_accuracy(small_tables):
    env, T, _ = small_tables
    n, wo, al = sample_set(150, 10, [0.12])
    ref = brute_force_S(env, n, al, wo)
    T64 = DoubleProductTables(env, [0.12], r_res=49, d_res=9, light_keep=64)
    e_full, e_64 = rel_rms(T.S(n, wo, al), ref), rel_rms(T64.S(n, wo, al), ref)
    assert e_64 > e_full and e_64 < 0.05
    assert T64.tables[0.12].stats["light_keep"] == 64


def test_lazy_tables_compute_only_the_mirror_nodes_samples_need(small_tables):
    """Skip "unused env-map directions": a lazy table computes a mirror node the first time a lookup
    needs it; its S equals an eager table's; grazing samples compute nothing."""
    env, _, _ = small_tables
    kw = dict(r_res=33, d_res=9)
    eager = DoubleProductTables(env, [0.12], lazy=False, **kw)
    lazy = DoubleProductTables(env, [0.12], **kw)
    te, tl = eager.tables[0.12], lazy.tables[0.12]
    assert te.complete and te.stats["nodes_built"] == te.grid.size
    assert not tl.complete and tl.stats["nodes_built"] == 0 and (tl.values == 0).all()
    # one side of an object seen from above: normals within 30 deg of +x, views from the upper half
    rng = np.random.default_rng(3)
    n = _unit(np.array([1.0, 0.0, 0.3]) + 0.35 * rng.normal(size=(400, 3)))
    wo = _unit(n + np.array([0.0, 0.0, 0.8]) + 0.3 * rng.normal(size=(400, 3)))
    keep = ((n * wo).sum(1) > 0.2) & (wo[:, 2] > 0)
    n, wo = n[keep], wo[keep]
    got = lazy.S(n, wo, 0.12)
    built = tl.stats["nodes_built"]
    assert 0 < built < 0.5 * tl.grid.size
    np.testing.assert_allclose(got, eager.S(n, wo, 0.12), rtol=2e-3, atol=1e-6 * float(got.max()))
    # the same samples again: nothing new; grazing and back-facing views: nothing
    lazy.S(n, wo, 0.12)
    graz = _unit(np.cross(n, [0.3, 0.1, 0.9]))
    assert (lazy.S(n, graz, 0.12) == 0).all() and (lazy.S(n, -wo, 0.12) == 0).all()
    assert tl.stats["nodes_built"] == built
    rep = lazy.report()
    assert rep["nodes_built"] == built and rep["nodes_total"] == tl.grid.size and rep["lazy"]
    # completing it gives the eager table, node for node
    assert tl.build_all() == tl.grid.size - built and tl.complete and tl.build_all() == 0
    np.testing.assert_allclose(tl.values.astype(np.float32), te.values.astype(np.float32), rtol=2e-3, atol=2.0)
    assert tl.scale == te.scale


def test_tables_without_alphas_give_D_only(small_tables):
    env, _, _ = small_tables
    T = DoubleProductTables(env, [], d_res=9)
    assert T.alphas == [] and T.D(np.array([[0.0, 0.0, 1.0]])).shape == (1, 3)
    with pytest.raises(AppFusionError, match="no S table"):
        T.S(np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, 1.0]]), 0.1)


def test_S_inputs_are_checked(small_tables):
    env, T, _ = small_tables
    with pytest.raises(AppFusionError, match="shape"):
        T.S(np.zeros((3, 3)), np.zeros((4, 3)), 0.12)
    with pytest.raises(AppFusionError, match="positive"):
        DoubleProductTables(env, [0.1, -0.2])
    with pytest.raises(AppFusionError):
        DoubleProductTables(env, [0.1], res=24)
    with pytest.raises(AppFusionError, match="theta_max"):
        DoubleProductTables(env, [0.1], theta_max_deg=90)


@pytest.mark.slow
def test_S_full_resolution_map_within_one_percent():
    """The acceptance figure: 2 x 128^2 map, alpha in {0.06, 0.1, 0.2, 0.35}, default tables."""
    env = synthetic_envmap(128, seed=1)
    t0 = time.perf_counter()
    T = DoubleProductTables(env, [0.06, 0.1, 0.2, 0.35])
    build = time.perf_counter() - t0
    assert T.nbytes / 2 ** 20 <= 64.0
    n, wo, al = sample_set(400, 0, [0.06, 0.1, 0.2, 0.35])
    ref = brute_force_S(env, n, al, wo)
    got = T.S(n, wo, al)
    err = rel_rms(got, ref)
    print(f"S rel RMS {err:.4f}, tables {T.nbytes / 2 ** 20:.1f} MB, build {build:.1f} s")
    assert err <= 0.01
    for a in (0.06, 0.1, 0.2, 0.35):
        m = al == a
        assert rel_rms(got[m], ref[m]) <= 0.0125, a


# -- GGX -------------------------------------------------------------------------------------------------

def ggx_reference(alpha, cos_h, cos_i, cos_o):
    """GGX / Trowbridge-Reitz D, separable Smith G1, no Fresnel (Walter et al. 2007), written
    independently of :mod:`appfusion.brdf`; 1/sr."""
    ok = (cos_i > 0) & (cos_o > 0) & (cos_h > 0)
    a2 = alpha * alpha
    ch2 = np.where(ok, cos_h, 1.0) ** 2
    D = a2 / (np.pi * (ch2 * (a2 - 1) + 1) ** 2)

    def g1(c):
        c = np.where(ok, c, 1.0)
        return 2 * c / (c + np.sqrt(a2 + (1 - a2) * c * c))          # = 2 / (1 + sqrt(1 + a^2 tan^2))

    return np.where(ok, D * g1(cos_i) * g1(cos_o) / (4 * np.where(ok, cos_i * cos_o, 1.0)), 0.0)


def brute_force_S_ggx(env, normals, alpha, w_o, chunk=64):
    """S = sum_t L_t f_ggx(alpha; w_t, w_o) max(n.w_t, 0) dw_t over all env texels; (P, 3)."""
    n_ = env.shape[1]
    dirs = octa.sphere_directions(n_).reshape(-1, 3)
    lw = np.asarray(env, np.float64).reshape(-1, 3) * octa.sphere_solid_angles(n_).reshape(-1, 1)
    alpha = np.broadcast_to(np.asarray(alpha, float), (len(normals),))
    out = np.zeros((len(normals), 3))
    for s in range(0, len(normals), chunk):
        n, wo, a = normals[s:s + chunk], w_o[s:s + chunk], alpha[s:s + chunk, None]
        co = (n * wo).sum(1)[:, None]
        ci = n @ dirs.T
        h2 = 2 + 2 * (wo @ dirs.T)
        ch = np.where(h2 > 1e-12, (ci + co) / np.sqrt(np.maximum(h2, 1e-12)), 0.0)
        out[s:s + chunk] = (ggx_reference(a, ch, ci, co) * np.maximum(ci, 0)) @ lw
    return out


@pytest.mark.parametrize("lobe, alphas, seed", [("ward", (0.2,), 11), ("ggx", (0.08, 0.3), 12)])
def test_reference_lobe_agrees_with_engine_lobe(lobe, alphas, seed):
    """The tests' own lobe formulas (in cosines) equal the engine's (appfusion.brdf) on random pairs."""
    reference, engine = {"ward": (ward_reference, ward), "ggx": (ggx_reference, ggx)}[lobe]
    rng = np.random.default_rng(seed)
    n = _unit(rng.normal(size=(300, 3)))
    wi, wo = _unit(n + rng.normal(size=(300, 3))), _unit(n + rng.normal(size=(300, 3)))
    h = _unit(wi + wo)
    ci, co, ch = (wi * n).sum(1), (wo * n).sum(1), (h * n).sum(1)
    for a in alphas:
        np.testing.assert_allclose(reference(a, ch, ci, co), engine(a, wi, wo, n), rtol=1e-9, atol=1e-12)


def test_stretched_cap_square():
    """The GGX square: polar angle cap (q^u - 1) / (q - 1), exact solid angles, q times finer at the pole."""
    for cap, q in ((2.0, 7.0), (2.8, 1.4)):
        sq = CapSquare(32, cap, sub=4, stretch=q)
        np.testing.assert_allclose(sq.solid_angles.sum(), 2 * math.pi * (1 - math.cos(cap)), rtol=2e-3)
        assert np.arccos(np.clip(sq.directions[..., 2], -1, 1)).max() < cap
        lin = CapSquare(32, cap, sub=1)
        np.testing.assert_allclose(sq.pole_step, lin.pole_step * math.log(q) / (q - 1), rtol=1e-9)
    np.testing.assert_array_equal(CapSquare(16, 1.0, 2, 1.0).directions, CapSquare(16, 1.0, 2).directions)
    with pytest.raises(AppFusionError, match="stretch"):
        CapSquare(16, 1.0, stretch=0.5)


def test_kernel_slice_is_the_ggx_lobe_times_cosine():
    sq = CapSquare(16, 2.5, sub=1, stretch=3.0)
    th, be, a = 0.7, 2.1, 0.15
    K = ggx_kernel_slices(a, sq, np.array([th]), np.array([be]))[0, 0]
    np.testing.assert_array_equal(K, kernel_slices("ggx", a, sq, np.array([th]), np.array([be]))[0, 0])
    n = np.array([math.sin(th) * math.cos(be), math.sin(th) * math.sin(be), math.cos(th)])
    wo = 2 * math.cos(th) * n - np.array([0, 0, 1.0])
    w = sq.directions.reshape(-1, 3)
    ref = ggx(a, w, np.broadcast_to(wo, w.shape), np.broadcast_to(n, w.shape)) * np.maximum(w @ n, 0)
    np.testing.assert_allclose(K.ravel() / math.sqrt(math.cos(th)), ref, rtol=1e-9, atol=1e-12)
    with pytest.raises(AppFusionError, match="unknown specular lobe"):
        kernel_slices("phong", a, sq, np.array([th]), np.array([be]))


def test_ggx_cap_holds_the_lobe_energy():
    """GGX caps leave GGX_TAIL (0.25 %) of the projected lobe outside at normal view; Ward's are unchanged."""
    for a in (0.08, 0.15, 0.3):
        c = default_cap(a, "ggx")
        t2 = math.tan(c / 2) ** 2
        assert abs(a * a / (a * a + t2) - 0.0025) < 1e-6 and c > default_cap(a) and c <= 2.9
        assert default_cap(a) == default_cap(a, "ward") == float(np.clip(5 * a + 0.1, 0.35, 2.2))
    with pytest.raises(AppFusionError, match="unknown specular lobe"):
        default_cap(0.1, "beckmann")


def test_lobe_api_keys_tables_by_lobe_and_alpha(small_tables):
    """Tables keyed (lobe, alpha); S groups samples by lobe; log-alpha blends stay within a lobe."""
    env, Tw, _ = small_tables
    T = DoubleProductTables(env, [0.12], lobes={"ggx": [0.12, 0.3]}, r_res=33, d_res=9)
    assert T.alphas == [0.12] and list(T.tables) == [0.12] and T.lobe_alphas("ggx") == [0.12, 0.3]
    assert set(T.all_tables) == {("ward", 0.12), ("ggx", 0.12), ("ggx", 0.3)}
    assert T.table(0.3, "ggx").lobe == "ggx" and T.add_alpha(0.3, "ggx") is T.table(0.3, "ggx")
    n, wo, al = sample_set(120, 13, [0.12, 0.3])
    lb = np.where(np.arange(120) % 3 == 0, "ward", "ggx")
    al = np.where(lb == "ward", 0.12, al)
    mixed = T.S(n, wo, al, lb)
    w, g = lb == "ward", lb == "ggx"
    np.testing.assert_array_equal(mixed[w], T.S(n[w], wo[w], 0.12))
    np.testing.assert_array_equal(mixed[g], T.S(n[g], wo[g], al[g], "ggx"))
    assert not np.allclose(T.S(n, wo, 0.12, "ggx"), T.S(n, wo, 0.12, "ward"), rtol=0.05)
    # between the two GGX tables: a blend of GGX tables only (Ward has no table at 0.3)
    a = math.sqrt(0.12 * 0.3)
    np.testing.assert_allclose(T.S(n, wo, a, "ggx"), 0.5 * (T.S(n, wo, 0.12, "ggx") + T.S(n, wo, 0.3, "ggx")),
                               rtol=1e-5, atol=1e-7)
    with pytest.raises(AppFusionError, match="outside"):
        T.S(n, wo, a)                                                     # Ward: only 0.12 built
    with pytest.raises(AppFusionError, match="unknown specular lobe"):
        T.S(n, wo, 0.12, "phong")
    with pytest.raises(AppFusionError, match="unknown specular lobe"):
        T.S(n, wo, 0.12, np.where(w, "ward", "blinn"))
    with pytest.raises(AppFusionError, match="unknown specular lobe"):
        T.add_alpha(0.2, "beckmann")
    with pytest.raises(AppFusionError, match="unknown specular lobe"):
        DoubleProductTables(env, [], lobes={"beckmann": [0.1]}, d_res=9)
    with pytest.raises(AppFusionError, match="positive"):
        DoubleProductTables(env, [], lobes={"ggx": [0.1, 0.0]}, d_res=9)
    with pytest.raises(AppFusionError, match="no ggx S table"):
        Tw.S(n, wo, 0.12, "ggx")
    # sizes and the report cover every lobe
    assert T.nbytes == T.diffuse.nbytes + sum(t.nbytes for t in T.all_tables.values())
    rep = T.report()
    assert set(rep["alphas"]) == {"0.12"} and set(rep["lobes"]["ggx"]) == {"0.12", "0.3"}
    assert rep["nodes_total"] == sum(t.grid.size for t in T.all_tables.values())
    assert T.table(0.3, "ggx").stats["stretch"] >= 1 and T.table(0.12, "ggx").stats["res"] == 64
    # the tables no pass reads any more are released (a scan's earlier lobes); the kept ones read as before
    before, mb = T.S(n[g], wo[g], 0.3, "ggx"), T.table(0.12, "ggx").nbytes / 2**20 + T.table(0.12).nbytes / 2**20
    assert T.keep_only({("ggx", 0.3)}) == pytest.approx(mb)
    assert set(T.all_tables) == {("ggx", 0.3)} and T.alphas == []
    np.testing.assert_array_equal(T.S(n[g], wo[g], 0.3, "ggx"), before)
    with pytest.raises(AppFusionError, match="no S table"):
        T.S(n, wo, 0.12)
    assert T.keep_only([("ggx", 0.3)]) == 0.0
    with pytest.raises(AppFusionError, match="unknown specular lobe"):
        T.keep_only({("phong", 0.3)})


@pytest.mark.slow
def test_S_ggx_full_resolution_map_within_one_percent():
    """GGX tables (model ladder's third rung) on a 2 x 128^2 map, alpha in {0.08, 0.15, 0.3}: S within
    ~1 % RMS of brute-force quadrature over the map's texels (lazy tables: only the nodes the samples
    need are computed)."""
    env = synthetic_envmap(128, seed=1)
    alphas = (0.08, 0.15, 0.3)
    T = DoubleProductTables(env, [], lobes={"ggx": alphas}, d_res=9)
    n, wo, al = sample_set(240, 0, alphas)
    ref = brute_force_S_ggx(env, n, al, wo)
    got = T.S(n, wo, al, "ggx")
    err = rel_rms(got, ref)
    print(f"GGX S rel RMS {err:.4f}, tables {T.nbytes / 2 ** 20:.1f} MB")
    assert err <= 0.01 and abs(got.sum() / ref.sum() - 1) < 0.005
    for a in alphas:
        m = al == a
        assert rel_rms(got[m], ref[m]) <= 0.0125, a
