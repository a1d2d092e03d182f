"""Environment map from a mirror ball (paper §4.3): accumulation, coverage, fill, files, previews.

Scenes come from the independent generator in tests/_mirrorball.py (analytic ray-sphere render of a known
environment from orbiting cameras, with noise).
"""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np
import pytest

from _mirrorball import (BOX, CENTER, DEPTH_TO_RGB, INTR, RADIUS, env, gt_latlong, gt_map, lit, orbit,
                         rel_errors, render_depth, render_rgb)
from appfusion import octahedral as octa
from appfusion.envmap import EnvMap, EnvMapAccumulator, EnvMapFileError, filling_strip
from appfusion.errors import AppFusionError, EstimationError
from appfusion.frame import Frame, invert_pose
from appfusion.lighting_pass import LightingPass, run_lighting_pass

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
import cv2  # noqa: E402


@pytest.fixture(scope="module")
def orbit_pass():
    """The whole pass: sphere fitted from 6 noisy depth views, 40 RGB views accumulated (n = 128)."""
    lp = LightingPass(n=128, box=BOX)
    for i, p in enumerate(orbit(6, seed=1)):
        lp.add_depth(render_depth(p, sigma=0.003, seed=i), INTR, p)
    lp.fit()
    for i, p in enumerate(orbit(40, seed=2)):
        prgb = p @ invert_pose(DEPTH_TO_RGB)
        lp.add_rgb(render_rgb(prgb, seed=i, noise=0.01), INTR, prgb)
    return lp, lp.envmap()


@pytest.fixture(scope="module")
def gt128():
    return gt_map(128)


# -- accuracy ------------------------------------------------------------------------------------

def test_orbit_recovers_environment(orbit_pass, gt128):
    lp, em = orbit_pass
    assert np.linalg.norm(lp.sphere.center - CENTER) < 0.002
    assert abs(lp.sphere.radius - RADIUS) / RADIUS < 0.02
    m = em.coverage & lit(gt128)
    assert m.sum() > 0.95 * m.size
    err = rel_errors(em.radiance, gt128, m)
    assert np.median(err) <= 0.05, np.median(err)
    assert np.percentile(err, 90) < 0.05
    e, eg = em.energy(m), (gt128[m] * em.solid_angles()[m][:, None]).sum(axis=0)
    assert np.all(np.abs(e / eg - 1) < 0.03), e / eg - 1
    # the bright rectangles are where they belong: the brightest texel's direction lies in rectangle 1
    d = em.directions()[np.unravel_index(np.argmax(em.radiance.mean(-1)), em.coverage.shape)]
    assert env(d).mean() > 4.0
    assert em.frame == "marker" and em.meta["rgb_frames"] == 40 and "sphere" in em.meta


def test_orbit_fills_without_holes(orbit_pass):
    _, em = orbit_pass
    assert em.coverage_fraction() > 0.999
    assert em.weight[em.coverage].min() > 0


def test_single_view_geometry_and_frame():
    """One noiseless view of an environment that encodes its own direction: every measured texel holds
    (close to) its own direction, so reflection, pose and frame conventions are right."""
    def dir_env(d):
        return np.asarray(d) + 1.5

    pose = orbit(1, seed=4)[0]
    img = render_rgb(pose, noise=0.0, environment=dir_env, ss=4)
    acc = EnvMapAccumulator(64, min_cos=0.3)
    n = acc.add_view(img, INTR, pose, CENTER, RADIUS)
    em = acc.envmap()
    assert n > 10000 and em.meta["n_views"] == 1
    got = em.radiance[em.coverage] - 1.5
    want = em.directions()[em.coverage]
    ang = np.degrees(np.arccos(np.clip((got * want).sum(-1) / np.linalg.norm(got, axis=-1), -1, 1)))
    assert np.median(ang) < 1.5 and np.percentile(ang, 95) < 5.0
    # the direction straight back to the camera is seen; the one straight behind the ball is not
    to_cam = (pose[:3, 3] - CENTER) / np.linalg.norm(pose[:3, 3] - CENTER)
    idx = octa.sphere_texel_index(np.stack([to_cam, -to_cam]), 64)
    assert em.coverage.reshape(-1)[idx[0]] and not em.coverage.reshape(-1)[idx[1]]


