"""Relighting against closed forms: constant environments, Ward albedo, shadows, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from appfusion import octahedral as oc
from appfusion.brdf import ward
from appfusion.errors import AppFusionError
from appfusion.frame import Intrinsics, make_pose
from appfusion.relight import EnvSampler, render_view, shade_points
from appfusion.result import ScanResult


def _const_env(n=16, value=1.0):
    return np.full((2, n, n, 3), value, np.float32)


def test_env_sampler_pdf_integrates_to_one():
    rng = np.random.default_rng(0)
    env = _const_env(16) * (1 + 5 * (oc.sphere_directions(16)[..., 2:3] > 0.8))
    s = EnvSampler(env)
    d = oc.sphere_directions(64).reshape(-1, 3)
    w = oc.sphere_solid_angles(64).ravel()
    assert np.sum(s.pdf(d) * w) == pytest.approx(1.0, rel=0.01)
    # Monte Carlo estimate of the integral of the map with its own pdf is exact up to noise
    dd, p = s.sample(rng.random(20000), rng)
    est = np.mean(s.radiance(dd)[:, 0] / p)
    truth = np.sum(env[..., 0].ravel() * oc.sphere_solid_angles(16).ravel())
    assert est == pytest.approx(truth, rel=0.03)


def test_lambertian_under_constant_env_is_rho_times_L():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    wo = n.copy()
    rd = np.tile([0.2, 0.5, 0.8], (200, 1))
    L = shade_points(np.zeros((200, 3)), n, wo, rd, np.zeros((200, 3)), np.full(200, 0.2), _const_env(16, 2.0), spp=256)
    ratio = L / (2.0 * rd)
    assert ratio.mean() == pytest.approx(1.0, abs=0.003)  # unbiased
    assert ratio.std() < 0.03  # MIS noise at 2 x 256 samples


@pytest.mark.parametrize("alpha", [0.08, 0.3])
def test_ward_albedo_under_constant_env(alpha):
    # white furnace: radiance = integral of f cos over the hemisphere (quadrature reference)
    m = 512
    d = oc.hemi_directions(m).reshape(-1, 3)
    w = oc.hemi_solid_angles(m).ravel()
    wo = np.array([0.3, 0.0, np.sqrt(1 - 0.09)])
    ref = np.sum(ward(alpha, d, np.broadcast_to(wo, d.shape)) * d[:, 2] * w)
    N = 64
    n = np.tile([0, 0, 1.0], (N, 1))
    L = shade_points(np.zeros((N, 3)), n, np.tile(wo, (N, 1)), np.zeros((N, 3)), np.ones((N, 3)),
                     np.full(N, alpha), _const_env(16), spp=256, seed=3)
    assert L[:, 0].mean() == pytest.approx(ref, rel=0.01)


def test_render_view_sphere_with_and_without_shadows():
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(0.05, resolution=30)
    m.compute_vertex_normals()
    V, F = np.asarray(m.vertices), np.asarray(m.triangles)
    nrm = np.asarray(m.vertex_normals)
    r = ScanResult(V, nrm, np.full((len(V), 3), 0.5), np.zeros(len(V), np.int32), [[0, 0, 0]], [0.3],
                   mesh_vertices=V, mesh_faces=F)
    K = Intrinsics(48, 40, 60, 60, 23.5, 19.5)
    R = np.diag([1.0, -1.0, -1.0])  # camera on +z looking down -z
    pose = make_pose(R, [0, 0, 0.3])
    img, mask = render_view(r, _const_env(8, 1.0), K, pose, spp=16, shadows=True)
    assert 150 < mask.sum() < mask.size
    # a convex sphere does not shadow itself: Lambertian 0.5 under L = 1 gives 0.5 (faceting aside)
    assert np.median(img[mask, 1]) == pytest.approx(0.5, rel=0.02)
    assert np.all(img[~mask] == 0)


def test_bad_env_rejected():
    with pytest.raises(AppFusionError, match="shape"):
        EnvSampler(np.ones((8, 16, 3)))
    with pytest.raises(AppFusionError, match="black"):
        EnvSampler(np.zeros((2, 4, 4, 3)))
    bad = _const_env(4)
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(AppFusionError, match="non-finite"):
        EnvSampler(bad)
