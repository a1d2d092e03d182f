"""Ward roughness from an HBSAB (paper §5.1): the paper's simulation protocol and the fit's behaviour."""

from __future__ import annotations

import numpy as np
import pytest

from appfusion.errors import EstimationError
from appfusion.hbsab import CH_M, CH_SAT, CH_W, CH_WG, N_MOMENTS, HBSAB
from appfusion.ir_synth import _ward, protocol_alpha_errors, protocol_pairs
from appfusion.ward_fit import ALPHA_MAX, ALPHA_MIN, WardFitter, fit_ward

Z = np.array([0.0, 0.0, 1.0])
ALPHAS = (0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.75)


@pytest.fixture(scope="module")
def pairs():
    """The paper's §5.1 simulation: 40 cm, emitter 7.5 cm off axis, random normals (1M pairs)."""
    return protocol_pairs(1_000_000, seed=11)


def test_protocol_pairs_geometry(pairs):
    wi, wo = pairs
    assert len(wi) > 900_000
    ang = np.degrees(np.arccos(np.clip(np.sum(wi * wo, 1), -1, 1)))
    assert 10.0 < ang.max() <= 10.75              # 2 atan(0.5 * 7.5 / 40) = 10.7 degrees (paper)
    assert np.all(wi[:, 2] > np.cos(np.radians(80))) and np.all(wo[:, 2] > np.cos(np.radians(80)))


def test_paper_protocol_alpha_error_below_0p1_percent(pairs):
    """Paper §5.1: alpha 0.05 .. 0.75, max relative error 0.26 % there; here <= 0.1 %."""
    err = protocol_alpha_errors(ALPHAS, pairs=pairs)
    worst = max(abs(e) for e in err.values())
    assert worst <= 1e-3, err
    # with a diffuse part as well (the fit removes it)
    err_d = protocol_alpha_errors((0.05, 0.3, 0.75), pairs=pairs, rho_d=0.4, rho_s=0.5)
    assert max(abs(e) for e in err_d.values()) <= 1e-3, err_d


def test_texel_centre_model_would_miss_the_goal(pairs):
    """The bias the moment channels remove: without them (uniform density in each texel) and without
    the geometry factor, alpha = 0.05 is off by far more than 0.1 % (so the protocol test can fail)."""
    wi, wo = pairs
    hb = HBSAB(1, 32)
    hb.update(0, wi, wo, _ward(0.05, wi, wo, Z))
    good = fit_ward(hb).alpha / 0.05 - 1
    hb.data[CH_M:CH_M + N_MOMENTS] = 0.0
    hb.data[CH_WG] = hb.data[CH_W]
    bad = fit_ward(hb).alpha / 0.05 - 1
    assert abs(good) < 1e-3 and abs(bad) > 2e-3, (good, bad)


def test_noisy_fit_alpha_within_its_uncertainty(pairs):
    """Multiplicative emitter noise (shifted Gamma, CV 0.45) on diffuse + specular samples."""
    wi, wo = pairs
    rng = np.random.default_rng(4)
    k, r = 1.6, 3.4 / 2.8
    mult = (rng.gamma(k, 1.0, len(wi)) + r) / (k + r)
    for alpha in (0.1, 0.4):
        f = 0.5 / np.pi + 0.3 * _ward(alpha, wi, wo, Z)
        hb = HBSAB(1, 32)
        hb.update(0, wi, wo, f * mult)
        res = fit_ward(hb)
        assert abs(res.alpha - alpha) < max(4 * res.alpha_sigma, 0.002), (alpha, res)
        assert abs(res.alpha - alpha) / alpha < 0.03
        assert 0 < res.alpha_sigma < 0.05 * alpha
        assert abs(res.rho_d - 0.5) < 0.02 and abs(res.rho_s - 0.3) < 0.03
        assert 0.3 < res.reduced_chi2 < 3.0
        # the paper's minimum-diffuse variant is biased by the noise: alpha is pulled up
        res_min = fit_ward(hb, diffuse="min")
        assert res_min.alpha > res.alpha


