"""The support plane as near-field light (appfusion.near_field): closed forms and brute-force references."""

from __future__ import annotations

import numpy as np
import pytest

from appfusion import octahedral as oc
from appfusion.errors import AppFusionError
from appfusion.near_field import SupportPlaneLight, paper_radiance_from_env
from appfusion.rgb_synth import brute_force_S

N = 64
FAR = np.array([[50.0, 50.0, 0.0]])          # a circle far outside every extent: no effect
R_FAR = np.array([0.01])


def _env(upper=(0.3, 0.3, 0.3), lower=(0.02, 0.03, 0.04)) -> np.ndarray:
    d = oc.sphere_directions(N)
    env = np.where(d[..., 2:3] >= 0, np.asarray(upper, float), np.asarray(lower, float))
    return env.astype(np.float32)


def test_delta_D_of_a_downward_normal_is_the_disc_form_factor():
    """A point at height h facing straight down sees the plane within ``extent`` as a disc:
    dD = (L_paper - L_env) sin^2(theta_max), tan(theta_max) = extent / h; a circle right below adds
    (L_circle - L_paper) a^2 / (a^2 + h^2)."""
    env = _env()
    paper = np.array([0.05, 0.05, 0.05])
    h, ext = 0.1, 0.4
    nf = SupportPlaneLight(env, FAR, R_FAR, paper, extent_m=ext, n_quad=64)
    p = np.array([[0.0, 0.0, h]])
    n = np.array([[0.0, 0.0, -1.0]])
    s2 = ext ** 2 / (ext ** 2 + h ** 2)
    want = (paper - np.array([0.02, 0.03, 0.04])) * s2
    np.testing.assert_allclose(nf.delta_D(p, n)[0], want, rtol=0.02, atol=2e-4)
    # an upward normal sees nothing of the plane
    np.testing.assert_allclose(nf.delta_D(p, -n)[0], 0.0, atol=1e-12)
    a = 0.03
    nfc = SupportPlaneLight(env, np.array([[0.0, 0.0, 0.0]]), np.array([a]), paper, circle_radiance=1.0,
                            extent_m=ext, n_quad=64)
    extra = nfc.delta_D(p, n)[0] - nf.delta_D(p, n)[0]
    np.testing.assert_allclose(extra, (1.0 - paper) * a * a / (a * a + h * h), rtol=0.03)
    # asked again for the same points (the RGB pass's second sweep), the kept answer: equal, and a copy
    first = nf.delta_D(p, n)
    first[:] = -1.0
    np.testing.assert_allclose(nf.delta_D(p, n)[0], want, rtol=0.02, atol=2e-4)


def _paper_hemisphere():
    """The map, the paper's radiance, the map with that paper as its lower hemisphere, and the plane
    model that should equal it (an extent far beyond every hit, circles far off)."""
    env = _env()
    paper = np.array([0.08, 0.06, 0.04])
    return env, paper, _env(lower=paper), SupportPlaneLight(env, FAR, R_FAR, paper, extent_m=1e4)


def _side_views(rng: np.random.Generator, m: int):
    """Up to m side-facing normals (their lobes reach the plane) seen by cameras above, n.w_o > 0.3."""
    n = rng.normal(size=(m, 3))
    n[:, 2] = np.abs(n[:, 2]) * 0.3
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    wo = n + rng.normal(size=(m, 3)) * 0.3
    wo[:, 2] = np.abs(wo[:, 2]) + 0.3
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    keep = np.sum(n * wo, 1) > 0.3
    return n[keep], wo[keep]


