"""HBSAB (paper §5.1, Eq. 3): texel mapping, the running weighted mean, channels, combining."""

from __future__ import annotations

import numpy as np
import pytest

from appfusion import octahedral as oc
from appfusion.errors import AppFusionError
from appfusion.hbsab import (CH_M, CH_SAT, CH_W, CH_WG, CH_WV, CH_WV2, HBSAB, N_CHANNELS, half_vector_samples,
                             scatter_add)


def _dirs(n, seed=0, max_deg=85.0):
    rng = np.random.default_rng(seed)
    th = np.radians(rng.uniform(0, max_deg, n))
    ph = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1)


def _pairs(n, seed=0):
    """Random (w_i, w_o) pairs a few degrees apart, both above the horizon."""
    rng = np.random.default_rng(seed)
    wo = _dirs(n, seed, 70)
    wi = wo + rng.normal(0, 0.05, wo.shape)
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    return wi, wo


def test_eq3_running_mean_equals_batch_update():
    """Eq. 3 applied sample by sample gives the same v and w as one vectorised update."""
    wi, wo = _pairs(300, 1)
    val = np.random.default_rng(2).uniform(0, 2, 300)
    hb = HBSAB(1, 8)
    used = hb.update(0, wi, wo, val)
    assert used == 300
    n = 8
    v = np.zeros(n * n)
    w = np.zeros(n * n)
    h = wi + wo
    tex = oc.texel_index(oc.hemi_encode(h), n)
    for t, vh, wh in zip(tex, val, wo[:, 2]):        # the paper's update, literally
        v[t] = (v[t] * w[t] + vh * wh) / (w[t] + wh)
        w[t] = w[t] + wh
    np.testing.assert_allclose(hb.weight.reshape(-1), w, rtol=1e-12)
    np.testing.assert_allclose(hb.value.reshape(-1), v, rtol=1e-10, atol=1e-14)


def test_texel_of_half_vector_and_channels():
    wi, wo = _pairs(500, 3)
    val = np.linspace(0.1, 1.0, 500)
    s = half_vector_samples(wi, wo, val, n=16)
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    np.testing.assert_array_equal(s.texel, oc.texel_index(oc.hemi_encode(h), 16))
    w = wo[:, 2]
    np.testing.assert_allclose(s.channels[CH_W], w)
    np.testing.assert_allclose(s.channels[CH_WV], w * val)
    np.testing.assert_allclose(s.channels[CH_WV2], w * val * val)
    g = h[:, 2] / np.sqrt(wi[:, 2] * wo[:, 2])
    np.testing.assert_allclose(s.channels[CH_WG], w * g)
    assert np.all(s.channels[CH_SAT] == 0)
    # Legendre moments: P1 of the position inside the texel reconstructs the half vector's uv
    uv = oc.hemi_encode(h)
    a = s.channels[CH_M] / w
    col = s.texel % 16
    np.testing.assert_allclose(((col + 0.5 + a / 2) * 2 / 16 - 1), uv[:, 0], atol=1e-12)
    assert np.all(np.abs(s.channels[CH_M:CH_M + 5] / w) <= 1 + 1e-12)


def test_uniform_samples_in_a_texel_have_zero_moments():
    n = 8
    rng = np.random.default_rng(5)
    m = 200000
    u = rng.uniform(-1 + 5 * 2 / n, -1 + 6 * 2 / n, m)      # inside texel (row 2, column 5)
    v = rng.uniform(-1 + 2 * 2 / n, -1 + 3 * 2 / n, m)
    h = oc.hemi_decode(np.stack([u, v], 1))
    hb = HBSAB(1, n)
    hb.update(0, h, h, np.ones(m), weight=np.ones(m))
    t = 2 * n + 5
    assert hb.weight.reshape(-1)[t] == m
    np.testing.assert_allclose(hb.moments()[:, 0, t], 0.0, atol=0.01)