def test_grazing_pixels_skipped():
    """Reflected directions r satisfy angle(r, w_o) = 2 acos(w_o . n): min_cos bounds how far behind
    the ball the map reaches."""
    pose = orbit(1, seed=5)[0]
    img = render_rgb(pose, noise=0.0)
    to_cam = (pose[:3, 3] - CENTER) / np.linalg.norm(pose[:3, 3] - CENTER)
    d = octa.sphere_directions(128)
    reach = {}
    for mc in (0.1, 0.5):
        acc = EnvMapAccumulator(128, min_cos=mc)
        acc.add_view(img, INTR, pose, CENTER, RADIUS)
        cov = acc.envmap().coverage
        reach[mc] = np.degrees(np.arccos(np.clip(d[cov] @ to_cam, -1, 1))).max()
    assert reach[0.5] < 2 * np.degrees(np.arccos(0.5)) + 3.0     # 120 deg (+ texel and camera-distance slack)
    assert reach[0.1] > 150.0


def test_rho_mirror_is_divided_out():
    pose = orbit(1, seed=6)[0]
    a, b = EnvMapAccumulator(64), EnvMapAccumulator(64, rho_mirror=(0.6, 0.65, 0.7))
    a.add_view(render_rgb(pose, noise=0.0, bg=0.0), INTR, pose, CENTER, RADIUS)
    b.add_view(render_rgb(pose, noise=0.0, bg=0.0, rho=np.array([0.6, 0.65, 0.7])), INTR, pose, CENTER, RADIUS)
    ea, eb = a.envmap(), b.envmap()
    assert np.array_equal(ea.coverage, eb.coverage)
    assert np.allclose(ea.radiance, eb.radiance, rtol=1e-5, atol=1e-6)
    assert eb.meta["rho_mirror"] == pytest.approx([0.6, 0.65, 0.7])


def test_running_mean_equals_weighted_mean():
    """Eq. 3 update in batches == the weighted mean of all samples at once (brute force with np.add.at)."""
    rng = np.random.default_rng(0)
    n = 8
    d = rng.normal(size=(5000, 3))
    v = rng.uniform(0, 3, (5000, 3))
    w = rng.uniform(0, 1, 5000)
    acc = EnvMapAccumulator(n)
    for part in np.array_split(np.arange(5000), 7):
        acc.add_samples(d[part], v[part], w[part])
    idx = octa.sphere_texel_index(d, n)
    sw = np.zeros(2 * n * n)
    svw = np.zeros((2 * n * n, 3))
    np.add.at(sw, idx, w)
    np.add.at(svw, idx, w[:, None] * v)
    em = acc.envmap()
    assert np.allclose(em.weight.reshape(-1), sw, rtol=1e-6)
    seen = sw > 0
    assert np.array_equal(em.coverage.reshape(-1), seen)
    assert np.allclose(em.radiance.reshape(-1, 3)[seen], svw[seen] / sw[seen, None], rtol=1e-5)
    # invalid samples are ignored, not averaged in
    assert acc.add_samples([[0, 0, 0], [np.nan, 0, 1], [0, 0, 1]], [[1, 1, 1], [1, 1, 1], [np.inf, 0, 0]],
                           [1, 1, 1]) == 0
    assert acc.add_samples([[0, 0, 1]], [[1, 1, 1]], [0.0]) == 0
    with pytest.raises(AppFusionError, match="directions"):
        acc.add_samples(d[:3], v[:2], w[:3])


def test_supersampling_fills_the_footprint():
    pose = orbit(1, seed=3)[0]
    img = render_rgb(pose, noise=0.0)
    to_cam = (pose[:3, 3] - CENTER) / np.linalg.norm(pose[:3, 3] - CENTER)
    front = octa.sphere_directions(128) @ to_cam > np.cos(np.radians(100))
    cov = {}
    for s in (1, "auto"):
        acc = EnvMapAccumulator(128)
        acc.add_view(img, INTR, pose, CENTER, RADIUS, supersample=s)
        cov[s] = acc.envmap().coverage[front].mean()
    assert cov[1] < 0.3 and cov["auto"] > 0.85, cov