def test_warm_start_refits_as_data_arrive(pairs):
    wi, wo = pairs
    fitter = WardFitter()
    hb = HBSAB(1, 32)
    f = 0.2 / np.pi + 0.5 * _ward(0.25, wi, wo, Z)
    chunks = np.array_split(np.arange(len(wi)), 4)
    nfev = []
    for c in chunks:
        hb.update(0, wi[c], wo[c], f[c])
        res = fitter.fit(hb)
        nfev.append(res.nfev)
    assert abs(res.alpha / 0.25 - 1) < 1e-3
    assert fitter.last is res
    assert max(nfev[1:]) <= 10


def test_warm_start_never_beats_a_better_grid_start(monkeypatch):
    """A warm start caught in the previous lobe's basin (the demo bottle: alpha 0.353 kept from an
    earlier fit where the grid start gives 0.071) loses to the grid start when it fits worse, and
    wins when it fits better."""
    import appfusion.ward_fit as W

    def fake(hb, min_weight, diffuse, x0=None, **kw):
        trapped = x0 is not None and x0[0] > 0.3
        chi2 = {None: 2.0, True: 9.0, False: 1.5}[None if x0 is None else trapped]
        alpha = 0.353 if trapped else 0.071
        return W.WardFit(alpha, 0.01, 0.05, 0.01, 0.1, 0.3, 100, chi2, False)

    monkeypatch.setattr(W, "fit_ward", fake)
    fitter = WardFitter()
    fitter.last = W.WardFit(0.35, 0.01, 0.05, 0.01, 0.1, 0.3, 100, 1.0, False)
    assert fitter.fit(None).alpha == 0.071 and fitter.last.reduced_chi2 == 2.0     # grid start wins
    assert fitter.fit(None).reduced_chi2 == 1.5                                     # warm start wins


def test_alpha_at_its_bounds_is_flagged(pairs):
    wi, wo = pairs
    sel = slice(0, 200_000)
    sharp = HBSAB(1, 32)
    sharp.update(0, wi[sel], wo[sel], 0.1 + _ward(0.004, wi[sel], wo[sel], Z))
    r = fit_ward(sharp)
    assert r.at_bound and r.alpha == pytest.approx(ALPHA_MIN) and np.isfinite(r.alpha_sigma)
    broad = HBSAB(1, 32)
    broad.update(0, wi[sel], wo[sel], 0.05 + _ward(3.0, wi[sel], wo[sel], Z))
    r = fit_ward(broad)
    assert np.isfinite(r.alpha) and ALPHA_MIN <= r.alpha <= ALPHA_MAX and np.isfinite(r.alpha_sigma)
    assert r.at_bound or r.alpha > 0.8


def test_saturated_texels_are_left_out(pairs):
    wi, wo = pairs
    sel = slice(0, 300_000)
    f = 0.1 + 0.3 * _ward(0.1, wi[sel], wo[sel], Z)
    clip = 2.0                                       # the peak (~2.4) is clipped
    hb = HBSAB(1, 32)
    hb.update(0, wi[sel], wo[sel], np.minimum(f, clip), saturated=f >= clip)
    biased = fit_ward(hb, max_saturated=1.0)          # uses the clipped texels
    hb2 = hb
    assert hb2.data[CH_SAT].sum() > 0
    ok = fit_ward(hb2)
    assert ok.n_saturated > 0
    assert abs(ok.alpha / 0.1 - 1) < 0.003 < abs(biased.alpha / 0.1 - 1)


def _emitter_gains(rng: np.random.Generator, m: int):
    """The Kinect's shifted-Gamma emitter noise (k, theta, shift) and m per-sample gains of mean 1."""
    k, theta, shift = 1.6, 2.8, 3.4
    return (k, theta, shift), (rng.gamma(k, theta, m) + shift) / (k * theta + shift)


