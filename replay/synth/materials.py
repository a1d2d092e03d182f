"""Reflectance models of the synthetic scanner: Lambertian + a specular lobe (Ward or GGX).

This is the scanner's *own* implementation, independent of the engine's ``appfusion.brdf`` so that the
engine is judged against something it does not share code with.

The BRDF of a surface point is (paper Eq. 1, with the lobe chosen per material)::

    f_r(w_i, w_o) = rho_d / pi + rho_s * f(w_i, w_o)

Lobes (unit vectors, ``n`` the shading normal; all values in 1/sr):

``ward``
    The original isotropic Ward (1992) lobe the paper uses (Eq. 1):
    ``f = exp(-tan^2(theta_h) / alpha^2) / (4 pi alpha^2 sqrt(cos_i cos_o))``.
    Importance sampling after Walter (2005), "Notes on the Ward BRDF": half vector with
    ``tan(theta_h) = alpha sqrt(-ln u1)``, ``phi_h = 2 pi u2``, density
    ``p(h) = exp(-tan^2 / alpha^2) / (pi alpha^2 cos^3 theta_h)`` over the solid angle of ``h``,
    ``p(w_i) = p(h) / (4 |w_o . h|)``.
``ggx``
    Microfacet lobe with the GGX / Trowbridge-Reitz distribution (Walter et al. 2007) and the separable
    Smith shadowing term, without Fresnel (so ``rho_s`` is the specular scale, as for Ward):
    ``D = alpha^2 / (pi cos^4 theta_h (alpha^2 + tan^2 theta_h)^2)``,
    ``G1(w) = 2 / (1 + sqrt(1 + alpha^2 tan^2 theta_w))``,
    ``f = D G1(w_i) G1(w_o) / (4 cos_i cos_o)``. Sampled by its visible normals (Heitz 2018).

A ``mirror`` material (the mirror ball) is a perfect specular reflector of reflectance ``rho_s``; it
is rendered by reflecting view rays, never integrated.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from appfusion.errors import AppFusionError

#: lobes the renderer knows
LOBES = ("ward", "ggx", "mirror")
#: cosines at or below this count as "below the horizon"
COS_EPS = 1e-6


@dataclass(frozen=True)
class Material:
    """One specular material (a cluster of the paper): shared by many vertices.

    Attributes
    ----------
    name : str
    rho_s : (3,) tuple of float
        Specular scale per RGB channel (unitless).
    alpha : float
        Lobe roughness: Ward alpha (``lobe == "ward"``) or GGX alpha (``lobe == "ggx"``).
    lobe : {"ward", "ggx", "mirror"}
    ir_rho_s : float
        Specular scale in the IR band (one channel).
    """

    name: str
    rho_s: tuple[float, float, float]
    alpha: float
    lobe: str = "ward"
    ir_rho_s: float = 0.0

    def __post_init__(self):
        if self.lobe not in LOBES:
            raise AppFusionError(f"material {self.name!r}: unknown lobe {self.lobe!r} (known: {', '.join(LOBES)})")
        if self.lobe != "mirror" and not (self.alpha > 0):
            raise AppFusionError(f"material {self.name!r}: alpha must be > 0, got {self.alpha}")
        if len(self.rho_s) != 3 or min(self.rho_s) < 0 or self.ir_rho_s < 0:
            raise AppFusionError(f"material {self.name!r}: rho_s must be 3 non-negative values, got {self.rho_s}")

    def to_json(self) -> dict:
        d = asdict(self)
        d["rho_s"] = list(self.rho_s)
        if self.lobe == "ggx":
            d["ggx_alpha"] = self.alpha
        return d


# -- helpers --------------------------------------------------------------------------------------

def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along ``v`` (..., 3); zero vectors stay zero."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def tangent_frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (t, b) with (t, b, n) right-handed orthonormal, for unit normals (..., 3).

    Branchless construction of Duff et al. (2017), "Building an orthonormal basis, revisited".
    """
    s = np.where(n[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (s + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    t = np.stack([1 + s * n[..., 0] ** 2 * a, s * b, -s * n[..., 0]], axis=-1)
    bt = np.stack([b, s + n[..., 1] ** 2 * a, -n[..., 1]], axis=-1)
    return t, bt


def reflect(w: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Mirror direction of ``w`` about ``n``: ``2 (w . n) n - w`` (both pointing away from the surface)."""
    return 2.0 * _dot(w, n)[..., None] * n - w


# -- lobes ----------------------------------------------------------------------------------------

def ward(alpha, wi, wo, n) -> np.ndarray:
    """Isotropic Ward lobe (paper Eq. 1), 1/sr; 0 where a direction is below the horizon.

    Parameters
    ----------
    alpha : float or (...) array
    wi, wo, n : (..., 3) arrays of unit vectors
    """
    ci, co = _dot(wi, n), _dot(wo, n)
    h = normalize(wi + wo)
    ch = _dot(h, n)
    ok = (ci > COS_EPS) & (co > COS_EPS) & (ch > COS_EPS)
    ch = np.where(ok, ch, 1.0)
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    tan2 = (1.0 - ch * ch) / (ch * ch)
    val = np.exp(-tan2 / a2) / (4.0 * np.pi * a2 * np.sqrt(np.where(ok, ci * co, 1.0)))
    return np.where(ok, val, 0.0)


def ggx_d(alpha, cos_h) -> np.ndarray:
    """GGX normal distribution D(h) (1/sr), normalised so that the integral of D cos(theta_h) is 1."""
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    c2 = np.clip(cos_h, 1e-12, 1.0) ** 2
    tan2 = (1.0 - c2) / c2
    return np.where(cos_h > COS_EPS, a2 / (np.pi * c2 * c2 * (a2 + tan2) ** 2), 0.0)


def ggx_g1(alpha, cos_w) -> np.ndarray:
    """Smith masking G1 of the GGX distribution for a direction at cosine ``cos_w`` to the normal."""
    c2 = np.clip(cos_w, 1e-12, 1.0) ** 2
    tan2 = (1.0 - c2) / c2
    return 2.0 / (1.0 + np.sqrt(1.0 + np.asarray(alpha, dtype=np.float64) ** 2 * tan2))


def ggx(alpha, wi, wo, n) -> np.ndarray:
    """GGX microfacet lobe ``D G1(w_i) G1(w_o) / (4 cos_i cos_o)`` without Fresnel, 1/sr."""
    ci, co = _dot(wi, n), _dot(wo, n)
    h = normalize(wi + wo)
    ch = _dot(h, n)
    ok = (ci > COS_EPS) & (co > COS_EPS) & (ch > COS_EPS)
    ci_, co_ = np.where(ok, ci, 1.0), np.where(ok, co, 1.0)
    val = ggx_d(alpha, ch) * ggx_g1(alpha, ci_) * ggx_g1(alpha, co_) / (4.0 * ci_ * co_)
    return np.where(ok, val, 0.0)


def lobe_eval(lobe: str, alpha, wi, wo, n) -> np.ndarray:
    """Value of the named lobe (1/sr)."""
    if lobe == "ward":
        return ward(alpha, wi, wo, n)
    if lobe == "ggx":
        return ggx(alpha, wi, wo, n)
    raise AppFusionError(f"lobe_eval: lobe {lobe!r} has no finite value (mirror) or is unknown")


def lobe_sample(lobe: str, alpha, wo, n, u1, u2):
    """Importance-sample incident directions of a lobe.

    Ward: the half vector after Walter (2005). GGX: the distribution of *visible* normals (Heitz 2018,
    "Sampling the GGX distribution of visible normals", JCGT 7(4)), whose weight ``f cos_i / p`` is
    just ``G1(w_i)`` (bounded, also at grazing view angles).

    Parameters
    ----------
    lobe : {"ward", "ggx"}
    alpha : float or (...) array
    wo, n : (..., 3) unit view directions and normals
    u1, u2 : (...) uniform numbers in [0, 1)

    Returns
    -------
    wi : (..., 3) unit directions (may lie below the horizon; their weight is then 0)
    weight : (...) ``f(w_i, w_o) cos_i / p(w_i)``, the estimator weight of each sample (0 below the horizon)
    """
    alpha = np.asarray(alpha, dtype=np.float64)
    u1 = np.clip(u1, 1e-12, 1.0 - 1e-12)
    phi = 2.0 * np.pi * u2
    t, b = tangent_frame(n)
    if lobe == "ward":
        tan2 = alpha ** 2 * (-np.log(u1))
        ch = 1.0 / np.sqrt(1.0 + tan2)
        sh = np.sqrt(np.maximum(1.0 - ch * ch, 0.0))
        h = (sh * np.cos(phi))[..., None] * t + (sh * np.sin(phi))[..., None] * b + ch[..., None] * n
    elif lobe == "ggx":
        vx, vy, vz = _dot(wo, t), _dot(wo, b), _dot(wo, n)
        Vh = np.stack([alpha * vx, alpha * vy, np.maximum(vz, 1e-9)], axis=-1)
        Vh = normalize(Vh)
        lensq = Vh[..., 0] ** 2 + Vh[..., 1] ** 2
        inv = np.where(lensq > 0, 1.0 / np.sqrt(np.where(lensq > 0, lensq, 1.0)), 0.0)
        T1 = np.where((lensq > 0)[..., None], np.stack([-Vh[..., 1] * inv, Vh[..., 0] * inv, np.zeros_like(inv)], -1),
                      np.array([1.0, 0.0, 0.0]))
        T2 = np.cross(Vh, T1)
        r = np.sqrt(u1)
        t1, t2 = r * np.cos(phi), r * np.sin(phi)
        sv = 0.5 * (1.0 + Vh[..., 2])
        t2 = (1.0 - sv) * np.sqrt(np.maximum(1.0 - t1 * t1, 0.0)) + sv * t2
        Nh = t1[..., None] * T1 + t2[..., None] * T2 + np.sqrt(np.maximum(0.0, 1.0 - t1 * t1 - t2 * t2))[..., None] * Vh
        Ne = normalize(np.stack([alpha * Nh[..., 0], alpha * Nh[..., 1], np.maximum(Nh[..., 2], 0.0)], axis=-1))
        h = Ne[..., 0:1] * t + Ne[..., 1:2] * b + Ne[..., 2:3] * n
        ch = Ne[..., 2]
    else:
        raise AppFusionError(f"lobe_sample: cannot sample lobe {lobe!r}")
    oh = _dot(wo, h)
    wi = 2.0 * oh[..., None] * h - wo
    ci, co = _dot(wi, n), _dot(wo, n)
    ok = (ci > COS_EPS) & (co > COS_EPS) & (oh > COS_EPS)
    ci_, co_ = np.where(ok, ci, 1.0), np.where(ok, co, 1.0)
    if lobe == "ward":
        # f cos_i / p = sqrt(cos_i / cos_o) (w_o . h) cos^3(theta_h)
        w = np.sqrt(ci_ / co_) * oh * ch ** 3
    else:
        # visible normals: f cos_i / p = G1(w_i)
        w = ggx_g1(alpha, ci_)
    return wi, np.where(ok, w, 0.0)


def lobe_pdf(lobe: str, alpha, wi, wo, n) -> np.ndarray:
    """Density (1/sr) with which :func:`lobe_sample` draws ``wi``."""
    h = normalize(wi + wo)
    ch = np.clip(_dot(h, n), 0.0, 1.0)
    oh = np.abs(_dot(wo, h))
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    if lobe == "ward":
        c = np.maximum(ch, 1e-12)
        tan2 = (1.0 - c * c) / (c * c)
        ph = np.exp(-tan2 / a2) / (np.pi * a2 * c ** 3)
        return np.where((ch > COS_EPS) & (oh > COS_EPS), ph / (4.0 * np.maximum(oh, 1e-12)), 0.0)
    # visible normals: p(w_i) = G1(w_o) D(h) / (4 cos_o)
    co = _dot(wo, n)
    ok = (ch > COS_EPS) & (oh > COS_EPS) & (co > COS_EPS)
    return np.where(ok, ggx_g1(alpha, np.where(ok, co, 1.0)) * ggx_d(alpha, ch) / (4.0 * np.where(ok, co, 1.0)), 0.0)


def lobe_fcos_bound(lobe: str, alpha, cos_h_max, cos_o) -> np.ndarray:
    """Upper bound of ``f(w_i, w_o) cos_i`` over all ``w_i`` whose half vector makes an angle with the
    normal of at least ``acos(cos_h_max)``; used to skip emitters whose contribution is negligible.

    Ward: ``f cos_i = exp(-tan^2/a^2) sqrt(cos_i / cos_o) / (4 pi a^2) <= exp(-tan^2/a^2) / (4 pi a^2 sqrt(cos_o))``.
    GGX: ``f cos_i = D G G / (4 cos_o) <= D(theta_h) / (4 cos_o)`` (D decreases with theta_h).
    """
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    co = np.maximum(cos_o, 1e-3)
    c = np.clip(cos_h_max, 1e-6, 1.0)
    if lobe == "ward":
        tan2 = (1.0 - c * c) / (c * c)
        return np.exp(-tan2 / a2) / (4.0 * np.pi * a2 * np.sqrt(co))
    return ggx_d(alpha, c) / (4.0 * co)


def ward_albedo_normal(alpha: float) -> float:
    """Directional albedo ``int f(w_i, n) cos_i dw_i`` of the Ward lobe viewed along the normal.

    With ``w_o = n`` the half vector at angle ``theta`` gives ``theta_i = 2 theta``; substituting
    ``t = tan(theta)`` the albedo is the 1-D integral
    ``(2 / alpha^2) int_0^1 exp(-t^2/alpha^2) sqrt((1 - t^2)/(1 + t^2)) t / (1 + t^2)^2 dt``,
    evaluated here with adaptive Gauss-Kronrod quadrature (``scipy.integrate.quad``). It tends to 1 as
    alpha -> 0 (the lobe's normalisation).
    """
    from scipy.integrate import quad

    a2 = alpha * alpha

    def g(t):
        return np.exp(-t * t / a2) * np.sqrt((1 - t * t) / (1 + t * t)) * t / (1 + t * t) ** 2

    pts = [min(alpha * k, 0.999) for k in (0.5, 1, 2, 4)]
    val, _ = quad(g, 0.0, 1.0, points=sorted(set(pts)), limit=200, epsabs=1e-13, epsrel=1e-11)
    return 2.0 / a2 * val


_ALBEDO_CACHE: dict = {}


def albedo_table(lobe: str, alpha: float, n: int = 129, strata: int = 96):
    """Directional albedo ``A(cos_o) = int f(w_i, w_o) cos_i dw_i`` of a lobe on a grid of ``n`` view
    cosines in [0, 1] (the renderer's control variate, see ``render._lobe_background``).

    Each entry is a stratified importance-sampling estimate with ``strata``^2 samples (relative error
    about 2e-4, tested against quadrature); cached per (lobe, alpha). Returns (cos_o grid (n,), A (n,)).
    """
    key = (lobe, float(alpha), n, strata)
    if key not in _ALBEDO_CACHE:
        rng = np.random.default_rng(12345)
        co = np.linspace(0.0, 1.0, n)
        co[0] = 1e-3
        k = strata
        i, j = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
        A = np.zeros(n)
        nrm = np.array([0.0, 0.0, 1.0])
        for t, c in enumerate(co):
            wo = np.array([np.sqrt(max(1 - c * c, 0.0)), 0.0, c])
            u1 = ((i.ravel() + rng.random(k * k)) / k)
            u2 = ((j.ravel() + rng.random(k * k)) / k)
            _, w = lobe_sample(lobe, alpha, np.broadcast_to(wo, (k * k, 3)), np.broadcast_to(nrm, (k * k, 3)), u1, u2)
            A[t] = w.mean()
        co[0] = 0.0
        _ALBEDO_CACHE[key] = (co, A)
    return _ALBEDO_CACHE[key]


def albedo_at(lobe: str, alpha: float, cos_o: np.ndarray) -> np.ndarray:
    """Directional albedo of a lobe at view cosines ``cos_o`` (linear interpolation of :func:`albedo_table`)."""
    co, A = albedo_table(lobe, alpha)
    return np.interp(np.clip(cos_o, 0.0, 1.0), co, A)


# -- reference materials ------------------------------------------------------------------------

@dataclass
class MaterialSet:
    """The materials of one object, indexed by the per-vertex ``material_id``."""

    materials: list[Material] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.materials)

    def __getitem__(self, i: int) -> Material:
        return self.materials[i]

    def arrays(self):
        """Per-material arrays: rho_s (M, 3), alpha (M,), lobe code (M,) (0 ward, 1 ggx, 2 mirror), ir_rho_s (M,)."""
        rs = np.array([m.rho_s for m in self.materials], dtype=np.float64).reshape(-1, 3)
        al = np.array([m.alpha for m in self.materials], dtype=np.float64)
        code = np.array([LOBES.index(m.lobe) for m in self.materials], dtype=np.int64)
        ir = np.array([m.ir_rho_s for m in self.materials], dtype=np.float64)
        return rs, al, code, ir

    def to_json(self) -> list[dict]:
        return [dict(id=i, **m.to_json()) for i, m in enumerate(self.materials)]