def test_auto_supersampling_and_pixel_kernel(gt128):
    """'auto' puts two sub-rays per texel at the ball's centre; a Gaussian pixel kernel (pixel_sigma)
    sharpens the bright rectangles' edges against the box kernel on the same views."""
    acc = EnvMapAccumulator(128)
    texel = np.sqrt(4 * np.pi / (2 * 128 * 128))
    for dist, f in ((0.6, 262.5), (0.6, 525.0), (1.2, 525.0)):
        step = 2 * (dist - 0.035) / (f * 0.035)                     # one pixel in reflected direction
        s = acc._supersample("auto", dist, 0.035, INTR.scaled(int(640 * f / 525), int(480 * f / 525)))
        assert s == min(int(np.ceil(2 * step / texel)), 16) and step / s <= texel / 2 + 1e-12
    poses = orbit(24, seed=41)
    imgs = [render_rgb(p, seed=i, noise=0.0) for i, p in enumerate(poses)]
    p90 = {}
    for sig in (None, 0.25):
        acc = EnvMapAccumulator(128, pixel_sigma=sig)
        for img, p in zip(imgs, poses):
            acc.add_view(img, INTR, p, CENTER, RADIUS)
        em = acc.envmap()
        assert em.meta["pixel_sigma"] == sig
        m = em.coverage & lit(gt128)
        p90[sig] = np.percentile(rel_errors(em.radiance, gt128, m), 90)
    assert p90[0.25] < 0.9 * p90[None], p90
    for bad in (0.0, -1.0, np.nan):
        with pytest.raises(AppFusionError, match="pixel_sigma"):
            EnvMapAccumulator(16, pixel_sigma=bad)


def test_add_view_bad_input_and_edge_cases():
    acc = EnvMapAccumulator(32)
    pose = orbit(1)[0]
    img = render_rgb(pose, noise=0.0)
    with pytest.raises(AppFusionError, match="does not match"):
        acc.add_view(img[:-1], INTR, pose, CENTER, RADIUS)
    with pytest.raises(AppFusionError, match="linear float"):
        acc.add_view((img * 100).astype(np.uint8), INTR, pose, CENTER, RADIUS)
    with pytest.raises(AppFusionError, match="4x4"):
        acc.add_view(img, INTR, np.full((4, 4), np.nan), CENTER, RADIUS)
    with pytest.raises(AppFusionError, match="inside the mirror ball"):
        acc.add_view(img, INTR, np.eye(4), [0, 0, 0.01], 0.05)
    with pytest.raises(AppFusionError, match="radius"):
        acc.add_view(img, INTR, pose, CENTER, -1.0)
    with pytest.raises(AppFusionError, match="supersample"):
        acc.add_view(img, INTR, pose, CENTER, RADIUS, supersample=0)
    with pytest.raises(AppFusionError, match="rho_mirror"):
        EnvMapAccumulator(32, rho_mirror=0.0)
    behind = np.eye(4)
    behind[:3, 3] = CENTER + [0, 0, 0.5]          # camera looking up (+z) from above the ball: not in view
    assert acc.add_view(img, INTR, behind, CENTER, RADIUS) == 0
    nan_img = img.copy()
    nan_img[:] = np.nan
    assert acc.add_view(nan_img, INTR, pose, CENTER, RADIUS) == 0
    mask = np.zeros(INTR.shape, bool)
    assert acc.add_view(img, INTR, pose, CENTER, RADIUS, mask=mask) == 0
    assert not acc.envmap().coverage.any()


def test_lens_distortion_is_undone():
    from dataclasses import replace
    intr = replace(INTR, dist=(0.12, -0.25, 0.001, -0.001, 0.1))
    pose = orbit(1, seed=7)[0]
    img = render_rgb(pose, intr=intr, noise=0.0, environment=lambda d: np.asarray(d) + 1.5)
    acc = EnvMapAccumulator(64, min_cos=0.3)
    acc.add_view(img, intr, pose, CENTER, RADIUS)
    em = acc.envmap()
    got = em.radiance[em.coverage] - 1.5
    ang = np.degrees(np.arccos(np.clip((got * em.directions()[em.coverage]).sum(-1)
                                       / np.linalg.norm(got, axis=-1), -1, 1)))
    assert np.median(ang) < 1.5


