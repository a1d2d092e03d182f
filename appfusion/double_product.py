"""Haar-wavelet double-product tables of the RGB pass (paper §5.3, Eq. 4-5; Ng, Ramamoorthi & Hanrahan 2003).

The RGB pass needs, per calibrated pixel ``L`` of a point with normal ``n`` seen from ``w_o``,

    L = rho_d D(n) + rho_s S(n, alpha, w_o)                                    (Eq. 5)
    S(n, alpha, w_o) = int L_i(w) f(alpha; w, w_o) (n.w)+ dw                   (double-product term)

with ``f`` the isotropic Ward lobe (``appfusion.brdf``; GGX: see the last section) and ``L_i`` the
environment map, a (2, N, N, 3) radiance array in the world (marker) frame (``appfusion.octahedral``). ``D`` is in
:mod:`appfusion.diffuse_term`. This module precomputes S so that a sample costs 16 table reads.

The double product, in the mirror frame
---------------------------------------
The paper writes S as the integral of the local lighting times a BRDF slice and evaluates it as a
dot product of Haar coefficients. Both functions are expressed here on one square of directions
around the **mirror direction** ``r = 2 (n.w_o) n - w_o`` instead of around the normal:

* lighting ``L~_r(w') = L_i(F_r^T w') dw'``: the environment pre-rotated into the frame ``F_r`` of a
  tabulated mirror direction (a :class:`~appfusion.diffuse_term.NodeGrid` over the whole sphere),
  the texel solid angle folded in;
* BRDF slice (kernel) ``K_{alpha,theta,beta}(w') = exp(-tan^2 theta_h / alpha^2) sqrt((n'.w')+) / (4 pi alpha^2)``
  with ``n' = (sin theta cos beta, sin theta sin beta, cos theta)`` the normal in that frame and
  ``w'_o`` the mirror image of the pole about it, so that ``f(alpha; w', w'_o) (n'.w')+ = K / sqrt(cos theta)``
  (``theta`` is theta_o; ``1/sqrt(cos theta_o)`` is applied after interpolation).

Then ``S sqrt(cos theta_o) = <L~_r, K> = sum_j c_j(L~_r) c_j(K)`` over orthonormal 2-D Haar
coefficients (``pywt.wavedec2(..., "haar", mode="periodization")``; Parseval).

Why the mirror frame: in the normal frame (the paper's) the lobe *moves* across the square as
``w'_o`` changes, so interpolating between tabulated ``w'_o`` blends two displaced lobes. With exact
node values, that interpolation alone left 4.8 % RMS error in S at 2 x 33^2 normals x 33^2 view
directions and 1.4 % at 2 x 65^2 x 65^2 (a 214 MB float16 table). In the mirror frame the lobe stays
at the pole and only changes shape with (theta, beta); by isotropy those two numbers are all the
kernel depends on. Its shape interpolates to ~0.3 % on a 10 x 12 polar grid, and the fast variation
(the environment blurred by the lobe) is resolved by the r grid, whose spacing follows the lobe
width: ``m_r ~ 10 / alpha`` nodes per side, in [33, 97].

The square is an octahedral map of the polar cap ``theta <= cap(alpha) = clip(5 alpha + 0.1, 0.35, 2.2)``
rad around r (octahedral polar angle scaled by ``cap / (pi/2)``; the lobe is < 1e-4 of its peak
outside), 32 x 32 texels (64 x 64 for caps wider than 1 rad, whose 32^2 texels would be coarser than
a 2 x 128^2 map's). The lighting is read with bicubic interpolation (bilinear flattens the map's
peaks: -0.45 % on S of alpha = 0.06); kernel texels are averaged over 4 x 4 sub-samples.

Tables, approximations, sizes
-----------------------------
Per alpha in use (a cluster's alpha is known before the RGB pass starts, so tables are built only for
those alphas -- "skip what the scene doesn't need"; an alpha between two built ones interpolates
linearly in log alpha):

* **BRDF tables** (:class:`SparseCoeffs`): Haar coefficients of the ``n_theta x n_beta`` kernel
  slices, the largest ``brdf_keep`` (default 512 of 1024) per slice, int16 with a per-slice scale.
  Non-linear approximation, 0.0 % change of S at 512, +0.1 % RMS at 256.
* **Lighting**: for every r node the pre-rotated environment. The paper stores it (145 MB of Haar
  coefficients); here it is streamed in blocks of nodes and consumed at once, so nothing of it is
  kept. With ``light_keep=K`` each node's lighting is Haar-transformed and cut to its K largest
  coefficients (NRH03's non-linear approximation; K = 128 of 1024 adds 0.2 % RMS error and costs
  ~1.6 s of CPU per sharp alpha for the transform and selection). Since it is not stored, the default
  keeps all coefficients, and Parseval lets the product be taken against the BRDF coefficients
  brought back to texels: one BLAS product per block of nodes does all the sparse dot products.
* **S table** (:class:`AlphaTable`): ``S sqrt(cos theta_o)`` at every (r node, theta node, beta
  node), RGB, float16 with a per-table scale: ``2 m_r^2 x n_theta x n_beta x 6`` bytes
  (alpha = 0.06: 21.0 MB; alpha = 0.35: 7.5 MB, with the default kernel grids; session 36).

A sample is then 16 reads (4 r nodes, bilinear on the octahedral node grid, x 2 theta x 2 beta). Samples
with ``n.w_o`` below ``cos(theta_max)`` (default theta_max = 80 degrees) are grazing: S = 0, and
:meth:`DoubleProductTables.valid` says so.

Measured on a 2 x 128^2 office environment (``tests/test_double_product.py``, ``appfusion bench
--stage rgb``): S within 0.9 % RMS of brute-force quadrature over the map's texels for alpha in
{0.06, 0.1, 0.2, 0.35} (r grid ~0.35 %, kernel grid ~0.3 %, texel discretisation ~0.15 %), 58.5 MB
for those four alphas (as ``docs/rgb-pass.md`` has it, with the build time); a GGX table adds 14-28 MB.

GGX tables (the model ladder's third rung)
------------------------------------------
Tables are keyed by ``(lobe, alpha)``: ``DoubleProductTables(env, ward_alphas, lobes={"ggx": [...]})``
or ``add_alpha(alpha, "ggx")``, and ``S(normals, w_o, alpha, lobe)`` with ``lobe`` a name or one per
sample (log-alpha interpolation only between tables of one lobe). The GGX kernel
(:func:`ggx_kernel_slices`, ``appfusion.brdf.ggx``: Trowbridge-Reitz D, separable Smith G1, no
Fresnel) is ``K = D G1(n'.w') G1(cos t) / (4 sqrt(cos t))``, the same ``S sqrt(cos theta_o)``
convention and lookup as Ward's. What differs is the long tail (the projected D has the CDF
``tan^2 theta_h / (alpha^2 + tan^2 theta_h)``: 10 % beyond ``tan theta_h = 3 alpha``):

* **cap** from the energy it holds (:func:`default_cap`): 0.25 % of the lobe outside at normal view,
  ``2 atan(alpha sqrt(399))`` clipped to [0.35, 2.9] rad (alpha 0.08 / 0.15 / 0.3: 2.02 / 2.50 / 2.81
  rad). Measured by brute force with and without the cap (2 x 128^2 map, views to 78 degrees), the lost
  tail leaves 0.17 / 0.15 / 0.03 % RMS in S; Ward's cap rule (2.2 rad at most) would leave up to 1.8 %.
* **stretched square** (:class:`CapSquare` ``stretch``, :func:`default_stretch`): 64^2 texels whose
  polar angle grows as ``cap (q^u - 1) / (q - 1)``, ``q`` chosen so that pole texels are 0.25 alpha
  (the peak sampled as finely as a Ward lobe's); the smooth tail gets texels ``q`` times wider
  (alpha 0.08 / 0.15 / 0.3: q = 7.3 / 3.8 / 1.4, rim texels 0.15 / 0.14 / 0.10 rad). Kernel texel
  averages over 2 x 2 sub-samples; the lighting is read at texel centres as for Ward.
* **r grid** as a Ward lobe of 0.8 alpha (GGX's half maximum is at ``tan theta_h = 0.64 alpha``,
  Ward's at 0.83 alpha), at least 49 nodes per side: 97 / 83 / 49.
* **kernel grid**: Ward's rule with 4 more beta nodes (the tail reaches far from the pole, where a
  rotation by the beta spacing moves it most): 0.15 has 1.1 % RMS error on (12, 17), 0.8 % on (12, 21).

Measured (``tests/test_double_product.py``, 2 x 128^2 office map, 300 samples, eager tables): S within
0.53 / 0.80 / 0.64 % RMS of brute-force quadrature at alpha 0.08 / 0.15 / 0.3 (0.58 % over all; bias
-0.35 / -0.15 / +0.03 %); the kernel grid is the largest part (0.15 on (12, 32): 0.5 %). Sizes 27.7 /
21.8 / 13.8 MB, eager builds 7.4 / 4.9 / 1.8 s (2 shared cores, noisy: 0.15 also measured 2.2 s);
lazy tables compute only the nodes the samples need. Ward 0.15 + GGX 0.15 (one cluster on both rungs):
34 MB with D, 9 s eager build. The four Ward alphas above with GGX 0.15 take 80 MB (the Ward four alone
58 MB with these defaults), over the 64 MB budget.

A scan holds only the tables its last colour sweep reads (:meth:`DoubleProductTables.keep_only`, session
37): each IR refit adds tables for new alphas, and the `ggx-two-material` scan ended with five (90.6 MB:
the first sweep's Ward 0.092, the split's GGX 0.075 and Ward 0.343, the final GGX 0.078 and Ward 0.329),
now with the last two (34.8 MB).
"""

