"""Ward (or GGX) roughness from an HBSAB: the last step of BRDF fusion (paper §5.1).

The paper treats every texel whose weight exceeds a threshold as a BRDF sample with both directions
set to the texel's half vector, takes the diffuse part as the minimum over those samples, and fits a
Ward lobe to the specular remainder by non-linear least squares [NDM05]. This module does the same,
with the model of a texel made exact instead of evaluating the lobe at the texel centre:

Texel model
-----------
A texel holds the weighted mean of the samples that fell in it, not the BRDF at its centre. For a
sharp lobe (``alpha = 0.05`` is ~3 degrees wide, a 32 x 32 texel ~5.6 degrees) the difference biases
``alpha`` by ~8 % (centre half vector) or ~10 % (mean ``tan^2 theta_h``). The buffer therefore also
keeps, per texel, the mean Legendre moments ``m_k = <P_k(a, b)>`` of the samples' positions ``(a, b)``
inside the texel (:mod:`appfusion.hbsab`). Projecting the sample density on the texel onto the
quadratic Legendre polynomials gives

    <f>_texel ~= J_0 + sum_k m_k J_k,     J_0 = E_u[f],  J_k = E_u[f P_k] / E_u[P_k^2],

with ``E_u`` the mean over the texel square, computed by ``Q x Q`` Gauss-Legendre quadrature of the
retro-reflection Ward lobe ``f = ward_retro(alpha, cos theta_h)`` (:func:`appfusion.brdf.ward_retro`,
``w_i = w_o = h``). The error is the product of the lobe's and the density's non-quadratic parts: in
the paper's §5.1 simulation (1 M pairs, N = 32) the largest relative alpha error over 0.05 .. 0.75 is
1.2e-4 (paper: 2.6e-3); first-order moments alone leave 1.8e-3 at ``alpha = 0.05``.

The second bias is the retro-reflection assumption itself: the true lobe divides by
``sqrt(cos theta_i cos theta_o)``, the retro one by ``cos^2 theta_h``; with the Kinect's 7.5 cm baseline the
ratio ``g = cos theta_h / sqrt(cos theta_i cos theta_o)`` differs from 1 by up to ~0.5 %, which biased
``alpha`` by -0.2 %. The buffer keeps the mean ``g`` per texel and the model multiplies by it:

    v_t = d + rho_s * g_t * (J_0 + sum_k m_kt J_k)(alpha)

Clipped highlights (censored texels)
------------------------------------
A Kinect's 10-bit IR clips a glossy highlight: on the synthetic two-material scan 99 % of the samples
within 3 degrees of the lobe's axis and half of those at 3-6 degrees are saturated. Leaving those texels
out (below) leaves only the flanks, and a lobe far too sharp and far too high fits them (alpha 0.02,
rho_s 1e9 instead of 0.06 / 0.15: the model is free wherever texels were dropped). When the emitter's
intensity distribution is known (``emitter=(k, theta, shift)``, the shifted-Gamma model of §6 from the
IR profile; ``emitter="flat"`` for an even flood light), every texel is used instead and its value is
modelled as the mean of *clipped* samples: with ``Z = (t + shift) / (k theta + shift)``,
``t ~ Gamma(k, theta)`` the emitter's multiplicative factor (mean 1), a texel of true mean ``mu`` whose
samples clip at ``c`` holds

    E[min(mu Z, c)] = mu (k theta P(k + 1, a / theta) + shift P(k, a / theta)) / (k theta + shift)
                      + c (1 - P(k, a / theta)),        a = c (k theta + shift) / mu - shift,

(``P`` the regularised lower incomplete gamma function), a Tobit-style censored mean. ``c`` is the
clip level in reflectance units, the median value of the texels whose samples are (almost) all
saturated. The partially saturated texels then constrain the peak. This is used when at least one
texel is saturated beyond ``max_saturated``; otherwise the fit is the plain one below.

When the emitter's *pattern* was divided out of every sample (``emitter=("pattern", k, theta, shift)``;
:mod:`calibration.ir_pattern`), a sample that did not clip is ``mu`` itself (times the sensor's noise):
it did not clip because the pattern was dim at that pixel, which says nothing about ``mu``. The IR
pass then keeps clipped samples out of the texel means (counting only their weight, ``WSAT``), every
texel with unclipped samples is fitted as it is, whatever share of it clipped, and a texel whose
samples *all* clipped is a lower bound: a one-sided residual ``min(model - c, 0)`` with ``c`` the mean
clip level of the clipped samples after the division. On a synthetic sphere (truth geometry and
pattern) the censored mean above gave alpha 0.1276 for 0.12 (reduced chi-square 81); this gives
0.1201 (0.32).

Fit
---
Texels with weight > ``min_weight`` are used, except those where saturated pixels carry more than
``max_saturated`` of the weight (a clipped highlight biases its texel low; dropping the clipped
samples instead biased alpha by +6 % in a test scan). ``d`` (the diffuse value ``rho_d / pi``) is their
minimum (``diffuse="min"``, the paper) or a third unknown started there (``diffuse="fit"``, the
default). With the Kinect's emitter noise (~45 % per sample) the minimum over hundreds of noisy texel
means lies several standard errors below the true diffuse level; the remainder then carries a
constant offset that a broad lobe explains, and alpha runs to its upper bound (measured on a
synthetic scan: alpha 1.0 instead of 0.12 with the minimum, 0.121 with the diffuse fitted).
Noise-free buffers give the same result either way. ``alpha`` in ``[0.01, 1]`` and ``rho_s >= 0``
are found by ``scipy.optimize.least_squares`` (trust region, analytic
Jacobian) started from a brute-force grid over ``alpha`` (``rho_s`` and ``d`` solved linearly per grid
value), or from the previous fit (:class:`WardFitter`, warm start). Residuals are divided by each
texel's standard error, by default ``sigma_t^2 = s^2 / W_t`` with ``s^2`` the pooled per-sample variance
of the buffer (``weighting="relative"`` uses a multiplicative-noise model instead). The uncertainty
of ``alpha`` is ``sqrt(s_r^2 (J^T J)^-1)`` with ``s_r^2`` the residual variance (reduced chi-square).
``WardFit.chi2`` is the total chi-square ``sum r_t^2`` of the normalised residuals.

GGX rung
--------
The model ladder (diffuse -> Ward -> GGX) has a third rung for highlights with the long tail no Ward
lobe has (:mod:`appfusion.brdf`: ``D G1(w_i) G1(w_o) / (4 cos_i cos_o)``, GGX ``D`` and separable Smith
``G1``, no Fresnel). Every path above fits it (``lobe="ggx"``): the texel model is the same with the
retro-reflection GGX lobe ``D G1^2 / (4 cos^2 theta_h) = a^2 / (pi c^6 (a^2 + T)^2 (1 + s)^2)``,
``c = cos theta_h``, ``T = tan^2 theta_h``, ``s = sqrt(1 + a^2 T)``, at the quadrature nodes (analytic
``d/d alpha``), and the geometry factor ``g^2`` instead of ``g`` (GGX divides by ``cos_i cos_o``, not by
its square root; the ``G1(w_i) G1(w_o) / G1(h)^2`` part is not modelled). On the paper's §5.1 protocol
(exact GGX values, 1 M pairs) the GGX fit's alpha error is <= 6e-4 for alpha 0.05 .. 0.3 and -1.0 % /
-0.7 % at 0.5 / 0.75 (the unmodelled ``G1`` ratio; ``rho_s`` -2.6 % / -8 % there); without any geometry
factor alpha came out within 2e-4 throughout but ``rho_s`` +0.7 %.

:func:`choose_lobe` keeps Ward unless the GGX fit of the same texels lowers the total chi-square by
at least ``LOBE_MIN_GAIN`` (5 %) of Ward's *and* by ``LOBE_MIN_Z`` (25) times the residual variance
``max(reduced chi2 of GGX, 1)`` (the IR noise is overdispersed: reduced chi-square 3-300 on scans, so raw
chi-square differences overstate the evidence). Measured on the stored scans (the BRDF cut's leaf
buffers, the pipeline's cluster buffers):

    cluster                  Ward alpha  rho_s  red.chi2   GGX alpha  rho_s  red.chi2    gain     z  pick
    ggx-sphere (GGX 0.15)       0.1477  0.087      61.0      0.1492  0.111      32.7   +0.46  +677  GGX
    demo, the IR's cluster      0.0502  0.231     273        0.0219  0.322     304     -0.11   -79  Ward
    demo paint (Ward 0.06)      0.0599  0.146       5.3      0.0233  0.419      73.9  -12.8   -721  Ward
    demo label (Ward 0.35)      0.3497  0.024       3.4      0.3247  0.031       3.5   -0.03   -17  Ward

(ggx-sphere truth: IR rho_s 0.09; the GGX fit's 0.111 is +23 %, where synthetic GGX buffers give rho_s
within 1 % and Ward fits of them 22 % low, as Ward's 0.087 is here.) On synthetic buffers with the Kinect's emitter noise (CV 0.45, 1 M pairs) GGX data (alpha 0.05 / 0.15 /
0.4, rho_s 0.3; 0.15 with rho_s 0.03) gave gains 0.36-0.96 (z 270-13000) and GGX alpha within 0.5 %;
Ward data (0.06, 0.1, 0.4; 0.35 and 0.15 with rho_s 0.03 / 0.01) gains -0.07 .. -43 (GGX worse).
A GGX fit costs about as much as a Ward fit (:class:`WardFitter` with ``lobes=("ward", "ggx")``: 1.6-1.9x
the Ward-only time per cluster on the two scans).
"""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np
from scipy.optimize import least_squares