# -- fill ----------------------------------------------------------------------------------------------

def _holey(n=64, seed=0):
    gt = gt_map(n, sub=2)
    d = octa.sphere_directions(n)
    axis = np.array([-0.5, 0.5, -0.7]) / np.linalg.norm([-0.5, 0.5, -0.7])    # clear of the rectangles
    hole = d @ axis > np.cos(np.radians(25))
    hole |= d[..., 2] < -0.9                                   # and the nadir (straddles no seam)
    hole |= (np.abs(d[..., 2]) < 0.08) & (d[..., 0] > 0.7)     # a band across the equator seam
    cov = ~hole
    return EnvMap(np.where(cov[..., None], gt, 0).astype(np.float32), cov.astype(np.float32), cov,
                  np.zeros_like(cov)), gt, hole


@pytest.mark.parametrize("method", ["harmonic", "nearest", "constant"])
def test_fill_marks_and_fills(method):
    em, gt, hole = _holey()
    f = em.fill(method)
    assert np.array_equal(f.filled, hole) and np.array_equal(f.coverage, em.coverage)
    assert np.array_equal(f.radiance[em.coverage], em.radiance[em.coverage])   # measured texels untouched
    assert (f.radiance[hole] > 0).all() and f.meta["fill"] == method
    if method == "harmonic":                       # maximum principle and accuracy on a smooth region
        lo, hi = em.radiance[em.coverage].min(0), em.radiance[em.coverage].max(0)
        assert (f.radiance[hole] >= lo - 1e-4).all() and (f.radiance[hole] <= hi + 1e-4).all()
        smooth = hole & (gt.mean(-1) < 1.0)
        const = em.fill("constant")
        # a membrane cannot extrapolate the gradient into the wide holes, but beats a constant
        assert np.median(rel_errors(f.radiance, gt, smooth)) < 0.15
        assert np.median(rel_errors(f.radiance, gt, smooth)) < 0.5 * np.median(rel_errors(const.radiance, gt, smooth))
        d = em.directions()
        band = hole & (np.abs(d[..., 2]) < 0.08)     # a narrow gap across the seam fills almost exactly
        assert np.median(rel_errors(f.radiance, gt, band)) < 0.01
        # no seam: texels facing each other across the equator have nearly the same filled value
        n = em.n
        border = np.zeros((n, n), bool)
        border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
        both = border & hole[0] & hole[1]
        assert both.any()
        assert np.abs(f.radiance[0][both] - f.radiance[1][both]).max() < 0.02
    # an empty map cannot be filled
    empty = EnvMap(np.zeros_like(em.radiance), np.zeros_like(em.weight), np.zeros_like(em.coverage),
                   np.zeros_like(em.coverage))
    with pytest.raises(EstimationError, match="nothing measured"):
        empty.fill(method)


def test_fill_unknown_method():
    em, _, _ = _holey(16)
    with pytest.raises(AppFusionError, match="unknown method"):
        em.fill("magic")


def test_envmap_defaults_for_a_bare_radiance_array():
    rad = gt_map(8, sub=2).astype(np.float32)
    em = EnvMap(rad)
    assert em.coverage.all() and not em.filled.any() and (em.weight == 1).all() and em.frame == "marker"
    assert em.coverage_fraction() == pytest.approx(1.0)
    assert np.allclose(em.energy(), (rad * em.solid_angles()[..., None]).sum(axis=(0, 1, 2)))


def test_envmap_validation():
    z = np.zeros((2, 8, 8, 3), np.float32)
    m = np.zeros((2, 8, 8), bool)
    with pytest.raises(AppFusionError, match="shape"):
        EnvMap(z[:, :, :4], m, m, m)
    with pytest.raises(AppFusionError, match="both"):
        EnvMap(z, m, ~m, ~m)
    with pytest.raises(AppFusionError, match="NaN"):
        EnvMap(z + np.nan, m, m, m)


# -- files ---------------------------------------------------------------------------------------------