def test_clipped_highlight_with_emitter_noise_is_modelled_not_dropped(pairs):
    """A sharp lobe whose peak the sensor clips heavily, under the Kinect's shifted-Gamma emitter
    noise (what the synthetic scan shows: 99 % of the samples within 3 degrees of the axis clipped).
    Dropping the clipped texels lets a far sharper, far higher lobe fit the flanks; the censored
    texel model (emitter distribution known) recovers alpha and rho_s."""
    from appfusion.ward_fit import censored_mean

    wi, wo = pairs
    rng = np.random.default_rng(8)
    (k, theta, shift), Zf = _emitter_gains(rng, len(wi))
    alpha, rho_s, d = 0.06, 0.12, 0.5 / np.pi
    f = (d + rho_s * _ward(alpha, wi, wo, Z)) * Zf
    clip = 3.0 * d                                     # peak ~ 17 d: clipped far down its flanks
    hb = HBSAB(1, 32)
    hb.update(0, wi, wo, np.minimum(f, clip), saturated=f >= clip)
    dropped = fit_ward(hb)
    modelled = fit_ward(hb, emitter=(k, theta, shift))
    assert abs(modelled.alpha / alpha - 1) < 0.05, modelled
    assert abs(modelled.rho_s / rho_s - 1) < 0.10, modelled
    assert abs(dropped.alpha / alpha - 1) > 2 * abs(modelled.alpha / alpha - 1), (dropped, modelled)
    # the censored mean: below both mu and c, -> mu far below the clip, -> c far above it
    mu = np.array([0.0, 0.01, 1.0, 100.0])
    cm = censored_mean(mu, 1.0, (k, theta, shift))
    assert np.all(cm <= np.minimum(mu, 1.0) + 1e-12) and cm[1] == pytest.approx(0.01, rel=1e-6)
    assert cm[3] == pytest.approx(1.0, rel=1e-3) and np.isfinite(cm).all()
    assert np.allclose(censored_mean(mu, 1.0, "flat"), np.minimum(mu, 1.0))


def test_pattern_divided_samples_fit_unclipped_texels_and_bound_clipped_ones(pairs):
    """The emitter's pattern divided out (calibration.ir_pattern): an unclipped sample is the BRDF
    (times 2 % sensor noise), a clipped one is left out of its texel's mean and only counted. The
    texels' unclipped means are fitted as they are; texels clipped throughout are lower bounds."""
    wi, wo = pairs
    rng = np.random.default_rng(9)
    (k, theta, shift), Zf = _emitter_gains(rng, len(wi))
    alpha, rho_s, d = 0.06, 0.12, 0.5 / np.pi
    f = d + rho_s * _ward(alpha, wi, wo, Z)
    raw = f * Zf                                       # what the sensor sees, before clipping
    for clip in (3.0 * d, 0.6 * d * 17):               # heavily clipped; clipped only near the peak
        sat = raw >= clip
        value = np.minimum(raw, clip) / Zf * rng.normal(1.0, 0.02, len(wi))
        hb = HBSAB(1, 32)
        w = (wo[:, 2] * ~sat)                          # clipped samples: weight 0 in the means ...
        hb.update(0, wi, wo, value, weight=w)
        hs = HBSAB(1, 32)
        hs.update(0, wi[sat], wo[sat], value[sat], weight=wo[sat, 2])
        hb.data[CH_SAT] += hs.data[CH_W]               # ... and counted in WSAT
        c_div = float(np.mean(value[sat]))
        fit = fit_ward(hb, emitter=("pattern", k, theta, shift), clip=c_div)
        assert abs(fit.alpha / alpha - 1) < 0.01, (clip, fit)
        assert abs(fit.rho_s / rho_s - 1) < 0.02, (clip, fit)
        assert np.isfinite(fit.alpha_sigma) and not fit.at_bound
    # a peak clipped throughout (every sample of the central texels): those texels are lower bounds;
    # met by the right lobe, and a bound far above it pulls the peak up (the residual is live)
    sat = raw >= 1.05 * d
    assert np.mean(sat[_ward(alpha, wi, wo, Z) > 5]) == 1.0
    value = np.minimum(raw, 1.05 * d) / Zf
    hb = HBSAB(1, 32)
    hb.update(0, wi, wo, value, weight=wo[:, 2] * ~sat)
    hs = HBSAB(1, 32)
    hs.update(0, wi[sat], wo[sat], value[sat], weight=wo[sat, 2])
    hb.data[CH_SAT] += hs.data[CH_W]
    c_div = float(np.mean(value[sat]))
    bounded = fit_ward(hb, emitter=("pattern", k, theta, shift), clip=c_div)
    assert bounded.n_saturated > 0
    # 2 %: texels mostly clipped count mainly from below (PATTERN_ONE_SIDED_FRAC); on these exact data
    # that costs ~1 % (0.0607 against 0.0601), on scans with normal errors it removes +2-9 %
    assert abs(bounded.alpha / alpha - 1) < 0.02 and abs(bounded.rho_s / rho_s - 1) < 0.03, bounded
    forced = fit_ward(hb, emitter=("pattern", k, theta, shift), clip=30 * c_div)
    assert forced.rho_s / forced.alpha ** 2 > 1.5 * bounded.rho_s / bounded.alpha ** 2, (forced, bounded)