from . import octahedral as oc
from .brdf import LOBES
from .errors import EstimationError
from .hbsab import CH_M, CH_SAT, CH_W, CH_WG, CH_WV, CH_WV2, LEGENDRE_NORMS, N_MOMENTS, HBSAB

try:                                                    # small matrix products: one BLAS thread is
    from threadpoolctl import threadpool_limits          # 10-20x faster than several fighting over
except ImportError:                                     # two busy cores
    threadpool_limits = None

ALPHA_MIN, ALPHA_MAX = 0.01, 1.0
#: largest specular albedo a fit may take (reflectances are relative to the calibration sheet, whose
#: albedo is ~1: energy conservation bounds rho_s by ~1; twice that for slack). Without it a clipped
#: peak let the fit run to a needle lobe (alpha 0.016, rho_s 3.6e7 on a 120-frame scan): the censored
#: texels are met by any lobe that clips them.
RHO_S_MAX = 2.0
#: pattern mode: a texel whose clipped samples carry more than this share of its weight is fitted mostly
#: from below (its residuals above the model count ``PATTERN_ONE_SIDED_W``). With normal errors the
#: samples that stay unclipped near a clipped peak are more often those whose true half vector lies
#: farther out, so such a texel's unclipped mean reads low. Measured (alpha, truth 0.06 / 0.12): demo
#: paint's points 0.0847 -> 0.0787, sphere 0.1227 -> 0.1209; exact data with the peak clipped
#: throughout 0.0601 -> 0.0607 (0 instead of 0.1 left that fit undetermined: 0.0611)
PATTERN_ONE_SIDED_FRAC = 0.3
PATTERN_ONE_SIDED_W = 0.1
#: quadrature points per texel side
DEFAULT_QUAD = 12
#: alpha values of the brute-force initial grid
_ALPHA_GRID = np.geomspace(ALPHA_MIN, ALPHA_MAX, 21)


