"""Synthetic scanner: the RGB renderer against closed forms, and against its brute-force reference."""

from __future__ import annotations

import numpy as np
import pytest

from appfusion.frame import srgb_to_linear
from replay.synth import camera as C
from replay.synth import envmaps
from replay.synth import materials as M
from replay.synth.objects import custom_sphere
from replay.synth.render import (KIND_BALL, KIND_OBJECT, KIND_PLANE, MirrorBall, Quality, Scene, SupportPlane,
                                 shade_simple)
from replay.synth.scanner import camera_rays, render_radiance
from replay.synth.sensors import RGBModel

LENV = np.array([1.0, 0.8, 0.6])


def _look(target, dist=0.6, elev=30.0, az=40.0):
    e, a = np.radians(elev), np.radians(az)
    t = np.asarray(target, dtype=float)
    return C.look_at(t + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]), t)


def test_lambertian_sphere_under_constant_environment_has_radiance_rho_times_L():
    """No plane, nothing occludes: every pixel of a Lambertian sphere reads rho_d * L (within 0.5%)."""
    rho = np.array([0.5, 0.3, 0.7])
    obj = custom_sphere(0.07, (0, 0, 0.3), rho, M.Material("lambert", (0.0, 0.0, 0.0), 0.1), level=3)
    sc = Scene(envmaps.constant(LENV), obj=obj, quality=Quality.preset("test"))
    L, kind = render_radiance(sc, _look((0, 0, 0.3)), C.rgb_intrinsics(160, 120), np.random.default_rng(0))
    m = kind == KIND_OBJECT
    assert m.sum() > 500
    rel = L[m] / (rho * LENV) - 1
    assert np.abs(rel).max() < 0.005
    # the background is the environment itself
    assert np.allclose(L[kind == 0], LENV, rtol=1e-3)


def test_white_plane_under_constant_environment_reads_back_its_albedo():
    """A white Lambertian plane lit by a constant sky has radiance rho * L; through the camera model
    (no noise, unit gains), decoding the sRGB pixels gives the albedo back to 8-bit precision."""
    plane = SupportPlane(albedo=0.8, marker_albedo=0.8, ir_albedo=0.8, marker_ir_albedo=0.8)
    sc = Scene(envmaps.constant(LENV), plane=plane, quality=Quality.preset("test"))
    L, kind = render_radiance(sc, _look((0, 0, 0), 0.8, 50.0), C.rgb_intrinsics(160, 120), np.random.default_rng(0))
    m = kind == KIND_PLANE
    assert m.sum() > 5000
    assert np.abs(L[m] / (0.8 * LENV) - 1).max() < 0.003
    cam = RGBModel(read_sigma=0.0, full_well=np.inf)
    img = cam.capture(L, exposure=0.9, gains=np.ones(3), rng=np.random.default_rng(0))
    albedo = srgb_to_linear(img)[m] / (0.9 * LENV)
    assert np.abs(albedo - 0.8).max() < 0.8 * 0.012  # one 8-bit sRGB step near 0.7 is ~1% in linear


def test_specular_white_furnace_gives_the_ward_albedo():
    """rho_d = 0, rho_s = 1, constant environment, convex and unoccluded: the radiance at the pixels seen
    head-on is the Ward albedo at normal incidence (the 1-D closed form), via plain lobe sampling."""
    alpha = 0.1
    obj = custom_sphere(0.07, (0, 0, 0.3), (0.0, 0.0, 0.0), M.Material("chrome-ish", (1.0, 1.0, 1.0), alpha), level=4)
    q = Quality(q_up=12, q_down=12, lobe_pilot=256, lobe_samples=256, control_variate=False)
    sc = Scene(envmaps.constant(1.0), obj=obj, quality=q)
    pose = _look((0, 0, 0.3))
    L, kind = render_radiance(sc, pose, C.rgb_intrinsics(320, 240), np.random.default_rng(3))
    o, d, _ = camera_rays(pose, C.rgb_intrinsics(320, 240))
    hits = sc.intersect(np.ascontiguousarray(o), d)
    co = -np.einsum("ij,ij->i", hits.normal, d).reshape(kind.shape)
    head_on = (kind == KIND_OBJECT) & (co > 0.995)
    assert head_on.sum() >= 10
    assert L[head_on].mean() == pytest.approx(M.ward_albedo_normal(alpha), rel=4e-3)
    # every pixel: the directional albedo at its view angle (no occlusion on a convex sphere)
    m = (kind == KIND_OBJECT) & (co > 0.2)
    A = M.albedo_at("ward", alpha, co[m])
    assert np.mean(L[m][:, 0] / A) == pytest.approx(1.0, abs=2e-3)