def test_empty_or_degenerate_buffers_raise_clearly():
    with pytest.raises(EstimationError, match="texels have weight"):
        fit_ward(HBSAB(1, 16))
    hb = HBSAB(1, 16)
    h = np.array([[0.0, 0.0, 1.0]] * 10)
    hb.update(0, h, h, np.zeros(10))
    with pytest.raises(EstimationError):
        fit_ward(hb, min_weight=0.5)
    with pytest.raises(EstimationError, match="diffuse"):
        fit_ward(hb, diffuse="max")


# -- the GGX rung (module docstring of appfusion.ward_fit, "GGX rung") --------------------------------

def _noisy_hbsab(pairs, kind, alpha, rho_s, rho_d=0.5, seed=4):
    """An HBSAB of ``rho_d / pi + rho_s f(alpha)`` (``f`` the Ward or GGX lobe of the true directions,
    not the retro-reflection one) under the Kinect's multiplicative emitter noise (shifted Gamma, CV 0.45)."""
    from appfusion.brdf import ggx

    wi, wo = pairs
    rng = np.random.default_rng(seed)
    k, r = 1.6, 3.4 / 2.8
    mult = (rng.gamma(k, 1.0, len(wi)) + r) / (k + r)
    lobe = ggx(alpha, wi, wo, Z) if kind == "ggx" else _ward(alpha, wi, wo, Z)
    hb = HBSAB(1, 32)
    hb.update(0, wi, wo, (rho_d / np.pi + rho_s * lobe) * mult)
    return hb


def test_ggx_texel_lobe_is_the_engines_retro_lobe_with_its_derivative():
    """GGX at the quadrature nodes is :func:`appfusion.brdf.ggx_retro`; both lobes' analytic alpha
    derivatives agree with central differences (with and without moments)."""
    from appfusion.brdf import ggx_retro, ward_retro
    from appfusion.ward_fit import _quadrature, texel_lobe, texel_nodes

    n, texels = 32, np.arange(0, 32 * 32, 7)
    rng = np.random.default_rng(1)
    moments = rng.uniform(-0.2, 0.2, (N_MOMENTS, len(texels)))
    _, ch, _ = _quadrature(n, 6)
    for alpha in (0.03, 0.15, 0.6):
        f, w = texel_nodes(alpha, n, texels, moments, lobe="ggx")
        assert np.allclose(f, ggx_retro(alpha, ch[texels]), rtol=1e-12, atol=0)
        assert np.allclose(texel_nodes(alpha, n, texels, moments)[0], ward_retro(alpha, ch[texels]), rtol=1e-12, atol=0)
        assert np.allclose(np.sum(f * w, axis=1), texel_lobe(alpha, n, texels, moments, q=6, lobe="ggx"), rtol=1e-12)
        for lobe in ("ward", "ggx"):
            for m in (np.zeros_like(moments), moments):
                val, der = texel_lobe(alpha, n, texels, m, derivative=True, lobe=lobe)
                h = 1e-6 * alpha
                hi, lo = (texel_lobe(alpha + s * h, n, texels, m, lobe=lobe) for s in (1, -1))
                fd = (hi - lo) / (2 * h)
                assert np.allclose(val, texel_lobe(alpha, n, texels, m, lobe=lobe))
                assert np.allclose(der, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max()), (lobe, alpha)
    with pytest.raises(EstimationError, match="unknown lobe"):
        fit_ward(HBSAB(1, 16), lobe="phong")


@pytest.mark.parametrize("kind, alpha, rho_s", [("ggx", 0.15, 0.3), ("ggx", 0.05, 0.3), ("ggx", 0.4, 0.3),
                                                ("ggx", 0.15, 0.03), ("ward", 0.1, 0.3), ("ward", 0.4, 0.3),
                                                ("ward", 0.06, 0.15), ("ward", 0.35, 0.03)])
