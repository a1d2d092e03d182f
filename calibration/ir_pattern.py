"""Emitter pattern map: the fixed intensity of a structured-light emitter over its directions (paper §6).

The paper models the Kinect's IR intensity as a *stationary* shifted-Gamma random field over emitter
directions and averages its multiplicative noise away in the HBSAB texels (§5.1). The field is also
*fixed*: the same dot pattern every frame. A scan whose highlights fall on the same part of the
pattern frame after frame keeps a per-texel bias that more frames do not remove (measured: alpha
+14 % on a one-material sphere, with truth geometry and poses). The calibration pass already images
the pattern: the white sheet, seen fronto-parallel at several distances with depth. This module turns
those frames into a map of the emitter's relative intensity ``m(u, v)`` over emitter directions and
divides it out of every IR sample, so that a sample becomes ``f_r * Z / m`` with ``Z / m ~ 1``.

Directions
----------
A point ``P`` (depth-camera frame, metres) is lit from the emitter at ``E`` along the direction
``(u, v) = ((P_x - E_x) / (P_z - E_z), (P_y - E_y) / (P_z - E_z))`` (tangent-plane coordinates in the
camera's axes; the emitter is taken parallel to the camera, as on the Kinect). The map is a regular grid
over ``(u, v)`` with cell size ``cell`` (default: one depth pixel, ``1 / fx``), cell ``(row, col)``
centred at ``(u, v) = ((col - c0) cell, (row - r0) cell)``, the origin ``(c0, r0)`` chosen so that the
cells' centres lie on the pixels' rays (:func:`estimate_pattern`, ``phase``). Because of the emitter's baseline, a
cell is seen by different camera pixels at different sheet distances, so the map is not a flat-field
image of the camera: it belongs to the emitter.

Estimate
--------
Each sheet pixel gives ``Z_hat = sample / (sheet_albedo / pi)`` with ``sample`` from the fitted profile
(:meth:`calibration.ir_profile.IRProfile.apply`, mean 1 over the pattern). The map is the mean of
``Z_hat`` per cell over all frames and distances, normalised to mean 1 over the cells seen; saturated
pixels and pixels below three noise sigmas are left out. Cells never seen read 1 (the mean: such
samples keep the shifted-Gamma noise that the HBSAB averages). How much of the map to trust is
cross-validated across sheet distances (:func:`estimate_pattern`): the map is shrunk towards 1 by a
factor ``lambda`` and rescaled so that the held-out pixels' ``Z / m`` average 1. The calibration's
``fit.pattern`` diagnostics hold ``lambda``, the held-out spread of ``Z / m`` with and without the map,
the coverage and the pixels per cell. Measured on a synthetic calibration (8 distances, 3 frames
each, the pattern's grid offset from the pixels): lambda 1, held-out spread 43 % without the map and
9 % with it.

Limits: the map is sampled at the camera's resolution. A real Kinect's dots are smaller than a pixel,
so what the map holds is the pattern as the IR camera images it at the calibration distances; finer
structure is left as multiplicative noise that the HBSAB averages as before.
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from appfusion.errors import CalibrationError

#: largest map side, cells (a guard against absurd cell sizes)
MAX_SIDE = 8192


@dataclass
class EmitterPattern:
    """Relative emitter intensity over emitter directions (module docstring).

    Attributes
    ----------
    values : (rows, cols) float32
        Relative intensity, mean 1 over the cells seen; 1 where never seen.
    counts : (rows, cols) uint16
        Calibration pixels averaged into each cell.
    cell : (2,) float
        Cell size along ``u`` and ``v`` in tangent-plane units (radians near the axis); a number is
        taken for both.
    origin : (2,) float
        ``(c0, r0)``: the column and row of direction ``(0, 0)``.
    stats : dict
        Diagnostics (:func:`estimate_pattern`).
    """

    values: np.ndarray
    counts: np.ndarray
    cell: float
    origin: tuple = (0.0, 0.0)
    stats: dict = field(default_factory=dict)

    def __post_init__(self):
        self.values = np.asarray(self.values, dtype=np.float32)
        self.counts = np.asarray(self.counts)
        if self.values.ndim != 2 or self.values.shape != self.counts.shape:
            raise CalibrationError(f"emitter pattern: values {self.values.shape} and counts {self.counts.shape} "
                                   "must be 2-D arrays of the same shape")
        if not (np.isfinite(self.values).all() and (self.values > 0).all()):
            raise CalibrationError("emitter pattern: values must be finite and positive")
        self.cell = _cell2(self.cell)
        self.origin = (float(self.origin[0]), float(self.origin[1]))

    @property
    def shape(self) -> tuple[int, int]:
        return self.values.shape

    def cells(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest cell ``(row, col)`` of directions ``(u, v)`` (int64; may lie outside the map)."""
        col = np.rint(np.asarray(u, dtype=np.float64) * (1.0 / self.cell[0]) + self.origin[0]).astype(np.int64)
        row = np.rint(np.asarray(v, dtype=np.float64) * (1.0 / self.cell[1]) + self.origin[1]).astype(np.int64)
        return row, col

    def lookup(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Relative intensity at directions ``(u, v)`` (arrays of one shape), float32; 1 off the map
        (and at non-finite directions).

        The per-frame path of the IR pass (~200k look-ups a frame): float32 arithmetic, and the map
        framed by a border of 1s (kept, rebuilt when ``values`` is replaced) so that a clipped index
        stands for "off the map" and one ``take`` reads every value -- 3x faster than masking.
        Float32 rounding of ``u / cell`` (relative 6e-8, a few 1e-5 cells on a 1400-cell map) can
        only change the cell of a direction within that of a cell boundary.
        """
        vals = self.values
        framed = getattr(self, "_framed", None)
        if framed is None or framed[0] is not vals:
            framed = (vals, np.pad(vals, 1, constant_values=np.float32(1.0)).ravel())
            self._framed = framed
        rows, cols = vals.shape
        f32 = np.float32
        u = np.asarray(u, dtype=f32)
        v = np.asarray(v, dtype=f32)
        # cell + 1 in the framed map; NaN -> a large negative int -> clipped to the frame
        with np.errstate(invalid="ignore"):
            col = np.rint(u * f32(1.0 / self.cell[0]) + f32(self.origin[0] + 1.0))
            row = np.rint(v * f32(1.0 / self.cell[1]) + f32(self.origin[1] + 1.0))
            np.clip(col, -1.0, cols + 1.0, out=col)
            np.clip(row, -1.0, rows + 1.0, out=row)
            ci = col.astype(np.intp)
            ri = row.astype(np.intp)
        np.clip(ci, 0, cols + 1, out=ci)
        np.clip(ri, 0, rows + 1, out=ri)
        ri *= cols + 2
        ri += ci
        return framed[1].take(ri).reshape(np.shape(u))

    def lookup_points(self, P: np.ndarray, emitter_position) -> np.ndarray:
        """Relative intensity at camera-frame points ``P`` (..., 3) lit from ``emitter_position``."""
        P = np.asarray(P, dtype=np.float64)
        e = np.asarray(emitter_position, dtype=np.float64).reshape(3)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = P[..., 2] - e[2]
            u = (P[..., 0] - e[0]) / z
            v = (P[..., 1] - e[1]) / z
        ok = np.isfinite(u) & np.isfinite(v) & (z > 0)
        out = np.ones(np.shape(u), dtype=np.float32)
        out[ok] = self.lookup(u[ok], v[ok])
        return out

    # -- persistence ------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write the map as a compressed ``.npz`` (atomically)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, values=self.values, counts=self.counts, cell=np.asarray(self.cell),
                                origin=np.asarray(self.origin), stats=np.asarray(repr(self.stats)))
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "EmitterPattern":
        """Read a map written by :meth:`save`."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                values, counts = z["values"], z["counts"]
                cell, origin = np.asarray(z["cell"], float).reshape(-1), tuple(np.asarray(z["origin"], float).reshape(2))
        except FileNotFoundError:
            raise CalibrationError(f"{path}: emitter pattern file not found (it is written beside the IR "
                                   "profile; copy both)") from None
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
            raise CalibrationError(f"{path}: not a valid emitter pattern file: {e}") from None
        try:
            return cls(values, counts, cell, origin)
        except CalibrationError as e:
            raise CalibrationError(f"{path}: {e}") from None


def describe(stats: dict) -> str:
    """One line of a map's diagnostics (:func:`estimate_pattern`'s ``stats``) for logs and the CLI."""
    return (f"{stats['coverage']:.0%} of {stats['cells']} cells, held-out spread "
            f"{stats['heldout_cv_without']:.0%} -> {stats['heldout_cv']:.0%} (lambda {stats['lambda']:.2f})")


def _cell2(cell) -> tuple[float, float]:
    c = np.asarray(cell, dtype=np.float64).reshape(-1)
    if c.size == 1:
        c = np.repeat(c, 2)
    if c.size != 2 or not (np.isfinite(c).all() and (c > 0).all()):
        raise CalibrationError(f"emitter pattern: cell size must be one or two positive numbers, got {cell!r}")
    return float(c[0]), float(c[1])


def sheet_directions(P: np.ndarray, emitter_position) -> np.ndarray:
    """Emitter directions ``(u, v)`` (m, 2) float32 of camera-frame points ``P`` (m, 3) (module docstring)."""
    P = np.asarray(P, dtype=np.float64)
    e = np.asarray(emitter_position, dtype=np.float64).reshape(3)
    z = P[:, 2] - e[2]
    return np.stack([(P[:, 0] - e[0]) / z, (P[:, 1] - e[1]) / z], axis=1).astype(np.float32)


def _accumulate(row, col, z, shape):
    """Per-cell sums of ``z`` and counts, (rows, cols) each."""
    idx = row * shape[1] + col
    s = np.bincount(idx, weights=z, minlength=shape[0] * shape[1])
    n = np.bincount(idx, minlength=shape[0] * shape[1])
    return s.reshape(shape), n.reshape(shape)


def _cell_means(row, col, z, shape, min_count):
    """Per-cell means (NaN where unseen), with sparse cells pooled with their u-neighbours, and counts."""
    s, n = _accumulate(row, col, z, shape)
    mc = max(int(min_count), 1)
    seen = n >= mc
    mean = np.where(seen, s / np.maximum(n, 1), np.nan)
    # a cell seen too rarely takes the mean of itself and its two neighbours along u (finer cells
    # than a pixel along the baseline are seen only at some sheet distances' parallax phases)
    s3 = s + np.pad(s, ((0, 0), (1, 0)))[:, :-1] + np.pad(s, ((0, 0), (0, 1)))[:, 1:]
    n3 = n + np.pad(n, ((0, 0), (1, 0)))[:, :-1] + np.pad(n, ((0, 0), (0, 1)))[:, 1:]
    pooled = ~seen & (n3 >= mc)
    mean[pooled] = s3[pooled] / n3[pooled]
    return mean, n


#: shrinkage factors tried for the map (0: no map, 1: the map as measured)
_LAMBDAS = np.linspace(0.0, 1.0, 21)


def estimate_pattern(dirs: np.ndarray, z: np.ndarray, fold: np.ndarray, cell: float,
                     min_count: int = 8, phase=(0.0, 0.0)) -> EmitterPattern:
    """Emitter pattern map from calibration-sheet pixels (module docstring, "Estimate").

    The map's cells are means of the pixels' relative intensities. How far the map is to be trusted
    is measured, not assumed: the map of one fold of the pixels (sheet distances alternately) predicts
    the other fold, and the map is shrunk towards 1, ``1 + lambda (m - 1)``, by the ``lambda`` that
    minimises the spread of ``Z / m`` over the held-out pixels, then scaled so that ``Z / m`` averages
    1 there (division by an imperfect map biases high: ``E[1 / m] > 1 / E[m]``). A pattern the camera
    resolves gives ``lambda`` ~1; one finer than the cells, or depth too noisy to find a pixel's
    cell again, gives a smaller ``lambda`` and, at worst, ``lambda = 0``: a map of ones (the caller
    then keeps the stationary model only).

    Parameters
    ----------
    dirs : (m, 2) array
        Emitter directions ``(u, v)`` of the pixels (:func:`sheet_directions`).
    z : (m,) array
        The pixels' relative intensities ``Z_hat`` (mean ~1); non-finite values are left out.
    fold : (m,) int array
        0 or 1: the cross-validation fold of each pixel (use alternate sheet distances, so that the
        held-out pixels see the pattern at other parallaxes, as a scan does).
    cell : float or 2 floats
        Cell size along ``u`` and ``v``, tangent-plane units (one depth pixel: ``1 / fx``).
    phase : 2 floats
        Where direction ``(0, 0)`` lies within its cell, cells (``origin``'s fractional part). With
        ``cell = 1 / fx``, ``(cx mod 1, cy mod 1)`` puts the cells' centres on the pixels' rays: the
        emitter is beside the camera on its x axis, so every pixel row has one y-direction at every
        depth, and with the centres on the rows none of them falls on a cell boundary.
    min_count : int
        Cells with fewer pixels read 1 (not seen). On a synthetic calibration (8 distances, 3 frames
        each) cells with 2-4 pixels were 16 % off the truth, 5-9: 8 %, 10-19: 2.6 %, 20 or more: 1-2 %.

    Returns
    -------
    EmitterPattern
        ``stats``: ``lambda``, ``scale``, the held-out spread of ``Z / m`` with the map
        (``heldout_cv``) and without it (``heldout_cv_without``), coverage and pixels per cell.

    Raises
    ------
    CalibrationError
        No usable pixels, or a map larger than ``MAX_SIDE`` cells a side.
    """
    dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    fold = np.asarray(fold).reshape(-1)
    if not (len(dirs) == len(z) == len(fold)):
        raise CalibrationError(f"emitter pattern: {len(dirs)} directions, {len(z)} values, {len(fold)} fold numbers")
    cell = np.asarray(_cell2(cell))
    ok = np.isfinite(z) & (z > 0) & np.isfinite(dirs).all(axis=1)
    if ok.sum() < 100:
        raise CalibrationError(f"emitter pattern: only {int(ok.sum())} usable sheet pixels (need 100)")
    dirs, z, fold = dirs[ok], z[ok], fold[ok] % 2
    ph = np.asarray(phase, dtype=np.float64).reshape(2) % 1.0
    lo = np.floor(dirs.min(axis=0) / cell + ph) - 1
    hi = np.ceil(dirs.max(axis=0) / cell + ph) + 1
    cols, rows = int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1
    if max(rows, cols) > MAX_SIDE:
        raise CalibrationError(f"emitter pattern: a {rows} x {cols} map (cell {cell[0]:.3g} x {cell[1]:.3g}) is too large; "
                               "use a coarser cell")
    shape = (rows, cols)
    pat = EmitterPattern(np.ones(shape, np.float32), np.zeros(shape, np.uint16), tuple(cell),
                         (ph[0] - lo[0], ph[1] - lo[1]))
    row, col = pat.cells(dirs[:, 0], dirs[:, 1])
    mean, n = _cell_means(row, col, z, shape, min_count)
    seen = np.isfinite(mean)
    norm = float(np.mean(mean[seen])) if seen.any() else 1.0
    m_full = np.where(seen, mean / norm, 1.0)
    # cross-validation: each fold predicted by the other fold's map
    ratios = []                                          # (z, m) of held-out pixels in cells the other fold saw
    for f in (0, 1):
        tr, te = fold != f, fold == f
        if not tr.any() or not te.any():
            continue
        mo, _ = _cell_means(row[tr], col[tr], z[tr], shape, min_count)
        so = np.isfinite(mo)
        if not so.any():
            continue
        mo = np.where(so, mo / float(np.mean(mo[so])), np.nan)
        mt = mo[row[te], col[te]]
        k = np.isfinite(mt)
        ratios.append((z[te][k], mt[k]))
    lam, scale, cv_with, cv_without = 1.0, 1.0, float("nan"), float("nan")
    if ratios and sum(len(a) for a, _ in ratios) > 100:
        zz = np.concatenate([a for a, _ in ratios])
        mm = np.concatenate([b for _, b in ratios])
        if len(zz) > 400_000:                            # the spread needs no more
            pick = np.random.default_rng(0).choice(len(zz), 400_000, replace=False)
            zz, mm = zz[pick], mm[pick]
        cvs = []
        for la in _LAMBDAS:
            r = zz / np.maximum(1.0 + la * (mm - 1.0), 1e-3)
            cvs.append(float(np.std(r) / np.mean(r)))
        i = int(np.argmin(cvs))
        lam = float(_LAMBDAS[i])
        r = zz / np.maximum(1.0 + lam * (mm - 1.0), 1e-3)
        scale = float(np.mean(r))
        cv_with, cv_without = cvs[i], cvs[0]
    vals = np.maximum((1.0 + lam * (m_full - 1.0)) * scale, 1e-3)
    vals = np.where(seen, vals, 1.0).astype(np.float32)
    stats = {"cells": int(rows * cols), "cells_seen": int(seen.sum()), "coverage": float(seen.mean()),
             "pixels": int(len(z)), "pixels_per_cell": float(np.mean(n[seen])) if seen.any() else 0.0,
             "cell": [float(c) for c in cell], "cv": float(np.std(vals[seen])) if seen.any() else 0.0,
             "lambda": lam, "scale": scale, "heldout_cv": cv_with, "heldout_cv_without": cv_without}
    pat.values = vals
    pat.counts = np.minimum(n, np.iinfo(np.uint16).max).astype(np.uint16)
    pat.stats = stats
    return pat