def _is_pattern(emitter) -> bool:
    return isinstance(emitter, (tuple, list)) and len(emitter) == 4 and emitter[0] == "pattern"


def censored_mean(mu: np.ndarray, c: float, emitter) -> np.ndarray:
    """Mean of ``min(mu Z, c)`` for the emitter factor ``Z`` (module docstring, "Clipped highlights").

    Parameters
    ----------
    mu : array
        True (unclipped) texel means, >= 0.
    c : float
        Clip level, same units as ``mu``.
    emitter : "flat" or (k, theta, shift)
        ``Z = 1`` (flat) or the shifted-Gamma factor ``(t + shift) / (k theta + shift)``.

    Returns
    -------
    array
        The expected texel value, ``<= min(mu, c)``.
    """
    from scipy.special import gammainc

    mu = np.maximum(np.asarray(mu, dtype=np.float64), 0.0)
    if isinstance(emitter, str):
        return np.minimum(mu, c)
    k, theta, shift = (float(x) for x in emitter)
    m0 = k * theta + shift
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(mu > 0, c * m0 / np.where(mu > 0, mu, 1.0) - shift, np.inf)
    x = np.maximum(a, 0.0) / theta
    pk = np.where(a > 0, gammainc(k, np.minimum(x, 1e300)), 0.0)
    pk1 = np.where(a > 0, gammainc(k + 1.0, np.minimum(x, 1e300)), 0.0)
    return mu * (k * theta * pk1 + shift * pk) / m0 + c * (1.0 - pk)


def one_blas_thread():
    """Context limiting BLAS to one thread (no-op without threadpoolctl)."""
    return threadpool_limits(1) if threadpool_limits is not None else contextlib.nullcontext()


@dataclass
class WardFit:
    """Result of fitting a Ward lobe to an HBSAB (paper §5.1).

    Attributes
    ----------
    alpha, alpha_sigma : float
        Roughness and its 1-sigma uncertainty.
    rho_s, rho_s_sigma : float
        Specular scale (IR band) and its 1-sigma uncertainty.
    diffuse : float
        Diffuse BRDF value ``rho_d / pi`` (1/sr) removed before the lobe fit.
    rho_d : float
        ``pi * diffuse``.
    n_texels : int
        Texels used.
    reduced_chi2 : float
        Residual variance in units of the texels' standard errors.
    at_bound : bool
        True if ``alpha`` ended on a bound of ``[0.01, 1]`` (the data are sharper / broader than the
        model can say; ``alpha`` is then a limit, not an estimate), or ``rho_s`` on ``RHO_S_MAX``.
    nfev : int
        Model evaluations of the final least-squares run.
    n_saturated : int
        Texels left out because saturated pixels biased them.
    lobe : {"ward", "ggx"}
        The specular lobe fitted (:data:`appfusion.brdf.LOBES`; module docstring, "GGX rung").
    chi2 : float
        Total chi-square: the sum of the squared normalised residuals (``reduced_chi2`` times the
        degrees of freedom). The texels' standard errors come from the data alone, so two fits of the
        same texels (two lobes) compare by it (:func:`choose_lobe`).
    """

    alpha: float
    alpha_sigma: float
    rho_s: float
    rho_s_sigma: float
    diffuse: float
    rho_d: float
    n_texels: int
    reduced_chi2: float
    at_bound: bool
    nfev: int = 0
    n_saturated: int = 0
    lobe: str = "ward"
    chi2: float = float("nan")

    def to_json(self) -> dict:
        def conv(v):
            if isinstance(v, (bool, np.bool_)):
                return bool(v)
            if isinstance(v, (int, np.integer)):
                return int(v)
            return str(v) if isinstance(v, str) else float(v)

        return {k: conv(v) for k, v in asdict(self).items()}


@lru_cache(maxsize=8)
def _quadrature(n: int, q: int):
    """Per-texel quadrature nodes of an n x n hemisphere square (read-only arrays).

    Returns ``tan2`` and ``cos_h`` at the nodes, (n*n, q*q), and the weight rows (1 + 5, q*q) that turn
    node values into ``J_0, J_1..J_5`` (mean over the texel and Legendre projections).
    """
    x, w = np.polynomial.legendre.leggauss(q)
    w = w / 2.0                                          # mean over [-1, 1]
    B, A = np.meshgrid(x, x, indexing="ij")              # A varies along a row (u), B along columns (v)
    WA = np.outer(w, w).ravel()
    A, B = A.ravel(), B.ravel()
    P = np.stack([A, B, 1.5 * A * A - 0.5, A * B, 1.5 * B * B - 0.5])
    rows = np.vstack([WA, P * WA / LEGENDRE_NORMS[:, None]])
    cen = oc.texel_centers(n).reshape(-1, 2)
    half = 1.0 / n                                       # half texel width in uv
    uv = np.stack([cen[:, 0, None] + A[None] * half, cen[:, 1, None] + B[None] * half], axis=-1)
    d = oc.hemi_decode(uv)
    ch = np.clip(d[..., 2], 1e-9, 1.0)
    tan2 = (1.0 - ch * ch) / (ch * ch)
    for arr in (tan2, ch, rows):
        arr.setflags(write=False)
    return tan2, ch, rows