def test_lobe_choice_and_ggx_alpha_on_noisy_synthetic_buffers(pairs, kind, alpha, rho_s):
    """The rule keeps Ward on Ward data (the demo's two materials, a weak broad lobe included) and takes
    GGX on GGX data (the ggx-sphere's alpha 0.15, a weak lobe too); the GGX fit recovers alpha and
    rho_s. Measured: GGX alpha 0.1498 / 0.0501 / 0.3978 / 0.1499 for 0.15 / 0.05 / 0.4 / 0.15 (weak),
    chi-square gains 0.36-0.96; on Ward data the GGX fit's chi-square is 7-4300 % higher."""
    from appfusion.ward_fit import choose_lobe

    hb = _noisy_hbsab(pairs, kind, alpha, rho_s)
    w, g = fit_ward(hb), fit_ward(hb, lobe="ggx")
    assert (w.lobe, g.lobe) == ("ward", "ggx") and w.n_texels == g.n_texels
    for f in (w, g):
        dof = f.n_texels - 3
        assert f.chi2 == pytest.approx(f.reduced_chi2 * dof, rel=1e-9)
    truth, other = (g, w) if kind == "ggx" else (w, g)
    assert abs(truth.alpha / alpha - 1) < 0.02, truth
    assert abs(truth.rho_s / rho_s - 1) < 0.03, truth
    assert abs(truth.alpha - alpha) < max(4 * truth.alpha_sigma, 0.003)
    assert truth.chi2 < other.chi2
    assert choose_lobe(w, g) is truth


def test_ggx_fits_clipped_highlights_censored_and_pattern_divided(pairs):
    """Every path of the fit takes the GGX lobe: a GGX highlight (alpha 0.15, peak 7.7x the diffuse
    level) clipped at 3x the diffuse level under the shifted-Gamma emitter noise, modelled as censored
    means (emitter known) and with the pattern divided out (clipped samples out of the means)."""
    from appfusion.brdf import ggx
    from appfusion.ward_fit import choose_lobe

    wi, wo = pairs
    rng = np.random.default_rng(9)
    (k, theta, shift), Zf = _emitter_gains(rng, len(wi))
    alpha, rho_s, d = 0.15, 0.3, 0.5 / np.pi
    raw = (d + rho_s * ggx(alpha, wi, wo, Z)) * Zf
    clip = 3.0 * d
    sat = raw >= clip
    hb = HBSAB(1, 32)
    hb.update(0, wi, wo, np.minimum(raw, clip), saturated=sat)
    w = fit_ward(hb, emitter=(k, theta, shift))
    g = fit_ward(hb, emitter=(k, theta, shift), lobe="ggx")
    assert g.n_saturated > 0 and abs(g.alpha / alpha - 1) < 0.02 and abs(g.rho_s / rho_s - 1) < 0.03, g
    assert abs(w.alpha / alpha - 1) > 0.1                   # Ward: 0.181 (measured)
    assert choose_lobe(w, g) is g
    value = np.minimum(raw, clip) / Zf * rng.normal(1.0, 0.02, len(wi))
    hp = HBSAB(1, 32)
    hp.update(0, wi, wo, value, weight=wo[:, 2] * ~sat)
    hs = HBSAB(1, 32)
    hs.update(0, wi[sat], wo[sat], value[sat], weight=wo[sat, 2])
    hp.data[CH_SAT] += hs.data[CH_W]
    em, c = ("pattern", k, theta, shift), float(np.mean(value[sat]))
    w, g = fit_ward(hp, emitter=em, clip=c), fit_ward(hp, emitter=em, clip=c, lobe="ggx")
    assert abs(g.alpha / alpha - 1) < 0.01 and abs(g.rho_s / rho_s - 1) < 0.02, g
    assert choose_lobe(w, g) is g


