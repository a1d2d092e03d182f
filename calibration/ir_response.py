"""IR response curve and emitter model from a white sheet at several distances (paper §6).

    "We calibrate the IR/depth camera response curve by viewing a sheet of white paper from different
    distances. Assuming that the IR light intensity distribution is spatially and temporally
    stationary, we compute both unknown IR intensity distribution, modeled as a shifted Gamma
    distribution, and the response curve, using the reflected IR light from the paper at different
    distances via a brute-force optimization."

Model (see :mod:`calibration.ir_profile` for the normalisation): a Lambertian sheet of albedo ``rho``
gives at a pixel ``raw - b0 = gain (rho / pi cos(theta_i) x)^gamma`` with ``x = theta (g + r) / d^p``,
``g ~ Gamma(k, 1)``, ``r = shift / theta``. Hence for the right ``gamma``

    z = (raw - b0)^(1/gamma) d^p / cos(theta_i) = A (g + r),     A = gain^(1/gamma) (rho / pi) theta,

has the *same* distribution at every distance; for a wrong ``gamma`` the distributions at different
distances are scaled apart by ``(d^p / cos)^(1 - gamma'/gamma)`` (and slightly reshaped). The fit
matches the quantiles of ``z`` per distance group (levels 3 % .. 97 %, trimmed where pixels are
saturated or below the noise) to ``A (Q_k(p) + r)``, ``Q_k`` the Gamma(k, 1) quantile function:

1. brute force over a grid of ``gamma`` (0.5 .. 1.5, step 0.02) and ``k`` (0.3 .. 20, log-spaced), with
   ``A`` and ``A r`` solved linearly for each grid point (the paper's brute-force optimisation);
2. ``scipy.optimize.least_squares`` on the log-quantile residuals over ``(gamma, log k, log A, r)``
   from the best grid point.

Then ``theta = 1 / (k + r)``, ``shift = r theta``, ``gain = (A pi / (rho theta))^gamma``.

Flat emitters (``model="flat"``) have ``z = A`` everywhere: ``log(raw - b0) = gamma log A + gamma log(cos / d^p)``
is fitted by robust (soft-L1) linear least squares over all pixels, ``gain = (A pi / rho)^gamma``.

Per frame the sheet is the dominant plane of the depth image (least squares on inliers within 3
robust sigmas); ``d`` is each pixel's distance to the emitter and ``cos(theta_i)`` uses the plane's
normal. Frames whose median distances are within 2 % form one distance group.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.special import gammaincinv

from appfusion.errors import CalibrationError
from appfusion.frame import Frame, Intrinsics

from .ir_background import Background, estimate_background
from .ir_pattern import EmitterPattern, estimate_pattern, sheet_directions
from .ir_profile import IRProfile

#: quantile levels matched by the shifted-Gamma fit
QUANTILE_LEVELS = np.linspace(0.03, 0.97, 24)
#: pattern-map cells per depth pixel along the emitter's baseline (u): the parallax moves a pixel's
#: emitter direction along u with the sheet's distance, so the calibration sees u finer than a pixel.
#: Measured on a synthetic sphere whose pattern grid is offset from the pixels by 0.37 cell: 2 cells
#: halve the map's error against the truth (1.9 % against 5.3 %) but gave the same alpha (0.1224 and
#: 0.1221 for 0.12; the truth pattern 0.1221), so one
PATTERN_SUBCELLS_U = 1
#: the pattern map is kept when the held-out spread of ``Z / m`` is at most this fraction of the
#: spread without it (synthetic Kinect: 0.21; a pattern finer than the pixels: 0.86)
PATTERN_MAX_RESIDUAL = 0.5
GAMMA_GRID = np.round(np.arange(0.5, 1.5001, 0.02), 4)
K_GRID = np.geomspace(0.3, 20.0, 40)


@dataclass
class SheetObservation:
    """Pixels of the calibration sheet in one frame (or a group of frames at one distance).

    Attributes
    ----------
    raw : (m,) float64
        Raw IR values, counts.
    d : (m,) float64
        Distance from the emitter, metres.
    cos_i : (m,) float64
        Cosine of incidence at the sheet.
    median_d : float
        Median of ``d``.
    frame : int
        Index of the (first) frame.
    dirs : (m, 2) float32 or None
        Emitter directions of the pixels (:func:`calibration.ir_pattern.sheet_directions`), of their
        points on the fitted plane (depth noise removed); None after :func:`group_by_distance`.
    """

    raw: np.ndarray
    d: np.ndarray
    cos_i: np.ndarray
    median_d: float
    frame: int = 0
    dirs: np.ndarray | None = None


def _plane(P: np.ndarray, where: str):
    """Robust plane through points (m, 3): unit normal facing the origin, inlier mask, a point on it."""
    rng = np.random.default_rng(0)
    sub = P if len(P) <= 20000 else P[rng.choice(len(P), 20000, replace=False)]
    inl = np.ones(len(sub), bool)
    n = c = None
    for _ in range(3):
        c = sub[inl].mean(0)
        _, _, vt = np.linalg.svd(sub[inl] - c, full_matrices=False)
        n = vt[2]
        r = (sub - c) @ n
        mad = float(np.median(np.abs(r - np.median(r[inl]))))
        thr = max(3.0 * 1.4826 * mad, 2e-3)
        inl = np.abs(r) < thr
        if inl.sum() < 3:
            raise CalibrationError(f"{where}: the depth image does not contain a flat sheet")
    if n @ c > 0:
        n = -n
    r_all = (P - c) @ n
    ok = np.abs(r_all) < thr
    return n, ok, c


def sheet_observation(ir: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics, emitter_position,
                      frame: int = 0, min_inliers: float = 0.3) -> SheetObservation:
    """Extract the sheet pixels of one calibration frame (module docstring).

    Parameters
    ----------
    ir, depth : (H, W) arrays
        Raw IR (counts) and depth (metres, NaN invalid) on the same pixel grid.
    intrinsics : Intrinsics
    emitter_position : 3 floats
        Emitter in the camera frame, metres.
    frame : int
        Frame index, for messages.
    min_inliers : float
        Smallest fraction of valid pixels on the plane.
    """
    where = f"IR calibration, frame {frame}"
    ir = np.asarray(ir, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    if ir.shape != depth.shape or depth.shape != intrinsics.shape:
        raise CalibrationError(f"{where}: IR {ir.shape}, depth {depth.shape} and intrinsics {intrinsics.shape} "
                               "differ in size")
    valid = np.isfinite(depth) & (depth > 0) & np.isfinite(ir)
    if valid.sum() < 100:
        raise CalibrationError(f"{where}: fewer than 100 pixels with both depth and IR")
    P = intrinsics.backproject(depth.astype(np.float32)).astype(np.float64)[valid]
    n, on, c = _plane(P, where)
    if on.mean() < min_inliers:
        raise CalibrationError(f"{where}: only {on.mean():.0%} of the pixels lie on one plane; "
                               "the white sheet must fill most of the view")
    e = np.asarray(emitter_position, dtype=np.float64).reshape(3)
    P = P[on]
    L = e - P
    d = np.linalg.norm(L, axis=1)
    cos_i = (L @ n) / d
    keep = cos_i > 0.2
    # the pixels' rays met with the fitted plane: their emitter directions without depth noise
    ray = P[keep] / P[keep, 2:3]
    with np.errstate(invalid="ignore", divide="ignore"):
        Pp = ray * ((n @ c) / (ray @ n))[:, None]
    return SheetObservation(ir[valid][on][keep], d[keep], cos_i[keep], float(np.median(d[keep])), frame,
                            sheet_directions(Pp, e))


def distance_groups(obs: Sequence[SheetObservation], rel_tol: float = 0.02) -> np.ndarray:
    """Distance group of each observation (int, 0 = nearest): sorted by median distance, an
    observation within ``rel_tol`` of its group's first (nearest) one joins that group."""
    gid = np.zeros(len(obs), np.int64)
    g, first = -1, None
    for i in sorted(range(len(obs)), key=lambda i: obs[i].median_d):
        if first is None or obs[i].median_d > first * (1 + rel_tol):
            g, first = g + 1, obs[i].median_d
        gid[i] = g
    return gid


