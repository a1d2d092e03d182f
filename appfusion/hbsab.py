"""Half-angle BRDF Sample Accumulation Buffers (HBSAB), paper §5.1, Eq. 3.

An HBSAB is a discretised BRDF over half vectors: the upper hemisphere of half vectors ``h`` (in the
local frame of a surface point, normal = +z) is mapped to an ``N x N`` square with the octahedral map
of :mod:`appfusion.octahedral` (Praun & Hoppe 2003), and every texel keeps the weighted mean ``v`` of the
IR reflectance samples whose half vector falls in it and their total weight ``w``. A new sample
``v_hat`` with weight ``w_hat = w_o . n`` updates its texel by Eq. 3::

    v_new = (v w + v_hat w_hat) / (w + w_hat),      w_new = w + w_hat.

Storing the sums ``W = sum w`` and ``WV = sum w v`` is the same update in a form that adds: the
buffer of a set of points is the plain sum of its parts' buffers (paper §5.2, "weighted-average the
HBSABs of its children"), so many buffers (one per BRDF-cut leaf) live in one array and a frame's
samples are added with one ``np.bincount`` per channel on flat ``(buffer, texel)`` indices.

Channels
--------
Besides ``W`` and ``WV`` (Eq. 3) every texel keeps weighted sums that make the later Ward fit exact
to second order in the texel size (see :mod:`appfusion.ward_fit`), all summable:

``W``      sum of weights ``w = w_o . n``
``WV``     sum ``w v``            -> texel mean ``v = WV / W`` (Eq. 3)
``WV2``    sum ``w v^2``          -> per-texel variance of the samples (noise level, clustering)
``WG``     sum ``w g``            with ``g = cos(theta_h) / sqrt(cos(theta_i) cos(theta_o))``: the ratio of
                                  the true Ward normalisation to the retro-reflection one (``w_i = w_o = h``)
``WSAT``   sum of ``w`` over samples that were saturated (clipped) on the sensor: they are included
                                  with their clipped value, and the Ward fit skips texels where they matter
``M1..M5`` sum ``w P_k(a, b)``    Legendre moments of where in the texel the half vectors fell:
                                  ``P = (a, b, (3a^2-1)/2, a b, (3b^2-1)/2)``, ``(a, b)`` in ``[-1, 1]^2`` the
                                  sample's position inside its texel

A buffer array has shape ``(C, B, N * N)`` (channel, buffer, texel; texel index ``row * N + col`` as in
:func:`appfusion.octahedral.texel_index`). Samples whose lighting or view direction is beyond
``max_angle_deg`` from the normal (default 80 degrees) are discarded as unreliable (§5.1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import AppFusionError

#: channel indices of the (C, B, N*N) data array
CH_W, CH_WV, CH_WV2, CH_WG, CH_SAT, CH_M = 0, 1, 2, 3, 4, 5
#: number of Legendre moment channels and of channels in all
N_MOMENTS = 5
N_CHANNELS = CH_M + N_MOMENTS
CHANNEL_NAMES = ("W", "WV", "WV2", "WG", "WSAT", "M_a", "M_b", "M_aa", "M_ab", "M_bb")
#: E_uniform[P_k^2] over the texel square: the Legendre basis' squared norms
LEGENDRE_NORMS = np.array([1 / 3, 1 / 3, 1 / 5, 1 / 9, 1 / 5])
#: default texels per side and grazing cut-off
DEFAULT_N = 32
DEFAULT_MAX_ANGLE_DEG = 80.0


@dataclass
class HalfVectorSamples:
    """Per-sample quantities of a batch of (w_i, w_o, value) triples, ready to accumulate.

    Attributes
    ----------
    keep : (m,) int64
        Indices into the input batch of the samples kept (both directions within the cut-off).
    texel : (k,) int64
        Flat texel index ``row * N + col`` of each kept sample.
    channels : (C, k) float64
        Per-sample contributions to every channel (see the module docstring).
    """

    keep: np.ndarray
    texel: np.ndarray
    channels: np.ndarray


def _check_n(n) -> int:
    n = int(n)
    if n < 2 or n > 512:
        raise AppFusionError(f"HBSAB: texels per side must be in 2..512, got {n}")
    return n


def half_vector_samples(wi: np.ndarray, wo: np.ndarray, value: np.ndarray, n: int = DEFAULT_N,
                        max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG, weight: np.ndarray | None = None,
                        dtype=np.float64, saturated: np.ndarray | None = None) -> HalfVectorSamples:
    """Half vectors, texels and channel contributions of samples in local frames (paper §5.1).

    Parameters
    ----------
    wi, wo : (m, 3) array
        Unit lighting (towards the emitter) and view (towards the camera) directions in the local
        frame of each sample's surface point (normal = +z).
    value : (m,) array
        Calibrated IR reflectance sample (a BRDF value, 1/sr; see ``calibration.ir_profile``).
    n : int
        Texels per side of the square.
    max_angle_deg : float
        Samples with ``theta_i`` or ``theta_o`` beyond this are discarded (grazing, unreliable).
    weight : (m,) array, optional
        Sample weights; default ``w_o . n`` (Eq. 3's ``w_hat``).
    dtype : numpy dtype
        Float type of the per-sample arithmetic (float32 is faster and ample for directions).
    saturated : (m,) bool array, optional
        Samples whose raw value was clipped by the sensor (counted in the ``WSAT`` channel).

    Returns
    -------
    HalfVectorSamples
    """
    n = _check_n(n)
    wi = np.asarray(wi, dtype=dtype).reshape(-1, 3)
    wo = np.asarray(wo, dtype=dtype).reshape(-1, 3)
    value = np.asarray(value, dtype=dtype).reshape(-1)
    if not (len(wi) == len(wo) == len(value)):
        raise AppFusionError(f"HBSAB update: w_i ({len(wi)}), w_o ({len(wo)}) and values ({len(value)}) "
                             "must have the same length")
    if weight is not None:
        weight = np.asarray(weight, dtype=dtype).reshape(-1)
        if len(weight) != len(value):
            raise AppFusionError(f"HBSAB update: {len(weight)} weights for {len(value)} samples")
    cmin = np.asarray(np.cos(np.radians(float(max_angle_deg))), dtype=dtype)
    ci, co = wi[:, 2], wo[:, 2]
    ok = (ci > cmin) & (co > cmin) & np.isfinite(value)
    if weight is not None:
        ok &= np.isfinite(weight) & (weight > 0)
    keep = np.flatnonzero(ok)
    sat = None if saturated is None else np.asarray(saturated, bool).reshape(-1)
    if len(keep) != len(value):
        wi, wo, value, ci, co = wi[keep], wo[keep], value[keep], ci[keep], co[keep]
        weight = None if weight is None else weight[keep]
        sat = None if sat is None else sat[keep]
    w = co if weight is None else weight
    hs = _channels(wi[:, 0] + wo[:, 0], wi[:, 1] + wo[:, 1], ci + co, ci, co, value, w, n)
    hs.keep = keep
    if sat is not None:
        hs.channels[CH_SAT] = np.where(sat, w, 0.0)
    return hs


def _channels(hx, hy, hz, ci, co, value, w, n) -> HalfVectorSamples:
    """Texels and channel contributions from local half vectors ``h = w_i + w_o`` (unnormalised
    components; ``hz = cos(theta_i) + cos(theta_o) > 0``) and the samples' values and weights.

    The IR pass's per-frame path (~200k samples): every channel is written in place into its row
    (no per-channel temporaries)."""
    dt = np.result_type(w.dtype, np.float32)
    m = len(w)
    ch = np.empty((N_CHANNELS, m), dtype=dt)
    # octahedral map (appfusion.octahedral.hemi_encode): p = h / (|hx| + |hy| + hz);
    # fu = (px + py + 1) n / 2, fv = (px - py + 1) n / 2, in [0, n]
    half_n = dt.type(0.5 * n)
    k = np.abs(hx, dtype=dt)
    k += np.abs(hy)
    k += hz
    np.divide(half_n, k, out=k)
    fu = hx + hy
    fu *= k
    fu += half_n
    fv = np.subtract(hx, hy, dtype=dt)
    fv *= k
    fv += half_n
    colf = np.floor(fu)
    np.clip(colf, 0, n - 1, out=colf)
    rowf = np.floor(fv)
    np.clip(rowf, 0, n - 1, out=rowf)
    # position inside the texel, [-1, 1]: a = 2 (fu - col) - 1, b likewise (in fu, fv's place)
    a, b = fu, fv
    a -= colf
    a *= 2
    a -= 1
    b -= rowf
    b *= 2
    b -= 1
    # g = cos(theta_h) / sqrt(cos_i cos_o), cos(theta_h) = hz / |h|
    g = np.multiply(hx, hx, dtype=dt)
    g += hy * hy
    g += hz * hz
    g *= ci
    g *= co
    np.sqrt(g, out=g)
    np.divide(hz, g, out=g)
    np.copyto(ch[CH_W], w)
    np.multiply(w, value, out=ch[CH_WV])
    np.multiply(ch[CH_WV], value, out=ch[CH_WV2])
    np.multiply(w, g, out=ch[CH_WG])
    ch[CH_SAT] = 0.0
    wa, wb = ch[CH_M], ch[CH_M + 1]
    np.multiply(w, a, out=wa)
    np.multiply(w, b, out=wb)
    half_w = np.multiply(w, dt.type(0.5))
    for row, x, y in ((CH_M + 2, wa, a), (CH_M + 4, wb, b)):   # w (1.5 x^2 - 0.5)
        np.multiply(x, y, out=ch[row])
        ch[row] *= dt.type(1.5)
        ch[row] -= half_w
    np.multiply(wa, b, out=ch[CH_M + 3])                       # w a b
    rowf *= n
    rowf += colf
    return HalfVectorSamples(None, rowf.astype(np.int64), ch)


def scatter_add(target: np.ndarray, keys: np.ndarray, channels: np.ndarray, lut: np.ndarray | None = None,
                mark: np.ndarray | None = None) -> None:
    """Add per-sample channel values into ``target[:, key]`` (vectorised, repeated keys summed).

    Parameters
    ----------
    target : (C, M) array
        Flat view of a buffer array (channel, buffer * texel); updated in place.
    keys : (m,) int array
        Flat ``buffer * N * N + texel`` index of each sample, in ``0..M-1``.
    channels : (C, m) array
        Per-sample contributions.
    lut : (M,) int64 array, optional
        Scratch space of length ``M`` reused between calls (saves an allocation per frame).
    mark : (M,) bool array, optional
        Scratch space of length ``M``, all False, reused between calls (left all False): the distinct
        keys are found by marking them, about 4x faster than counting them into a fresh ``M``-long
        array (on a 100k-point IR pass, M ~ 1.5 M: 1 ms instead of 4.6 ms a frame).

    Notes
    -----
    The keys of one frame hit few distinct (buffer, texel) pairs, so they are first compressed
    (``bincount`` -> distinct keys -> look-up table), the channels summed per distinct key with one
    ``bincount`` each in float64, and only then added to ``target``.
    """
    m = len(keys)
    if m == 0:
        return
    M = target.shape[1]
    if m * 16 < M:                               # few samples: sorting them is cheaper
        uniq, inv = np.unique(keys, return_inverse=True)
    else:
        if mark is not None and len(mark) >= M:
            mark[keys] = True
            uniq = np.flatnonzero(mark[:M])
            mark[uniq] = False
        else:
            uniq = np.flatnonzero(np.bincount(keys, minlength=M))
        if lut is None or len(lut) < M:
            lut = np.empty(M, np.int64)
        lut[uniq] = np.arange(len(uniq))
        inv = lut[keys]
    k = len(uniq)
    agg = np.zeros((channels.shape[0], k), np.float64)
    for c in range(channels.shape[0]):          # a handful of channels, not a loop over samples
        row = channels[c]
        if c == CH_SAT:                          # mostly zero: sum only the saturated samples
            if row.any():
                nz = np.flatnonzero(row)
                agg[c] = np.bincount(inv[nz], row[nz], k)
            continue
        agg[c] = np.bincount(inv, row, k)
    target[:, uniq] += agg.astype(target.dtype, copy=False)


class HBSAB:
    """An array of ``B`` HBSABs of ``N x N`` texels each (paper §5.1).

    Parameters
    ----------
    n_buffers : int
        Number of buffers ``B`` (one per BRDF-cut leaf, or 1).
    n : int
        Texels per side (default 32).
    max_angle_deg : float
        Grazing cut-off for both directions, degrees (default 80).
    dtype : numpy dtype
        Storage type of the sums (float32 halves the memory; per-frame sums are formed in float64).
    data : (C, B, N*N) array, optional
        Existing sums to wrap (not copied).

    Attributes
    ----------
    data : (C, B, N*N) ndarray
        The channel sums (see the module docstring).
    """

    def __init__(self, n_buffers: int = 1, n: int = DEFAULT_N, max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG,
                 dtype=np.float64, data: np.ndarray | None = None):
        self.n = _check_n(n)
        if not (0.0 < float(max_angle_deg) < 90.0):
            raise AppFusionError(f"HBSAB: max_angle_deg must be in (0, 90), got {max_angle_deg}")
        self.max_angle_deg = float(max_angle_deg)
        if data is None:
            nb = int(n_buffers)
            if nb < 1:
                raise AppFusionError(f"HBSAB: need at least one buffer, got {n_buffers}")
            data = np.zeros((N_CHANNELS, nb, self.n * self.n), dtype=dtype)
        elif data.ndim != 3 or data.shape[0] != N_CHANNELS or data.shape[2] != self.n * self.n:
            raise AppFusionError(f"HBSAB: data must have shape ({N_CHANNELS}, B, {self.n * self.n}), got {data.shape}")
        self.data = data
        self._lut: np.ndarray | None = None                # scatter_add's scratch (not state)
        self._mark: np.ndarray | None = None

    # -- shape and views -----------------------------------------------------------------
    @property
    def n_buffers(self) -> int:
        return int(self.data.shape[1])

    def __len__(self) -> int:
        return self.n_buffers

    @property
    def nbytes(self) -> int:
        """Memory held by the sums, bytes (independent of how many samples were added)."""
        return int(self.data.nbytes)

    def _like(self, data: np.ndarray) -> "HBSAB":
        return HBSAB(n=self.n, max_angle_deg=self.max_angle_deg, data=data)

    def copy(self) -> "HBSAB":
        return self._like(self.data.copy())

    def __getitem__(self, idx) -> "HBSAB":
        """Buffers ``idx`` (int, slice or index array) as a new HBSAB (a copy for arrays)."""
        if isinstance(idx, (int, np.integer)):
            if not -self.n_buffers <= idx < self.n_buffers:
                raise AppFusionError(f"HBSAB: buffer {idx} out of range 0..{self.n_buffers - 1}")
            idx = slice(int(idx), int(idx) + 1 if idx != -1 else None)
        return self._like(self.data[:, idx])

    @property
    def weight(self) -> np.ndarray:
        """Total weight ``w`` per texel, shape (B, N, N)."""
        return self.data[CH_W].reshape(-1, self.n, self.n)

    def total_weight(self) -> np.ndarray:
        """Total weight of each buffer, shape (B,)."""
        return self.data[CH_W].sum(axis=1, dtype=np.float64)

    def _ratio(self, ch: int, min_weight: float = 0.0) -> np.ndarray:
        W = self.data[CH_W].astype(np.float64)
        ok = W > max(min_weight, 0.0)
        out = np.zeros(W.shape)
        np.divide(self.data[ch], W, out=out, where=ok)
        return out

    def mean(self) -> np.ndarray:
        """Weighted mean value ``v`` per texel (Eq. 3), shape (B, N*N); 0 where ``w == 0``."""
        return self._ratio(CH_WV)

    @property
    def value(self) -> np.ndarray:
        """Weighted mean value ``v`` per texel as images, shape (B, N, N)."""
        return self.mean().reshape(-1, self.n, self.n)

    def variance(self) -> np.ndarray:
        """Weighted variance of the samples in each texel, shape (B, N*N); 0 where empty."""
        m = self.mean()
        return np.maximum(self._ratio(CH_WV2) - m * m, 0.0)

    def geometry_factor(self) -> np.ndarray:
        """Mean ``g = cos(theta_h) / sqrt(cos(theta_i) cos(theta_o))`` per texel, (B, N*N); 1 where empty."""
        W = self.data[CH_W].astype(np.float64)
        out = np.ones(W.shape)
        np.divide(self.data[CH_WG], W, out=out, where=W > 0)
        return out

    def moments(self) -> np.ndarray:
        """Mean Legendre moments of the half vectors' positions within their texels, (5, B, N*N)."""
        W = self.data[CH_W].astype(np.float64)
        out = np.zeros((N_MOMENTS,) + W.shape)
        np.divide(self.data[CH_M:CH_M + N_MOMENTS], W[None], out=out, where=W[None] > 0)
        return out

    # -- updates -------------------------------------------------------------------------
    def update(self, buffer, wi: np.ndarray, wo: np.ndarray, value: np.ndarray,
               weight: np.ndarray | None = None, saturated: np.ndarray | None = None) -> int:
        """Add samples by Eq. 3 (vectorised; repeated texels are summed).

        Parameters
        ----------
        buffer : int or (m,) int array
            Buffer of each sample.
        wi, wo : (m, 3) array
            Unit lighting / view directions in the samples' local frames (normal = +z).
        value : (m,) array
            IR reflectance samples (1/sr).
        weight : (m,) array, optional
            Default ``w_o . n``.
        saturated : (m,) bool array, optional
            Samples clipped by the sensor (``WSAT`` channel).

        Returns
        -------
        int
            Number of samples used (the others were grazing or not finite).
        """
        value = np.asarray(value).reshape(-1)
        buf = np.broadcast_to(np.asarray(buffer, dtype=np.int64), value.shape)
        if buf.size and (buf.min() < 0 or buf.max() >= self.n_buffers):
            raise AppFusionError(f"HBSAB update: buffer index out of range 0..{self.n_buffers - 1} "
                                 f"(got {int(buf.min())}..{int(buf.max())})")
        s = half_vector_samples(wi, wo, value, self.n, self.max_angle_deg, weight, saturated=saturated)
        self.add(buf[s.keep] * (self.n * self.n) + s.texel, s.channels)
        return len(s.keep)

    def add(self, keys: np.ndarray, channels: np.ndarray) -> None:
        """Low-level: add channel contributions at flat ``buffer * N*N + texel`` keys."""
        flat = self.data.reshape(N_CHANNELS, -1)
        if self._lut is None or len(self._lut) != flat.shape[1]:
            self._lut = np.empty(flat.shape[1], np.int64)
            self._mark = np.zeros(flat.shape[1], bool)
        scatter_add(flat, np.asarray(keys, dtype=np.int64), channels, self._lut, self._mark)

    def clear(self) -> None:
        self.data[...] = 0

    # -- combining -----------------------------------------------------------------------
    def sum(self, indices=None) -> "HBSAB":
        """Weight-sum of buffers (all, or ``indices``) into one buffer: the combined HBSAB (§5.2)."""
        d = self.data if indices is None else self.data[:, np.asarray(indices)]
        return self._like(d.sum(axis=1, dtype=np.float64, keepdims=True))

    def range_sums(self, starts: np.ndarray) -> "HBSAB":
        """Sums over consecutive buffer ranges ``[starts[i], starts[i+1])`` (last to the end).

        ``starts`` must be strictly increasing and start at 0, e.g. the first leaves of the nodes of
        a BRDF cut in depth-first order; exact (``np.add.reduceat``), float64.
        """
        starts = np.asarray(starts, dtype=np.int64)
        if len(starts) == 0 or starts[0] != 0 or np.any(np.diff(starts) <= 0) or starts[-1] >= self.n_buffers:
            raise AppFusionError("HBSAB.range_sums: starts must increase strictly from 0 within the buffers")
        return self._like(np.add.reduceat(self.data, starts, axis=1, dtype=np.float64))

    def merge(self, fractions: np.ndarray) -> "HBSAB":
        """Weighted sums of buffers: ``out[k] = sum_b fractions[k, b] * buffer[b]``, fractions (K, B)."""
        F = np.asarray(fractions, dtype=np.float64)
        if F.ndim != 2 or F.shape[1] != self.n_buffers:
            raise AppFusionError(f"HBSAB.merge: fractions must have shape (K, {self.n_buffers}), got {F.shape}")
        out = np.empty((N_CHANNELS, len(F), self.n * self.n))
        for c in range(N_CHANNELS):             # one (K, B) @ (B, N*N) product per channel
            out[c] = F @ self.data[c].astype(np.float64, copy=False)
        return self._like(out)

    def __iadd__(self, other: "HBSAB") -> "HBSAB":
        if other.n != self.n or other.data.shape != self.data.shape:
            raise AppFusionError("HBSAB: cannot add buffers of different shapes")
        self.data += other.data
        return self