def test_delta_S_matches_brute_force_with_the_plane_as_lower_hemisphere():
    """With an extent far beyond every hit, the plane model is a lower hemisphere of uniform paper:
    dS = S(env with paper below) - S(env), by brute-force quadrature over all texels."""
    env, paper, env_p, nf = _paper_hemisphere()
    rng = np.random.default_rng(0)
    n, wo = _side_views(rng, 40)
    p = np.tile([0.0, 0.0, 0.08], (len(n), 1))
    for alpha in (0.08, 0.3):
        want = brute_force_S(env_p, n, alpha, wo) - brute_force_S(env, n, alpha, wo)
        got = np.mean([nf.delta_S(p, n, wo, alpha, n_samples=256, seed=s) for s in range(12)], axis=0)
        scale = np.abs(want).max()
        assert scale > 1e-3
        np.testing.assert_allclose(got, want, atol=0.04 * scale + 1e-5)       # Monte Carlo: ~1.5 % rms
        assert abs(np.mean(got - want)) < 0.005 * scale                       # and no bias
    # a lobe that reflects a white circle gets it, with the circle's own sample count
    nfc = SupportPlaneLight(env, np.array([[0.1, 0.0, 0.0]]), np.array([0.03]), paper, extent_m=1e4)
    pc = np.array([[0.0, 0.0, 0.1]])
    nc = np.array([[1.0, 0.0, 0.0]])                    # a side facing +x ...
    wc = np.array([[np.sqrt(0.5), 0.0, np.sqrt(0.5)]])  # ... seen from 45 deg up: mirror ray 45 deg down
    with_c = np.mean([nfc.delta_S(pc, nc, wc, 0.05, n_samples=4, seed=s) for s in range(16)], axis=0)
    without = np.mean([nf.delta_S(pc, nc, wc, 0.05, n_samples=4, seed=s) for s in range(16)], axis=0)
    assert with_c[0, 0] > without[0, 0] + 0.3          # the circle (radiance 1 against paper 0.08)
    # lobes that point up get no correction at all
    up = np.tile([0.0, 0.0, 1.0], (3, 1))
    assert np.all(nf.delta_S(p[:3], up, up, 0.05) == 0)


def test_paper_radiance_read_from_the_ball_map_ignores_circles_and_the_ball_shadow():
    paper = np.array([0.05, 0.051, 0.052])
    env = _env(lower=paper)
    c = np.array([0.0, 0.0, 0.035])
    d = oc.sphere_directions(N)
    t = c[2] / np.maximum(-d[..., 2], 1e-9)
    xy = c[:2] + t[..., None] * d[..., :2]
    h = 0.15
    centres = np.array([[h, h, 0], [h, -h, 0], [-h, -h, 0], [-h, h, 0]], float)
    radii = np.array([0.035, 0.025, 0.025, 0.025])
    circ = np.any(np.sum((xy[..., None, :] - centres[:, :2]) ** 2, -1) <= radii ** 2, -1) & (d[..., 2] < 0)
    env[circ] = 1.0
    env[(d[..., 2] < -0.8)] *= 0.5                    # the ball's own shadow right below it
    np.testing.assert_allclose(paper_radiance_from_env(env, c, centres, radii), paper, rtol=1e-5)
    with pytest.raises(AppFusionError, match="above the plane"):
        paper_radiance_from_env(env, [0, 0, -0.1], centres, radii)


def test_object_shadow_darkens_the_plane_under_an_object_only():
    """A 10 cm box standing on the plane under a map lit from above: the plane under it is dark,
    far from it lit; the plane's radiance follows."""
    import open3d as o3d

    env = _env(upper=(1.0, 1.0, 1.0))
    nf = SupportPlaneLight(env, FAR, R_FAR, [0.05, 0.05, 0.05], extent_m=0.3)
    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.1, 0.1).translate((-0.05, -0.05, 0.0))
    nf.with_object_shadow(np.asarray(box.vertices), np.asarray(box.triangles), step_m=0.01)
    f = nf._shadow_at(np.array([[0.0, 0.0], [0.28, 0.28], [5.0, 5.0]]))
    assert f[0] < 0.05 and f[1] > 0.5 and f[2] == 1.0
    L = nf.plane_radiance(np.array([[0.0, 0.0], [5.0, 5.0]]))
    assert L[0, 0] < 0.05 * 0.05 + 1e-6 and L[1, 0] == pytest.approx(0.05)