def group_by_distance(obs: Sequence[SheetObservation], rel_tol: float = 0.02,
                      max_pixels: int = 60000, seed: int = 0) -> list[SheetObservation]:
    """Merge observations whose median distances are within ``rel_tol``; subsample each group."""
    if not obs:
        return []
    rng = np.random.default_rng(seed)
    gid = distance_groups(obs, rel_tol)
    order = sorted(range(len(obs)), key=lambda i: obs[i].median_d)
    groups: list[list[SheetObservation]] = [[] for _ in range(int(gid.max()) + 1)]
    for i in order:
        groups[gid[i]].append(obs[i])
    out = []
    for g in groups:
        raw = np.concatenate([o.raw for o in g])
        d = np.concatenate([o.d for o in g])
        c = np.concatenate([o.cos_i for o in g])
        if len(raw) > max_pixels:
            s = rng.choice(len(raw), max_pixels, replace=False)
            raw, d, c = raw[s], d[s], c[s]
        out.append(SheetObservation(raw, d, c, float(np.median(d)), g[0].frame))
    return out


# -- shifted Gamma --------------------------------------------------------------------------------

def _group_quantiles(groups, b0, gamma, p_exp, low, sat):
    """Per group: the quantile levels usable and the quantiles of z for this gamma."""
    out = []
    for g in groups:
        u = g.raw - b0
        is_sat = g.raw >= sat
        is_low = u < low
        z = np.maximum(u, 1e-6) ** (1.0 / gamma) * g.d ** p_exp / g.cos_i
        z[is_sat] = np.inf
        lo = is_low.mean() + 0.01
        hi = 1.0 - is_sat.mean() * 1.5 - 0.01
        p = QUANTILE_LEVELS[(QUANTILE_LEVELS > lo) & (QUANTILE_LEVELS < hi)]
        q = np.quantile(z, p) if len(p) else np.zeros(0)
        out.append((p, q))
    return out


