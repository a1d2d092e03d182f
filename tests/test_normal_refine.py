"""Specular normal refinement (appfusion.normal_refine): normals moved to where the highlights say.

The sphere's images are rendered by brute-force quadrature (:mod:`appfusion.rgb_synth`) with its true
normals; the RGB pass and the refiner are given normals of which half are tilted by 3 degrees.
"""

from __future__ import annotations

import numpy as np
import pytest

from _rgb_sphere import TABLES, sphere_frames
from appfusion.errors import AppFusionError
from appfusion.normal_refine import NormalRefiner, candidate_normals, tangent_frames
from appfusion.rgb_pass import RGBPass


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1, 1)))


def test_candidate_normals_are_unit_rings_at_the_given_tilts():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[0] = (0, 0, 1)                                        # both branches of the tangent choice
    t, b = tangent_frames(n)
    assert np.allclose(np.einsum("ij,ij->i", t, n), 0, atol=1e-12)
    assert np.allclose(np.einsum("ij,ij->i", b, t), 0, atol=1e-12)
    c = candidate_normals(n, (1.0, 2.5), 6)
    assert c.shape == (50, 13, 3)
    assert np.allclose(np.linalg.norm(c, axis=2), 1, atol=1e-6)
    tilt = np.stack([_angle(c[:, k], n) for k in range(13)], 1)
    assert np.allclose(tilt[:, 0], 0, atol=0.05)
    assert np.allclose(tilt[:, 1:7], 1.0, atol=0.01) and np.allclose(tilt[:, 7:], 2.5, atol=0.01)


@pytest.fixture(scope="module")
def tilted_run():
    sc, poses, rng, frames = sphere_frames()
    # half of the points' normals tilted by 3 degrees, each in its own random direction
    tilted = rng.random(len(sc.normals)) < 0.5
    t, b = tangent_frames(sc.normals)
    ph = rng.uniform(0, 2 * np.pi, len(sc.normals))[:, None]
    a = np.radians(3.0)
    N = np.where(tilted[:, None], sc.normals * np.cos(a) + (t * np.cos(ph) + b * np.sin(ph)) * np.sin(a), sc.normals)
    rp = RGBPass(sc.positions, N, sc.labels, sc.alphas, sc.env, table_kwargs=TABLES)
    for (rgb, depth, _), T in zip(frames, poses):
        rp.add_frame(rgb, depth, sc.rgb_intrinsics, sc.depth_intrinsics, T, sc.depth_to_rgb)
    return sc, poses, frames, rp, N, tilted


def test_tilted_glossy_normals_move_back_and_the_right_ones_stay(tilted_run):
    sc, poses, frames, rp, N, tilted = tilted_run
    res = rp.result()
    normals, only = N, None
    for radii in ((1.5, 3.0), (0.75, 1.5)):                   # as the pipeline's rounds: then the moved ones
        ref = NormalRefiner(rp, res.rho_s, normals, radii_deg=radii, screen=None, only=only)
        for (rgb, depth, _), T in zip(frames, poses):
            ref.add_frame(rgb, depth, sc.rgb_intrinsics, sc.depth_intrinsics, T, sc.depth_to_rgb)
        normals, rho_d, st = ref.result()
        only = np.isfinite(rho_d).all(axis=1)
        print(radii, st)
    glossy = sc.labels == 0                                   # alpha 0.08: sharp highlights
    seen = res.counts >= 8
    before = _angle(N, sc.normals)
    after = _angle(normals, sc.normals)
    moved = _angle(normals, N) > 0.1
    g_t, g_u = glossy & tilted & seen, glossy & ~tilted & seen
    print(f"tilted glossy: median {np.median(before[g_t]):.2f} -> {np.median(after[g_t]):.2f} deg, "
          f"moved {moved[g_t].mean():.2f}, the moved {np.median(after[g_t & moved]):.2f} deg; "
          f"untilted moved {moved[g_u].mean():.2f}, median after {np.median(after[g_u]):.2f}")
    assert moved[g_t].mean() > 0.5 and np.median(after[g_t & moved]) < 1.0
    assert np.median(after[g_t]) < 0.6 * np.median(before[g_t])
    assert moved[g_u].mean() < 0.2 and np.median(after[g_u]) < 0.05       # 0.16: rho_s is biased by the tilts
    # the last round's moved points' rho_d solved again near the truth; the others NaN (keep the pass's)
    mv = np.isfinite(rho_d).all(axis=1)
    assert mv.any() and not mv[~moved].any()
    rel = np.abs(rho_d[mv] / sc.rho_d[mv] - 1)
    print(f"rho_d of the moved: median rel err {np.median(rel):.4f}")
    # the factor a caller scales its own (pooled, corrected) rho_d by: the pass's rho_d at the
    # tilted normals times it lands where the re-solve does; NaN for the points that did not move
    f = ref.rho_d_factor
    assert np.isfinite(f[mv]).all() and np.isnan(f[~mv]).all()
    scaled = np.abs(res.rho_d[mv] * f[mv] / sc.rho_d[mv] - 1)
    unscaled = np.abs(res.rho_d[mv] / sc.rho_d[mv] - 1)
    print(f"pass rho_d of the moved: {np.median(unscaled):.4f}, times the factor {np.median(scaled):.4f}")
    assert np.median(scaled) < np.median(unscaled)
    assert np.median(rel) < 0.05


def test_add_samples_equals_add_frame_and_bad_input_is_refused(tilted_run):
    sc, poses, frames, rp, N, tilted = tilted_run
    res = rp.result()
    a = NormalRefiner(rp, res.rho_s, N, screen=None)
    b = NormalRefiner(rp, res.rho_s, N, screen=None)
    (rgb, depth, _), T = frames[3], poses[3]
    assert a.add_frame(rgb, depth, sc.rgb_intrinsics, sc.depth_intrinsics, T, sc.depth_to_rgb) > 50
    # the same samples by hand: the points a registered, their RGB pixels
    sel = np.flatnonzero(a.n > 0)
    p_int = a.sel[sel]
    pts, Xd = rp._project_points(depth, sc.depth_intrinsics, T)
    pts, L, C = rp._lookup_rgb(rgb, pts, Xd, sc.rgb_intrinsics, T, sc.depth_to_rgb)
    order = np.argsort(pts)
    k = np.searchsorted(pts[order], p_int)
    assert b.add_samples(rp._order[p_int], L[order][k], C) == len(sel)
    assert np.allclose(a.rss(), b.rss())
    with pytest.raises(AppFusionError, match="rho_s"):
        NormalRefiner(rp, np.zeros((1, 3)))
    with pytest.raises(AppFusionError, match="one sample per point"):
        b.add_samples([1, 1], np.ones((2, 3)), C)
    with pytest.raises(AppFusionError, match="normals"):
        NormalRefiner(rp, res.rho_s, N[:10])
    with pytest.raises(AppFusionError, match="z > 0"):
        NormalRefiner(rp, res.rho_s, z=0)