def test_npz_roundtrip_is_lossless(orbit_pass, tmp_path):
    _, em = orbit_pass
    f = em.fill("harmonic")
    p = f.save(tmp_path / "env.npz")
    g = EnvMap.load(p)
    for k in ("radiance", "weight", "coverage", "filled"):
        assert np.array_equal(getattr(f, k), getattr(g, k)), k
    assert g.frame == "marker" and g.meta["fill"] == "harmonic" and g.meta["sphere"]["radius"] > 0
    assert not list(tmp_path.glob("*.tmp*"))


def test_exr_and_hdr_roundtrip(orbit_pass, tmp_path, gt128):
    _, em = orbit_pass
    em = EnvMap(em.radiance, em.weight, em.coverage, em.filled, meta=em.meta)
    em.coverage[1, :20, :20] = False                 # a hole, to see the masks survive the EXR alpha
    em.radiance[1, :20, :20] = 0
    f = em.fill("harmonic")
    exr = EnvMap.load(f.save(tmp_path / "env.exr"), n=128)
    hdr = EnvMap.load(f.save(tmp_path / "env.hdr"), n=128)
    smooth = f.coverage & (gt128.mean(-1) < 1.0)
    smooth[:, :2] = smooth[:, -2:] = smooth[:, :, :2] = smooth[:, :, -2:] = False
    assert np.median(rel_errors(exr.radiance, f.radiance, smooth)) < 0.01
    assert np.median(rel_errors(hdr.radiance, f.radiance, smooth)) < 0.015
    agree = (exr.coverage == f.coverage).mean(), (exr.filled == f.filled).mean()
    assert min(agree) > 0.98, agree
    assert hdr.coverage.all() and not hdr.filled.any()
    # the lat-long export itself matches the known environment
    img = cv2.imread(str(tmp_path / "env.exr"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (256, 512, 4) and img.dtype == np.float32
    gl = gt_latlong(256)
    sky = (gl.mean(-1) < 1.0) & (img[..., 3] == 1.0)
    sky[:, :3] = sky[:, -3:] = False
    assert np.median(np.abs(img[..., 2::-1][sky] - gl[sky]).mean(-1) / gl[sky].mean(-1)) < 0.02


def test_from_latlong_and_rotation():
    gl = gt_latlong(128)
    em = EnvMap.from_latlong(gl, n=64)
    gt = gt_map(64, sub=4)
    assert em.coverage.all() and np.median(rel_errors(em.radiance, gt, np.ones(gt.shape[:3], bool))) < 0.01
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])     # 90 deg about z
    rot = EnvMap.from_latlong(gl, n=64, rotation=Rz)
    d = octa.sphere_directions(64)
    want = env(d @ Rz)                                # image direction = R^T d
    assert np.median(np.abs(rot.radiance - want).mean(-1) / want.mean(-1)) < 0.01
    with pytest.raises(AppFusionError, match="rotation"):
        EnvMap.from_latlong(gl, n=8, rotation=np.eye(3) * 2)
    with pytest.raises(AppFusionError, match=r"\(H, W, 3\)"):
        EnvMap.from_latlong(gl[..., 0], n=8)


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(EnvMapFileError, match="no such"):
        EnvMap.load(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip at all")
    with pytest.raises(EnvMapFileError, match=str(bad)):
        EnvMap.load(bad)
    other = tmp_path / "other.npz"
    np.savez(other, something=np.zeros(3))
    with pytest.raises(EnvMapFileError, match="missing arrays"):
        EnvMap.load(other)
    em, _, _ = _holey(8)
    good = em.save(tmp_path / "good.npz")
    trunc = tmp_path / "trunc.npz"
    trunc.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(EnvMapFileError, match="trunc.npz"):
        EnvMap.load(trunc)
    shapes = tmp_path / "shapes.npz"
    with zipfile.ZipFile(good) as z:
        arrays = {k[:-4]: np.load(z.open(k)) for k in z.namelist()}
    arrays["weight"] = arrays["weight"][:, :4]
    np.savez(shapes, **arrays)
    with pytest.raises(EnvMapFileError, match="weight must have shape"):
        EnvMap.load(shapes)
    newer = tmp_path / "newer.npz"
    arrays = {k[:-4]: np.load(zipfile.ZipFile(good).open(k)) for k in zipfile.ZipFile(good).namelist()}
    arrays["version"] = np.int64(99)
    np.savez(newer, **arrays)
    with pytest.raises(EnvMapFileError, match="newer"):
        EnvMap.load(newer)
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"\x76\x2f\x31\x01garbage")
    with pytest.raises(EnvMapFileError, match="junk.exr"):
        EnvMap.load(junk)
    grey = tmp_path / "grey.exr"
    cv2.imwrite(str(grey), np.ones((8, 16), np.float32))
    with pytest.raises(EnvMapFileError, match="colour"):
        EnvMap.load(grey)
    with pytest.raises(EnvMapFileError, match="suffix"):
        EnvMap.load(good.with_suffix(".npz").rename(tmp_path / "x.png"))
    with pytest.raises(EnvMapFileError, match="suffix"):
        em.save(tmp_path / "x.jpg")