def _linear_ab(Qs, qs):
    """A, B minimising sum ((A Q + B) / q - 1)^2 (relative linear least squares)."""
    M = np.stack([Qs / qs, 1.0 / qs], axis=1)
    sol, *_ = np.linalg.lstsq(M, np.ones(len(qs)), rcond=None)
    return float(sol[0]), float(sol[1])


def fit_shifted_gamma(groups: Sequence[SheetObservation], background: float, noise_sigma: float = 1.0,
                      saturation: float = 1023.0, falloff_exponent: float = 1.0) -> dict:
    """Fit ``gamma, k, r, A`` of the shifted-Gamma model to sheet observations (module docstring).

    Returns a dict with ``gamma, k, r, A`` and diagnostics ``rms_log, n_levels, grid_best``.
    """
    low = max(3.0 * noise_sigma, 2.0)
    best = None
    for gamma in GAMMA_GRID:
        gq = _group_quantiles(groups, background, gamma, falloff_exponent, low, saturation)
        ps = np.concatenate([p for p, _ in gq])
        qs = np.concatenate([q for _, q in gq])
        if len(qs) < 6 or not np.all(np.isfinite(qs)) or np.any(qs <= 0):
            continue
        lq = np.log(qs)
        for k in K_GRID:
            Q = gammaincinv(k, ps)
            A, B = _linear_ab(Q, qs)
            if not (A > 0):
                continue
            m = A * Q + B
            if np.any(m <= 0):
                continue
            cost = float(np.sum((lq - np.log(m)) ** 2))
            if best is None or cost < best[0]:
                best = (cost, gamma, k, A, B / A)
    if best is None:
        raise CalibrationError("IR calibration: the sheet's IR values are unusable (all saturated or below "
                               "the background noise)")
    _, g0, k0, A0, r0 = best

    def resid(x):
        gamma, lk, lA, r = x
        gq = _group_quantiles(groups, background, gamma, falloff_exponent, low, saturation)
        res = []
        for p, q in gq:
            m = np.exp(lA) * (gammaincinv(np.exp(lk), p) + r)
            res.append(np.log(np.maximum(q, 1e-300)) - np.log(np.maximum(m, 1e-300)))
        # keep a fixed residual length: pad groups' missing levels with zeros
        return np.concatenate([np.pad(r_, (0, len(QUANTILE_LEVELS) - len(r_))) for r_ in res])

    x0 = np.array([g0, np.log(k0), np.log(A0), max(r0, 0.0)])
    res = least_squares(resid, x0, bounds=([0.3, np.log(0.05), -np.inf, 0.0], [2.0, np.log(100.0), np.inf, 100.0]),
                        diff_step=[1e-4, 1e-4, 1e-4, 1e-4], x_scale=[0.01, 0.05, 0.05, 0.05], max_nfev=200)
    gamma, lk, lA, r = res.x
    n_lev = int(sum(len(p) for p, _ in _group_quantiles(groups, background, gamma, falloff_exponent, low, saturation)))
    rms = float(np.sqrt(np.sum(res.fun ** 2) / max(n_lev, 1)))
    return {"gamma": float(gamma), "k": float(np.exp(lk)), "r": float(r), "A": float(np.exp(lA)),
            "rms_log": rms, "n_levels": n_lev,
            "grid_best": {"gamma": float(g0), "k": float(k0), "r": float(r0), "A": float(A0)}}


