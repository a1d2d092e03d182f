"""The engine's reflectance model (paper §3, Eq. 1): Lambertian plus an isotropic specular lobe.

    f_r(w_i, w_o) = rho_d / pi + rho_s * f(alpha; w_i, w_o)

The paper's lobe, and the engine's default, is the original Ward (1992) isotropic lobe

    f(alpha; w_i, w_o) = exp(-tan^2(theta_h) / alpha^2) / (4 pi alpha^2 sqrt(cos(theta_i) cos(theta_o)))

where theta_h is the angle between the half vector and the normal. The model ladder's third rung
(a cluster whose highlight has the long tail no Ward lobe has) is the GGX / Trowbridge-Reitz
microfacet lobe (Walter et al. 2007) with the separable Smith shadowing term and no Fresnel factor,
so that ``rho_s`` is a plain specular scale as for Ward:

    f(alpha; w_i, w_o) = D(theta_h) G1(w_i) G1(w_o) / (4 cos(theta_i) cos(theta_o)),
    D = alpha^2 / (pi cos^4(theta_h) (alpha^2 + tan^2(theta_h))^2),
    G1(w) = 2 / (1 + sqrt(1 + alpha^2 tan^2(theta_w))).

:data:`LOBES` names the lobes; :func:`lobe`, :func:`lobe_half` and :func:`lobe_retro` evaluate the
one a cluster's model names. Directions are unit vectors in the local frame (normal = +z) unless a
normal is given. This module is the engine's own implementation; the synthetic scanner
(``replay/synth``) has an independent one.
"""

from __future__ import annotations

import numpy as np

from .errors import AppFusionError

#: smallest cosine treated as above the horizon
COS_EPS = 1e-6
#: the specular lobes the engine knows (a cluster's model is one of these, or "diffuse")
LOBES = ("ward", "ggx")


def ward(alpha, wi: np.ndarray, wo: np.ndarray, n: np.ndarray | None = None) -> np.ndarray:
    """Isotropic Ward specular lobe f(alpha; w_i, w_o) (paper Eq. 1), 1/sr.

    Parameters
    ----------
    alpha : float or ndarray
        Roughness (> 0), broadcast against the directions' leading shape.
    wi, wo : (..., 3) ndarray
        Unit lighting and view directions.
    n : (..., 3) ndarray, optional
        Unit normals; +z when omitted.

    Returns
    -------
    (...) ndarray
        Lobe value; 0 where either direction is below the horizon.
    """
    ci, co, ch = _cosines(wi, wo, n)
    return ward_half(alpha, ch, ci, co)


def ward_half(alpha, cos_h, cos_i, cos_o) -> np.ndarray:
    """Ward lobe from cosines: half-vector, lighting and view angle to the normal."""
    alpha = np.asarray(alpha, dtype=np.float64)
    cos_h = np.asarray(cos_h, dtype=np.float64)
    valid = (cos_i > COS_EPS) & (cos_o > COS_EPS) & (cos_h > COS_EPS)
    ch = np.where(valid, cos_h, 1.0)
    tan2 = (1.0 - ch * ch) / (ch * ch)
    denom = 4.0 * np.pi * alpha * alpha * np.sqrt(np.where(valid, cos_i * cos_o, 1.0))
    return np.where(valid, np.exp(-tan2 / (alpha * alpha)) / denom, 0.0)


def ward_retro(alpha, cos_h) -> np.ndarray:
    """Ward lobe with w_i = w_o = h (the HBSAB convention of §5.1): exp(-tan^2/a^2) / (4 pi a^2 cos_h)."""
    return ward_half(alpha, cos_h, cos_h, cos_h)


def ggx_d(alpha, cos_h) -> np.ndarray:
    """GGX normal distribution ``D(theta_h)`` (1/sr), normalised so that ``int D cos(theta_h) dh = 1``;
    0 at or below the horizon."""
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    cos_h = np.asarray(cos_h, dtype=np.float64)
    c2 = np.clip(cos_h, COS_EPS, 1.0) ** 2
    tan2 = (1.0 - c2) / c2
    return np.where(cos_h > COS_EPS, a2 / (np.pi * c2 * c2 * (a2 + tan2) ** 2), 0.0)