# -- previews ------------------------------------------------------------------------------------------

def test_preview_shows_coverage(tmp_path):
    em, _, hole = _holey(32)
    img = em.preview(scale=2, label="test")
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[1] == 2 * (2 * 32 + 1)
    # unknown texels are a grey checkerboard: pixel values only 89 or 128, equal in R, G and B
    ij = np.argwhere(hole[0])                         # unknown texels of the upper square
    assert len(ij)
    px = img[2 * ij[:, 0] + 1, 2 * ij[:, 1] + 1]
    assert (px[:, 0] == px[:, 1]).all() and (px[:, 1] == px[:, 2]).all() and np.isin(px[:, 0], (89, 128)).all()
    known = np.argwhere(~hole[0])
    assert not np.isin(img[2 * known[:, 0] + 1, 2 * known[:, 1] + 1, 0], (89, 128)).all()
    filled = em.fill().preview(scale=2)
    assert not np.array_equal(filled, img)
    strip = filling_strip([("a", em), ("b", em.fill())])
    one = em.preview(scale=1)
    assert strip.shape[0] == one.shape[0] and strip.shape[1] > 2 * one.shape[1]
    p = em.save_preview(tmp_path / "p.png")
    assert cv2.imread(str(p)).shape == img.shape
    with pytest.raises(AppFusionError):
        filling_strip([])


# -- the pass glue --------------------------------------------------------------------------------------

def test_lighting_pass_order_and_errors():
    lp = LightingPass(n=32, box=BOX)
    pose = orbit(1)[0]
    with pytest.raises(EstimationError, match="fit"):
        lp.add_rgb(render_rgb(pose), INTR, pose)
    with pytest.raises(EstimationError, match="no depth points"):
        lp.fit()
    lp.set_sphere(CENTER, RADIUS)
    assert lp.add_rgb(render_rgb(pose), INTR, pose) > 0
    with pytest.raises(AppFusionError):
        lp.set_sphere([np.nan, 0, 0], 0.05)


def test_add_frame_holds_rgb_until_fit():
    lp = LightingPass(n=64, box=BOX, radius=RADIUS, min_cos=0.6)     # grazing views skipped: holes to fill
    for i, p in enumerate(orbit(4, seed=8)):
        prgb = p @ invert_pose(DEPTH_TO_RGB)
        fr = Frame(index=i, timestamp=i / 30, depth=render_depth(p, seed=i), rgb=render_rgb(prgb, seed=i),
                   rgb_encoding="linear", depth_intrinsics=INTR, rgb_intrinsics=INTR, depth_to_rgb=DEPTH_TO_RGB,
                   pose=p)
        if i == 0:
            lp.add_depth(fr.depth, INTR, p)           # the same image through both doors counts once
        lp.add_frame(fr)
    assert lp.n_depth_frames == 4 and lp.n_rgb_frames == 0
    fit = lp.fit()
    assert lp.n_rgb_frames == 4 and fit.radius == RADIUS
    assert np.linalg.norm(fit.center - CENTER) < 0.002
    em = lp.envmap(fill="nearest", meta={"markers": "set-1"})
    assert em.filled.any() and em.known.all() and em.meta["markers"] == "set-1" and em.meta["fill"] == "nearest"
    with pytest.raises(AppFusionError, match="no pose"):
        lp.add_frame(Frame(index=9, timestamp=1.0))