def test_bad_inputs_name_the_problem():
    with pytest.raises(AppFusionError, match=r"\(2, N, N, 3\)"):
        SupportPlaneLight(np.zeros((3, 4)), FAR, R_FAR, [0.05] * 3)
    with pytest.raises(AppFusionError, match="radius"):
        SupportPlaneLight(_env(), FAR, np.array([-1.0]), [0.05] * 3)
    with pytest.raises(AppFusionError, match="finite"):
        SupportPlaneLight(_env(), FAR, R_FAR, [np.nan, 0, 0])
    nf = SupportPlaneLight(_env(), FAR, R_FAR, [0.05] * 3)
    # points on or below the plane, grazing views, empty input: zeros, no NaN
    p = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.01], [0.0, 0.0, 0.05]])
    n = np.array([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]])
    wo = np.array([[0, 1.0, 0], [0, 1.0, 0], [0, 1.0, 0]])
    assert np.isfinite(nf.delta_S(p, n, wo, 0.1)).all() and np.isfinite(nf.delta_D(p, n)).all()
    assert nf.delta_S(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), 0.1).shape == (0, 3)


def _lobes_near_circles(m, seed):
    """Random points 2-15 cm above the plane, side-facing normals, cameras above: lobes that reach the
    plane and, for many, a circle."""
    rng = np.random.default_rng(seed)
    p = np.column_stack([rng.uniform(-0.1, 0.1, m), rng.uniform(-0.1, 0.1, m), rng.uniform(0.02, 0.15, m)])
    n = rng.normal(size=(m, 3))
    n[:, 2] = -np.abs(n[:, 2]) * 0.5
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    wo = n + rng.normal(size=(m, 3)) * 0.5
    wo[:, 2] = np.abs(wo[:, 2]) + 0.2
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    return p, n, wo, rng.choice([0.03, 0.08, 0.25], m)


def _textured_plane() -> SupportPlaneLight:
    """The plane of the fast-against-reference tests: circles near the lobes (one far off), the
    object's shadow on the plane, and a map that varies below the horizon."""
    env = _env()
    d = oc.sphere_directions(N)
    env = env * (1.0 + 0.5 * np.sin(7 * d[..., :1]) * np.cos(5 * d[..., 1:2])).astype(np.float32)
    centres = np.array([[0.12, 0.1, 0], [-0.15, 0.05, 0], [0.0, -0.14, 0], [0.3, 0.3, 0]], float)
    radii = np.array([0.025, 0.03, 0.02, 0.025])
    nf = SupportPlaneLight(env, centres, radii, [0.05, 0.06, 0.04], extent_m=0.35)
    nodes = np.arange(-0.35, 0.351, 0.01)
    nf.shadow = (nodes, 0.5 + 0.5 * np.cos(nodes[:, None] * 20) * np.sin(nodes[None, :] * 13))
    return nf


def test_fast_delta_S_matches_the_per_ray_reference_on_the_same_random_numbers():
    """The vectorised lobe estimator (closed-form weight, float32 rays, circle cells, four-texel map
    look-up) against the original per-ray implementation (sample_ward, ward, delta_radiance on every
    ray), on the same stratified patterns: circles near the lobes, the object's shadow on the plane,
    a map that varies below the horizon."""
    nf = _textured_plane()
    p, n, wo, al = _lobes_near_circles(3000, 1)
    for ns in (4, 16):
        ref = nf.delta_S(p, n, wo, al, n_samples=ns, seed=3, reference=True)
        got = nf.delta_S(p, n, wo, al, n_samples=ns, seed=3, circle_samples=0)
        assert np.abs(ref).max() > 0.05                                      # circles were hit
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-6)