def ggx_g1(alpha, cos_w) -> np.ndarray:
    """Smith masking ``G1 = 2 / (1 + sqrt(1 + alpha^2 tan^2 theta_w))`` of the GGX distribution."""
    c2 = np.clip(np.asarray(cos_w, dtype=np.float64), COS_EPS, 1.0) ** 2
    tan2 = (1.0 - c2) / c2
    return 2.0 / (1.0 + np.sqrt(1.0 + np.asarray(alpha, dtype=np.float64) ** 2 * tan2))


def ggx_half(alpha, cos_h, cos_i, cos_o) -> np.ndarray:
    """GGX lobe from cosines (half vector, lighting, view to the normal): ``D G1 G1 / (4 cos_i cos_o)``, 1/sr."""
    cos_i = np.asarray(cos_i, dtype=np.float64)
    cos_o = np.asarray(cos_o, dtype=np.float64)
    cos_h = np.asarray(cos_h, dtype=np.float64)
    valid = (cos_i > COS_EPS) & (cos_o > COS_EPS) & (cos_h > COS_EPS)
    ci, co = np.where(valid, cos_i, 1.0), np.where(valid, cos_o, 1.0)
    val = ggx_d(alpha, np.where(valid, cos_h, 1.0)) * ggx_g1(alpha, ci) * ggx_g1(alpha, co) / (4.0 * ci * co)
    return np.where(valid, val, 0.0)


def ggx(alpha, wi: np.ndarray, wo: np.ndarray, n: np.ndarray | None = None) -> np.ndarray:
    """GGX specular lobe f(alpha; w_i, w_o) (module docstring), 1/sr; arguments as :func:`ward`."""
    ci, co, ch = _cosines(wi, wo, n)
    return ggx_half(alpha, ch, ci, co)


def ggx_retro(alpha, cos_h) -> np.ndarray:
    """GGX lobe with w_i = w_o = h (the HBSAB convention of §5.1): ``D G1^2 / (4 cos_h^2)``."""
    return ggx_half(alpha, cos_h, cos_h, cos_h)


def _cosines(wi, wo, n):
    """Cosines of w_i, w_o and their half vector to the normal (+z when ``n`` is None), (...) each."""
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    if n is None:
        ci, co = wi[..., 2], wo[..., 2]
    else:
        ci, co = np.sum(wi * n, axis=-1), np.sum(wo * n, axis=-1)
    h = wi + wo
    hn = np.linalg.norm(h, axis=-1)
    hn = np.where(hn > 0, hn, 1.0)
    ch = (h[..., 2] if n is None else np.sum(h * n, axis=-1)) / hn
    return ci, co, ch


def _check_lobe(kind: str) -> str:
    if kind not in LOBES:
        raise ValueError(f"unknown specular lobe {kind!r}; the engine knows {', '.join(LOBES)}")
    return kind


def lobe(kind: str, alpha, wi: np.ndarray, wo: np.ndarray, n: np.ndarray | None = None) -> np.ndarray:
    """The specular lobe named ``kind`` (:data:`LOBES`), 1/sr; arguments as :func:`ward`."""
    return (ggx if _check_lobe(kind) == "ggx" else ward)(alpha, wi, wo, n)


def lobe_half(kind: str, alpha, cos_h, cos_i, cos_o) -> np.ndarray:
    """The lobe named ``kind`` from cosines (:func:`ward_half`, :func:`ggx_half`)."""
    return (ggx_half if _check_lobe(kind) == "ggx" else ward_half)(alpha, cos_h, cos_i, cos_o)


def lobe_retro(kind: str, alpha, cos_h) -> np.ndarray:
    """The lobe named ``kind`` with w_i = w_o = h (:func:`ward_retro`, :func:`ggx_retro`)."""
    return (ggx_retro if _check_lobe(kind) == "ggx" else ward_retro)(alpha, cos_h)


