"""Core types: octahedral map, intrinsics, sRGB, Ward lobe, CLI error handling."""

from __future__ import annotations

import numpy as np
import pytest

from appfusion import brdf, octahedral as oc
from appfusion.cli import main
from appfusion.errors import AppFusionError
from appfusion.frame import Frame, Intrinsics, invert_pose, linear_to_srgb, make_pose, srgb_to_linear, transform_points


def _random_dirs(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_hemi_roundtrip_and_pole():
    d = _random_dirs(2000)
    d[:, 2] = np.abs(d[:, 2])
    uv = oc.hemi_encode(d)
    assert np.all(np.abs(uv) <= 1 + 1e-12)
    np.testing.assert_allclose(oc.hemi_decode(uv), d, atol=1e-12)
    np.testing.assert_allclose(oc.hemi_encode(np.array([0, 0, 1.0])), [0, 0], atol=1e-15)


def test_sphere_roundtrip_both_faces():
    d = _random_dirs(2000, 1)
    face, uv = oc.sphere_encode(d)
    assert set(np.unique(face)) == {0, 1}
    np.testing.assert_allclose(oc.sphere_decode(face, uv), d, atol=1e-12)


@pytest.mark.parametrize("n", [8, 32, 128])
def test_solid_angles_sum_to_hemisphere(n):
    w = oc.hemi_solid_angles(n)
    assert w.shape == (n, n)
    assert abs(w.sum() - 2 * np.pi) < 1e-4
    assert abs(oc.sphere_solid_angles(n).sum() - 4 * np.pi) < 2e-4


def test_texel_index_matches_directions():
    n = 16
    d = oc.hemi_directions(n).reshape(-1, 3)
    idx = oc.texel_index(oc.hemi_encode(d), n)
    np.testing.assert_array_equal(idx, np.arange(n * n))


def test_latlong_sphere_roundtrip_smooth_function():
    f = lambda d: 1.0 + 0.5 * d[..., 0] + 0.25 * d[..., 2] ** 2
    ll = f(oc.latlong_directions(64))
    m = oc.latlong_to_sphere(ll, 32)
    np.testing.assert_allclose(m, f(oc.sphere_directions(32)), atol=0.01)
    back = oc.sphere_to_latlong(m, 64)
    np.testing.assert_allclose(back, ll, atol=0.02)


def test_intrinsics_project_backproject():
    K = Intrinsics(64, 48, 50.0, 52.0, 31.5, 23.5)
    depth = np.full((48, 64), 0.7, np.float32)
    depth[0, 0] = np.nan
    pts = K.backproject(depth)
    assert np.isnan(pts[0, 0]).all()
    uv, z = K.project(pts[1:].reshape(-1, 3))
    u, v = np.meshgrid(np.arange(64), np.arange(1, 48))
    np.testing.assert_allclose(uv[:, 0], u.ravel(), atol=1e-4)
    np.testing.assert_allclose(uv[:, 1], v.ravel(), atol=1e-4)
    assert Intrinsics.from_json(K.to_json()) == K
    with pytest.raises(AppFusionError, match="focal"):
        Intrinsics(64, 48, -1, 50, 0, 0)
    with pytest.raises(AppFusionError, match="missing field 'fx'"):
        Intrinsics.from_json({"width": 1, "height": 1})


def test_pose_helpers():
    a = 0.3
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    T = make_pose(R, [0.1, 0.2, 0.3])
    p = np.random.default_rng(0).normal(size=(10, 3))
    np.testing.assert_allclose(transform_points(invert_pose(T), transform_points(T, p)), p, atol=1e-12)


def test_srgb_roundtrip():
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-5)
    assert srgb_to_linear(np.array([255], np.uint8))[0] == pytest.approx(1.0)
    # uint8 codes (table look-up) decode exactly as the same values given as floats
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    lin = srgb_to_linear(codes)
    assert lin.dtype == np.float32 and lin.shape == (16, 16)
    np.testing.assert_array_equal(lin, srgb_to_linear(codes.astype(np.float32) / 255.0))
    assert lin[0, 10] == pytest.approx(10 / 255 / 12.92) and lin[8, 0] == pytest.approx(((128 / 255 + 0.055) / 1.055) ** 2.4)
    f = Frame(0, 0.0, rgb=np.full((2, 2, 3), 128, np.uint8))
    assert f.rgb_linear().dtype == np.float32 and f.streams == ("rgb",)
    with pytest.raises(AppFusionError, match="rgb_encoding"):
        Frame(0, 0.0, rgb_encoding="bgr")


def test_ward_lobe_normalisation_and_symmetry():
    # Ward's lobe: the hemispherical integral of f cos(theta_i) at normal view is ~1 for small alpha.
    alpha = 0.1
    n = 256
    d = oc.hemi_directions(n).reshape(-1, 3)
    w = oc.hemi_solid_angles(n).ravel()
    wo = np.array([0, 0, 1.0])
    f = brdf.ward(alpha, d, np.broadcast_to(wo, d.shape))
    albedo = np.sum(f * d[:, 2] * w)
    assert 0.97 < albedo < 1.01
    wi, wo2 = _random_dirs(100, 2), _random_dirs(100, 3)
    wi[:, 2], wo2[:, 2] = np.abs(wi[:, 2]), np.abs(wo2[:, 2])
    np.testing.assert_allclose(brdf.ward(0.2, wi, wo2), brdf.ward(0.2, wo2, wi))
    assert np.all(brdf.ward(0.2, -wi, wo2) == 0)


def test_local_frame_orthonormal():
    n = _random_dirs(500, 4)
    F = brdf.local_frame(n)
    np.testing.assert_allclose(F @ np.swapaxes(F, -1, -2), np.broadcast_to(np.eye(3), F.shape), atol=1e-12)
    np.testing.assert_allclose(brdf.to_local(F, n), np.broadcast_to([0, 0, 1.0], n.shape), atol=1e-12)


def test_cli_help_and_unknown(capsys):
    assert main([]) == 1
    with pytest.raises(SystemExit):
        main(["no-such-command"])


def test_latlong_to_sphere_rgb_channels():
    d = oc.latlong_directions(32)
    rgb = np.stack([d[..., 0], d[..., 1], d[..., 2]], -1) + 2.0
    m = oc.latlong_to_sphere(rgb, 16)
    assert m.shape == (2, 16, 16, 3)
    np.testing.assert_allclose(m, oc.sphere_directions(16) + 2.0, atol=0.03)