def _disc_quadrature():
    """A point 10 cm above the plane, one white circle (r = 2 cm, 10 cm off) on dark paper, the same
    plane without the circle, and a dense quadrature of the disc (400 x 400 polar cells): positions
    ``x``, areas ``dA``, distances ``r`` and unit directions ``wi`` from the point."""
    env = _env()
    paper = np.array([0.08, 0.06, 0.04])
    cen, rad = np.array([0.1, 0.0, 0.0]), 0.02
    nfc = SupportPlaneLight(env, cen[None], np.array([rad]), paper, extent_m=1e4)
    nf0 = SupportPlaneLight(env, FAR, R_FAR, paper, extent_m=1e4)
    p = np.array([0.0, 0.0, 0.1])
    rr = (np.arange(400) + 0.5) / 400 * rad
    ph = (np.arange(400) + 0.5) / 400 * 2 * np.pi
    R_, P_ = np.meshgrid(rr, ph, indexing="ij")
    x = np.stack([cen[0] + R_ * np.cos(P_), cen[1] + R_ * np.sin(P_), np.zeros_like(R_)], -1).reshape(-1, 3)
    dA = (R_ * (rad / 400) * (2 * np.pi / 400)).reshape(-1)
    dv = x - p
    r = np.linalg.norm(dv, axis=1)
    return env, paper, cen, rad, nfc, nf0, p, x, dA, r, dv / r[:, None]


def _disc_excess(lobe, alpha, nrm, view, paper, p, dA, r, wi, S: int):
    """The circle's excess over the paper at point ``p`` for the lobe function ``lobe`` (brdf.ward or
    brdf.ggx) by the quadrature of :func:`_disc_quadrature`, and delta_S's arguments for S copies."""
    nrm = np.asarray(nrm) / np.linalg.norm(nrm)
    view = np.asarray(view) / np.linalg.norm(view)
    f = lobe(alpha, wi, np.broadcast_to(view, wi.shape), np.broadcast_to(nrm, wi.shape))
    want = (1.0 - paper) * np.sum(f * np.maximum(wi @ nrm, 0) * (p[2] / r) / r ** 2 * dA)
    return want, (np.tile(p, (S, 1)), np.tile(nrm, (S, 1)), np.tile(view, (S, 1)), alpha)


def test_circle_area_samples_keep_dS_unbiased_and_less_noisy():
    """Lobes that reflect a white circle, sharp to broad: dS with the circle minus dS without it is
    the circle's excess over the paper, int_disc (1 - paper) f cos_i cos_c / r^2 dA (dense polar
    quadrature of the disc). The default (4 lobe + 4 disc samples, power heuristic, for lobes broader
    than the disc; 16 lobe samples for the others) gets it without bias and with no more noise than
    the earlier 16 lobe samples everywhere (same seed: the sharp lobes draw the same numbers)."""
    from appfusion.brdf import ward

    env, paper, cen, rad, nfc, nf0, p, x, dA, r, wi = _disc_quadrature()
    S = 400
    for alpha, nrm, view in ((0.03, [1.0, 0, 0], [np.sqrt(0.5), 0, np.sqrt(0.5)]),     # lobe inside the disc
                             (0.08, [1.0, 0, 0], [np.sqrt(0.5), 0, np.sqrt(0.5)]),     # comparable
                             (0.25, [1.0, 0, 0], [np.sqrt(0.5), 0, np.sqrt(0.5)]),     # broad
                             (0.25, [1.0, 0, 0], [0.6, 0.3, 0.75]),                    # circle off the mirror ray
                             (0.12, [1.0, 0, -0.3], [0.8, -0.1, 0.6])):
        want, args = _disc_excess(ward, alpha, nrm, view, paper, p, dA, r, wi, S)
        # one call with S copies of the sample: S independent estimates
        new = nfc.delta_S(*args, n_samples=4, seed=1) - nf0.delta_S(*args, n_samples=4, seed=1)
        old = nfc.delta_S(*args, n_samples=4, seed=1, reference=True) - nf0.delta_S(*args, n_samples=4, seed=1,
                                                                                   reference=True)
        assert want[0] > 1e-3
        se = new.std(0) / np.sqrt(S)
        assert np.all(np.abs(new.mean(0) - want) < 4 * se + 1e-3 * want), (alpha, new.mean(0), want)
        assert np.all(np.abs(old.mean(0) - want) < 4 * old.std(0) / np.sqrt(S) + 1e-3 * want)
        assert np.all(new.std(0) <= 1.05 * old.std(0)), (alpha, new.std(0), old.std(0))