def sample_ward(alpha, wo_l: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ward half-vector sampling (Walter 2005) in the local frame (normal +z).

    Parameters
    ----------
    alpha : float or ndarray
        Roughness, broadcast against ``u1``.
    wo_l : (..., 3) ndarray
        Unit view directions, local frame.
    u1, u2 : ndarray
        Uniforms in (0, 1): ``tan^2 theta_h = -alpha^2 log u1``, ``phi_h = 2 pi u2``.

    Returns
    -------
    wi : (..., 3) ndarray
        The sampled lighting directions (``w_o`` reflected about the half vector).
    cos_oh : (...) ndarray
        ``w_o . h``; where it is <= 0 the half vector faces away from the viewer and the sample is void.
    pdf : (...) ndarray
        The samples' solid-angle density, as :func:`ward_pdf` gives it (from the sampled half vector,
        without recomputing it).
    """
    a2 = np.asarray(alpha) ** 2
    tan2 = -a2 * np.log(np.maximum(u1, 1e-12))
    ch = 1.0 / np.sqrt(1.0 + tan2)
    sh = np.sqrt(np.maximum(1 - ch * ch, 0))
    phi = 2 * np.pi * np.asarray(u2)
    h = np.stack([sh * np.cos(phi), sh * np.sin(phi), ch], axis=-1)
    cos_oh = np.sum(wo_l * h, -1)
    pdf = np.exp(-tan2 / a2) / (np.pi * a2 * ch ** 3) / (4 * np.maximum(np.abs(cos_oh), 1e-6))
    return 2 * cos_oh[..., None] * h - wo_l, cos_oh, pdf


def ward_pdf(alpha, wi_l: np.ndarray, wo_l: np.ndarray) -> np.ndarray:
    """Solid-angle density of :func:`sample_ward` drawing ``wi_l`` for ``wo_l`` (local frame), 1/sr:
    ``exp(-tan^2 theta_h / alpha^2) / (pi alpha^2 cos^3 theta_h) / (4 |w_o . h|)``."""
    h = wi_l + wo_l
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    ch = np.clip(h[..., 2], 1e-6, 1)
    tan2 = (1 - ch * ch) / (ch * ch)
    pdf_h = np.exp(-tan2 / np.asarray(alpha) ** 2) / (np.pi * np.asarray(alpha) ** 2 * ch ** 3)
    return pdf_h / (4 * np.maximum(np.abs(np.sum(wo_l * h, -1)), 1e-6))


def sample_ggx(alpha, wo_l: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GGX visible-normal sampling (Heitz 2018, "Sampling the GGX distribution of visible normals",
    JCGT 7(4)) in the local frame (normal +z), for :func:`ggx`.

    The half vector ``h`` is drawn with density ``G1(w_o) (w_o . h)+ D(h) / cos_o`` (the normals the
    viewer sees), ``w_o`` reflected about it; the solid-angle density of ``w_i`` is then
    ``G1(w_o) D(h) / (4 cos_o)`` and the estimator weight ``f cos_i / pdf = G1(w_i)`` (<= 1, also at
    grazing views, unlike the ``D cos(theta_h)`` half-vector sampling of Walter et al. 2007).

    Parameters
    ----------
    alpha : float or ndarray
        GGX roughness (> 0), broadcast against ``u1``.
    wo_l : (..., 3) ndarray
        Unit view directions, local frame, above the horizon (a view at or below it is treated as
        grazing, ``cos_o = 1e-9``).
    u1, u2 : ndarray
        Uniforms in [0, 1): radius ``sqrt(u1)`` and azimuth ``2 pi u2`` on the projected hemisphere
        of visible normals (a stratified pattern of ``(u1, u2)`` stays stratified).

    Returns
    -------
    wi : (..., 3) ndarray
        The sampled lighting directions (may lie below the horizon: their lobe value is 0).
    cos_oh : (...) ndarray
        ``w_o . h`` (>= 0 by construction).
    pdf : (...) ndarray
        The samples' solid-angle density (1/sr), as :func:`ggx_pdf` gives it.
    """
    a = np.asarray(alpha, dtype=np.float64)
    wo_l = np.asarray(wo_l, dtype=np.float64)
    u1 = np.asarray(u1, dtype=np.float64)
    u2 = np.asarray(u2, dtype=np.float64)
    # the view in the stretched configuration (alpha -> 1), hemisphere of visible normals
    vz = np.maximum(wo_l[..., 2], 1e-9)
    hx, hy, hz = a * wo_l[..., 0], a * wo_l[..., 1], vz
    ln = np.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / ln, hy / ln, hz / ln
    lensq = hx * hx + hy * hy
    pos = lensq > 0
    inv = np.where(pos, 1.0 / np.sqrt(np.where(pos, lensq, 1.0)), 0.0)
    t1x, t1y = np.where(pos, -hy * inv, 1.0), np.where(pos, hx * inv, 0.0)       # T1 = (t1x, t1y, 0)
    t2x, t2y, t2z = -hz * t1y, hz * t1x, hx * t1y - hy * t1x                      # T2 = V_h x T1
    r = np.sqrt(u1)
    phi = 2 * np.pi * u2
    p1, p2 = r * np.cos(phi), r * np.sin(phi)
    s = 0.5 * (1.0 + hz)
    p2 = (1.0 - s) * np.sqrt(np.maximum(1.0 - p1 * p1, 0.0)) + s * p2
    p3 = np.sqrt(np.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))
    nx = p1 * t1x + p2 * t2x + p3 * hx
    ny = p1 * t1y + p2 * t2y + p3 * hy
    nz = p2 * t2z + p3 * hz
    # back to the ellipsoid configuration
    mx, my, mz = a * nx, a * ny, np.maximum(nz, 0.0)
    mn = np.maximum(np.sqrt(mx * mx + my * my + mz * mz), 1e-300)
    h = np.stack([mx / mn, my / mn, mz / mn], axis=-1)
    cos_oh = np.sum(wo_l * h, -1)
    pdf = ggx_g1(a, vz) * ggx_d(a, h[..., 2]) / (4.0 * vz)
    return 2 * cos_oh[..., None] * h - wo_l, cos_oh, pdf