def test_run_lighting_pass_over_a_recorded_session(tmp_path):
    from replay.session import SessionReader, SessionWriter
    exposure = 0.1                                   # keep the HDR scene below 1 in the 16-bit linear PNGs
    with SessionWriter(tmp_path / "s", device="synthetic", intrinsics={"depth": INTR, "rgb": INTR},
                       depth_to_rgb=DEPTH_TO_RGB, rgb_encoding="linear") as w:
        for i, p in enumerate(orbit(10, seed=9)):
            prgb = p @ invert_pose(DEPTH_TO_RGB)
            rgb = np.clip(render_rgb(prgb, seed=i, noise=0.005) * exposure, 0, 1)
            w.write(Frame(index=i, timestamp=1.0 + i / 30, depth=render_depth(p, seed=i), rgb=rgb,
                          rgb_encoding="linear", depth_intrinsics=INTR, rgb_intrinsics=INTR,
                          depth_to_rgb=DEPTH_TO_RGB, pose=p, pass_name="environment"))
    r = SessionReader(tmp_path / "s")
    steps = []
    em, fit = run_lighting_pass(r, box=BOX, n=64, calibrate=lambda f, pose: f.rgb_linear() / exposure,
                                progress=lambda stage, k: steps.append(stage))
    assert steps.count("depth") == 10 and steps.count("rgb") == 10
    assert np.linalg.norm(fit.center - CENTER) < 0.002
    gt = gt_map(64, sub=4)
    m = em.coverage & lit(gt)
    assert m.mean() > 0.9 and np.median(rel_errors(em.radiance, gt, m)) < 0.05
    from appfusion.errors import PassMissingError
    with pytest.raises(PassMissingError, match="geometry"):
        run_lighting_pass(r, box=BOX, n=16, pass_name="geometry")
    json.dumps(em.meta)


# -- evaluation against a scanner's truth ---------------------------------------------------------------

def _truth_dir(tmp_path, white=(2.0, 1.8, 1.5), with_white=True):
    """A minimal synthetic-scanner truth/ folder: the test environment (absolute radiance) as a lat-long
    EXR, the white circles' radiance, a ball resting on a 0.6 m support plane."""
    t = tmp_path / "truth"
    (t / "envmaps").mkdir(parents=True)
    cv2.imwrite(str(t / "envmaps" / "office.exr"), gt_latlong(128)[..., ::-1].astype(np.float32))
    mk = {"white_radiance_rgb": {"environment": [list(white)] * 4}} if with_white else {}
    (t / "markers.json").write_text(json.dumps(mk))
    (t / "scene.json").write_text(json.dumps({"environment": {"name": "office"},
                                              "ball": {"centre_m": [0, 0, 0.035], "radius_m": 0.035},
                                              "plane": {"half_size_m": 0.6}}))
    return t


def test_envmap_comparison_calibrates_and_masks(tmp_path):
    from appfusion.evaluate import envmap_comparison, envmap_energy_rel_err, envmap_error, truth_envmap
    white = np.array([2.0, 1.8, 1.5])
    t = _truth_dir(tmp_path, white)
    ref = truth_envmap(t, "office", 64) / white                # what a perfect capture holds (white units)
    down = octa.sphere_directions(64)[..., 2] < 0
    c = envmap_comparison(ref, t)
    assert c["median_rel_err"] < 1e-6 and np.abs(c["energy_rel_err"]).max() < 1e-6
    assert c["known_fraction"] == pytest.approx(0.5, abs=0.01)      # the plane hides the lower half
    est = ref * 1.04
    est[down] = 0.01                                            # the black paper the ball sees below
    assert envmap_error(est, t) == pytest.approx(0.04, abs=1e-4)
    assert envmap_energy_rel_err(est, t) == pytest.approx(0.04, abs=1e-4)
    est[..., 2] *= 0.9                                          # a colour error counts too
    assert envmap_energy_rel_err(EnvMap(est), t) == pytest.approx(1.04 * 0.9 - 1, abs=1e-4)
    assert envmap_error(ref * white, t) > 0.4                   # absolute radiance is not the engine's unit
    cov = np.ones(down.shape, bool)
    cov[0, :, :32] = False                                     # only what was measured is compared
    assert envmap_comparison(EnvMap(ref, coverage=cov), t)["n_texels"] < c["n_texels"]
    t2 = _truth_dir(tmp_path / "b", with_white=False)
    assert np.isnan(envmap_error(ref, t2)) and np.isnan(envmap_energy_rel_err(ref, t2))
    with pytest.raises(AppFusionError, match="shape"):
        envmap_error(np.zeros((64, 64, 3)), t)