# -- the GGX rung: dS of a GGX lobe ---------------------------------------------------------------------

def _brute_S_lobe(env, n, alpha, wo, lobe):
    """``S = sum_t L_t f(w_t, w_o) (n.w_t)+ dw_t`` over every texel of the map (texel centres), (P, 3),
    with ``lobe(alpha, wi, wo, n)`` (world frame)."""
    d = oc.sphere_directions(env.shape[1]).reshape(-1, 3)
    Lw = np.asarray(env, np.float64).reshape(-1, 3) * oc.sphere_solid_angles(env.shape[1]).reshape(-1, 1)
    out = np.zeros((len(n), 3))
    for i in range(len(n)):
        f = lobe(alpha, d, np.broadcast_to(wo[i], d.shape), np.broadcast_to(n[i], d.shape))
        out[i] = (f * np.maximum(d @ n[i], 0.0)) @ Lw
    return out


def test_delta_S_of_a_ggx_lobe_matches_brute_force_including_its_tail():
    """As for Ward: with the plane as a uniform lower hemisphere of paper, dS = S(env with paper below)
    - S(env), here with the GGX lobe (brute force over all texels with appfusion.brdf.ggx, which the
    synthetic scanner's independent replay.synth.materials.ggx matches texel by texel). Also samples
    whose mirror ray is 25 degrees *above* the horizon: a Ward lobe of the same alpha does not reach the
    plane (dS = 0), GGX's long tail does, and delta_S must not cut it off."""
    from appfusion.brdf import ggx
    from replay.synth.materials import ggx as ggx_scanner

    env, _, env_p, nf = _paper_hemisphere()
    rng = np.random.default_rng(0)
    n, wo = _side_views(rng, 30)
    # the tail set: normals 40-60 degrees from vertical, views such that the mirror ray is 25 deg up
    k = 12
    az = rng.uniform(0, 2 * np.pi, k)
    tn = np.radians(rng.uniform(40, 60, k))
    nt = np.stack([np.sin(tn) * np.cos(az), np.sin(tn) * np.sin(az), np.cos(tn)], 1)
    el = np.radians(25.0)
    r = np.stack([np.cos(el) * np.cos(az + 0.3), np.cos(el) * np.sin(az + 0.3), np.full(k, np.sin(el))], 1)
    wt = 2 * np.sum(r * nt, 1, keepdims=True) * nt - r
    ok = (np.sum(wt * nt, 1) > 0.2) & (wt[:, 2] > 0.05)
    nt, wt = nt[ok], wt[ok]
    assert len(nt) >= 5
    d = oc.sphere_directions(N).reshape(-1, 3)
    np.testing.assert_allclose(ggx(0.2, d, np.broadcast_to(wo[0], d.shape), np.broadcast_to(n[0], d.shape)),
                               ggx_scanner(0.2, d, np.broadcast_to(wo[0], d.shape), np.broadcast_to(n[0], d.shape)),
                               rtol=1e-9, atol=1e-12)
    # the tail is a few per cent of the lobe's samples: more of them (MC noise ~1.5 % rms either way)
    for alpha, nn, ww, ns, seeds in ((0.08, n, wo, 256, 8), (0.3, n, wo, 256, 8), (0.08, nt, wt, 4096, 20)):
        p = np.tile([0.0, 0.0, 0.08], (len(nn), 1))
        want = _brute_S_lobe(env_p, nn, alpha, ww, ggx) - _brute_S_lobe(env, nn, alpha, ww, ggx)
        got = np.mean([nf.delta_S(p, nn, ww, alpha, n_samples=ns, seed=s, lobe="ggx") for s in range(seeds)], axis=0)
        scale = np.abs(want).max()
        assert scale > 1e-4
        np.testing.assert_allclose(got, want, atol=0.04 * scale + 1e-5)
        assert abs(np.mean(got - want)) < 0.01 * scale
        if nn is nt:
            # a Ward lobe of that alpha is cut off (and has next to nothing there); GGX's is not
            assert np.all(nf.delta_S(p, nn, ww, alpha, n_samples=16) == 0)
            assert np.all(np.abs(want).max(1) > 0.05 * scale)