def ggx_pdf(alpha, wi_l: np.ndarray, wo_l: np.ndarray) -> np.ndarray:
    """Solid-angle density (1/sr) of :func:`sample_ggx` drawing ``wi_l`` for ``wo_l`` (local frame):
    ``G1(w_o) D(h) / (4 cos_o)``, 0 where the half vector or the view is at or below the horizon or
    the half vector faces away from the viewer."""
    wi_l = np.asarray(wi_l, dtype=np.float64)
    wo_l = np.asarray(wo_l, dtype=np.float64)
    h = wi_l + wo_l
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    ch = h[..., 2]
    co = wo_l[..., 2]
    ok = (ch > COS_EPS) & (co > COS_EPS) & (np.sum(wo_l * h, -1) > 0)
    co_ = np.where(ok, co, 1.0)
    return np.where(ok, ggx_g1(alpha, co_) * ggx_d(alpha, np.where(ok, ch, 1.0)) / (4.0 * co_), 0.0)


def ggx_rows(lobe, M: int, who: str = "shade_points") -> np.ndarray | None:
    """(M,) bool, the points whose lobe is GGX, from ``lobe`` (None, a name or (M,) names; "diffuse"
    counts as Ward); None where there is none (the all-Ward path). ``who`` names the caller in errors."""
    if lobe is None:
        return None
    names = np.asarray(lobe)
    if names.ndim > 1 or (names.ndim == 1 and len(names) != M):
        raise AppFusionError(f"{who}: lobe must be a name or one name per point ({M}), got shape {names.shape}")
    names = np.broadcast_to(names.astype(str), (M,))
    bad = sorted(set(np.unique(names).tolist()) - set(LOBES) - {"diffuse"})
    if bad:
        raise AppFusionError(f"{who}: unknown specular lobe(s) {bad}; the engine knows {', '.join(LOBES)}")
    g = names == "ggx"
    return g if g.any() else None


def lobe_rows(a, wi_l: np.ndarray, wo_l: np.ndarray, g: np.ndarray | None) -> np.ndarray:
    """Specular lobe values (m, K) 1/sr: Ward, GGX on the rows ``g`` (m,) (None: none). ``a`` (m, 1)
    roughness, ``wi_l`` (m, K, 3) and ``wo_l`` (m, K, 3) local directions."""
    if g is None or not np.any(g):
        return ward(a, wi_l, wo_l)
    g = np.asarray(g, bool)
    f = np.empty(np.shape(wi_l)[:-1])
    w = ~g
    if w.any():
        f[w] = ward(a[w], wi_l[w], wo_l[w])
    f[g] = ggx(a[g], wi_l[g], wo_l[g])
    return f


def local_frame(n: np.ndarray) -> np.ndarray:
    """Orthonormal frames (..., 3, 3) whose rows are (t, b, n) for unit normals ``n`` (..., 3).

    ``local = frame @ world`` maps world vectors into the local frame with the normal as +z
    (Duff et al. 2017 branchless construction).
    """
    n = np.asarray(n, dtype=np.float64)
    s = np.where(n[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (s + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    t = np.stack([1 + s * n[..., 0] ** 2 * a, s * b, -s * n[..., 0]], axis=-1)
    bt = np.stack([b, s + n[..., 1] ** 2 * a, -n[..., 1]], axis=-1)
    return np.stack([t, bt, n], axis=-2)


def to_local(frame: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Express world vectors ``v`` (..., 3) in local frames from :func:`local_frame`."""
    return np.einsum("...ij,...j->...i", frame, v)