def _check_lobe(lobe: str) -> str:
    if lobe not in LOBES:
        raise EstimationError(f"lobe fit: unknown lobe {lobe!r}; known: {', '.join(LOBES)}")
    return lobe


def _retro_nodes(lobe: str, alpha: float, T: np.ndarray, ch: np.ndarray, derivative: bool = False):
    """Retro-reflection lobe (``w_i = w_o = h``) at quadrature nodes of ``tan^2 theta_h = T`` and
    ``cos theta_h = ch``, 1/sr, and optionally its derivative with respect to ``alpha``.

    Ward: ``exp(-T / a^2) / (4 pi a^2 ch)``. GGX: ``D G1^2 / (4 ch^2) = a^2 / (pi ch^6 (a^2 + T)^2 (1 + s)^2)``
    with ``s = sqrt(1 + a^2 T)`` (``G1 = 2 / (1 + s)``), and
    ``d ln f / d a = 2 / a - 4 a / (a^2 + T) - 2 a T / (s (1 + s))``.
    """
    a2 = alpha * alpha
    if lobe == "ward":
        f = np.exp(-T / a2) / (4.0 * np.pi * a2 * ch)
        if not derivative:
            return f
        return f, f * (2.0 * T / (a2 * alpha) - 2.0 / alpha)
    c2 = ch * ch
    den = a2 + T
    sq = np.sqrt(1.0 + a2 * T)
    f = a2 / (np.pi * c2 * c2 * c2 * den * den * (1.0 + sq) ** 2)
    if not derivative:
        return f
    return f, f * (2.0 / alpha - 4.0 * alpha / den - 2.0 * alpha * T / (sq * (1.0 + sq)))


def texel_lobe(alpha: float, n: int, texels: np.ndarray, moments: np.ndarray, q: int = DEFAULT_QUAD,
               derivative: bool = False, lobe: str = "ward"):
    """Mean retro-reflection lobe over the samples of each texel (module docstring), 1/sr.

    Parameters
    ----------
    alpha : float
        Roughness.
    n : int
        Texels per side.
    texels : (T,) int array
        Flat texel indices.
    moments : (5, T) array
        Mean Legendre moments of the samples in each texel (zeros: uniform density).
    q : int
        Gauss-Legendre points per texel side.
    derivative : bool
        Also return the derivative with respect to ``alpha`` (analytic, for either lobe).
    lobe : {"ward", "ggx"}
        The lobe: :func:`appfusion.brdf.ward_retro` (paper §5.1) or :func:`appfusion.brdf.ggx_retro`
        (``D G1^2 / (4 cos^2 theta_h)``; module docstring, "GGX rung").

    Returns
    -------
    (T,) array, or a pair of (T,) arrays with the derivative.
    """
    _check_lobe(lobe)
    tan2, ch, rows = _quadrature(int(n), int(q))
    out = _retro_nodes(lobe, alpha, tan2[texels], ch[texels], derivative)
    f = out[0] if derivative else out
    J = f @ rows.T                                       # (T, 6)
    coef = np.vstack([np.ones((1, J.shape[0])), moments])
    val = np.einsum("tk,kt->t", J, coef)
    if not derivative:
        return val
    dJ = out[1] @ rows.T
    return val, np.einsum("tk,kt->t", dJ, coef)


def texel_nodes(alpha: float, n: int, texels: np.ndarray, moments: np.ndarray, q: int = 6,
                lobe: str = "ward"):
    """Lobe values at each texel's quadrature nodes and the node weights that average them as
    :func:`texel_lobe` does: ``texel_lobe = sum(values * weights, axis=1)``. Both (T, q*q).

    Used where a non-linear function of the lobe (the sensor's clipping) must be averaged over the
    texel rather than applied to its mean. ``lobe`` as :func:`texel_lobe`.
    """
    _check_lobe(lobe)
    tan2, ch, rows = _quadrature(int(n), int(q))
    f = _retro_nodes(lobe, alpha, tan2[texels], ch[texels])
    coef = np.vstack([np.ones((1, len(texels))), moments])       # (6, T)
    return f, (rows.T @ coef).T


def _geometry_factor(g: np.ndarray, kind: str) -> np.ndarray:
    """The texels' correction from the retro-reflection lobe to the true one (module docstring):
    Ward divides by ``sqrt(cos_i cos_o)``, the mean ``g`` of the buffer; GGX by ``cos_i cos_o``: ``g^2``
    (module docstring, "GGX rung")."""
    return g if kind == "ward" else g * g