def test_grazing_samples_are_discarded():
    wo = np.array([[0.0, 0.0, 1.0], [np.sin(np.radians(85)), 0, np.cos(np.radians(85))],
                   [0.0, np.sin(np.radians(75)), np.cos(np.radians(75))]])
    wi = wo.copy()
    hb = HBSAB(1, 8)
    assert hb.update(0, wi, wo, np.ones(3)) == 2
    assert HBSAB(1, 8, max_angle_deg=70).update(0, wi, wo, np.ones(3)) == 1
    wi2 = wi.copy()
    wi2[0] = [np.sin(np.radians(82)), 0, np.cos(np.radians(82))]   # w_i grazing, w_o fine
    assert HBSAB(1, 8).update(0, wi2, wo, np.ones(3)) == 1
    # non-finite values are not added either
    assert HBSAB(1, 8).update(0, wi, wo, np.array([np.nan, 1.0, 2.0])) == 1
    assert HBSAB(1, 8).update(0, wi, wo, np.array([1.0, 1.0, np.inf])) == 1


def test_many_buffers_equal_separate_buffers_and_combine():
    wi, wo = _pairs(3000, 7)
    val = np.random.default_rng(8).gamma(2.0, 0.5, 3000)
    buf = np.random.default_rng(9).integers(0, 5, 3000)
    many = HBSAB(5, 16)
    many.update(buf, wi, wo, val)
    for b in range(5):
        one = HBSAB(1, 16)
        one.update(0, wi[buf == b], wo[buf == b], val[buf == b])
        np.testing.assert_allclose(many.data[:, b], one.data[:, 0], rtol=1e-12, atol=1e-12)
    # combining children = weight-sum; the combined mean is the weighted mean of the parts
    whole = HBSAB(1, 16)
    whole.update(0, wi, wo, val)
    np.testing.assert_allclose(many.sum().data, whole.data, rtol=1e-10, atol=1e-10)
    rs = many.range_sums(np.array([0, 2]))
    np.testing.assert_allclose(rs.data[:, 0], many.data[:, :2].sum(1), rtol=1e-12)
    np.testing.assert_allclose(rs.data[:, 1], many.data[:, 2:].sum(1), rtol=1e-12)
    F = np.array([[1, 1, 0, 0, 0], [0, 0, 0.5, 0.5, 1.0]])
    mg = many.merge(F)
    np.testing.assert_allclose(mg.data[:, 1], 0.5 * many.data[:, 2] + 0.5 * many.data[:, 3] + many.data[:, 4],
                               rtol=1e-12, atol=1e-12)
    assert many.nbytes == N_CHANNELS * 5 * 256 * 8


def test_scatter_add_both_paths():
    rng = np.random.default_rng(1)
    M = 4096
    for m in (100, 100000):                          # np.unique path and look-up-table path
        keys = rng.integers(0, M, m)
        ch = rng.random((N_CHANNELS, m))
        ch[CH_SAT] = np.where(rng.random(m) < 0.01, ch[CH_SAT], 0.0)
        ref = np.stack([np.bincount(keys, c, M) for c in ch])
        out = np.zeros((N_CHANNELS, M))
        scatter_add(out, keys, ch)
        np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-12)
        # with the scratch arrays (the IR pass's path): same sums, the mark left all False
        lut, mark = np.empty(M, np.int64), np.zeros(M, bool)
        out = np.zeros((N_CHANNELS, M))
        for _ in range(2):
            scatter_add(out, keys, ch, lut, mark)
            assert not mark.any()
        np.testing.assert_allclose(out, 2 * ref, rtol=1e-12, atol=1e-12)


def test_bad_input_is_named():
    hb = HBSAB(2, 8)
    wi, wo = _pairs(4)
    with pytest.raises(AppFusionError, match="buffer index out of range"):
        hb.update(2, wi, wo, np.ones(4))
    with pytest.raises(AppFusionError, match="same length"):
        hb.update(0, wi, wo[:3], np.ones(4))
    with pytest.raises(AppFusionError, match="texels per side"):
        HBSAB(1, 1)
    with pytest.raises(AppFusionError, match="max_angle_deg"):
        HBSAB(1, 8, max_angle_deg=95)
    with pytest.raises(AppFusionError, match="strictly"):
        hb.range_sums(np.array([1]))
    with pytest.raises(AppFusionError, match="fractions"):
        hb.merge(np.ones((1, 3)))