def fit_flat(groups: Sequence[SheetObservation], background: float, noise_sigma: float = 1.0,
             saturation: float = 1023.0, falloff_exponent: float = 2.0) -> dict:
    """Fit ``gamma, A`` of the flat-emitter model: ``raw - b0 = (A cos / d^p)^gamma`` (robust)."""
    low = max(3.0 * noise_sigma, 2.0)
    xs, ys = [], []
    for g in groups:
        u = g.raw - background
        ok = (u > low) & (g.raw < saturation)
        xs.append(np.log(g.cos_i[ok] / g.d[ok] ** falloff_exponent))
        ys.append(np.log(u[ok]))
    x, y = np.concatenate(xs), np.concatenate(ys)
    if len(x) < 10:
        raise CalibrationError("IR calibration: the sheet's IR values are unusable (all saturated or below "
                               "the background noise)")
    A_ = np.stack([x, np.ones_like(x)], axis=1)
    sol, *_ = np.linalg.lstsq(A_, y, rcond=None)
    res = least_squares(lambda s: A_ @ s - y, sol, loss="soft_l1", f_scale=0.05)
    gamma, c = res.x
    if not gamma > 0:
        raise CalibrationError(f"IR calibration: fitted response exponent {gamma:.3g} is not positive; "
                               "the sheet gets brighter with distance?")
    rms = float(np.sqrt(np.mean((A_ @ res.x - y) ** 2)))
    return {"gamma": float(gamma), "A": float(np.exp(c / gamma)), "rms_log": rms, "n_pixels": int(len(x))}


# -- the emitter pattern --------------------------------------------------------------------------------

