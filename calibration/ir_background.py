"""IR background level from emitter-off frames (paper §6, "Calibrations").

    "We estimate the IR background noise by switching off the IR emitter, capturing and averaging a
    number of IR frames, and finding in a histogram the bin with most pixels as the noise level."

:func:`estimate_background` averages the frames pixel-wise, histograms the averaged image in bins of
``1 / n_frames`` counts (the lattice of means of integer counts, so no bin is favoured by
quantisation), smooths the histogram with a Gaussian of ``smooth_counts`` counts and returns the
centre of the fullest bin, refined by a parabola through it and its neighbours. It also reports the
per-pixel sensor noise (median temporal variance, corrected to the mean for Gaussian noise, or a
robust spatial spread from a single frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.stats import chi2

from appfusion.errors import CalibrationError


@dataclass(frozen=True)
class Background:
    """IR background estimate.

    Attributes
    ----------
    level : float
        Background level ``b0`` in raw counts (mode of the averaged emitter-off frames).
    noise_sigma : float
        Per-pixel sensor noise of one frame, counts (1 sigma).
    n_frames : int
        Emitter-off frames used.
    """

    level: float
    noise_sigma: float
    n_frames: int


def estimate_background(frames: Iterable[np.ndarray], smooth_counts: float = 0.5,
                        max_value: float = 1023.0) -> Background:
    """Background level and sensor noise from IR frames taken with the emitter off (paper §6).

    Parameters
    ----------
    frames : iterable of (H, W) arrays
        Raw IR images (counts), emitter off, all of one shape. Non-finite pixels are ignored.
    smooth_counts : float
        Standard deviation (counts) of the Gaussian that smooths the histogram before its mode is
        taken.
    max_value : float
        Largest raw value the sensor produces (10-bit: 1023).

    Returns
    -------
    Background

    Raises
    ------
    CalibrationError
        No frames, frames of different shapes, or no finite pixel.
    """
    total = None
    total2 = None
    count = None
    n = 0
    shape = None
    for i, f in enumerate(frames):
        f = np.asarray(f, dtype=np.float64)
        if f.ndim != 2:
            raise CalibrationError(f"IR background: emitter-off frame {i} is not a 2-D image (shape {f.shape})")
        if shape is None:
            shape = f.shape
            total = np.zeros(shape)
            total2 = np.zeros(shape)
            count = np.zeros(shape)
        elif f.shape != shape:
            raise CalibrationError(f"IR background: emitter-off frame {i} has shape {f.shape}, the first had {shape}")
        ok = np.isfinite(f)
        fz = np.where(ok, f, 0.0)
        total += fz
        total2 += fz * fz
        count += ok
        n += 1
    if n == 0:
        raise CalibrationError("IR background: no emitter-off frames (record some IR frames with the emitter "
                               "switched off at the start of the ir-calibration pass)")
    valid = count > 0
    if not valid.any():
        raise CalibrationError("IR background: the emitter-off frames have no finite pixel")
    mean = total[valid] / count[valid]
    step = 1.0 / n
    lo, hi = float(mean.min()), float(mean.max())
    if hi - lo < step:
        level = float(np.median(mean))
    else:
        nb = int(np.ceil((hi - lo) / step)) + 3
        nb = min(nb, int(np.ceil((max_value + 1) / step)) + 3, 2_000_000)
        edges = lo - step + np.arange(nb + 1) * ((hi - lo + 2 * step) / nb)
        hist, edges = np.histogram(mean, bins=edges)
        width = edges[1] - edges[0]
        hs = gaussian_filter1d(hist.astype(np.float64), max(smooth_counts / width, 0.5), mode="constant")
        j = int(np.argmax(hs))
        off = 0.0
        if 0 < j < len(hs) - 1:
            a, b, c = hs[j - 1], hs[j], hs[j + 1]
            den = a - 2 * b + c
            if den < 0:
                off = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
        level = float(edges[j] + (0.5 + off) * width)
    if n >= 2:
        multi = count >= 2
        m = total[multi] / count[multi]
        var = np.maximum(total2[multi] / count[multi] - m * m, 0.0) * count[multi] / (count[multi] - 1)
        # median of the per-pixel variances, unbiased for Gaussian noise (robust to hot pixels)
        dof = np.maximum(count[multi] - 1, 1)
        corr = chi2.ppf(0.5, dof) / dof
        sigma = float(np.sqrt(np.median(var / corr))) if var.size else 0.0
    else:
        mad = float(np.median(np.abs(mean - np.median(mean))))
        sigma = 1.4826 * mad
    return Background(level=level, noise_sigma=sigma, n_frames=n)