def test_choose_lobe_margins():
    """GGX only with both margins met (relative gain and overdispersion-scaled z), not at a bound;
    a missing fit yields the other."""
    from appfusion.ward_fit import LOBE_MIN_GAIN, LOBE_MIN_Z, WardFit, choose_lobe

    def fit(lobe, chi2, n=1000, at_bound=False):
        return WardFit(0.1, 0.01, 0.1, 0.01, 0.1, 0.3, n, chi2 / (n - 3), at_bound, lobe=lobe, chi2=chi2)

    w = fit("ward", 50_000.0)                                          # reduced chi2 ~50
    assert choose_lobe(w, fit("ggx", 25_000.0)).lobe == "ggx"          # ggx-sphere-like: gain 0.5, z ~1000
    assert choose_lobe(w, fit("ggx", 50_000.0 * (1 - 0.9 * LOBE_MIN_GAIN))).lobe == "ward"   # gain too small
    small = fit("ward", 1000.0)                                        # reduced chi2 ~1: z = dchi2
    assert choose_lobe(small, fit("ggx", 1000.0 - 0.9 * LOBE_MIN_Z)).lobe == "ward"      # gain 2 %, z < min
    assert choose_lobe(small, fit("ggx", 1000.0 - 1.1 * max(LOBE_MIN_Z, LOBE_MIN_GAIN * 1000))).lobe == "ggx"
    assert choose_lobe(w, fit("ggx", 100.0, at_bound=True)).lobe == "ward"
    assert choose_lobe(w, fit("ggx", 100.0, n=999)).lobe == "ward"      # not the same texels
    assert choose_lobe(w, None) is w and choose_lobe(None, w) is w
    with pytest.raises(EstimationError):
        choose_lobe(fit("ggx", 1.0), fit("ward", 1.0))
    j = fit("ggx", 10.0).to_json()
    assert j["lobe"] == "ggx" and j["chi2"] == 10.0 and j["n_texels"] == 1000


def test_fitter_fits_each_lobe_and_returns_the_chosen_one(pairs):
    """``WardFitter(lobes=("ward", "ggx"))``: both lobes refitted as data arrive (each warm-started from
    its own last fit), the chosen one returned; the default fits Ward only."""
    wi, wo = pairs
    from appfusion.brdf import ggx

    f = 0.2 / np.pi + 0.5 * ggx(0.2, wi, wo, Z)
    both, ward_only = WardFitter(lobes=("ward", "ggx")), WardFitter()
    hb = HBSAB(1, 32)
    for c in np.array_split(np.arange(len(wi)), 3):
        hb.update(0, wi[c], wo[c], f[c])
        res = both.fit(hb)
        assert res.lobe == "ggx" and both.last is res and set(both.fits) == {"ward", "ggx"}
        assert both.fits["ggx"] is res
        assert ward_only.fit(hb).lobe == "ward" and set(ward_only.fits) == {"ward"}
        assert ward_only.last.to_json() == both.fits["ward"].to_json()
    assert abs(res.alpha / 0.2 - 1) < 1e-3 and res.nfev <= 10          # warm start of the GGX lobe
    hw = HBSAB(1, 32)
    hw.update(0, wi, wo, 0.2 / np.pi + 0.5 * _ward(0.2, wi, wo, Z))
    assert WardFitter(lobes=("ward", "ggx")).fit(hw).lobe == "ward"
    assert WardFitter(lobes=("ggx",)).fit(hw).lobe == "ggx"              # one lobe: no choice
    for bad in (("ggx", "ggx"), ("ward", "ward"), ("phong",), ()):
        with pytest.raises(EstimationError):
            WardFitter(lobes=bad)


def test_brdf_cut_clusters_may_be_ggx(pairs):
    """``BRDFCut(lobes=("ward", "ggx"))``: the cluster's fit is GGX on a GGX surface and says so; the
    default cut keeps Ward (unchanged behaviour)."""
    from appfusion.brdf import ggx
    from appfusion.brdf_cut import BRDFCut
    from appfusion.ir_synth import sphere_points

    wi, wo = pairs
    P, N = sphere_points(512)
    rng = np.random.default_rng(2)
    pidx = rng.integers(0, len(P), len(wi))
    k, r = 1.6, 3.4 / 2.8
    v = (0.5 / np.pi + 0.3 * ggx(0.15, wi, wo, Z)) * (rng.gamma(k, 1.0, len(wi)) + r) / (k + r)
    out = {}
    for lobes in (("ward",), ("ward", "ggx")):
        cut = BRDFCut(P, N, min_leaf=64, lobes=lobes)
        cut.add_samples(pidx, wi, wo, v)
        (c,) = cut.result(k=1).clusters
        out[lobes] = c
    cw, cg = out[("ward",)], out[("ward", "ggx")]
    assert cw.fit.lobe == "ward" and set(cw.fits) == {"ward"}
    assert cg.fit.lobe == "ggx" and set(cg.fits) == {"ward", "ggx"} and cg.fits["ward"].to_json() == cw.fit.to_json()
    assert abs(cg.alpha / 0.15 - 1) < 0.02
    with pytest.raises(EstimationError):
        BRDFCut(P, N, min_leaf=64, lobes=("phong",))