def pattern_from_sheets(profile: IRProfile, obs: Sequence[SheetObservation], cell: float,
                        phase=(0.0, 0.0)) -> EmitterPattern:
    """The emitter's pattern map (:mod:`calibration.ir_pattern`) from every sheet pixel of the calibration.

    Each pixel's relative intensity is its reflectance sample under the fitted ``profile`` over the
    sheet's ``sheet_albedo / pi``; saturated pixels and those within three noise sigmas of the
    background are left out. ``phase``: see :func:`calibration.ir_pattern.estimate_pattern`.
    """
    dirs, z, fold = [], [], []
    low = profile.background + max(3.0 * profile.noise_sigma, 2.0)
    group = distance_groups(obs)                       # cross-validation folds: alternate distances
    for i, o in enumerate(obs):
        if o.dirs is None:
            continue
        ok = (o.raw < profile.saturation) & (o.raw > low)
        s, valid = profile.apply(o.raw[ok], o.d[ok], o.cos_i[ok])
        dirs.append(o.dirs[ok][valid])
        z.append(s[valid] / (profile.sheet_albedo / np.pi))
        fold.append(np.full(int(valid.sum()), group[i] % 2, np.int64))
    if not dirs:
        raise CalibrationError("IR calibration: no sheet pixels with emitter directions for the pattern map")
    return estimate_pattern(np.concatenate(dirs), np.concatenate(z), np.concatenate(fold), cell, phase=phase)


# -- the whole calibration ----------------------------------------------------------------------------