# -- the map's own blur (beyond the paper) -------------------------------------------------------

def test_map_blur_variance_and_effective_alpha_undo_the_ball_images_blur(orbit_pass, gt128):
    """The captured map is the scene seen through the pixels of the ball's images (and the splat and
    the texels): a sharp Ward lobe read against it sees the lights widened, so a least-squares fit of
    the true S on the captured one comes out high (the rho_s of Eq. 8 with it). The map's own blur
    variance (meta ``blur_var_rad2``, from the ball's geometry) read through ``effective_alpha``
    takes most of that bias away. S by brute-force quadrature over the texels; mirror directions
    around the brightest rectangle and its edges."""
    from appfusion.brdf import ward
    from appfusion.envmap import effective_alpha, map_blur_var

    _, em = orbit_pass
    v = em.meta["blur_var_rad2"]
    # 40 views at 0.65 m, f = 525 px, R = 5 cm: one pixel turns the reflection by ~2.3 degrees at
    # the ball's centre; the variance must be of that order (box pixel + splat + texel)
    step = 2 * (0.65 - RADIUS) / (525.0 * RADIUS)
    assert 0.05 * step ** 2 < v < 0.5 * step ** 2, (v, step ** 2)
    D = octa.sphere_directions(128).reshape(-1, 3)
    Om = octa.sphere_solid_angles(128).reshape(-1)
    rng = np.random.default_rng(0)
    k = 300
    th, ph = np.radians(rng.uniform(14, 46, k)), np.radians(rng.uniform(4, 56, k))
    r = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1)
    tilt, az = np.radians(rng.uniform(10, 50, k)), rng.uniform(0, 2 * np.pi, k)
    t = np.cross(r, [0.0, 0.0, 1.0])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(r, t)
    n = np.cos(tilt / 2)[:, None] * r + np.sin(tilt / 2)[:, None] * (np.cos(az)[:, None] * t + np.sin(az)[:, None] * b)
    wo = 2 * (r * n).sum(1, keepdims=True) * n - r                  # the view whose mirror direction is r
    ok = (n[:, 2] > 0) & ((n * wo).sum(1) > 0.3)
    n, wo = n[ok], wo[ok]

    def S(L, alpha):
        out = np.empty((len(n), 3))
        for i in range(len(n)):
            f = ward(alpha, D, np.broadcast_to(wo[i], D.shape), np.broadcast_to(n[i], D.shape))
            out[i] = (L.reshape(-1, 3) * (f * np.maximum(D @ n[i], 0) * Om)[:, None]).sum(0)
        return out

    a = 0.05
    St = S(gt128, a)
    slope = {}
    for name, al in (("alpha", a), ("effective", effective_alpha(a, v))):
        Sc = S(em.radiance, al)
        slope[name] = float(np.mean((Sc * St).sum(0) / (Sc ** 2).sum(0)))
    assert slope["alpha"] > 1.004, slope
    assert abs(slope["effective"] - 1) < 0.5 * (slope["alpha"] - 1), slope
    # the rule itself: variances add, floored at half the roughness; none without blur
    assert effective_alpha(0.06, 0.0) == 0.06
    assert np.isclose(effective_alpha(0.06, 2e-4) ** 2, 0.06 ** 2 - 1e-4)
    assert effective_alpha(0.01, 1.0) == 0.005
    assert np.allclose(effective_alpha(np.array([0.06, 0.35]), 2e-4) ** 2, np.array([0.06, 0.35]) ** 2 - 1e-4)
    # a map without measured texels has no blur to speak of
    z = np.zeros((2, 8, 8))
    assert map_blur_var(np.zeros((2, 8, 8, 3)), z > 0, z, z) == 0.0
