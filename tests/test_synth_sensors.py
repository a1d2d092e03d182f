"""Synthetic scanner: the depth, IR and RGB sensor models reproduce the statistics they claim."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from appfusion.frame import srgb_to_linear
from replay.synth import camera as C
from replay.synth import envmaps
from replay.synth.objects import custom_sphere
from replay.synth import materials as M
from replay.synth.render import Quality, Scene, Sheet
from replay.synth.scanner import render_depth_ir
from replay.synth.sensors import DepthModel, IRModel, RGBModel

INTR = C.depth_intrinsics(160, 120)


def _sheet_scene(obj=None):
    return Scene(envmaps.constant(1.0), obj=obj, sheet=Sheet(), quality=Quality.preset("test"))


def _sheet_pose(d):
    _, poses, _ = C.fronto_parallel_poses([d], 1, seed=0, shake_deg=0.0)
    return poses[0]


def _render(sc, pose, seed=0, emitter=True, ir=None):
    ir = ir or IRModel(seed=0)
    return render_depth_ir(sc, pose, INTR, DepthModel(), ir, np.random.default_rng(seed),
                           np.random.default_rng(seed + 1), emitter=emitter)


@pytest.mark.parametrize("z,tol", [(0.6, 0.06), (1.0, 0.06), (1.6, 0.06), (2.5, 0.12)])
def test_depth_noise_matches_nguyen_and_lies_on_the_disparity_lattice(z, tol):
    dm = DepthModel()
    r = _render(_sheet_scene(), _sheet_pose(z), seed=int(z * 10))
    d = r.depth[np.isfinite(r.depth)].astype(np.float64)
    assert d.size > 0.95 * INTR.width * INTR.height
    err = d - z
    assert err.std() == pytest.approx(dm.sigma(z), rel=tol)
    assert abs(err.mean()) < 0.15 * dm.sigma(z)
    disp8 = dm.subpixel * dm.focal_native_px * dm.baseline_m / d  # 1/8-pixel disparity steps: integers
    assert np.abs(disp8 - np.round(disp8)).max() < 2e-3


def test_nguyen_formula_values():
    dm = DepthModel()
    assert dm.sigma(0.4) == pytest.approx(0.0012)
    assert dm.sigma(1.4) == pytest.approx(0.0012 + 0.0019)
    assert dm.sigma(1.0, np.radians(60)) == pytest.approx(0.0012 + 0.0019 * 0.36 + 0.0001 * 4.0, rel=1e-9)
    assert dm.step(1.0) == pytest.approx(1.0 / (8 * 580 * 0.075))


def test_depth_invalid_too_near_too_far_and_grazing():
    sc = _sheet_scene()
    assert np.isnan(_render(sc, _sheet_pose(0.35)).depth).all()
    assert np.isnan(_render(sc, _sheet_pose(4.3)).depth).all()
    # view the sheet obliquely: pixels beyond 78 degrees incidence have no depth, those below mostly do
    pose = C.look_at([np.sin(np.radians(75)) * 1.0, -np.cos(np.radians(75)) * 1.0, 0.5], [0.0, 0.0, 0.5])
    r = _render(sc, pose)
    from replay.synth.scanner import camera_rays

    _, d, _ = camera_rays(pose, INTR)
    inc = np.degrees(np.arccos(np.clip(d[:, 1], -1, 1))).reshape(INTR.shape)  # sheet normal is -y
    hit = np.isfinite(r.z_true) & (r.z_true > 0.45) & (r.z_true < 3.5)
    assert np.isnan(r.depth[hit & (inc > 78.0)]).all() and (hit & (inc > 78.0)).sum() > 500
    assert np.isfinite(r.depth[hit & (inc < 76.0)]).mean() > 0.99


def test_emitter_shadow_band_has_no_depth_and_no_ir():
    """A ball in front of the sheet hides part of the sheet from the emitter (7.5 cm to the camera's +x):
    that band, just beside the ball's image, has no depth and reads the IR background."""
    ball = custom_sphere(0.05, (0.0, -0.35, 0.5), (0.5, 0.5, 0.5), M.Material("m", (0, 0, 0), 0.2), level=3)
    sc = _sheet_scene(ball)
    r = _render(sc, _sheet_pose(0.8))
    sheet = r.kind == 4
    shadow = sheet & np.isnan(r.depth)
    assert shadow.sum() > 30
    lit = sheet & np.isfinite(r.depth)
    assert np.median(r.ir[shadow]) < 60 and np.median(r.ir[lit]) > 200
    # the shadow is on the side away from the emitter: left of the ball in the image (camera x right)
    cols = np.nonzero(shadow.any(axis=0))[0]
    ball_cols = np.nonzero((r.kind == 1).any(axis=0))[0]
    assert cols.mean() < ball_cols.mean()


def test_ir_background_mode_and_spread():
    ir = IRModel(seed=3)
    sc = _sheet_scene()
    pose = _sheet_pose(0.8)
    frames = np.stack([_render(sc, pose, seed=k, emitter=False, ir=ir).ir for k in range(20)])
    single = frames[0]
    assert np.all(np.isnan(_render(sc, pose, emitter=False, ir=ir).depth))
    assert single.std() == pytest.approx(np.hypot(ir.sigma_fpn, ir.sigma_read), rel=0.1)
    mean = frames.mean(axis=0)
    hist, edges = np.histogram(mean, bins=np.arange(30.0, 70.0, 1.0))
    mode = 0.5 * (edges[hist.argmax()] + edges[hist.argmax() + 1])
    assert abs(mode - ir.b0) <= 1.0
    assert mean.std() == pytest.approx(np.hypot(ir.sigma_fpn, ir.sigma_read / np.sqrt(20)), rel=0.15)


def test_emitter_field_is_shifted_gamma_and_spatially_correlated():
    ir = IRModel(seed=5)
    t = ir.pattern().astype(np.float64)
    sub = t[::12, ::12].ravel()  # cells 12 apart are practically independent
    ks = stats.kstest(sub, stats.gamma(ir.k, scale=ir.theta).cdf)
    assert ks.pvalue > 1e-3
    assert sub.mean() == pytest.approx(ir.k * ir.theta, rel=0.05)

    def corr(a, b):
        return np.corrcoef(a.ravel(), b.ravel())[0, 1]

    assert corr(t[:, :-1], t[:, 1:]) > 0.6
    assert abs(corr(t[:, :-10], t[:, 10:])) < 0.05
    # the same every time (a property of the device), different for another device
    assert np.array_equal(IRModel(seed=5).pattern(), ir.pattern())
    assert not np.array_equal(IRModel(seed=6).pattern()[:50, :50], ir.pattern()[:50, :50])


def test_ir_white_sheet_level_follows_the_model():
    """White sheet (rho 0.8) straight ahead: counts = gain * R^0.9 + b0 with R = x cos / pi * 0.8 and
    x = (t + 3.4) / (57.7 d); the gain puts the mean-t sheet at 0.6 m at 60% of 1023."""
    ir = IRModel(seed=1)
    sc = _sheet_scene()
    tg = stats.gamma(ir.k, scale=ir.theta).rvs(size=400000, random_state=np.random.default_rng(0))
    for d in (0.6, 1.0):
        r = _render(sc, _sheet_pose(d), ir=ir)
        c = r.ir[50:70, 70:90]  # centre: emitter ray within ~4 degrees of the normal
        R = (tg + ir.shift) / (ir.scale * d) * ir.ref_albedo / np.pi
        want = np.mean(np.minimum(ir.gain * R ** ir.gamma + ir.b0, 1023))
        assert c.mean() == pytest.approx(want, rel=0.04)
    x_ref = (ir.k * ir.theta + ir.shift) / (ir.scale * 0.6) * 0.8 / np.pi
    assert ir.gain * x_ref ** ir.gamma + ir.b0 == pytest.approx(0.6 * 1023)


def test_rgb_noise_and_drift():
    cam = RGBModel(seed=2)
    v = 0.5
    img = cam.capture(np.full((200, 200, 3), v), 1.0, np.ones(3), np.random.default_rng(0))
    lin = srgb_to_linear(img)
    assert lin.mean() == pytest.approx(v, rel=0.01)
    assert lin.std() == pytest.approx(np.sqrt(cam.read_sigma ** 2 + v / cam.full_well), rel=0.12)
    e, g = cam.drift(np.linspace(0, 60, 1800))
    assert e.min() >= 0.8 - 1e-9 and e.max() <= 1.2 + 1e-9 and e.max() - e.min() > 0.15
    assert np.all(np.abs(g / np.array(cam.wb_gains) - 1) <= 0.03 + 1e-9)
    assert np.abs(np.diff(e)).max() < 0.01  # slow: under 1% per frame