def calibrate_ir(frames: Iterable[Frame], emitter_position=None, model: str = "shifted_gamma",
                 sheet_albedo: float = 1.0, device: str = "", saturation: float = 1023.0,
                 min_distance_ratio: float = 1.2, max_pixels: int = 60000, pattern: bool = True,
                 pattern_cell: float | None = None) -> IRProfile:
    """IR device profile from the frames of an ``ir-calibration`` pass (paper §6).

    Parameters
    ----------
    frames : iterable of Frame
        Frames with ``ir``; those with ``emitter is False`` give the background, the others (with
        depth) show the white sheet fronto-parallel at several distances.
    emitter_position : 3 floats, optional
        Emitter in the depth-camera frame, metres (default ``(0.075, 0, 0)``).
    model : {"shifted_gamma", "flat"}
        Emitter model (Kinect v1 dot pattern / flood illuminator).
    sheet_albedo : float
        Albedo of the sheet; samples are absolute BRDF values if it is right (relative to the sheet
        otherwise).
    device : str
        Stored in the profile.
    saturation : float
        Raw level at which the sensor clips.
    min_distance_ratio : float
        Farthest over nearest sheet distance needed.
    max_pixels : int
        Pixels used per distance group.
    pattern : bool
        Shifted-Gamma model only: also map the emitter's fixed pattern over its directions from all
        sheet pixels (:mod:`calibration.ir_pattern`; ``profile.pattern``, diagnostics in
        ``profile.fit["pattern"]``). The map is kept only where it predicts sheet pixels at held-out
        distances well (``PATTERN_MAX_RESIDUAL``); ``profile.fit["pattern"]["used"]`` says.
    pattern_cell : float, optional
        Cell of that map, tangent-plane units (default: one depth pixel, ``1 / fx``).

    Returns
    -------
    IRProfile

    Raises
    ------
    CalibrationError
        No emitter-off frames, no sheet frames, the sheet at one distance only, unusable values.
    """
    if model not in ("shifted_gamma", "flat"):
        raise CalibrationError(f"IR calibration: unknown emitter model {model!r} (use shifted_gamma or flat)")
    if not sheet_albedo > 0:
        raise CalibrationError(f"IR calibration: sheet albedo must be positive, got {sheet_albedo}")
    if not (np.isfinite(saturation) and saturation > 0):
        raise CalibrationError(f"IR calibration: saturation must be a positive raw IR level (where the sensor "
                               f"clips, e.g. 1023 for 10 bits), got {saturation}")
    e = np.asarray((0.075, 0.0, 0.0) if emitter_position is None else emitter_position, dtype=float).reshape(3)
    off, obs, skipped = [], [], []
    pattern_phase = (0.0, 0.0)
    n_frames = 0
    for f in frames:
        n_frames += 1
        if f.ir is None:
            skipped.append(f.index)
            continue
        if f.emitter is False:
            off.append(f.ir)
            continue
        if f.depth is None:
            skipped.append(f.index)
            continue
        intr = f.depth_intrinsics or f.ir_intrinsics
        if intr is None:
            raise CalibrationError(f"IR calibration, frame {f.index}: no intrinsics")
        obs.append(sheet_observation(f.ir, f.depth, intr, e, frame=f.index))
        if pattern_cell is None:
            su = PATTERN_SUBCELLS_U
            pattern_cell = (1.0 / (su * float(intr.fx)), 1.0 / float(intr.fy))
            pattern_phase = (su * float(intr.cx), float(intr.cy))
    if n_frames == 0:
        raise CalibrationError("IR calibration: no frames (is there an ir-calibration pass?)")
    if not off:
        raise CalibrationError("IR calibration: no emitter-off frames; the ir-calibration pass must start with "
                               "IR frames taken with the emitter switched off")
    if not obs:
        raise CalibrationError("IR calibration: no emitter-on frames with depth showing the white sheet")
    bg: Background = estimate_background(off, max_value=saturation)
    groups = group_by_distance(obs, max_pixels=max_pixels)
    dists = [g.median_d for g in groups]
    if len(groups) < 2 or max(dists) / min(dists) < min_distance_ratio:
        raise CalibrationError(f"IR calibration: the sheet was seen at {len(groups)} distance(s) "
                               f"({', '.join(f'{x:.3f}' for x in dists)} m); need at least two, the farthest "
                               f"{min_distance_ratio:g}x the nearest")
    p_exp = 1.0 if model == "shifted_gamma" else 2.0
    diag = {"distances_m": dists, "n_sheet_frames": len(obs), "n_background_frames": bg.n_frames,
            "skipped_frames": skipped}
    if model == "shifted_gamma":
        fit = fit_shifted_gamma(groups, bg.level, bg.noise_sigma, saturation, p_exp)
        k, r = fit["k"], fit["r"]
        theta = 1.0 / (k + r)
        shift = r * theta
        gain = (fit["A"] * np.pi / (sheet_albedo * theta)) ** fit["gamma"]
        diag.update({kk: v for kk, v in fit.items() if kk not in ("gamma", "k", "A")})
        diag["shift_over_theta"] = r
        prof = IRProfile(emitter_model=model, background=bg.level, noise_sigma=bg.noise_sigma,
                         gamma=fit["gamma"], gain=float(gain), k=k, theta=theta, shift=shift, scale=1.0,
                         falloff_exponent=p_exp, sheet_albedo=sheet_albedo, saturation=saturation,
                         emitter_position_m=list(e), device=device, fit=diag)
        if pattern:
            pat = pattern_from_sheets(prof, obs, pattern_cell, pattern_phase)
            st = pat.stats
            # kept where it predicts held-out sheet pixels clearly better than the mean: the IR pass
            # then treats its unclipped samples as unbiased (appfusion.ward_fit), which holds only when
            # little of the pattern's spread is left
            used = bool(st["lambda"] > 0 and st["heldout_cv"] <= PATTERN_MAX_RESIDUAL * st["heldout_cv_without"])
            diag["pattern"] = dict(st, used=used)
            prof.pattern = pat if used else None
        return prof
    fit = fit_flat(groups, bg.level, bg.noise_sigma, saturation, p_exp)
    gain = (fit["A"] * np.pi / sheet_albedo) ** fit["gamma"]
    diag.update({kk: v for kk, v in fit.items() if kk not in ("gamma", "A")})
    return IRProfile(emitter_model=model, background=bg.level, noise_sigma=bg.noise_sigma, gamma=fit["gamma"],
                     gain=float(gain), scale=1.0, falloff_exponent=p_exp, sheet_albedo=sheet_albedo,
                     saturation=saturation, emitter_position_m=list(e), device=device, fit=diag)
