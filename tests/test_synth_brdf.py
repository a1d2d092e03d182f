"""Synthetic scanner: its own reflectance lobes against closed forms and their sampling densities."""

from __future__ import annotations

import numpy as np
import pytest

from replay.synth import materials as M


def _dirs_on(n_theta: int, upper_only: bool = False):
    """Midpoint lat-long quadrature over the sphere (or the upper hemisphere): dirs, solid angles."""
    span = np.pi / 2 if upper_only else np.pi
    t0 = np.arange(n_theta) * span / n_theta
    t1 = t0 + span / n_theta
    tc = 0.5 * (t0 + t1)
    ph = (np.arange(2 * n_theta) + 0.5) * np.pi / n_theta
    T, P = np.meshgrid(tc, ph, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    dw = np.repeat((np.cos(t0) - np.cos(t1)) * np.pi / n_theta, 2 * n_theta)
    return d, dw


@pytest.mark.parametrize("alpha", [0.05, 0.1, 0.2, 0.4])
def test_ward_albedo_at_normal_incidence_matches_1d_integral(alpha):
    """The renderer's lobe estimator (importance sampling, stratified) integrates the Ward lobe to the
    albedo given by the 1-D Gauss-Kronrod integral of ward_albedo_normal."""
    known = M.ward_albedo_normal(alpha)
    k = 200
    rng = np.random.default_rng(0)
    i, j = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    u1 = (i.ravel() + rng.random(k * k)) / k
    u2 = (j.ravel() + rng.random(k * k)) / k
    n = np.broadcast_to([0.0, 0.0, 1.0], (k * k, 3))
    _, w = M.lobe_sample("ward", alpha, n, n, u1, u2)
    assert w.mean() == pytest.approx(known, rel=1e-3)
    # and an independent brute-force quadrature over the hemisphere (fine near the peak)
    d, dw = _dirs_on(1200, upper_only=True)
    f = M.ward(alpha, d, np.broadcast_to([0, 0, 1.0], d.shape), np.broadcast_to([0, 0, 1.0], d.shape))
    assert np.sum(f * d[:, 2] * dw) == pytest.approx(known, rel=2e-3)


def test_ward_albedo_tends_to_one_for_small_alpha():
    assert M.ward_albedo_normal(0.01) == pytest.approx(1.0, abs=5e-4)
    assert M.ward_albedo_normal(0.05) == pytest.approx(1.0, abs=1e-2)
    assert M.ward_albedo_normal(0.4) < 0.8  # rough lobes lose energy below the horizon


@pytest.mark.parametrize("lobe,alpha", [("ward", 0.08), ("ward", 0.3), ("ggx", 0.1), ("ggx", 0.35)])
@pytest.mark.parametrize("theta_o", [0.0, 0.7, 1.3])
def test_sampling_density_is_normalised_and_matches_weights(lobe, alpha, theta_o):
    wo = np.array([np.sin(theta_o), 0.0, np.cos(theta_o)])
    nz = np.array([0.0, 0.0, 1.0])
    # the density integrates to 1 over the sphere, less the mass of Ward half vectors facing away from
    # w_o (whose mirror directions the density does not cover; GGX visible normals never do that)
    d, dw = _dirs_on(900)
    pdf = M.lobe_pdf(lobe, alpha, d, np.broadcast_to(wo, d.shape), np.broadcast_to(nz, d.shape))
    total = np.sum(pdf * dw)
    rng = np.random.default_rng(1)
    m = 200000
    wi, _ = M.lobe_sample(lobe, alpha, np.broadcast_to(wo, (m, 3)), np.broadcast_to(nz, (m, 3)), rng.random(m),
                          rng.random(m))
    lost = np.mean(M.lobe_pdf(lobe, alpha, wi, np.broadcast_to(wo, (m, 3)), np.broadcast_to(nz, (m, 3))) == 0)
    if lobe == "ggx":
        assert lost == 0.0
    assert total == pytest.approx(1.0 - lost, abs=0.01)
    # weight = f cos / pdf for the samples drawn
    rng = np.random.default_rng(2)
    m = 5000
    wi, w = M.lobe_sample(lobe, alpha, np.broadcast_to(wo, (m, 3)), np.broadcast_to(nz, (m, 3)), rng.random(m), rng.random(m))
    f = M.lobe_eval(lobe, alpha, wi, np.broadcast_to(wo, (m, 3)), np.broadcast_to(nz, (m, 3)))
    p = M.lobe_pdf(lobe, alpha, wi, np.broadcast_to(wo, (m, 3)), np.broadcast_to(nz, (m, 3)))
    ok = w > 0
    np.testing.assert_allclose(w[ok], f[ok] * wi[ok, 2] / p[ok], rtol=1e-9)


def test_ggx_distribution_normalised():
    d, dw = _dirs_on(1000, upper_only=True)
    for a in (0.05, 0.2, 0.6):
        assert np.sum(M.ggx_d(a, d[:, 2]) * d[:, 2] * dw) == pytest.approx(1.0, rel=2e-3)


def test_albedo_table_matches_quadrature():
    d, dw = _dirs_on(800, upper_only=True)
    nz = np.broadcast_to([0.0, 0.0, 1.0], d.shape)
    for lobe, a in (("ward", 0.1), ("ggx", 0.2)):
        for c in (0.2, 0.6, 1.0):
            wo = np.array([np.sqrt(1 - c * c), 0.0, c])
            ref = np.sum(M.lobe_eval(lobe, a, d, np.broadcast_to(wo, d.shape), nz) * d[:, 2] * dw)
            assert M.albedo_at(lobe, a, np.array([c]))[0] == pytest.approx(ref, rel=3e-3)


def test_material_validation():
    from appfusion.errors import AppFusionError

    with pytest.raises(AppFusionError, match="lobe"):
        M.Material("x", (0.1, 0.1, 0.1), 0.1, "phong")
    with pytest.raises(AppFusionError, match="alpha"):
        M.Material("x", (0.1, 0.1, 0.1), 0.0, "ward")