def _prepare(hb: HBSAB, min_weight: float, buffer: int = 0, weighting: str = "count",
             max_saturated: float = 0.02):
    if hb.n_buffers <= buffer:
        raise EstimationError(f"Ward fit: HBSAB has no buffer {buffer}")
    d = hb.data[:, buffer].astype(np.float64)
    W = d[CH_W]
    heavy = W > max(float(min_weight), 0.0)
    clipped = heavy & (d[CH_SAT] > max_saturated * W) if np.isfinite(max_saturated) else np.zeros_like(heavy)
    sel = np.flatnonzero(heavy & ~clipped)
    if len(sel) < 3:
        raise EstimationError(f"Ward fit: only {len(sel)} texels have weight above {min_weight:g} "
                              f"({int(clipped.sum())} more are saturated); need at least 3: scan more of the object")
    Ws = W[sel]
    v = d[CH_WV, sel] / Ws
    var = np.maximum(d[CH_WV2, sel] / Ws - v * v, 0.0)
    g = d[CH_WG, sel] / Ws
    m = d[CH_M:CH_M + N_MOMENTS, sel] / Ws
    if not (np.isfinite(v).all() and np.isfinite(g).all() and np.isfinite(m).all()):
        raise EstimationError("Ward fit: the HBSAB holds non-finite sums")
    vmax = float(np.max(np.abs(v)))
    if not (vmax > 1e-250 and np.isfinite(vmax)):
        raise EstimationError("Ward fit: every reliable texel of the HBSAB is zero (no reflected IR)")
    # work in units of the largest texel value (scale-free: no under/overflow for any units)
    v, var = v / vmax, var / vmax / vmax
    if weighting == "relative":
        pos = (v > 1e-6) & (Ws >= 3 * max(min_weight, 1e-12))
        c2 = float(np.median(var[pos] / (v[pos] ** 2))) if np.any(pos) else 0.0
        s2 = c2 * v * v + 1e-6
    else:
        s2 = float(np.sum(Ws * var) / np.sum(Ws)) + 1e-12
    sigma = np.sqrt(s2 / np.maximum(Ws, 1e-12))
    return sel, v, g, m, sigma, int(clipped.sum()), vmax


def fit_ward(hb: HBSAB, min_weight: float = 1.0, diffuse: str = "fit", x0: tuple | None = None,
             buffer: int = 0, q: int = DEFAULT_QUAD, weighting: str = "count",
             max_saturated: float = 0.02, emitter=None, clip: float | None = None,
             lobe: str = "ward") -> WardFit:
    """Fit ``rho_d / pi + rho_s * f(alpha)`` to one HBSAB (paper §5.1, last step), ``f`` the Ward lobe
    (default, the paper's) or the GGX lobe (``lobe="ggx"``, module docstring "GGX rung").

    Parameters
    ----------
    hb : HBSAB
        The buffer (``hb.data[:, buffer]`` is used).
    min_weight : float
        Texels with total weight (sum of ``w_o . n``) at or below this are not used.
    diffuse : {"fit", "min"}
        ``"min"``: the diffuse value is the minimum over the used texels (paper). ``"fit"`` (default):
        a third unknown, started at that minimum (see the module docstring for why).
    x0 : tuple, optional
        ``(alpha, rho_s[, diffuse])`` to start from (warm start); default: brute-force grid.
    buffer : int
        Which buffer of ``hb``.
    q : int
        Quadrature points per texel side.
    weighting : {"count", "relative"}
        Standard error model of a texel: ``"count"``: ``s^2 / W_t`` with ``s^2`` the buffer's pooled
        per-sample variance; ``"relative"``: ``(c^2 v_t^2 + (1e-3 v_max)^2) / W_t`` (multiplicative noise,
        ``c`` the median relative spread of a sample).
    max_saturated : float
        Texels where saturated samples carry more than this fraction of the weight are clipped.
    emitter : None, "flat", (k, theta, shift) or ("pattern", k, theta, shift)
        The emitter's intensity distribution: with it, clipped texels are modelled (censored mean,
        module docstring) instead of left out; "pattern": the emitter's pattern was divided out of
        the samples and clipped samples left out of the texel means (module docstring).
    clip : float, optional
        The clip level in the buffer's units (mean value of the saturated samples, kept by the IR
        pass); default: the median value of the texels whose samples are >= 90 % saturated. In
        "pattern" mode the lower bound of fully clipped texels (none without it).
    lobe : {"ward", "ggx"}
        The specular lobe fitted (:data:`appfusion.brdf.LOBES`); every path (plain, censored, pattern)
        fits either. ``x0``'s alpha is that lobe's.

    Returns
    -------
    WardFit
        With ``lobe`` set and the total chi-square ``chi2``.

    Raises
    ------
    EstimationError
        Fewer than 3 usable texels, no reflected IR at all, or an unknown ``lobe``.
    """
    _check_lobe(lobe)
    with one_blas_thread():
        return _fit_ward(hb, min_weight, diffuse, x0, buffer, q, weighting, max_saturated, emitter, clip, lobe)


