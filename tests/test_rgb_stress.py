"""Stress tests of the RGB pass: adversarial directions, bad pixels, broken frames, no NaN anywhere.

Property tests (hypothesis) on small tables; the update-rate test (640 x 480, 100k points) is slow.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from appfusion.double_product import DoubleProductTables
from appfusion.frame import Intrinsics, make_pose
from appfusion.rgb_pass import RGBPass, histogram_percentile
from appfusion.rgb_synth import SphereScene, fibonacci_sphere, orbit_poses, synthetic_envmap, two_material_sphere

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def small():
    env = synthetic_envmap(16, seed=4)
    T = DoubleProductTables(env, [0.1, 0.3], r_res=17, d_res=9, kernel_grid=(4, 6))
    sc = two_material_sphere(300, env=env, seed=1, image_scale=0.25,
                             materials=((0.1, (0.3, 0.3, 0.3)), (0.3, (0.5, 0.5, 0.5))))
    return env, T, sc


special = st.sampled_from([0.0, 1.0, -1.0, 1e-12, -1e-12, 0.5, -0.5, 1e-7])
coord = st.one_of(special, st.floats(-1, 1, allow_nan=False))


@SETTINGS
@given(n=st.tuples(coord, coord, coord), w=st.tuples(coord, coord, coord))
def test_S_is_finite_and_nonnegative_for_any_directions(small, n, w):
    _, T, _ = small
    n, w = np.array([n]), np.array([w])
    if np.linalg.norm(n) < 1e-6 or np.linalg.norm(w) < 1e-6:
        return
    n /= np.linalg.norm(n)
    w /= np.linalg.norm(w)
    for a in (0.1, 0.3, 0.2):
        S = T.S(n, w, a)
        assert np.isfinite(S).all() and (S >= 0).all()
        if not T.valid(n, w)[0]:
            assert (S == 0).all()
    assert np.isfinite(T.D(n)).all() and (T.D(n) >= 0).all()


def test_S_on_grid_edges_and_poles(small):
    _, T, _ = small
    pts = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [1, 1, 0], [1, -1, 0]]
    d = np.array(pts, float)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = np.repeat(d, len(d), 0)
    w = np.tile(d, (len(d), 1))
    S = T.S(n, w, 0.1)
    assert np.isfinite(S).all() and (S >= 0).all()
    same = np.einsum("ij,ij->i", n, w) > 0.99                           # w_o = n: mirror direction = n
    assert (S[same] > 0).mean() > 0.7            # (a 2 x 16^2 map is too coarse for a few of them)


bad_float = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32),
                      st.sampled_from([0.0, -1.0, 0.98, 0.979, 1e-9, 1e30]))


@SETTINGS
@given(L=hnp.arrays(np.float32, (6, 3), elements=bad_float),
       idx=hnp.arrays(np.int64, (6,), elements=st.integers(0, 299)),
       cam=st.sampled_from([0, 1, 2, 3]))
def test_add_samples_never_produces_nan(small, L, idx, cam):
    _, T, sc = small
    rp = RGBPass(sc.positions, sc.normals, sc.labels, sc.alphas, sc.env, tables=T)
    centres = [np.array([0.3, 0.1, 0.4]), sc.positions[idx[0]], sc.positions[idx] + 0.3 * sc.normals[idx],
               sc.positions[idx] - 0.3 * sc.normals[idx]]
    used = rp.add_samples(idx, L, centres[cam])
    res = rp.result()
    assert np.isfinite(res.rho_d).all() and np.isfinite(res.rho_s).all() and (res.rho_s >= 0).all()
    assert res.counts.sum() == used <= len(idx)
    assert (rp.sum_s2 >= 0).all() and np.isfinite(rp.sum_sl).all()
    st_ = rp.stats
    assert st_["samples"] + st_["skipped_dark"] + st_["skipped_saturated"] + st_["skipped_grazing"] \
        + st_["skipped_unlit"] == len(idx)


@SETTINGS
@given(h=hnp.arrays(np.uint16, (3, 16), elements=st.integers(0, 65535)),
       m=hnp.arrays(np.uint8, (3, 16), elements=st.integers(0, 255)),
       pct=st.floats(0.5, 99.5))
def test_histogram_percentile_bounds_and_monotonicity(h, m, pct):
    lo, w = math.log(0.01), 0.25
    v, tot = histogram_percentile(h, lo, w, pct, m)
    v2, _ = histogram_percentile(h, lo, w, min(pct + 5, 99.9), m)
    assert np.isfinite(v).all()
    ok = tot > 0
    assert (v[ok] >= math.exp(lo) * (1 - 1e-12)).all() and (v[ok] <= math.exp(lo + 16 * w) * (1 + 1e-12)).all()
    assert (v[~ok] == 0).all()
    assert (v2[ok] >= v[ok] * (1 - 1e-9)).all()


def test_broken_frames_are_survived(small):
    _, T, sc = small
    rp = RGBPass(sc.positions, sc.normals, sc.labels, sc.alphas, sc.env, tables=T, registration="points")
    rq = RGBPass(sc.positions, sc.normals, sc.labels, sc.alphas, sc.env, tables=T, registration="pixels")
    rng = np.random.default_rng(0)
    poses = orbit_poses(sc.center, 0.45, 6, seed=2)
    for i, T_ in enumerate(poses):
        rgb, depth, _ = sc.render(T_, rng)
        if i == 0:
            depth[:] = np.nan                                             # no depth at all
        elif i == 1:
            depth[::2] = 0.0
            depth[1::3] = -1.0
            rgb[::3] = np.nan                                             # corrupted pixels
        elif i == 2:
            rgb[:] = 1.0                                                  # fully saturated
        elif i == 3:
            rgb[:] = np.inf
        elif i == 4:
            T_ = make_pose(np.diag([1.0, -1.0, -1.0]), sc.center + [0, 0, 0.5])   # looking away (up)
        for r in (rp, rq):
            assert r.add_frame(rgb, depth, sc.rgb_intrinsics, sc.depth_intrinsics, T_, sc.depth_to_rgb) >= 0
    for r in (rp, rq):
        res = r.result()
        assert np.isfinite(res.rho_d).all() and np.isfinite(res.rho_s).all()
        assert res.counts.sum() > 0                                       # frame 5 is fine


@pytest.mark.slow
def test_update_rate_vga_100k_points():
    """RGB updates at 640 x 480 with a 100k-point object filling the view: the issue's goal is 30 per
    second on 2 cores, which ``appfusion bench`` reports (``fps_rgb_update``); timings are noisy and do
    not gate the tests, so this one only catches a gross slowdown (3x below the goal)."""
    env = synthetic_envmap(128, seed=3) * 0.5
    n = fibonacci_sphere(100_000)
    R, c = 0.2, np.array([0.0, 0.0, 0.2])
    labels = (n[:, 0] > 0.3).astype(np.int64)
    K = Intrinsics(640, 480, 575.8, 575.8, 319.5, 239.5)
    Kc = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
    E = make_pose(np.eye(3), [-0.025, 0, 0])
    sc = SphereScene(env, c, R, c + R * n, n, labels, np.full((len(n), 3), 0.4), np.full((2, 3), 0.3),
                     np.array([0.08, 0.25]), K, Kc, E)
    rp = RGBPass(sc.positions, sc.normals, labels, sc.alphas, env)
    frames = []
    for T in orbit_poses(c, 0.6, 5, seed=1):
        t, kind, X = sc._raycast(T, K)
        depth = np.where(kind > 0, t, np.nan).reshape(480, 640).astype(np.float32)
        t2, kind2, X2 = sc._raycast(T @ np.linalg.inv(E), Kc)
        nn = np.nan_to_num((X2 - c) / R)
        img = np.where((kind2 == 1)[:, None], 0.4 * rp.tables.D(nn), 0.02)
        frames.append((np.clip(img, 0, 1).reshape(480, 640, 3).astype(np.float32), depth, T))
    for rgb, depth, T in frames[:2]:
        rp.add_frame(rgb, depth, Kc, K, T, E)
    cpu = []
    for rgb, depth, T in frames * 2:
        c0 = time.process_time()
        used = rp.add_frame(rgb, depth, Kc, K, T, E)
        cpu.append(time.process_time() - c0)
        assert used > 15000
    fps = 1.0 / float(np.median(cpu))
    print(f"RGB update: {fps:.1f} frames/s (CPU), {used} samples per frame")
    assert fps >= 10.0, f"RGB update {fps:.1f} frames/s: far below the 30 frames/s goal"


def test_points_with_no_irradiance_are_skipped():
    """A black lower hemisphere: points facing down have D ~ 0, are not sampled, and make no NaN."""
    env = synthetic_envmap(16, seed=4)
    env[1] = 0.0
    n = fibonacci_sphere(400)
    P = np.array([0.0, 0.0, 0.2]) + 0.1 * n
    labels = np.zeros(len(n), np.int64)
    T = DoubleProductTables(env, [0.2], r_res=17, d_res=9, kernel_grid=(4, 6))
    rp = RGBPass(P, n, labels, [0.2], env, tables=T)
    down = np.flatnonzero(n[:, 2] < -0.95)
    assert len(down) and (T.D(n[down]).min(axis=1) < 0.01 * T.D(n).max()).all()   # (a sliver of sky only)
    assert not rp.lit[rp._rank[down]].any()
    cams = P[down] + 0.3 * n[down]                                        # in front of each point
    assert rp.add_samples(down, np.full((len(down), 3), 0.2), cams) == 0
    assert rp.stats["skipped_unlit"] == len(down)
    res = rp.result()
    assert np.isfinite(res.rho_d).all() and np.isfinite(res.rho_s).all() and res.counts.sum() == 0