from __future__ import annotations

import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
import pywt

from . import octahedral as octa
from .brdf import LOBES, ggx_d, ggx_g1
from .diffuse_term import DiffuseTable, NodeGrid, envmap_check
from .errors import AppFusionError

__all__ = ["signed_frames", "CapSquare", "ward_kernel_slices", "ggx_kernel_slices", "kernel_slices", "check_lobe",
           "haar2", "ihaar2", "SparseCoeffs", "AlphaTable", "DoubleProductTables", "mirror_params", "default_r_res",
           "default_cap", "default_stretch", "default_kernel_grid", "truncate"]


def signed_frames(d: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """Orthonormal frames (..., 3, 3) with rows (t, b, d) for unit ``d``, on a chosen branch.

    The branchless construction of Duff et al. (2017) with the branch sign ``s`` given instead of
    ``sign(d_z)``: ``s = +1`` is smooth on ``d_z > -1``, ``s = -1`` on ``d_z < 1``. Using +1 on face 0
    and -1 on face 1 of a :class:`NodeGrid` (including its equator nodes) makes the frame a smooth
    function of the direction within each face, which is what interpolation between nodes needs.
    ``local = frame @ world``.
    """
    d = np.asarray(d, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)
    a = -1.0 / (s + d[..., 2])
    b = d[..., 0] * d[..., 1] * a
    t = np.stack([1 + s * d[..., 0] ** 2 * a, s * b * np.ones_like(a), -s * d[..., 0]], axis=-1)
    bt = np.stack([b, s + d[..., 1] ** 2 * a, -d[..., 1]], axis=-1)
    return np.stack([t, bt, d], axis=-2)


# -- the local square over a polar cap ---------------------------------------------------------

class CapSquare:
    """An R x R texel-centred square of directions over the cap ``theta <= cap`` around +z.

    Texel (i, j) has the octahedral hemisphere direction of ``appfusion.octahedral`` with its polar
    angle scaled by ``s = cap / (pi/2)`` (azimuth kept); ``cap = pi/2`` is the plain octahedral
    hemisphere square. Solid angles integrate the exact Jacobian
    ``dw = s sin(theta) / sin(theta_oct) dw_oct`` over ``sub x sub`` midpoints per texel.

    Parameters
    ----------
    res : int
        Texels per side, a power of two (the Haar transform needs it).
    cap : float
        Cap half-angle, rad, in (0, pi).
    sub : int
        Sub-samples per side and texel (solid angles and kernel averages).
    stretch : float
        Radial stretch ``q >= 1`` (GGX squares): the polar angle is
        ``theta = cap (q^u - 1) / (q - 1)`` of ``u = theta_oct / (pi/2)``, so texels are ``q`` times
        wider (radially) at the rim than at the pole. 1 (default) is the linear scaling above.
    """

    def __init__(self, res: int, cap: float, sub: int = 4, stretch: float = 1.0):
        if res < 2 or res & (res - 1):
            raise AppFusionError(f"CapSquare: resolution must be a power of two >= 2, got {res}")
        if not 0 < cap < math.pi:
            raise AppFusionError(f"CapSquare: cap half-angle must be in (0, pi) rad, got {cap}")
        if not (np.isfinite(stretch) and stretch >= 1.0):
            raise AppFusionError(f"CapSquare: stretch must be >= 1, got {stretch}")
        self.res, self.cap, self.sub = int(res), float(cap), int(sub)
        self.stretch = float(stretch)
        self.scale = self.cap / (math.pi / 2)
        self.directions = self._dirs(octa.texel_centers(res))                    # (R, R, 3)
        m = res * sub
        c = (np.arange(m) + 0.5) * (2.0 / m) - 1.0
        u, v = np.meshgrid(c, c)
        uv = np.stack([u, v], axis=-1)
        d_sub = self._dirs(uv)
        x, y = 0.5 * (u + v), 0.5 * (u - v)
        z = 1.0 - np.abs(x) - np.abs(y)
        j_oct = 0.5 * (x * x + y * y + z * z) ** -1.5 * (2.0 / m) ** 2        # dw_oct per sub-sample
        th_oct = np.arccos(np.clip(octa.hemi_decode(uv)[..., 2], -1, 1))
        if self.stretch == 1.0:
            th = th_oct * self.scale
            ratio = np.where(th_oct > 1e-9, np.sin(th) / np.maximum(np.sin(th_oct), 1e-300), self.scale)
            w_sub = j_oct * self.scale * ratio
        else:                                   # dw = g'(t) sin(g(t)) / sin(t) dw_oct, theta = g(t)
            th, dth = self._polar(th_oct)
            ratio = np.where(th_oct > 1e-9, np.sin(th) / np.maximum(np.sin(th_oct), 1e-300), dth)
            w_sub = j_oct * dth * ratio
        #: (R, R, sub*sub, 3) sub-sample directions and (R, R, sub*sub) their solid angles
        self.sub_directions = d_sub.reshape(res, sub, res, sub, 3).transpose(0, 2, 1, 3, 4).reshape(res, res, sub * sub, 3)
        self.sub_weights = w_sub.reshape(res, sub, res, sub).transpose(0, 2, 1, 3).reshape(res, res, sub * sub)
        #: (R, R) texel solid angles, sr
        self.solid_angles = self.sub_weights.sum(axis=-1)

    def _polar(self, th_oct: np.ndarray):
        """Polar angle ``theta = g(theta_oct)`` and ``g'(theta_oct)`` of the (stretched) mapping."""
        if self.stretch == 1.0:
            return th_oct * self.scale, np.full_like(th_oct, self.scale)
        q = self.stretch
        u = th_oct / (math.pi / 2)
        k = self.cap / (q - 1.0)
        e = np.power(q, u)
        return k * (e - 1.0), k * math.log(q) * e / (math.pi / 2)

    @property
    def pole_step(self) -> float:
        """Radial texel size at the pole, rad (``cap / (res/2)`` unstretched)."""
        return float(self._polar(np.array([0.0]))[1][0]) * (math.pi / 2) / (self.res / 2)

    def _dirs(self, uv: np.ndarray) -> np.ndarray:
        d = octa.hemi_decode(uv)
        th = self._polar(np.arccos(np.clip(d[..., 2], -1, 1)))[0]
        rho = np.hypot(d[..., 0], d[..., 1])
        k = np.where(rho > 1e-12, np.sin(th) / np.maximum(rho, 1e-300), 0.0)
        return np.stack([d[..., 0] * k, d[..., 1] * k, np.cos(th)], axis=-1)


@lru_cache(maxsize=32)
def _cap_square(res: int, cap: float, sub: int, stretch: float = 1.0) -> CapSquare:
    return CapSquare(res, cap, sub, stretch)


#: GGX: fraction of the lobe's energy (normal view) left outside the cap (see :func:`default_cap`)
GGX_TAIL = 0.0025
#: GGX: largest cap half-angle, rad (the hemisphere of n reaches pi/2 + theta_o from r)
GGX_CAP_MAX = 2.9
#: GGX: radial texel size at the pole of the stretched square, in units of alpha
GGX_POLE_STEP = 0.25
#: GGX: sub-samples per side averaging the kernel over a texel
GGX_SUB = 2


def default_cap(alpha: float, lobe: str = "ward") -> float:
    """Cap half-angle (rad) of the mirror-frame square for roughness ``alpha`` and ``lobe``.

    Ward: ``clip(5 a + 0.1, 0.35, 2.2)``. The Ward lobe ``exp(-tan^2 theta_h / alpha^2)`` is below
    1e-4 of its peak beyond ``theta_h = 3 alpha``, i.e. ~6 alpha from the mirror direction in the plane
    of incidence (less across it); with 32^2 texels that keeps texels at ~0.4 alpha near the pole.

    GGX: chosen from the energy the cap holds. The projected GGX distribution has the CDF
    ``tan^2 theta_h / (alpha^2 + tan^2 theta_h)`` (10 % of it beyond ``tan theta_h = 3 alpha``); at
    normal view a cap ``c`` around the mirror direction holds ``theta_h <= c / 2``, so the cap leaving
    the fraction ``GGX_TAIL`` (0.25 %) outside is ``2 atan(alpha sqrt(1 / GGX_TAIL - 1))``, clipped to
    [0.35, ``GGX_CAP_MAX`` = 2.9] rad (alpha 0.08: 2.02, 0.15: 2.50, 0.3: 2.81 rad). The S error the
    lost tail leaves (brute-force quadrature with and without the cap, 2 x 128^2 office map, views up
    to 78 degrees) is 0.17 / 0.15 / 0.03 % RMS at alpha 0.08 / 0.15 / 0.3 (a bias of the same size,
    low); caps of 2.2 rad for all would leave 0.10 / 0.45 / 1.8 %.
    """
    if check_lobe(lobe, "default_cap") == "ggx":
        c = 2.0 * math.atan(alpha * math.sqrt(1.0 / GGX_TAIL - 1.0))
        return float(np.clip(c, 0.35, GGX_CAP_MAX))
    return float(np.clip(5.0 * alpha + 0.1, 0.35, 2.2))


def default_stretch(alpha: float, cap: float, res: int, lobe: str = "ward") -> float:
    """Radial stretch ``q`` of the mirror-frame square (:class:`CapSquare`) for ``lobe``.

    Ward: 1 (linear). GGX: the smallest ``q >= 1`` whose pole texel is ``GGX_POLE_STEP * alpha`` rad
    (``cap ln q / (q - 1) / (res / 2)``): the peak is sampled as finely as a Ward lobe's while the
    long tail, where the kernel is smooth, gets texels up to ``q`` times wider.
    """
    if check_lobe(lobe, "default_stretch") == "ward":
        return 1.0
    want = GGX_POLE_STEP * alpha * (res / 2) / cap             # = ln q / (q - 1), decreasing in q
    if want >= 1.0:
        return 1.0
    lo, hi = 1.0 + 1e-9, 1e6
    for _ in range(100):                                       # bisection on log q
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if math.log(mid) / (mid - 1.0) > want else (lo, mid)
    return float(round(hi, 4))


def default_r_res(alpha: float, scale: float = 10.0, lobe: str = "ward") -> int:
    """Nodes per side of the mirror-direction grid for ``alpha``: odd, ``~scale / alpha``, in [33, 97].

    GGX's peak is narrower than Ward's of the same alpha (half maximum at ``tan theta_h = 0.64 alpha``
    against ``0.83 alpha``): its grid is that of a Ward lobe of ``GGX_R_ALPHA * alpha``.
    """
    lo = 33
    if check_lobe(lobe, "default_r_res") == "ggx":
        alpha, lo = GGX_R_ALPHA * alpha, GGX_R_MIN
    m = int(np.clip(round(scale / alpha), lo, 97))
    return m if m % 2 else m + 1


#: GGX: the r grid of a GGX lobe is that of a Ward lobe this many times narrower (see default_r_res)
GGX_R_ALPHA = 0.8
#: GGX: fewest r nodes per side (the cuspy peak blurs the map less than a Ward lobe of equal width)
GGX_R_MIN = 49


def default_kernel_grid(alpha: float, lobe: str = "ward") -> tuple[int, int]:
    """(n_theta, n_beta) of the kernel grid for ``alpha``: broad lobes change shape faster with the normal.

    ``(clip(10 + 16 alpha, 12, 16), clip(12 + 32 alpha, 16, 24))``; with exact mirror directions the
    kernel interpolation error of S is 0.44 % RMS at alpha = 0.08 on (12, 16) (0.63 % on (10, 12)).
    GGX: the same n_theta and ``GGX_EXTRA_BETA`` (4) more beta nodes. Its long tail reaches far from
    the pole, where rotating the kernel by the beta spacing moves it most: on (12, 17) the kernel
    interpolation left 1.1 % RMS error of S at alpha = 0.15, 0.55 % on (10, 24), 0.5 % on (12, 32).
    """
    nt, nb = int(np.clip(round(10 + 16 * alpha), 12, 16)), int(np.clip(round(12 + 32 * alpha), 16, 24))
    if check_lobe(lobe, "default_kernel_grid") == "ggx":
        nb += GGX_EXTRA_BETA
    return nt, nb


#: GGX: beta nodes added to the Ward rule of :func:`default_kernel_grid`
GGX_EXTRA_BETA = 4


def truncate(c: np.ndarray, k: int) -> np.ndarray:
    """Non-linear approximation of coefficient vectors: keep the ``k`` largest of each, zero the rest.

    Parameters
    ----------
    c : (B, n, C) float32
        B vectors of n coefficients with C channels; ranked by the summed |value| over channels
        (one index set shared by the channels, as a stored table would share it).
    k : int
        Coefficients kept per vector (all when ``k >= n``).

    Returns
    -------
    (B, n, C) float32
        ``c`` with the dropped coefficients set to 0 (in place when possible).
    """
    B, n, C = c.shape
    if k >= n:
        return c
    mag = np.abs(c).sum(axis=-1)
    thr = np.partition(mag, n - k, axis=1)[:, n - k]
    c *= (mag >= thr[:, None])[..., None]
    return c


# -- Ward kernel slices in the mirror frame -------------------------------------------------------

def ward_kernel_slices(alpha: float, square: CapSquare, thetas: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """Texel averages of the mirror-frame Ward kernel, shape (n_theta, n_beta, R, R), float64.

    ``K(w') = exp(-tan^2(theta_h) / alpha^2) sqrt((n'.w')+) / (4 pi alpha^2)`` with the normal
    ``n' = (sin t cos b, sin t sin b, cos t)``, view ``w'_o = 2 cos(t) n' - z`` (so the mirror direction
    is the pole) and ``h = w' + w'_o``; ``f(alpha; w', w'_o) (n'.w')+ = K / sqrt(cos t)`` (paper Eq. 1,
    original isotropic Ward). Averaged over each texel's sub-samples, weighted by solid angle.
    """
    d = square.sub_directions                                 # (R, R, s, 3)
    wts = square.sub_weights / square.solid_angles[..., None]
    out = np.empty((len(thetas), len(betas), square.res, square.res))
    a2 = alpha * alpha
    for i, t in enumerate(thetas):
        for j, b in enumerate(betas):
            n = np.array([math.sin(t) * math.cos(b), math.sin(t) * math.sin(b), math.cos(t)])
            wo = 2.0 * math.cos(t) * n - np.array([0.0, 0.0, 1.0])
            ci = d @ n
            co = math.cos(t)
            h2 = 2.0 + 2.0 * (d @ wo)                         # |w' + w'_o|^2
            nh = ci + co                                      # n'.(w' + w'_o)
            ok = (ci > 0) & (nh > 0)
            tan2 = np.where(ok, h2 / np.where(ok, nh * nh, 1.0) - 1.0, np.inf)
            k = np.where(ok, np.exp(-np.maximum(tan2, 0.0) / a2) * np.sqrt(np.maximum(ci, 0.0)), 0.0)
            out[i, j] = (k * wts).sum(axis=-1) / (4 * math.pi * a2)
    return out


def ggx_kernel_slices(alpha: float, square: CapSquare, thetas: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """Texel averages of the mirror-frame GGX kernel, shape (n_theta, n_beta, R, R), float64.

    ``K(w') = D(theta_h) G1(n'.w') G1(cos t) / (4 sqrt(cos t))`` (``appfusion.brdf.ggx``: GGX /
    Trowbridge-Reitz ``D``, separable Smith ``G1``, no Fresnel), with ``n'``, ``w'_o`` and ``h`` as in
    :func:`ward_kernel_slices`, so that again ``f(alpha; w', w'_o) (n'.w')+ = K / sqrt(cos t)``.
    ``D`` and ``G1`` are :func:`appfusion.brdf.ggx_d` and :func:`appfusion.brdf.ggx_g1`, with
    ``cos theta_h = n'.h / |h|``. Averaged over each texel's sub-samples.
    """
    d = square.sub_directions                                 # (R, R, s, 3)
    wts = square.sub_weights / square.solid_angles[..., None]
    out = np.empty((len(thetas), len(betas), square.res, square.res))
    for i, t in enumerate(thetas):
        co = math.cos(t)
        g_o = float(ggx_g1(alpha, co)) / (4.0 * math.sqrt(co))
        for j, b in enumerate(betas):
            n = np.array([math.sin(t) * math.cos(b), math.sin(t) * math.sin(b), co])
            wo = 2.0 * co * n - np.array([0.0, 0.0, 1.0])
            ci = d @ n
            h2 = 2.0 + 2.0 * (d @ wo)                         # |w' + w'_o|^2
            nh = ci + co                                      # n'.(w' + w'_o)
            ok = (ci > 0) & (nh > 0) & (h2 > 1e-12)
            ch = np.where(ok, nh / np.sqrt(np.where(ok, h2, 1.0)), 1.0)
            k = np.where(ok, ggx_d(alpha, ch) * ggx_g1(alpha, np.where(ok, ci, 1.0)), 0.0) * g_o
            out[i, j] = (k * wts).sum(axis=-1)
    return out


_KERNELS = {"ward": ward_kernel_slices, "ggx": ggx_kernel_slices}


def check_lobe(lobe, where: str = "DoubleProductTables") -> str:
    """The lobe name ``lobe`` if the tables know it (``appfusion.brdf.LOBES``), else an AppFusionError."""
    if not isinstance(lobe, str) or lobe not in LOBES:
        raise AppFusionError(f"{where}: unknown specular lobe {lobe!r}; S tables exist for {', '.join(LOBES)}")
    return lobe


def kernel_slices(lobe: str, alpha: float, square: CapSquare, thetas: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """Mirror-frame kernel slices (n_theta, n_beta, R, R) of the lobe named ``lobe`` (``"ward"``:
    :func:`ward_kernel_slices`, ``"ggx"``: :func:`ggx_kernel_slices`)."""
    return _KERNELS[check_lobe(lobe, "kernel_slices")](alpha, square, thetas, betas)


# -- 2-D Haar transform and sparse coefficient vectors ------------------------------------------

def haar2(x: np.ndarray) -> np.ndarray:
    """Orthonormal 2-D Haar coefficients of squares ``x`` (B, R, R[, C]) over axes (1, 2), same shape.

    Full decomposition (``pywt.wavedec2(x, "haar", mode="periodization")``), laid out by
    ``pywt.coeffs_to_array``: the scaling coefficient first, then details coarse to fine.
    """
    c = pywt.wavedec2(x, "haar", mode="periodization", axes=(1, 2))
    arr, _ = pywt.coeffs_to_array(c, axes=(1, 2))
    return arr


def ihaar2(c: np.ndarray) -> np.ndarray:
    """Inverse of :func:`haar2`."""
    proto = pywt.wavedec2(np.zeros(c.shape, c.dtype), "haar", mode="periodization", axes=(1, 2))
    _, slices = pywt.coeffs_to_array(proto, axes=(1, 2))
    coeffs = pywt.array_to_coeffs(c, slices, output_format="wavedec2")
    return pywt.waverec2(coeffs, "haar", mode="periodization", axes=(1, 2))


@dataclass
class SparseCoeffs:
    """The ``k`` largest coefficients of each of B vectors, int16-quantised (non-linear approximation).

    Attributes
    ----------
    idx : (B, k) uint16 (uint32 for vectors longer than 65536)
        Coefficient indices, ascending per row.
    q : (B, k, C) int16
        Quantised values: ``value = q * scale``.
    scale : (B, C) float32
        Per-vector, per-channel step (max |value| / 32767).
    length : int
        Length of the dense vectors.
    """

    idx: np.ndarray
    q: np.ndarray
    scale: np.ndarray
    length: int

    @classmethod
    def from_dense(cls, c: np.ndarray, k: int) -> "SparseCoeffs":
        """Keep the ``k`` largest of each row of ``c`` (B, n[, C]) by summed |value| over channels."""
        c = np.asarray(c, dtype=np.float32)
        if c.ndim == 2:
            c = c[..., None]
        B, n, C = c.shape
        k = int(min(max(k, 1), n))
        mag = np.abs(c).sum(axis=-1)
        if k < n:
            idx = np.argpartition(mag, n - k, axis=1)[:, n - k:]
            idx.sort(axis=1)
        else:
            idx = np.broadcast_to(np.arange(n), (B, n)).copy()
        vals = np.take_along_axis(c, idx[..., None], axis=1)
        scale = np.abs(vals).max(axis=1) / 32767.0
        scale = np.where(scale > 0, scale, 1.0).astype(np.float32)
        q = np.rint(vals / scale[:, None, :]).astype(np.int16)
        return cls(idx.astype(np.uint16 if n <= 65536 else np.uint32), q, scale, n)

    def values(self) -> np.ndarray:
        """Dequantised kept values, (B, k, C) float32."""
        return self.q.astype(np.float32) * self.scale[:, None, :]

    def dense(self) -> np.ndarray:
        """Dense (B, n, C) float32 vectors with the dropped coefficients set to 0."""
        B, k, C = self.q.shape
        out = np.zeros((B, self.length, C), np.float32)
        np.put_along_axis(out, self.idx.astype(np.int64)[..., None], self.values(), axis=1)
        return out

    @property
    def nbytes(self) -> int:
        return int(self.idx.nbytes + self.q.nbytes + self.scale.nbytes)


# -- environment sampling ---------------------------------------------------------------------

class _EnvSampler:
    """Interpolation of a (2, N, N, 3) map in arbitrary directions with cv2.remap on a padded atlas.

    Each face is padded with ``PAD`` texels continued across the equator from the other face (the
    octahedral fold: beyond an edge of one square lies the other square reflected across that edge),
    so interpolation is exact on both sides of the horizon. Bilinear interpolation flattens the
    peaks of a sampled map (with a 2 x 128^2 map it lowers S of a sharp lobe, alpha = 0.06, by
    ~0.45 %), so the default is bicubic (OpenCV's ``INTER_CUBIC``, Catmull-Rom). Bicubic rings below
    zero beside small bright lights; those lobes are kept (clamping them adds energy: +4 % bias of S
    against texel-centre quadrature on a 2 x 32^2 map, where plain bicubic is within 1.6 % RMS and
    bilinear 4.7 %); S itself is clamped at 0 in the tables. ``upsample=2`` resamples the map once to
    2N (bicubic, clamped) and reads that bilinearly.
    """

    PAD = 2

    def __init__(self, env: np.ndarray, interpolation: int = cv2.INTER_CUBIC, upsample: int = 1):
        env = np.asarray(env, dtype=np.float32)
        if upsample > 1:
            n2 = env.shape[1] * upsample
            fine = _EnvSampler(env, cv2.INTER_CUBIC, upsample=1)(octa.sphere_directions(n2))
            env = np.maximum(fine, 0.0)
        n = env.shape[1]
        self.n = n
        self.interpolation = interpolation
        p = self.PAD
        faces = []
        for f in (0, 1):
            a, o = env[f], env[1 - f]
            big = np.zeros((n + 2 * p, n + 2 * p, 3), np.float32)
            big[p:p + n, p:p + n] = a
            for k in range(p):
                big[p:p + n, p + n + k] = o[:, n - 1 - k]
                big[p:p + n, p - 1 - k] = o[:, k]
                big[p + n + k, p:p + n] = o[n - 1 - k, :]
                big[p - 1 - k, p:p + n] = o[k, :]
                for l in range(p):
                    big[p - 1 - k, p - 1 - l] = o[k, l]
                    big[p - 1 - k, p + n + l] = o[k, n - 1 - l]
                    big[p + n + k, p - 1 - l] = o[n - 1 - k, l]
                    big[p + n + k, p + n + l] = o[n - 1 - k, n - 1 - l]
            faces.append(big)
        self.atlas = np.ascontiguousarray(np.concatenate(faces, axis=1), dtype=np.float32)

    def __call__(self, d: np.ndarray) -> np.ndarray:
        """Radiance (..., 3) float32 in directions ``d`` (..., 3) (need not be unit; float32 math)."""
        d = np.asarray(d, dtype=np.float32)
        return self.components(d[..., 0], d[..., 1], d[..., 2])

    def components(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Radiance (..., 3) float32 in directions given by their components (arrays of one shape)."""
        shp = np.shape(x)
        x = np.ascontiguousarray(x, dtype=np.float32).reshape(-1)
        y = np.ascontiguousarray(y, dtype=np.float32).reshape(-1)
        z = np.ascontiguousarray(z, dtype=np.float32).reshape(-1)
        n = self.n
        s = np.abs(x)
        s += np.abs(y)
        s += np.abs(z)
        np.maximum(s, np.float32(1e-30), out=s)
        half = np.float32(0.5 * n)
        np.divide(half, s, out=s)                                # half / (|x| + |y| + |z|)
        px, py = x * s, y * s
        off = np.float32(self.PAD - 0.5 + 0.5 * n)
        mx = px + py
        mx += off
        mx += (z < 0) * np.float32(n + 2 * self.PAD)
        my = px - py
        my += off
        out = np.empty((len(x), 3), np.float32)
        step = 32 * 32000                                        # remap maps: (rows < 32767, 32) blocks
        for s0 in range(0, len(x), step):
            k = min(step, len(x) - s0)
            cols = 32 if k % 32 == 0 else 1
            out[s0:s0 + k] = cv2.remap(self.atlas, mx[s0:s0 + k].reshape(-1, cols), my[s0:s0 + k].reshape(-1, cols),
                                       self.interpolation, borderMode=cv2.BORDER_REPLICATE).reshape(k, 3)
        return out.reshape(shp + (3,))


# -- S tables -----------------------------------------------------------------------------------

def mirror_params(normals: np.ndarray, w_o: np.ndarray):
    """Mirror direction and the normal's polar coordinates in the mirror frame.

    Parameters
    ----------
    normals, w_o : (..., 3) ndarray
        Unit normals and unit view directions (from the surface towards the camera).

    Returns
    -------
    r : (..., 3) float64
        ``2 (n.w_o) n - w_o``.
    cos_o : (...) float64
        ``n.w_o`` (= cos theta, the normal's angle from r).
    beta : (...) float64
        Azimuth of n in the frame :func:`signed_frames` (r, +1 if r_z >= 0 else -1), in [0, 2 pi).
    """
    n = np.asarray(normals, dtype=np.float64)
    wo = np.asarray(w_o, dtype=np.float64)
    co = np.einsum("...i,...i->...", n, wo)
    r = 2.0 * co[..., None] * n - wo
    r /= np.linalg.norm(r, axis=-1, keepdims=True)
    s = np.where(r[..., 2] >= 0, 1.0, -1.0)
    F = signed_frames(r, s)
    x = np.einsum("...i,...i->...", F[..., 0, :], n)
    y = np.einsum("...i,...i->...", F[..., 1, :], n)
    beta = np.mod(np.arctan2(y, x), 2 * np.pi)
    return r, co, beta


def _blas_one_thread():
    """Context manager: BLAS limited to one thread while inside (no-op without threadpoolctl)."""
    from .fusion import blas_threads

    return blas_threads(1)


class _NodeBuilder:
    """Everything needed to compute S at any subset of one alpha's mirror nodes (see
    :meth:`DoubleProductTables.add_alpha`); a lazy table keeps it until all its nodes are built."""

    def __init__(self, nodes, signs, dirs32, dw, Bd, res, ls, keep, sampler, chunk, threads):
        self.nodes, self.signs = nodes, signs
        self.dx, self.dy, self.dz = (np.ascontiguousarray(dirs32[:, i]) for i in range(3))
        self.dw, self.Bd = dw, Bd
        self.res, self.ls, self.keep = res, ls, keep
        self.R2 = res * res
        self.sampler, self.chunk, self.threads = sampler, chunk, threads
        self.timing = np.zeros(4)          # sample, haar, keep, dot (CPU seconds summed over blocks)

    def _block(self, idx: np.ndarray) -> np.ndarray:
        """S sqrt(cos theta_o) (c, n_slices, 3) float32 >= 0 at nodes ``idx`` (c,)."""
        c, R2, ls, res, keep = len(idx), self.R2, self.ls, self.res, self.keep
        ta = time.perf_counter()
        F = signed_frames(self.nodes[idx], self.signs[idx]).astype(np.float32)     # (c, 3, 3)
        # world directions F^T w' of the block's texels, one component plane at a time
        comp = [self.dx[None, :] * F[:, 0, i, None] + self.dy[None, :] * F[:, 1, i, None]
                + self.dz[None, :] * F[:, 2, i, None] for i in range(3)]
        L = self.sampler.components(*comp)                     # (c, R^2 ls^2, 3): env at F^T w'
        L *= self.dw[None, :, None]
        if ls > 1:
            L = L.reshape(c, R2, ls * ls, 3).sum(axis=2)
        L = np.ascontiguousarray(L.reshape(c, R2, 3).transpose(0, 2, 1))      # (c, 3, R^2)
        tb = tc = time.perf_counter()
        if keep < R2:
            # non-linear approximation of each node's lighting (NRH03): Haar, keep the largest
            C = haar2(L.reshape(c * 3, res, res)).reshape(c, 3, R2)
            tc = time.perf_counter()
            mag = np.abs(C).sum(axis=1)                                           # (c, R^2)
            thr = np.partition(mag, R2 - keep, axis=1)[:, R2 - keep]
            C *= (mag >= thr[:, None])[:, None, :]
            L = C
        td = time.perf_counter()
        # the double products of all (node, slice) pairs of the block at once (dropped lighting
        # coefficients are zeros): one BLAS product
        v = (L.reshape(c * 3, R2) @ self.Bd).reshape(c, 3, -1).transpose(0, 2, 1)
        # S >= 0; the kept Haar coefficients of a slice can ring slightly below 0 where the lighting is dark
        v = np.maximum(v, 0.0)
        te = time.perf_counter()
        self.timing += (tb - ta, tc - tb, td - tc, te - td)
        return v

    def compute(self, idx: np.ndarray, out: np.ndarray, scale: float) -> None:
        """Compute nodes ``idx`` into ``out`` (N, n_slices, 3) float16, in units of ``scale``, in blocks
        of ``chunk`` nodes, ``threads`` blocks at a time."""
        inv = np.float32(1.0 / scale)

        def block(s0: int) -> None:
            sel = idx[s0:s0 + self.chunk]
            v = self._block(sel)
            v *= inv
            np.minimum(v, np.float32(65000.0), out=v)            # float16 range (scale has 4x headroom)
            out[sel] = v.astype(np.float16)

        starts = range(0, len(idx), self.chunk)
        if self.threads > 1 and len(starts) > 1:
            with ThreadPoolExecutor(self.threads) as ex:
                list(ex.map(block, starts))
        else:
            for s0 in starts:
                block(s0)


_F16_TO_F32 = np.arange(65536, dtype=np.uint16).view(np.float16).astype(np.float32)   # every float16, exactly


@dataclass
class AlphaTable:
    """The S table of one roughness: ``S sqrt(cos theta_o)`` on (r node, theta node, beta node), RGB.

    Attributes
    ----------
    alpha : float
        Roughness of the lobe.
    grid : NodeGrid
        Grid of mirror directions.
    cap : float
        Half-angle of the mirror-frame square, rad.
    thetas, betas : ndarray
        Kernel nodes: theta in [0, theta_max] (n_theta, inclusive), beta in [0, 2 pi) (n_beta, periodic).
    values : (2 m^2, n_theta, n_beta, 3) float16
        The table, in units of ``scale`` (so that bright environments do not overflow float16).
    brdf : SparseCoeffs
        The BRDF tables: kept Haar coefficients of the n_theta * n_beta kernel slices.
    scale : float
        Unit of ``values``: an upper bound of ``S sqrt(cos theta_o)`` (largest radiance times the
        largest kernel integral) / 16384.
    stats : dict
        Build timings and sizes (``nodes_built``: mirror nodes computed so far).
    built : (2 m^2,) bool or None
        Lazy tables: which mirror nodes are computed (None: all are).
    lobe : str
        The specular lobe (``"ward"`` or ``"ggx"``, ``appfusion.brdf.LOBES``).
    """

    alpha: float
    grid: NodeGrid
    cap: float
    thetas: np.ndarray
    betas: np.ndarray
    values: np.ndarray
    brdf: SparseCoeffs
    scale: float = 1.0
    stats: dict = field(default_factory=dict)
    built: np.ndarray | None = None
    builder: _NodeBuilder | None = field(default=None, repr=False)
    lobe: str = "ward"

    def __post_init__(self):
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        return int(self.values.nbytes + self.brdf.nbytes)

    @property
    def complete(self) -> bool:
        """All mirror nodes computed."""
        return self.builder is None

    def ensure(self, node_idx: np.ndarray) -> int:
        """Compute the mirror nodes among ``node_idx`` (flat indices) not built yet; returns how many.

        "Unused environment-map directions are never computed" (issue #11): a lazy table computes a
        mirror node the first time a sample's lookup needs it.
        """
        if self.builder is None:
            return 0
        idx = np.asarray(node_idx, dtype=np.int64).ravel()
        if not len(idx):
            return 0
        with self._lock:
            if self.builder is None:
                return 0
            miss = np.zeros(len(self.built), bool)
            miss[idx] = True
            miss &= ~self.built
            need = np.flatnonzero(miss)
            if not len(need):
                return 0
            t0 = time.perf_counter()
            # one BLAS thread: a lazy build runs between frames, and OpenBLAS's idle threads would spin
            # on the cores the next frames need (measured: 50 ms instead of 27 ms frames after a build)
            with _blas_one_thread():
                self.builder.compute(need, self.values.reshape(len(self.built), -1, 3), self.scale)
            self.built[need] = True
            st = self.stats
            st["nodes_built"] = int(self.built.sum())
            st["node_build_s"] = st.get("node_build_s", 0.0) + time.perf_counter() - t0
            st["sample_s"], st["haar_s"], st["keep_s"], st["dot_s"] = (float(x) for x in self.builder.timing)
            if self.built.all():
                self.builder, self.built = None, None       # complete: drop the build inputs
            return len(need)

    def build_all(self) -> int:
        """Compute every mirror node not built yet (a lazy table becomes complete)."""
        return self.ensure(np.arange(self.grid.size)) if self.builder is not None else 0

    def lookup(self, normals: np.ndarray, w_o: np.ndarray) -> np.ndarray:
        """Interpolated ``S`` (P, 3) float32 for unit normals and view directions (P, 3); 0 where grazing.

        Computes :func:`mirror_params` inline in float32, then interpolates bilinearly over the 4 r
        nodes around ``r`` and bilinearly over (theta, beta): one gather of 16 table rows per sample,
        then multiplies by ``scale / sqrt(cos theta_o)``.
        """
        n = np.asarray(normals, dtype=np.float32).reshape(-1, 3)
        wo = np.asarray(w_o, dtype=np.float32).reshape(-1, 3)
        nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
        co = nx * wo[:, 0] + ny * wo[:, 1] + nz * wo[:, 2]
        c2 = co + co
        rx, ry, rz = c2 * nx - wo[:, 0], c2 * ny - wo[:, 1], c2 * nz - wo[:, 2]
        # normal's azimuth in the signed Duff frame of r (see signed_frames)
        neg = rz < 0
        sg = np.where(neg, np.float32(-1.0), np.float32(1.0))
        den = sg + rz
        a = np.float32(-1.0) / np.where(np.abs(den) > 1e-12, den, np.float32(1e-12))
        bb = rx * ry * a
        x = nx * (1 + sg * rx * rx * a) + ny * (sg * bb) - nz * (sg * rx)
        y = nx * bb + ny * (sg + ry * ry * a) - nz * ry
        # r on the vertex-centred octahedral grid (face of r)
        m = self.grid.m
        inv = np.float32(1.0) / (np.abs(rx) + np.abs(ry) + np.abs(rz))
        px, py = rx * inv, ry * inv
        half = np.float32(0.5 * (m - 1))
        fu = (px + py + 1) * half
        fv = (px - py + 1) * half
        iu = np.clip(fu.astype(np.int32), 0, m - 2)
        iv = np.clip(fv.astype(np.int32), 0, m - 2)
        au = np.clip(fu - iu, 0, 1)
        av = np.clip(fv - iv, 0, 1)
        base = neg.astype(np.int32) * (m * m) + iv * m + iu                      # (P,)
        ok = co >= np.float32(math.cos(self.thetas[-1]) - 1e-6)
        if self.builder is not None:                  # lazy table: compute the nodes these samples need
            b = base[ok].astype(np.int64)
            self.ensure(np.concatenate([b, b + 1, b + m, b + m + 1]))
        # kernel grid
        nt, nb = len(self.thetas), len(self.betas)
        ft = np.arccos(np.clip(co, -1.0, 1.0)) * np.float32((nt - 1) / self.thetas[-1])
        t0 = np.clip(ft.astype(np.int32), 0, nt - 2)
        at = np.clip(ft - t0, 0, 1)
        fb = np.arctan2(y, x) * np.float32(nb / (2 * np.pi))
        fb = np.where(fb < 0, fb + nb, fb)
        b0 = np.minimum(fb.astype(np.int32), nb - 1)
        ab = np.clip(fb - b0, 0, 1)
        b1 = np.where(b0 == nb - 1, 0, b0 + 1)
        ntb = nt * nb
        # corners built sample-last ((4, P), (4, 4, P): numpy's inner loops run over P, not over 4),
        # then made (P, 16) for the gather: 3x faster than broadcasting (P, 4, 1) against (P, 1, 4)
        kofs = np.stack([t0 * nb + b0, t0 * nb + b1, (t0 + 1) * nb + b0, (t0 + 1) * nb + b1])
        kw = np.stack([(1 - at) * (1 - ab), (1 - at) * ab, at * (1 - ab), at * ab])
        rofs = np.stack([base, base + 1, base + m, base + m + 1]) * ntb
        rw = np.stack([(1 - au) * (1 - av), au * (1 - av), (1 - au) * av, au * av])
        k16 = np.ascontiguousarray((rofs[:, None, :] + kofs[None, :, :]).reshape(16, -1).T)
        w16 = np.ascontiguousarray((rw[:, None, :] * kw[None, :, :]).reshape(16, -1).T)[:, None, :]
        # float16 -> float32 through a 65536-entry table (L2-resident): 25 % faster than astype
        vals = _F16_TO_F32.take(self.values.view(np.uint16).reshape(-1, 3).take(k16, axis=0))   # (P, 16, 3)
        acc = np.matmul(w16, vals)[:, 0]
        fac = np.where(ok, np.float32(self.scale) / np.sqrt(np.where(ok, co, np.float32(1.0))), np.float32(0.0))
        return acc * fac[:, None]


class DoubleProductTables:
    """D and S tables of one environment map for a set of roughnesses of each lobe (paper §5.3).

    S tables are keyed by ``(lobe, alpha)``: the paper's Ward lobe (``"ward"``, the default
    everywhere) and the model ladder's GGX rung (``"ggx"``, ``appfusion.brdf.ggx``). :attr:`tables`
    and :attr:`alphas` keep their Ward-only meaning (dict keyed by alpha, sorted alphas);
    :attr:`all_tables`, :meth:`table` and :meth:`lobe_alphas` see every lobe.

    Parameters
    ----------
    env : (2, N, N, 3) ndarray
        Environment radiance in the world (marker) frame, ``appfusion.octahedral`` layout.
    alphas : sequence of float
        Ward roughnesses to build S tables for (the clusters' alphas). :meth:`S` at another alpha
        between two built ones (of the same lobe) interpolates linearly in log alpha, which is
        accurate only for close alphas (within ~10 %); use :meth:`add_alpha` for an exact table.
    lobes : mapping of str to sequence of float, optional
        Further tables per lobe, e.g. ``{"ggx": [0.15]}`` (``"ward"`` entries join ``alphas``); an
        unknown lobe name is an AppFusionError. Tables can also be added later with
        ``add_alpha(alpha, lobe)``.
    res : int
        Texels per side of the mirror-frame square (power of two; default 32). Ward squares of caps
        wider than two map texels per square texel and all GGX squares use ``2 res``.
    kernel_grid : (int, int), optional
        Kernel grid (n_theta, n_beta): theta nodes over [0, theta_max] and beta nodes over [0, 2 pi);
        default :func:`default_kernel_grid` per alpha and lobe.
    theta_max_deg : float
        Largest view angle to the normal tabulated, degrees (samples beyond are grazing: S = 0, invalid).
    light_keep : int or None
        Haar coefficients of the pre-rotated lighting kept per mirror node (of ``res^2``; scaled for
        64^2 squares): NRH03's non-linear approximation. None (default) keeps all: the lighting is
        streamed, not stored, so truncating it saves no memory (see the module notes).
    brdf_keep : int or None
        Haar coefficients kept per BRDF slice (of ``res^2``, scaled likewise); None keeps all.
    r_res : int or callable, optional
        Nodes per side of the mirror-direction grid, or ``alpha -> int`` (called with the alpha of
        either lobe); default :func:`default_r_res` of the alpha and lobe.
    d_res : int
        Nodes per side of the D table's normal grid.
    light_sub : int, optional
        Sub-samples per side integrating the lighting over a texel (default 1: the texel centre).
    chunk : int
        Mirror nodes per vectorised block (memory ~ chunk x res^2 x 40 bytes).
    threads : int
        Blocks built concurrently (numpy, PyWavelets and OpenCV release the GIL in their loops).
    lazy : bool
        "Unused environment-map directions are never computed" (issue #11): S at a mirror node is
        computed the first time a lookup needs it (default), so a cluster whose normals and views reach
        only part of the sphere of mirror directions (a label on one side of an object) pays only for
        that part; the values are identical to an eager build. False builds every node up front.
    """

    def __init__(self, env: np.ndarray, alphas, *, lobes=None, res: int = 32,
                 kernel_grid: tuple[int, int] | None = None,
                 theta_max_deg: float = 80.0, light_keep: int | None = None, brdf_keep: int | None = 512,
                 r_res=None, d_res: int = 65, light_sub: int | None = None, chunk: int = 512, threads: int = 2,
                 lazy: bool = True):
        t0 = time.perf_counter()
        self.env = envmap_check(env, "DoubleProductTables")
        want = [("ward", alphas)] + ([] if lobes is None else list(dict(lobes).items()))
        keys = []
        for lb, als in want:
            check_lobe(lb)
            al = np.atleast_1d(np.asarray(als, dtype=np.float64)).ravel()
            if not np.isfinite(al).all() or (al <= 0).any():    # none: D only (a diffuse-only scene)
                what = "alphas" if lb == "ward" and als is alphas else f"{lb} alphas"
                raise AppFusionError(f"DoubleProductTables: {what} must be positive finite roughnesses, got {list(al)}")
            keys += [(lb, float(a)) for a in np.unique(al)]
        if not 5.0 <= theta_max_deg <= 89.0:
            raise AppFusionError(f"DoubleProductTables: theta_max_deg must be in [5, 89], got {theta_max_deg}")
        if kernel_grid is not None and (kernel_grid[0] < 2 or kernel_grid[1] < 3):
            raise AppFusionError(f"DoubleProductTables: kernel grid needs >= 2 theta and >= 3 beta nodes, got {kernel_grid}")
        if res < 4 or res & (res - 1):
            raise AppFusionError(f"DoubleProductTables: res must be a power of two >= 4, got {res}")
        self.res = int(res)
        self._kgrid = None if kernel_grid is None else (int(kernel_grid[0]), int(kernel_grid[1]))
        self.theta_max = math.radians(theta_max_deg)
        self.light_keep, self.brdf_keep, self.chunk = light_keep, brdf_keep, int(chunk)
        self.threads = max(1, int(threads))
        self.light_sub = light_sub
        self.lazy = bool(lazy)
        self._r_res = r_res
        self._sampler = _EnvSampler(self.env)
        td = time.perf_counter()
        self.diffuse = DiffuseTable(self.env, m=d_res)
        self.stats = {"diffuse_s": time.perf_counter() - td}
        #: every S table, keyed by (lobe, alpha), in build order
        self.all_tables: dict[tuple[str, float], AlphaTable] = {}
        for lb, a in dict.fromkeys(keys):
            self.add_alpha(a, lb)
        self.build_seconds = time.perf_counter() - t0

    # -- building
    def r_res_for(self, alpha: float, lobe: str = "ward") -> int:
        """Nodes per side of the mirror grid of ``(lobe, alpha)`` (the ``r_res`` argument, or :func:`default_r_res`)."""
        if self._r_res is None:
            return default_r_res(alpha, lobe=lobe)
        return int(self._r_res(alpha)) if callable(self._r_res) else int(self._r_res)

    def square_for(self, alpha: float, lobe: str = "ward") -> tuple[float, int, int, float]:
        """Mirror-frame square of ``(lobe, alpha)``: ``(cap rad, res, kernel sub-samples, stretch)``.

        Ward: cap :func:`default_cap`; ``2 res`` texels when ``res`` would make them wider than two of
        the map's (2 x 128^2: caps over ~1.2 rad; the lighting and the kernel alias otherwise: 1.1 % vs
        0.8 % RMS error of S at alpha = 0.2, 0.35), kernel averages over 4 x 4 sub-samples (2 x 2 on
        64^2 squares: rough lobes are smooth there); linear. GGX: cap :func:`default_cap`, ``2 res``
        texels, 2 x 2 sub-samples, stretched by :func:`default_stretch` (pole texels of
        ``GGX_POLE_STEP * alpha``).
        """
        cap = default_cap(alpha, lobe)
        if lobe == "ggx":
            res = 2 * self.res
            return cap, res, GGX_SUB, default_stretch(alpha, cap, res, lobe)
        texel = math.sqrt(4 * math.pi / (2 * self.env.shape[1] ** 2))
        res = self.res if cap / (self.res / 2) <= 2 * texel else 2 * self.res
        return cap, res, 4 if res <= self.res else 2, 1.0

    def add_alpha(self, alpha: float, lobe: str = "ward") -> AlphaTable:
        """Build (or return the existing) S table of ``alpha`` for the lobe named ``lobe``.

        Parameters
        ----------
        alpha : float
            Roughness (> 0, dimensionless).
        lobe : str
            ``"ward"`` (default) or ``"ggx"`` (``appfusion.brdf.LOBES``); others are an AppFusionError.

        Returns
        -------
        AlphaTable
            The table (lazy unless the tables were built with ``lazy=False``).
        """
        check_lobe(lobe)
        alpha = float(alpha)
        if (lobe, alpha) in self.all_tables:
            return self.all_tables[(lobe, alpha)]
        if not (np.isfinite(alpha) and alpha > 0):
            raise AppFusionError(f"DoubleProductTables: alpha must be a positive roughness, got {alpha}")
        t0 = time.perf_counter()
        cap, res, ksub, stretch = self.square_for(alpha, lobe)
        sq = _cap_square(res, round(cap, 6), ksub, stretch)
        # lighting: texel integrals of the environment over ls x ls sub-samples (default 1)
        ls = max(1, int(self.light_sub or 1))
        lsq = sq if ls == 1 else _cap_square(res * ls, round(cap, 6), 4, stretch)
        nt, nb = default_kernel_grid(alpha, lobe) if self._kgrid is None else self._kgrid
        thetas = np.linspace(0.0, self.theta_max, nt)
        betas = np.arange(nb) * (2 * np.pi / nb)
        kern = kernel_slices(lobe, alpha, sq, thetas, betas).reshape(-1, res, res)
        R2 = res * res
        scale_keep = R2 / (self.res * self.res)
        brdf = SparseCoeffs.from_dense(haar2(kern.astype(np.float32)).reshape(len(kern), -1),
                                       int(self.brdf_keep * scale_keep) if self.brdf_keep else R2)
        Bd = np.ascontiguousarray(brdf.dense()[..., 0].T)              # (R^2, n_slices) BRDF coefficients
        keep = int(self.light_keep * scale_keep) if self.light_keep else R2
        if keep >= R2:
            # exact lighting: <Haar(L), c_K> = <L, iHaar(c_K)> (Parseval), so the kept BRDF coefficients
            # are brought back to texels once and the lighting is never transformed
            Bd = np.ascontiguousarray(ihaar2(brdf.dense()[..., 0].reshape(-1, res, res)).reshape(len(kern), R2).T,
                                      dtype=np.float32)
        tk = time.perf_counter()
        grid = NodeGrid(self.r_res_for(alpha, lobe))
        nodes = grid.directions.reshape(-1, 3)
        signs = grid.signs.reshape(-1)
        # texel (or sub-texel) centres and solid angles, sub-texels of one texel contiguous
        dw = lsq.solid_angles.reshape(res, ls, res, ls).transpose(0, 2, 1, 3).reshape(-1).astype(np.float32)
        dirs32 = lsq.directions.reshape(res, ls, res, ls, 3).transpose(0, 2, 1, 3, 4).reshape(-1, 3).astype(np.float32)
        # unit of the float16 table: an upper bound of S sqrt(cos) = sum_texels L dw K (largest radiance,
        # 1.25 for bicubic overshoot, times the largest kernel integral), so that a lazy table knows it
        # before computing any node; values keep float16's relative precision below it
        k_texel = Bd if keep >= R2 else ihaar2(brdf.dense()[..., 0].reshape(-1, res, res)).reshape(len(kern), R2).T
        k_int = float((np.abs(k_texel) * dw.reshape(R2, ls * ls).sum(axis=1)[:, None]).sum(axis=0).max())
        bound = 1.25 * float(np.max(self.env)) * k_int
        scale = bound / 16384.0 if bound > 0 else 1.0
        builder = _NodeBuilder(nodes, signs, dirs32, dw, Bd, res, ls, keep, self._sampler, self.chunk, self.threads)
        values = np.zeros((len(nodes), nt, nb, 3), np.float16)
        tab = AlphaTable(alpha, grid, cap, thetas, betas, values, brdf, scale=scale,
                         built=np.zeros(len(nodes), bool), builder=builder, lobe=lobe)
        tab.stats = {"lobe": lobe, "kernel_s": tk - t0, "r_nodes": len(nodes), "r_res": grid.m, "cap_rad": cap,
                     "res": res, "stretch": stretch, "light_sub": ls, "light_keep": keep, "n_theta": nt, "n_beta": nb,
                     "mb": tab.nbytes / 2**20,
                     "light_mb_if_stored": len(nodes) * (keep * 8 + 12) / 2**20, "lazy": self.lazy, "nodes_built": 0,
                     "node_build_s": 0.0, "sample_s": 0.0, "haar_s": 0.0, "keep_s": 0.0, "dot_s": 0.0}
        if not self.lazy:
            tab.build_all()
        tab.stats["seconds"] = time.perf_counter() - t0
        self.all_tables[(lobe, alpha)] = tab
        return tab

    # -- queries
    @property
    def tables(self) -> dict[float, AlphaTable]:
        """The Ward tables keyed by alpha (a new dict; :attr:`all_tables` has every lobe's)."""
        return {a: t for (lb, a), t in self.all_tables.items() if lb == "ward"}

    def lobe_alphas(self, lobe: str = "ward") -> list[float]:
        """Sorted alphas of the built tables of ``lobe``."""
        check_lobe(lobe)
        return sorted(a for lb, a in self.all_tables if lb == lobe)

    @property
    def alphas(self) -> list[float]:
        """Sorted alphas of the Ward tables (:meth:`lobe_alphas` for another lobe)."""
        return self.lobe_alphas("ward")

    def table(self, alpha: float, lobe: str = "ward") -> AlphaTable:
        """The built table of ``(lobe, alpha)`` (KeyError-free: an AppFusionError when there is none)."""
        key = (check_lobe(lobe), float(alpha))
        if key not in self.all_tables:
            raise AppFusionError(f"DoubleProductTables: no {lobe} table at alpha {alpha:g}; add_alpha({alpha:g}, {lobe!r}) first")
        return self.all_tables[key]

    def D(self, normals: np.ndarray) -> np.ndarray:
        """Diffuse term D(n) (..., 3) at unit normals (..., 3)."""
        return self.diffuse(normals)

    def _bracket(self, alpha: float, lobe: str = "ward"):
        al = self.lobe_alphas(lobe)
        name = "" if lobe == "ward" else f"{lobe} "
        if not al:
            raise AppFusionError(f"DoubleProductTables: no {name}S table built (alpha {alpha:g} asked for); "
                                 "add_alpha first")
        if (lobe, alpha) in self.all_tables:
            return [(self.all_tables[(lobe, alpha)], 1.0)]
        if alpha < al[0] or alpha > al[-1]:
            raise AppFusionError(f"DoubleProductTables: alpha {alpha:g} is outside the built {name}range "
                                 f"[{al[0]:g}, {al[-1]:g}]; add_alpha({alpha:g}" + (")" if lobe == "ward" else f", {lobe!r})")
                                 + " first")
        i = int(np.searchsorted(al, alpha))
        a0, a1 = al[i - 1], al[i]
        t = (math.log(alpha) - math.log(a0)) / (math.log(a1) - math.log(a0))
        return [(self.all_tables[(lobe, a0)], 1.0 - t), (self.all_tables[(lobe, a1)], t)]

    def S(self, normals: np.ndarray, w_o: np.ndarray, alpha, lobe="ward") -> np.ndarray:
        """Double-product term S(n, alpha, w_o) (P, 3), vectorised over samples (paper §5.3, Eq. 4-5).

        Parameters
        ----------
        normals, w_o : (P, 3) ndarray
            Unit normals and unit directions towards the camera, world frame.
        alpha : float or (P,) ndarray
            Roughness per sample (each value built, or between two built ones of its lobe).
        lobe : str or (P,) array of str
            Specular lobe per sample, ``"ward"`` (default) or ``"ggx"``. Samples are grouped by
            (lobe, alpha); an alpha between two built ones interpolates in log alpha between the two
            tables of its own lobe.

        Returns
        -------
        (P, 3) float32
            S, in the environment's radiance units (``f`` in 1/sr times radiance times sr); 0 where
            ``n.w_o < cos(theta_max)`` (grazing or back-facing; see :meth:`valid`).
        """
        n = np.asarray(normals, dtype=np.float32).reshape(-1, 3)
        wo = np.asarray(w_o, dtype=np.float32).reshape(-1, 3)
        if n.shape != wo.shape:
            raise AppFusionError(f"DoubleProductTables.S: normals {n.shape} and w_o {wo.shape} differ in shape")
        a = np.broadcast_to(np.asarray(alpha, dtype=np.float64), (len(n),))
        lb = np.asarray(lobe)
        if lb.ndim not in (0, 1) or (lb.ndim == 1 and lb.shape != (len(n),)):
            raise AppFusionError(f"DoubleProductTables.S: lobe must be a name or {len(n)} names, got shape {lb.shape}")
        names = [check_lobe(str(x)) for x in np.unique(lb)]
        if len(names) == 1:
            return self._S_of_lobe(n, wo, a, names[0])
        out = np.zeros((len(n), 3), np.float32)
        for name in names:
            rows = np.flatnonzero(lb == name)
            out[rows] = self._S_of_lobe(n[rows], wo[rows], a[rows], name)
        return out

    def _S_of_lobe(self, n: np.ndarray, wo: np.ndarray, a: np.ndarray, lobe: str) -> np.ndarray:
        """:meth:`S` of samples that share one lobe, (P, 3) float32: grouped by alpha, each group read
        from its table or blended between the two of its lobe around it."""
        out = np.zeros((len(n), 3), np.float32)
        uniq = np.unique(a)
        for av in uniq:
            sel = slice(None) if len(uniq) == 1 else np.flatnonzero(a == av)
            for tab, wt in self._bracket(float(av), lobe):
                v = tab.lookup(n[sel], wo[sel])
                out[sel] += v if wt == 1.0 else np.float32(wt) * v
        return out

    def valid(self, normals: np.ndarray, w_o: np.ndarray) -> np.ndarray:
        """True where a sample is within the tabulated view angles (``n.w_o >= cos(theta_max)``)."""
        co = np.einsum("...i,...i->...", np.asarray(normals, float), np.asarray(w_o, float))
        return co >= math.cos(self.theta_max)

    def keep_only(self, keys) -> float:
        """Release every S table whose ``(lobe, alpha)`` is not among ``keys``; returns the MB released.

        A scan's colour sweeps read the tables of the lobes fitted at the time, and each refit of the
        IR lobes adds tables for the new alphas (the first sweep's, the split's, the final clusters');
        the earlier ones are not read again. The ``ggx-two-material`` scan ended holding five tables
        (90.6 MB with D), of which its last sweep read two (34.8 MB with D; session 37).
        """
        keep = {(check_lobe(lb), float(a)) for lb, a in keys}
        drop = [k for k in self.all_tables if k not in keep]
        freed = sum(self.all_tables[k].nbytes for k in drop)
        for k in drop:
            del self.all_tables[k]
        return freed / 2**20

    @property
    def nbytes(self) -> int:
        """Bytes of all tables kept (D table, S tables and BRDF tables of every lobe)."""
        return int(self.diffuse.nbytes + sum(t.nbytes for t in self.all_tables.values()))

    def report(self) -> dict:
        """Sizes and timings: ``mb``, ``build_s`` (construction), ``diffuse_s``, ``node_build_s`` (mirror nodes
        computed so far, lazily or not), ``nodes_built`` / ``nodes_total`` over every lobe's tables;
        per-table ``stats`` under ``alphas`` (Ward, keyed ``str(alpha)`` as before) and ``lobes``
        (``{lobe: {str(alpha): stats}}``, every lobe)."""
        tabs = self.all_tables.values()
        lobes: dict[str, dict] = {}
        for (lb, a), t in self.all_tables.items():
            lobes.setdefault(lb, {})[str(a)] = t.stats
        return {"mb": self.nbytes / 2**20, "build_s": self.build_seconds, "diffuse_s": self.stats["diffuse_s"],
                "node_build_s": sum(t.stats.get("node_build_s", 0.0) for t in tabs),
                "nodes_built": sum(t.stats.get("nodes_built", 0) for t in tabs),
                "nodes_total": sum(t.grid.size for t in tabs), "lazy": self.lazy,
                "alphas": {str(a): t.stats for a, t in self.tables.items()}, "lobes": lobes}