def _censored_setup(hb: HBSAB, min_weight: float, buffer: int, max_saturated: float, unit: float, s2_pool: float,
                    clip: float | None = None):
    """All heavy texels (clipped ones included) for the censored fit, or None when nothing clips."""
    d = hb.data[:, buffer].astype(np.float64)
    W = d[CH_W]
    heavy = W > max(float(min_weight), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(heavy, d[CH_SAT] / np.where(heavy, W, 1.0), 0.0)
    if not np.any(heavy & (frac > max_saturated)):
        return None
    full = heavy & (frac >= 0.9)
    if clip is None and not full.any():
        return None                                      # no texel shows the clip level itself
    sel = np.flatnonzero(heavy)
    Ws = W[sel]
    v = d[CH_WV, sel] / Ws / unit
    c = (float(clip) if clip is not None else float(np.median(d[CH_WV][full] / W[full]))) / unit
    g = d[CH_WG, sel] / Ws
    m = d[CH_M:CH_M + N_MOMENTS, sel] / Ws
    sigma = np.sqrt(s2_pool / np.maximum(Ws, 1e-12))
    if not (np.isfinite(v).all() and np.isfinite(g).all() and np.isfinite(m).all() and np.isfinite(c) and c > 0):
        return None
    return sel, v, g, m, sigma, c, int(np.count_nonzero(heavy & (frac > max_saturated)))


def _fit_ward(hb, min_weight, diffuse, x0, buffer, q, weighting, max_saturated, emitter=None, clip=None,
              kind="ward") -> WardFit:
    if diffuse not in ("min", "fit"):
        raise EstimationError(f"Ward fit: diffuse must be 'min' or 'fit', got {diffuse!r}")
    if weighting not in ("count", "relative"):
        raise EstimationError(f"Ward fit: weighting must be 'count' or 'relative', got {weighting!r}")
    pattern = _is_pattern(emitter)
    # pattern divided out: unsaturated samples are unbiased whatever their texel's saturated share
    # (they are the pixels where the pattern was dim), and the IR pass keeps the saturated ones out of
    # the texel means; texels with saturated samples only are lower bounds (below)
    sel, v, g, m, sigma, n_sat, unit = _prepare(hb, min_weight, buffer, weighting,
                                                np.inf if pattern else max_saturated)
    if x0 is not None:                                   # to the fit's units (values / unit)
        x0 = tuple(x / unit if i else x for i, x in enumerate(x0))
    n = hb.n
    d0 = float(v.min())
    inv_s = 1.0 / sigma
    free_d = diffuse == "fit"
    g = _geometry_factor(g, kind)

    def lobe(alpha, deriv=False):
        out = texel_lobe(alpha, n, sel, m, q, derivative=deriv, lobe=kind)
        if deriv:
            return g * out[0], g * out[1]
        return g * out

    # brute-force initial grid: for each alpha, rho_s (and d) by weighted linear least squares
    if x0 is None:
        best = None
        for a in _ALPHA_GRID:
            L = lobe(a) * inv_s
            if free_d:
                A = np.stack([L, inv_s], axis=1)
                sol, *_ = np.linalg.lstsq(A, v * inv_s, rcond=None)
                rs, dd = max(sol[0], 0.0), max(sol[1], 0.0)
            else:
                dd = d0
                den = float(L @ L)
                rs = max(float(L @ ((v - dd) * inv_s)) / den, 0.0) if den > 0 else 0.0
            cost = float(np.sum((rs * L + dd * inv_s - v * inv_s) ** 2))
            if best is None or cost < best[0]:
                best = (cost, a, rs, dd)
        x0 = (best[1], best[2], best[3]) if free_d else (best[1], best[2])
    x0 = np.array(x0[:3 if free_d else 2], dtype=float)
    if free_d and len(x0) < 3:
        x0 = np.append(x0, d0)
    x0[0] = np.clip(x0[0], ALPHA_MIN, ALPHA_MAX)
    x0[1] = max(x0[1], 1e-12)
    if free_d:
        x0[2] = max(x0[2], 0.0)
    scale = max(float(np.max(v)) - d0, 1e-12)

    # lower bounds: texels whose every sample clipped hold a value above the clip level (pattern mode)
    hsel = np.zeros(0, np.int64)
    if pattern and clip is not None and np.isfinite(clip) and clip > 0:
        dall = hb.data[:, buffer]
        Wsat = dall[CH_SAT].astype(np.float64)
        hsel = np.flatnonzero((dall[CH_W] <= max(float(min_weight), 0.0)) & (Wsat > max(float(min_weight), 0.0)))
        if len(hsel):
            h_lo = float(clip) / unit
            h_m = np.zeros((N_MOMENTS, len(hsel)))
            Wsel = hb.data[CH_W, buffer, sel].astype(np.float64)
            h_inv = 1.0 / np.sqrt(float(np.median(sigma ** 2 * Wsel)) / Wsat[hsel])
            n_sat = int(len(hsel))

    one = np.zeros(len(sel), bool)
    if pattern:
        dsel = hb.data[:, buffer, sel].astype(np.float64)
        one = dsel[CH_SAT] > PATTERN_ONE_SIDED_FRAC * (dsel[CH_SAT] + dsel[CH_W])

    def resid(x):
        dd = x[2] if free_d else d0
        r = (x[1] * lobe(x[0]) + dd - v) * inv_s
        if one.any():
            r[one] = np.where(r[one] > 0, r[one] * PATTERN_ONE_SIDED_W, r[one])
        if len(hsel):
            ph = x[1] * texel_lobe(x[0], n, hsel, h_m, q, lobe=kind) + dd
            r = np.concatenate([r, np.minimum(ph - h_lo, 0.0) * h_inv])
        return r

    def jac(x):
        dd = x[2] if free_d else d0
        L, dL = lobe(x[0], True)
        cols = [x[1] * dL * inv_s, L * inv_s]
        if free_d:
            cols.append(inv_s)
        J = np.stack(cols, axis=1)
        if one.any():
            J[one & ((x[1] * L + dd - v) * inv_s > 0)] *= PATTERN_ONE_SIDED_W
        if len(hsel):
            Lh, dLh = texel_lobe(x[0], n, hsel, h_m, q, derivative=True, lobe=kind)
            act = ((x[1] * Lh + dd) < h_lo) * h_inv
            hc = [x[1] * dLh * act, Lh * act] + ([act] if free_d else [])
            J = np.vstack([J, np.stack(hc, axis=1)])
        return J

    rs_max = RHO_S_MAX / unit
    x0[1] = min(x0[1], rs_max * (1 - 1e-9))
    lo = [ALPHA_MIN, 0.0] + ([0.0] if free_d else [])
    hi = [ALPHA_MAX, rs_max] + ([np.inf] if free_d else [])
    x_scale = np.array([0.05, scale * 0.05] + ([scale * 0.05] if free_d else []))
    cen = None
    if emitter is not None and not pattern:
        # per-sample variance of the unclipped texels (sigma_t^2 W_t), in the fit's units
        Wsel = hb.data[CH_W, buffer, sel].astype(np.float64)
        s2_pool = float(np.median(sigma ** 2 * Wsel))
        cen = _censored_setup(hb, min_weight, buffer, max_saturated, unit, s2_pool, clip)
    if cen is None:
        # scipy's trust-region step search (common.phi_and_derivative) can overflow a power on a
        # near-singular Jacobian (a sharp lobe seen by a few texels, found by the hypothesis test
        # test_ward_fit_any_lobe_is_finite_and_bounded); it recovers, and the fit's bounds and
        # standard errors are judged below as for any fit: the warning tells a user nothing
        with np.errstate(over="ignore"):
            res = least_squares(resid, x0, jac=jac, bounds=(lo, hi), method="trf", x_scale=x_scale,
                                xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    else:
        csel, cv, cg, cm, csig, clip, _ = cen
        cg = _geometry_factor(cg, kind)
        c_inv = 1.0 / csig

        # texels with clipped samples: clipping averaged over the texel's quadrature nodes (the lobe
        # varies a lot across a texel near its peak); the others: clipping of the texel mean
        part = hb.data[CH_SAT, buffer, csel] > 0
        ip = np.flatnonzero(part)

        def cresid(x):
            dd = x[2] if free_d else d0
            pred = censored_mean(x[1] * cg * texel_lobe(x[0], n, csel, cm, q, lobe=kind) + dd, clip, emitter)
            if len(ip):
                f, w = texel_nodes(x[0], n, csel[ip], cm[:, ip], lobe=kind)
                pred[ip] = np.sum(censored_mean(x[1] * cg[ip, None] * f + dd, clip, emitter) * w, axis=1)
            return (pred - cv) * c_inv

        # start: for each alpha of the grid, rho_s (and d) from the unclipped texels, scored censored
        best = None
        for a in _ALPHA_GRID:
            L = lobe(a) * inv_s
            if free_d:
                sol, *_ = np.linalg.lstsq(np.stack([L, inv_s], axis=1), v * inv_s, rcond=None)
                cand = [a, max(sol[0], 1e-12), max(sol[1], 0.0)]
            else:
                den = float(L @ L)
                cand = [a, max(float(L @ ((v - d0) * inv_s)) / den, 1e-12) if den > 0 else 1e-12]
            for f in (1.0, 0.3, 3.0):                       # the clipped texels may want a lower/higher peak
                xx = np.array(cand, float)
                xx[1] = min(xx[1] * f, rs_max * (1 - 1e-9))
                cost = float(np.sum(cresid(xx) ** 2))
                if best is None or cost < best[0]:
                    best = (cost, xx)
        xc = best[1]
        xc[0] = np.clip(xc[0], ALPHA_MIN, ALPHA_MAX)
        with np.errstate(over="ignore"):                # as above
            res = least_squares(cresid, xc, jac="2-point", bounds=(lo, hi), method="trf", x_scale=x_scale,
                                xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=400)
        sel = csel
    x = res.x
    r = res.fun
    J = res.jac
    dof = max(len(r) - len(x), 1)
    s2 = float(r @ r) / dof
    at_bound = bool(x[0] <= ALPHA_MIN * (1 + 1e-6) or x[0] >= ALPHA_MAX * (1 - 1e-6)
                    or x[1] >= rs_max * (1 - 1e-6))
    with np.errstate(all="ignore"):
        try:
            cov = np.linalg.pinv(J.T @ J) * s2
            sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
        except np.linalg.LinAlgError:
            sig = np.full(len(x), np.nan)
    a_sig = float(sig[0]) if np.isfinite(sig[0]) else ALPHA_MAX - ALPHA_MIN
    s_sig = float(sig[1]) if np.isfinite(sig[1]) else float(abs(x[1]))
    dd = float(x[2]) if free_d else d0
    return WardFit(alpha=float(x[0]), alpha_sigma=min(a_sig, ALPHA_MAX - ALPHA_MIN), rho_s=float(x[1]) * unit,
                   rho_s_sigma=s_sig * unit, diffuse=dd * unit, rho_d=float(np.pi * dd * unit), n_texels=int(len(sel)),
                   reduced_chi2=float(s2), at_bound=at_bound, nfev=int(res.nfev), n_saturated=n_sat,
                   lobe=kind, chi2=float(r @ r))


#: :func:`choose_lobe`: GGX replaces Ward only when it lowers the total chi-square of the same texels by
#: at least this fraction ...
LOBE_MIN_GAIN = 0.05
#: ... and by at least this many units of the residual variance (the overdispersion: chi2 reduction /
#: max(reduced chi2 of the GGX fit, 1), a likelihood-ratio statistic under quasi-likelihood)
LOBE_MIN_Z = 25.0


def choose_lobe(ward: WardFit | None, ggx: WardFit | None, min_gain: float = LOBE_MIN_GAIN,
                min_z: float = LOBE_MIN_Z) -> WardFit | None:
    """The model ladder's choice between a Ward and a GGX fit of the same texels (module docstring,
    "GGX rung"): Ward (the paper's lobe, §5.1) unless GGX fits clearly better.

    GGX is chosen when both hold, with ``dchi2 = ward.chi2 - ggx.chi2`` (total chi-squares, same
    texels and standard errors, same number of parameters):

    * ``dchi2 >= min_gain * ward.chi2`` (a relative margin: a better lobe shape removes a large
      share of the misfit, not a sliver), and
    * ``dchi2 / max(ggx.reduced_chi2, 1) >= min_z`` (the reduction in units of the residual variance:
      the IR noise is overdispersed, reduced chi-square often >> 1, so raw chi-square differences
      overstate the evidence),

    and the GGX fit is not at a bound (``at_bound``: no lobe measured) while its numbers are finite.

    Parameters
    ----------
    ward, ggx : WardFit or None
        Fits of the same HBSAB texels (``lobe`` "ward" and "ggx"); None where a fit failed.
    min_gain : float
        Relative chi-square margin (default :data:`LOBE_MIN_GAIN`).
    min_z : float
        Overdispersion-scaled chi-square margin (default :data:`LOBE_MIN_Z`).

    Returns
    -------
    WardFit or None
        ``ward`` or ``ggx``; the one that exists if the other is None.
    """
    if ggx is None:
        return ward
    if ward is None:
        return ggx
    if ward.lobe != "ward" or ggx.lobe != "ggx":
        raise EstimationError(f"choose_lobe: expected a Ward and a GGX fit, got {ward.lobe!r} and {ggx.lobe!r}")
    vals = (ward.chi2, ggx.chi2, ggx.reduced_chi2, ggx.alpha, ggx.rho_s)
    if ggx.at_bound or not all(np.isfinite(v) for v in vals) or ward.n_texels != ggx.n_texels:
        return ward
    d = ward.chi2 - ggx.chi2
    if d >= min_gain * ward.chi2 and d / max(ggx.reduced_chi2, 1.0) >= min_z:
        return ggx
    return ward


class WardFitter:
    """Refits one HBSAB as data arrives, warm-started from the previous fit (paper §5.1: "we update
    the HBSAB and perform BRDF fitting from time to time").

    Parameters
    ----------
    min_weight, diffuse, q, weighting, max_saturated, emitter
        As :func:`fit_ward`.
    lobes : tuple of str
        The lobes fitted at every :meth:`fit` (:data:`appfusion.brdf.LOBES`, each warm-started from its
        own previous fit); with more than one, :func:`choose_lobe` picks the result. Default
        ``("ward",)``: the paper's Ward lobe only.

    Attributes
    ----------
    last : WardFit or None
        The latest successful fit (the chosen lobe's).
    fits : dict
        ``lobe -> WardFit``: the fits of the latest :meth:`fit`, every lobe that could be fitted (the
        chosen one and the others).
    """

    def __init__(self, min_weight: float = 1.0, diffuse: str = "fit", q: int = DEFAULT_QUAD,
                 weighting: str = "count", max_saturated: float = 0.02, emitter=None,
                 lobes: tuple = ("ward",)):
        lobes = tuple(lobes)
        if not lobes or len(set(lobes)) != len(lobes) or any(lb not in LOBES for lb in lobes):
            raise EstimationError(f"Ward fitter: lobes must be distinct names out of {', '.join(LOBES)}, got {lobes!r}")
        if len(lobes) > 1 and "ward" not in lobes:
            raise EstimationError("Ward fitter: a choice between lobes needs the Ward lobe among them")
        self.min_weight = min_weight
        self.emitter = emitter
        self.clip: float | None = None     # clip level (see fit_ward), set by the owner as data arrive
        self.diffuse = diffuse
        self.q = q
        self.weighting = weighting
        self.max_saturated = max_saturated
        self.lobes = lobes
        self.last: WardFit | None = None
        self.fits: dict[str, WardFit] = {}
        self._prev: dict[str, WardFit] = {}      # each lobe's latest fit (warm starts)

    def fit(self, hb: HBSAB, buffer: int = 0) -> WardFit:
        """Fit ``hb`` with every lobe of ``lobes``, each from its last result and from the grid (the
        better start wins), and return the chosen lobe's fit (:func:`choose_lobe`).

        The warm start alone let a cluster whose make-up had changed since the last fit (k-means
        renumbers and regroups clusters as data arrive) stay in the previous lobe's basin: on the
        demo bottle a cluster of the glossy paint (alpha 0.06) kept alpha 0.353 from an earlier fit,
        where a grid start gives 0.071 on the same buffer.

        Raises
        ------
        EstimationError
            When no lobe could be fitted (the Ward fit's error).
        """
        kw = dict(buffer=buffer, q=self.q, weighting=self.weighting, max_saturated=self.max_saturated,
                  emitter=self.emitter, clip=self.clip)
        fits: dict[str, WardFit] = {}
        err = None
        for lb in self.lobes:
            lkw = kw if lb == "ward" else dict(kw, lobe=lb)
            prev = self.last if self.last is not None and self.last.lobe == lb else self._prev.get(lb)
            try:
                res = fit_ward(hb, self.min_weight, self.diffuse, x0=None, **lkw)
            except EstimationError as e:
                err = err or e
                continue
            if prev is not None and not prev.at_bound:
                x0 = (prev.alpha, prev.rho_s, prev.diffuse)
                warm = fit_ward(hb, self.min_weight, self.diffuse, x0=x0, **lkw)
                if warm.reduced_chi2 < res.reduced_chi2 and not warm.at_bound:
                    res = warm
            fits[lb] = res
        if not fits:
            raise err
        res = next(iter(fits.values())) if len(fits) == 1 else choose_lobe(fits.get("ward"), fits.get("ggx"))
        self._prev.update(fits)
        self.fits = fits
        self.last = res
        return res