def test_fast_ggx_delta_S_matches_the_per_ray_reference_and_ward_is_unchanged():
    """Mixed Ward and GGX samples: the vectorised GGX estimator against the per-ray reference
    (sample_ggx, ggx, delta_radiance on every ray) on the same random numbers; lobe=None, "ward" and
    "diffuse" give Ward's numbers bit for bit; unknown names are refused."""
    nf = _textured_plane()
    p, n, wo, al = _lobes_near_circles(2000, 1)
    lobe = np.where(np.arange(len(p)) % 3 == 0, "ward", "ggx")
    for ns in (4, 16):
        ref = nf.delta_S(p, n, wo, al, n_samples=ns, seed=3, reference=True, lobe=lobe)
        got = nf.delta_S(p, n, wo, al, n_samples=ns, seed=3, circle_samples=0, lobe=lobe)
        assert np.abs(ref[lobe == "ggx"]).max() > 0.05
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-6)
    base = nf.delta_S(p, n, wo, al, n_samples=4, seed=3)
    for lb in ("ward", "diffuse", ["ward"] * len(p)):
        assert np.array_equal(nf.delta_S(p, n, wo, al, n_samples=4, seed=3, lobe=lb), base)
    assert not np.allclose(nf.delta_S(p, n, wo, al, n_samples=4, seed=3, lobe="ggx"), base, atol=1e-3)
    with pytest.raises(AppFusionError, match="unknown specular lobe"):
        nf.delta_S(p, n, wo, al, lobe="phong")
    with pytest.raises(AppFusionError, match="one name per point"):
        nf.delta_S(p, n, wo, al, lobe=["ggx"] * 3)


def test_circle_area_samples_keep_ggx_dS_unbiased():
    """GGX lobes that reflect a white circle, sharp to broad: dS with the circle minus dS without it is
    int_disc (1 - paper) f_ggx cos_i cos_c / r^2 dA (dense polar quadrature of the disc), for the
    default MIS scheme (4 lobe + 4 disc samples) and for lobe samples alone (circle_samples=0)."""
    from appfusion.brdf import ggx

    env, paper, cen, rad, nfc, nf0, p, x, dA, r, wi = _disc_quadrature()
    S = 400
    for alpha, nrm, view in ((0.03, [1.0, 0, 0], [np.sqrt(0.5), 0, np.sqrt(0.5)]),
                             (0.12, [1.0, 0, 0], [np.sqrt(0.5), 0, np.sqrt(0.5)]),
                             (0.3, [1.0, 0, 0], [0.6, 0.3, 0.75]),
                             (0.12, [1.0, 0, -0.3], [0.8, -0.1, 0.6])):
        want, args = _disc_excess(ggx, alpha, nrm, view, paper, p, dA, r, wi, S)
        assert want[0] > 1e-3
        for kw in ({}, {"circle_samples": 0}):
            est = (nfc.delta_S(*args, n_samples=4, seed=1, lobe="ggx", **kw)
                   - nf0.delta_S(*args, n_samples=4, seed=1, lobe="ggx", **kw))
            se = est.std(0) / np.sqrt(S)
            assert np.all(np.abs(est.mean(0) - want) < 4 * se + 2e-3 * want), (alpha, kw, est.mean(0), want)