def test_mirror_ball_reflects_the_environment():
    ball = MirrorBall(centre_m=(0.0, 0.0, 0.3), radius_m=0.035, reflectance=0.95)
    sc = Scene(envmaps.constant(LENV), ball=ball, quality=Quality.preset("test"))
    L, kind = render_radiance(sc, _look((0, 0, 0.3), 0.4), C.rgb_intrinsics(160, 120), np.random.default_rng(0))
    from scipy.ndimage import binary_erosion

    inner = binary_erosion(kind == KIND_BALL, iterations=2)
    assert inner.sum() > 100
    np.testing.assert_allclose(L[inner], np.broadcast_to(0.95 * LENV, L[inner].shape), rtol=1e-6)
    # office: a ray that hits the ball sees 0.95 x the environment in the mirror direction
    office = envmaps.office()
    sc = Scene(office, ball=ball, quality=Quality.preset("test"))
    o = np.array([[0.3, 0.2, 0.5]])
    d = np.array(ball.centre_m) + [0.005, -0.01, 0.012] - o
    d /= np.linalg.norm(d)
    h = sc.intersect(o, d)
    assert h.kind[0] == KIND_BALL
    r = M.reflect(-d, h.normal)
    want = 0.95 * (office.background(r) + office.emitter_radiance(r))
    np.testing.assert_allclose(shade_simple(sc, o, d, h), want, rtol=1e-9)


def test_plane_irradiance_sees_the_object_shadow_and_the_sky():
    """Far from any occluder the plane's irradiance is the unoccluded integral of the environment's upper
    hemisphere (office: quadrature of the analytic map); under the object it drops."""
    from replay.synth.objects import build_object

    sc = Scene(envmaps.office(), obj=build_object("sphere", "test"), plane=SupportPlane(), quality=Quality.preset("test"))
    lt = sc.ensure_lighting()
    d, dw = envmaps.latlong_cells(96)
    up = d[:, 2] > 0
    E_bg = (sc.env.background_exact(d[up]) * (d[up, 2] * dw[up])[:, None]).sum(axis=0)
    ed, edw, eL, _ = sc.env.emitter_cells(0.5)
    E_em = (eL * (np.maximum(ed[:, 2], 0) * edw)[:, None]).sum(axis=0)
    E_far = lt.irradiance_up(np.array([[0.0, 5.0]]))[0]  # no plane point sees the sphere from 5 m
    np.testing.assert_allclose(E_far, E_bg + E_em, rtol=4e-3)
    E_near = lt.plane_irradiance_at(np.array([[0.09, 0.0], [0.3, 0.3]]))
    assert np.all(E_near[0] < 0.8 * E_far) and np.all(E_near[1] > 0.95 * E_far)


@pytest.mark.slow
def test_render_error_below_half_a_percent():
    """The fast renderer against the 16x brute-force reference (two-material, office, plane)."""
    from replay.synth.accuracy import render_error

    r = render_error("two-material", n_pixels=48, frames=2, size=(160, 120), detail="test", quality=Quality())
    assert r["n"] >= 100
    assert r["rms_rel"] < 0.006
    assert abs(r["mean_rel"]) < 0.002
