"""Relighting: render a captured object under any environment map from any view.

Solves the rendering equation (paper Eq. 2) with the captured reflectance of Eq. 1,

    L(w_o) = integral L_env(w) (rho_d / pi + rho_s f(alpha; w, w_o)) (n . w) V(w) dw,

by Monte Carlo integration with multiple importance sampling (balance heuristic) of two strategies:
the environment map (texels chosen in proportion to luminance x solid angle) and the BRDF (cosine
lobe for the diffuse part, Ward's half-vector distribution for the specular part, chosen in proportion
to their albedos). Visibility V (self-shadowing) is traced against the object's own mesh with Open3D's
RaycastingScene. Unlike the capture passes, which ignore visibility as the paper does (§3), relighting
can afford it. The same model as the engine (:mod:`appfusion.brdf`).
"""

from __future__ import annotations

import numpy as np

from . import octahedral as oc
from .brdf import local_frame, ward
from .errors import AppFusionError
from .frame import Intrinsics
from .result import ScanResult


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


class EnvSampler:
    """Importance sampling of a (2, N, N, 3) octahedral environment map by luminance x solid angle."""

    def __init__(self, env: np.ndarray):
        env = np.asarray(env, np.float64)
        if env.ndim != 4 or env.shape[0] != 2 or env.shape[1] != env.shape[2] or env.shape[3] != 3:
            raise AppFusionError(f"environment map must have shape (2, N, N, 3), got {env.shape}")
        if not np.all(np.isfinite(env)) or np.any(env < 0):
            raise AppFusionError("environment map has negative or non-finite radiance")
        self.env = env
        self.n = env.shape[1]
        self.omega = oc.sphere_solid_angles(self.n).ravel()
        w = np.maximum(_luminance(env.reshape(-1, 3)), 0) * self.omega
        total = w.sum()
        if total <= 0:
            raise AppFusionError("environment map is black: nothing to light the object with")
        self.p = w / total
        self.cdf = np.cumsum(self.p)
        self.cdf[-1] = 1.0

    def sample(self, u: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Directions (M, 3) and their solid-angle pdf (M,) for uniforms ``u`` (M,)."""
        idx = np.minimum(np.searchsorted(self.cdf, u, side="right"), len(self.cdf) - 1)
        n = self.n
        face, rem = np.divmod(idx, n * n)
        row, col = np.divmod(rem, n)
        jit = rng.random((len(u), 2))
        uv = np.stack([(col + jit[:, 0]) * 2.0 / n - 1, (row + jit[:, 1]) * 2.0 / n - 1], axis=1)
        d = oc.sphere_decode(face, uv)
        return d, self.pdf(d)

    def pdf(self, d: np.ndarray) -> np.ndarray:
        """Solid-angle pdf of drawing direction ``d`` (..., 3) with :meth:`sample`.

        Within a texel the sample is uniform in (u, v), so the density is the texel probability times
        the local Jacobian dA/domega = 2 |p|^3 over the texel's (u, v) area (2/N)^2.
        """
        i = oc.sphere_texel_index(d, self.n)
        face, uv = oc.sphere_encode(d)
        x, y = 0.5 * (uv[..., 0] + uv[..., 1]), 0.5 * (uv[..., 0] - uv[..., 1])
        z = 1.0 - np.abs(x) - np.abs(y)
        jac = 2.0 * (x * x + y * y + z * z) ** 1.5  # du dv per steradian
        return self.p[i] * jac / (2.0 / self.n) ** 2

    def radiance(self, d: np.ndarray) -> np.ndarray:
        """Environment radiance in directions ``d`` (..., 3), bilinear, (..., 3)."""
        return oc.sample_sphere_map(self.env, d)


def _sample_ward(alpha, wo_l, u1, u2):
    """Ward half-vector sampling in the local frame; returns w_i (M, 3)."""
    tan2 = -(alpha ** 2) * np.log(np.maximum(u1, 1e-12))
    ch = 1.0 / np.sqrt(1.0 + tan2)
    sh = np.sqrt(np.maximum(1 - ch * ch, 0))
    phi = 2 * np.pi * u2
    h = np.stack([sh * np.cos(phi), sh * np.sin(phi), ch], axis=-1)
    return 2 * np.sum(wo_l * h, -1, keepdims=True) * h - wo_l


def _pdf_ward(alpha, wi_l, wo_l):
    h = wi_l + wo_l
    h /= np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    ch = np.clip(h[..., 2], 1e-6, 1)
    tan2 = (1 - ch * ch) / (ch * ch)
    pdf_h = np.exp(-tan2 / alpha ** 2) / (np.pi * alpha ** 2 * ch ** 3)
    return pdf_h / (4 * np.maximum(np.abs(np.sum(wo_l * h, -1)), 1e-6))


def shade_points(positions, normals, wo, rho_d, rho_s, alpha, env: np.ndarray | EnvSampler,
                 spp: int = 256, scene=None, seed: int = 0, chunk: int = 4096) -> np.ndarray:
    """Outgoing radiance (linear RGB) at surface points towards ``wo``.

    Parameters
    ----------
    positions, normals, wo : (M, 3) ndarray
        Points (world), unit normals, unit directions towards the viewer.
    rho_d, rho_s : (M, 3) ndarray; alpha : (M,) ndarray
        Reflectance of each point (paper Eq. 1).
    env : (2, N, N, 3) ndarray or EnvSampler
        Environment radiance in the same world frame.
    spp : int
        Samples per point per strategy (total 2 x spp).
    scene : open3d.t.geometry.RaycastingScene, optional
        Occluders for visibility; no shadows when None.

    Returns
    -------
    (M, 3) float32 radiance.
    """
    import open3d as o3d

    sampler = env if isinstance(env, EnvSampler) else EnvSampler(env)
    rng = np.random.default_rng(seed)
    M = len(positions)
    out = np.zeros((M, 3))
    for s in range(0, M, chunk):
        sl = slice(s, min(s + chunk, M))
        p, n, v = positions[sl], normals[sl], wo[sl]
        rd, rs, al = rho_d[sl], rho_s[sl], np.maximum(alpha[sl], 1e-3)
        m = len(p)
        F = local_frame(n)
        wo_l = np.einsum("mij,mj->mi", F, v)
        wo_l[:, 2] = np.maximum(wo_l[:, 2], 1e-4)
        wo_l /= np.linalg.norm(wo_l, axis=1, keepdims=True)
        # probability of choosing the Ward lobe within the BRDF strategy, from the albedo ratio
        wd, ws = rd.mean(1), rs.mean(1)
        q_spec = np.where(ws > 0, ws / np.maximum(wd + ws, 1e-12), 0.0)
        # --- strategy A: environment samples; strategy B: BRDF samples
        # stratified (Latin hypercube) uniforms per point: each of the spp samples of a point falls in
        # its own 1/spp slice of every dimension, which cuts the variance of the env map's bright spots
        dA, pA = sampler.sample(_stratified(rng, m, spp).reshape(-1), rng)
        dA = dA.reshape(m, spp, 3)
        pA = pA.reshape(m, spp)
        u = np.stack([_stratified(rng, m, spp) for _ in range(3)], -1)
        choose_spec = u[..., 0] < q_spec[:, None]
        cos_dir = np.stack(_cosine(u[..., 1], u[..., 2]), -1)
        spec_dir = _sample_ward(al[:, None], wo_l[:, None, :], u[..., 1], u[..., 2])
        wiB_l = np.where(choose_spec[..., None], spec_dir, cos_dir)
        dB = np.einsum("mji,msj->msi", F, wiB_l)
        wiA_l = np.einsum("mij,msj->msi", F, dA)
        total = np.zeros((m, 3))
        for wi_l, wi in ((wiA_l, dA), (wiB_l, dB)):
            cos_i = wi_l[..., 2]
            ok = cos_i > 1e-6
            f_spec = ward(al[:, None], wi_l, np.broadcast_to(wo_l[:, None, :], wi_l.shape))
            pdf_b = (1 - q_spec[:, None]) * np.maximum(cos_i, 0) / np.pi + q_spec[:, None] * _pdf_ward(
                al[:, None], wi_l, wo_l[:, None, :])
            pdf_a = sampler.pdf(wi)
            denom = spp * (pdf_a + pdf_b)
            L = sampler.radiance(wi)
            fr = rd[:, None, :] / np.pi + rs[:, None, :] * f_spec[..., None]
            contrib = np.where(ok[..., None], L * fr * np.maximum(cos_i, 0)[..., None], 0.0)
            contrib = contrib / np.maximum(denom, 1e-30)[..., None]
            if scene is not None:
                org = p[:, None, :] + 1e-4 * n[:, None, :]
                rays = np.concatenate([np.broadcast_to(org, wi.shape), wi], -1).reshape(-1, 6).astype(np.float32)
                occ = scene.test_occlusions(o3d.core.Tensor(rays), tnear=1e-4).numpy().reshape(m, spp)
                contrib = np.where(occ[..., None], 0.0, contrib)
            total += contrib.sum(1)  # balance heuristic: sum over both strategies' samples
        out[sl] = total
    return out.astype(np.float32)


def _stratified(rng: np.random.Generator, m: int, spp: int) -> np.ndarray:
    """(m, spp) uniforms, one in each interval [k/spp, (k+1)/spp) per row, in random order."""
    perm = np.argsort(rng.random((m, spp)), axis=1)
    return (perm + rng.random((m, spp))) / spp


def _cosine(u1, u2):
    r = np.sqrt(u1)
    phi = 2 * np.pi * u2
    return r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1 - u1, 0))


def render_view(result: ScanResult, env: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray,
                spp: int = 256, shadows: bool = True, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Render the captured object under ``env`` seen by a pinhole camera.

    Parameters
    ----------
    result : ScanResult
        Must carry a mesh.
    env : (2, N, N, 3) ndarray
        Environment radiance in the marker frame.
    intrinsics : Intrinsics
    pose : (4, 4) ndarray
        Camera-to-world pose of the rendering camera (OpenCV axes).

    Returns
    -------
    image : (H, W, 3) float32 linear radiance (0 where the object is not hit)
    mask : (H, W) bool, pixels that see the object
    """
    import open3d as o3d
    from .export import transfer_to_vertices

    V, Fc = np.asarray(result.mesh_vertices, np.float32), np.asarray(result.mesh_faces, np.int32)
    if len(Fc) == 0:
        raise AppFusionError("relighting needs a mesh: export the scan first (appfusion scan writes one)")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(Fc.astype(np.uint32)))
    H, W = intrinsics.height, intrinsics.width
    dirs_cam = intrinsics.rays().reshape(-1, 3).astype(np.float64)
    dirs = dirs_cam @ pose[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    org = np.broadcast_to(pose[:3, 3], dirs.shape)
    rays = np.concatenate([org, dirs], 1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy()
    mask = np.isfinite(t)
    img = np.zeros((H * W, 3), np.float32)
    if mask.any():
        prim = hit["primitive_ids"].numpy()[mask]
        bu, bv = hit["primitive_uvs"].numpy()[mask].T
        bary = np.stack([1 - bu - bv, bu, bv], 1)
        tri = Fc[prim]
        vn = transfer_to_vertices(result.positions, result.normals, V)
        vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
        n = np.einsum("mk,mki->mi", bary, vn[tri])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        pos = org[mask] + dirs[mask] * t[mask][:, None]
        v_rd = transfer_to_vertices(result.positions, result.rho_d, V)
        rd = np.einsum("mk,mki->mi", bary, v_rd[tri])
        # per-point cluster parameters taken at the nearest sampled point (no blending across clusters)
        from scipy.spatial import cKDTree
        _, nearest = cKDTree(result.positions).query(pos)
        lab = result.labels[nearest]
        wo = -dirs[mask]
        n = np.where(np.sum(n * wo, 1, keepdims=True) < 0, -n, n)  # face the viewer
        img[mask] = shade_points(pos, n, wo, rd, result.rho_s[lab], result.alpha[lab], env, spp=spp,
                                 scene=scene if shadows else None, seed=seed)
    return img.reshape(H, W, 3), mask.reshape(H, W)
