"""Robust sphere fit to the mirror ball's geometry (paper §4.3).

The paper scans the mirror ball with KinectFusion and, because a mirror returns weak and noisy depth,
"fit[s] a perfect sphere to the captured geometry using least squares, right after the automatic
object/background geometry separation". This module does that robustly:

1. validation (finite points, plausible units, not coincident / collinear / coplanar);
2. RANSAC over minimal 4-point spheres (vectorised, MSAC cost) for outlier-free starts;
3. geometric least squares ``r_i = |p_i - c| - R`` with a robust ``soft_l1`` loss
   (:func:`scipy.optimize.least_squares`), a few rounds on the points within a band around the current
   sphere that shrinks to 3 sigma of the noise; the best of the refined candidates wins;
4. checks that the answer is determined: the radius must lie in a plausible range, enough points must
   lie on the shell, the shell must be much denser than its surroundings (a cloud of outliers is not),
   the scatter must be small against the radius, and the radius (when it is estimated) must be
   determined by the patch's curvature (its standard error from the Gauss-Newton covariance, and the
   cap's sagitta against the noise).

Anything that fails raises :class:`~appfusion.errors.EstimationError` naming the reason; the result
never contains NaN.

Points can come from a fused mesh (:func:`fit_sphere`) or straight from depth frames cropped to the
object box (:func:`points_from_depth`, :class:`PointReservoir`, :func:`fit_sphere_from_depth`).
:func:`refine_center` re-locates a ball of known radius in a single frame's points (used per frame by
the lighting pass to cancel tracking error).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np
from scipy.optimize import least_squares

from .errors import AppFusionError, EstimationError
from .frame import Intrinsics, transform_points

#: largest coordinate magnitude accepted (metres); anything beyond is taken as a units mistake
MAX_COORD_M = 1.0e4


@dataclass(frozen=True)
class SphereFit:
    """Result of a sphere fit. All lengths in metres.

    Attributes
    ----------
    center : (3,) float64 ndarray
        Sphere centre in the frame of the input points (the marker/world frame in the pipeline).
    radius : float
        Sphere radius (the given one when the radius was fixed).
    rms_m : float
        Root-mean-square geometric residual ``|p - c| - R`` over the inliers.
    inlier_fraction : float
        Fraction of the (finite) points within ``inlier_threshold_m`` of the sphere.
    n_points, n_inliers : int
        Number of finite points used and of inliers among them.
    radius_std_m : float
        Standard error of the radius from the Gauss-Newton covariance (0 when the radius was fixed).
    center_std_m : float
        Largest standard error of a centre coordinate, from the same covariance.
    radius_fixed : bool
        True if the radius was given and only the centre was fitted.
    method : str
        ``"geometric"`` (:func:`fit_sphere`: distances of depth points to the sphere) or ``"mirror"``
        (:func:`fit_mirror_ball`: specular-spot points with known normals and silhouette rays).
    n_spots, n_rays : int
        Mirror fit only: specular-spot points and silhouette rays that agree with the result (inliers).
    on_plane : bool
        The ball was constrained to rest on the support plane (``center_z = plane_z + radius``).
    plane_gap_m : float
        Mirror fit only: ``center_z - plane_z - radius`` of the unconstrained fit (0 when not computed);
        near 0 for a ball resting on the plane.
    """

    center: np.ndarray
    radius: float
    rms_m: float
    inlier_fraction: float
    n_points: int
    n_inliers: int
    radius_std_m: float = 0.0
    center_std_m: float = 0.0
    radius_fixed: bool = False
    method: str = "geometric"
    n_spots: int = 0
    n_rays: int = 0
    on_plane: bool = False
    plane_gap_m: float = 0.0

    def residuals(self, points: np.ndarray) -> np.ndarray:
        """Signed distances ``|p - c| - R`` (metres) of points (N, 3) to this sphere, shape (N,)."""
        return np.linalg.norm(np.asarray(points, float) - self.center, axis=-1) - self.radius

    def to_json(self) -> dict[str, Any]:
        return {"center": [float(x) for x in self.center], "radius": float(self.radius),
                "rms_m": float(self.rms_m), "inlier_fraction": float(self.inlier_fraction),
                "n_points": int(self.n_points), "n_inliers": int(self.n_inliers),
                "radius_std_m": float(self.radius_std_m), "center_std_m": float(self.center_std_m),
                "radius_fixed": bool(self.radius_fixed), "method": self.method, "n_spots": int(self.n_spots),
                "n_rays": int(self.n_rays), "on_plane": bool(self.on_plane),
                "plane_gap_m": float(self.plane_gap_m)}


# -- validation --------------------------------------------------------------------------------

def _validate(points: Any, min_points: int, where: str) -> np.ndarray:
    try:
        p = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise EstimationError(f"{where}: points must be numbers of shape (N, 3): {e}") from None
    if p.ndim != 2 or p.shape[1] != 3:
        raise EstimationError(f"{where}: points must have shape (N, 3), got {p.shape}")
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) < min_points:
        raise EstimationError(f"{where}: too few points: {len(p)} finite points, need at least {min_points}")
    if np.abs(p).max() > MAX_COORD_M:
        raise EstimationError(f"{where}: coordinates up to {np.abs(p).max():.3g} m; points must be in metres "
                              f"within {MAX_COORD_M:g} m of the origin")
    return p


def _shape_check(p: np.ndarray, where: str) -> None:
    """Reject coincident, collinear and coplanar point sets (singular values of the centred cloud)."""
    q = p - p.mean(axis=0)
    s = np.linalg.svd(q, compute_uv=False) / np.sqrt(len(p))  # standard deviations along principal axes
    scale = max(s[0], np.abs(p).max(), 1e-300)
    tol = 1e-9 * scale
    if s[0] <= tol:
        raise EstimationError(f"{where}: all {len(p)} points coincide; a sphere needs a spread of points")
    if s[1] <= tol + 1e-6 * s[0]:
        raise EstimationError(f"{where}: the {len(p)} points are collinear; a sphere cannot be fitted")
    if s[2] <= tol + 1e-6 * s[0]:
        raise EstimationError(f"{where}: the {len(p)} points are coplanar; a plane does not determine a sphere")


# -- algebraic pieces ------------------------------------------------------------------------------

def algebraic_fit(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Linear least-squares sphere ``|p|^2 = 2 c.p + (R^2 - |c|^2)`` (Kasa fit).

    Parameters
    ----------
    points : (N, 3) array, metres, N >= 4, not coplanar.

    Returns
    -------
    center : (3,) ndarray
    radius : float

    Raises
    ------
    EstimationError
        If the system is singular or the radius comes out imaginary.
    """
    p = np.asarray(points, dtype=np.float64)
    m = p.mean(axis=0)
    q = p - m
    A = np.column_stack([2.0 * q, np.ones(len(q))])
    b = (q * q).sum(axis=1)
    sol, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    if rank < 4 or not np.isfinite(sol).all():
        raise EstimationError("sphere fit: algebraic fit is singular (points coplanar or too few)")
    c = sol[:3]
    r2 = sol[3] + c @ c
    if not np.isfinite(r2) or r2 <= 0:
        raise EstimationError("sphere fit: algebraic fit gave no real radius")
    return c + m, float(np.sqrt(r2))


def _ransac(p: np.ndarray, tau: float, radius: float | None, r_range: tuple[float, float],
            n_hyp: int, rng: np.random.Generator, n_keep: int = 4) -> list[tuple[np.ndarray, float]]:
    """The ``n_keep`` best distinct of ``n_hyp`` 4-point spheres by MSAC cost ``sum min(r^2, tau^2)``."""
    n = len(p)
    m = p.mean(axis=0)
    q = p - m
    idx = rng.integers(0, n, size=(n_hyp, 4))
    S = q[idx]                                              # (K, 4, 3)
    A = np.concatenate([2.0 * S, np.ones((n_hyp, 4, 1))], axis=2)
    b = (S * S).sum(axis=2)
    scale = max(np.abs(q).max(), 1e-12)
    det = np.linalg.det(A / np.array([scale, scale, scale, scale * scale]))
    ok = np.abs(det) > 1e-9
    if not ok.any():
        return []
    A = A[ok]
    b = b[ok]
    try:
        sol = np.linalg.solve(A, b[..., None])[..., 0]      # (K', 4)
    except np.linalg.LinAlgError:
        # a sample the determinant test let through is exactly singular in LU (the scaled test can
        # pass for points all but on one plane): solve one by one and drop the singular ones
        sol = np.full((len(A), 4), np.nan)
        for i in range(len(A)):
            try:
                sol[i] = np.linalg.solve(A[i], b[i])
            except np.linalg.LinAlgError:
                pass
    c = sol[:, :3]
    r2 = sol[:, 3] + (c * c).sum(axis=1)
    good = np.isfinite(r2) & (r2 > 0)
    c, r2 = c[good], r2[good]
    if not len(c):
        return []
    r = np.sqrt(r2)
    if radius is not None:
        good = np.abs(r - radius) < 0.5 * radius
        c, r = c[good], np.full(good.sum(), radius)
    else:
        good = (r >= r_range[0]) & (r <= r_range[1])
        c, r = c[good], r[good]
    if not len(c):
        return []
    # score in chunks so memory stays bounded (K x N distances)
    costs = np.empty(len(c))
    chunk = max(1, int(4e6 // n))
    for s in range(0, len(c), chunk):
        d = np.linalg.norm(q[None, :, :] - c[s:s + chunk, None, :], axis=2) - r[s:s + chunk, None]
        costs[s:s + chunk] = np.minimum(d * d, tau * tau).sum(axis=1)
    # the n_keep best candidates that differ from each other by more than tau
    out: list[tuple[np.ndarray, float]] = []
    for k in np.argsort(costs, kind="stable"):
        if all(np.linalg.norm(c[k] + m - co) > tau or abs(r[k] - ro) > tau for co, ro in out):
            out.append((c[k] + m, float(r[k])))
            if len(out) == n_keep:
                break
    return out


def _refine(p: np.ndarray, c0: np.ndarray, r0: float, radius: float | None, f_scale: float,
            r_bounds: tuple[float, float] | None = None) -> tuple[np.ndarray, float, np.ndarray]:
    """Geometric least squares with a soft-L1 loss; returns centre, radius and the Jacobian at the end.

    ``r_bounds`` (when the radius is free) keeps the radius in a box so that a hopeless start (a plane,
    a blob) cannot run the solver off to an infinite sphere.
    """
    m = p.mean(axis=0)
    q = p - m

    if radius is None:
        def fun(x):
            return np.linalg.norm(q - x[:3], axis=1) - x[3]

        def jac(x):
            d = q - x[:3]
            nrm = np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
            return np.column_stack([-d / nrm, -np.ones(len(d))])

        x0 = np.r_[c0 - m, r0]
    else:
        def fun(x):
            return np.linalg.norm(q - x, axis=1) - radius

        def jac(x):
            d = q - x
            return -d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)

        x0 = np.asarray(c0 - m, dtype=np.float64)
    bounds = (-np.inf, np.inf)
    if radius is None and r_bounds is not None:
        lo, hi = float(r_bounds[0]), float(r_bounds[1])
        x0[3] = np.clip(x0[3], lo * 1.0001, hi * 0.9999)
        bounds = (np.array([-np.inf, -np.inf, -np.inf, lo]), np.array([np.inf, np.inf, np.inf, hi]))
    res = least_squares(fun, x0, jac=jac, bounds=bounds, loss="soft_l1", f_scale=f_scale, method="trf",
                        x_scale="jac", max_nfev=50)
    x = res.x
    if radius is None:
        return x[:3] + m, float(x[3]), jac(x)
    return x + m, float(radius), jac(x)


def _robust_refine(p: np.ndarray, c: np.ndarray, r: float, radius: float | None, tau: float,
                   min_points: int, where: str, r_bounds: tuple[float, float] | None = None
                   ) -> tuple[np.ndarray, float, float]:
    """Robust geometric least squares from a start (c, r); returns centre, radius and noise sigma.

    A few rounds, each on the points within a band around the current sphere that shrinks to 3 sigma of
    the inlier noise (sigma from the MAD): outliers outside the band have no influence at all, those
    inside are damped by the soft-L1 loss.
    """
    band, sigma = tau, tau
    for _ in range(4):
        d = np.abs(np.linalg.norm(p - c, axis=1) - r)
        near = d < band
        if near.sum() < min_points:
            break
        sigma = float(np.clip(1.4826 * np.median(d[near]), 2e-4, tau))
        c, r, _ = _refine(p[near], c, r, radius, sigma, r_bounds)
        if not (np.isfinite(c).all() and np.isfinite(r)):
            raise EstimationError(f"{where}: least squares diverged on {len(p)} points")
        band = float(np.clip(3.0 * sigma, 1e-3, tau))
    return c, r, sigma


# -- the fit ---------------------------------------------------------------------------------------

def fit_sphere(points: Any, radius: float | None = None, *, inlier_threshold_m: float = 0.01,
               radius_range_m: tuple[float, float] = (0.01, 1.0), min_inlier_fraction: float = 0.3,
               min_points: int = 10, max_points: int = 20000, n_hypotheses: int = 256,
               max_radius_rel_std: float = 0.01, max_rms_rel: float = 0.1, seed: int = 0,
               where: str = "sphere fit") -> SphereFit:
    """Fit a sphere to noisy, partial points with outliers (paper §4.3).

    Parameters
    ----------
    points : (N, 3) array_like
        Points in metres (world/marker frame). Rows with NaN/inf are dropped.
    radius : float, optional
        Known radius of the ball (metres); then only the centre is fitted.
    inlier_threshold_m : float
        A point is an inlier if its distance to the sphere is below this (metres). About 2-3x the depth
        noise; the default suits Kinect depth of a mirror ball at 0.5-1 m (sigma 2-5 mm).
    radius_range_m : (float, float)
        Plausible radii (metres); hypotheses outside are discarded and a result outside is an error.
    min_inlier_fraction : float
        Smallest accepted fraction of the points on the sphere; below it the input is taken as outliers.
    min_points : int
        Smallest number of finite points accepted.
    max_points : int
        Larger inputs are randomly subsampled to this many points (deterministic with ``seed``).
    n_hypotheses : int
        RANSAC hypotheses (minimal 4-point spheres).
    max_radius_rel_std : float
        Largest accepted standard error of the radius relative to the radius (only when it is fitted).
    max_rms_rel : float
        Largest accepted RMS residual of the inliers relative to the radius (a blob is not a ball).
    seed : int
        Seed of the random generator (subsampling, RANSAC), for reproducible fits.
    where : str
        Prefix of error messages (which input is being fitted).

    Returns
    -------
    SphereFit

    Raises
    ------
    EstimationError
        Too few points, coincident/collinear/coplanar points, a patch too small or flat to determine the
        radius, no sphere explaining enough points (all outliers), or a radius outside ``radius_range_m``.
    """
    if not (np.isfinite(inlier_threshold_m) and inlier_threshold_m > 0):
        raise AppFusionError(f"{where}: inlier_threshold_m must be a positive number, got {inlier_threshold_m}")
    if radius is not None:
        radius = float(radius)
        if not (np.isfinite(radius) and radius > 0):
            raise AppFusionError(f"{where}: the given radius must be a positive number of metres, got {radius}")
    min_points = max(int(min_points), 5)
    p = _validate(points, min_points, where)
    rng = np.random.default_rng(seed)
    if len(p) > max_points:
        p = p[rng.choice(len(p), size=max_points, replace=False)]
    _shape_check(p, where)
    n = len(p)
    tau = float(inlier_threshold_m)

    cands = _ransac(p, tau, radius, radius_range_m, n_hypotheses, rng)
    if not cands:
        try:
            c, r = algebraic_fit(p)
        except EstimationError as e:
            raise EstimationError(f"{where}: no sphere candidate from {n} points ({e})") from None
        cands = [(c, radius if radius is not None else r)]
    r_bounds = (0.5 * radius_range_m[0], 2.0 * radius_range_m[1])
    refined = [_robust_refine(p, c, r, radius, tau, min_points, where, r_bounds) for c, r in cands]
    # Pick the candidate with the lowest MSAC cost at the finest noise level found (threshold 2.5 sigma):
    # a wrong sphere through a partial cap plus outliers collects points loosely, the right one tightly.
    t2 = (2.5 * min(s for _, _, s in refined)) ** 2
    costs = [float(np.minimum((np.linalg.norm(p - c, axis=1) - r) ** 2, t2).sum()) for c, r, _ in refined]
    c, r, _ = refined[int(np.argmin(costs))]

    res = np.linalg.norm(p - c, axis=1) - r
    inl = np.abs(res) < tau
    n_in = int(inl.sum())
    frac = n_in / n
    if radius is None and not (radius_range_m[0] <= r <= radius_range_m[1]):
        raise EstimationError(f"{where}: fitted radius {r * 1000:.1f} mm is outside the plausible range "
                              f"{radius_range_m[0] * 1000:.0f}-{radius_range_m[1] * 1000:.0f} mm")
    if frac < min_inlier_fraction or n_in < min_points:
        raise EstimationError(f"{where}: no sphere explains the points: the best one has only {n_in} of {n} "
                              f"points ({100 * frac:.0f}%) within {tau * 1000:.1f} mm; need "
                              f"{100 * min_inlier_fraction:.0f}% (all outliers, or noise above the threshold)")
    ri = res[inl]
    # Shell contrast: points on a noisy sphere crowd into the shell |r| < tau, while outliers that happen
    # to meet a shell are as dense there as just outside it (tau < |r| < 3 tau, twice as wide).
    n_out = int(((np.abs(res) >= tau) & (np.abs(res) < 3.0 * tau)).sum())
    contrast = n_in / ((n_out + 4.0) / 2.0)   # 4 pseudo-counts: few points prove little
    if contrast < 4.0:
        raise EstimationError(f"{where}: the {n_in} points within {tau * 1000:.1f} mm of the best sphere are hardly "
                              f"denser than those just outside it ({n_out} within {3 * tau * 1000:.0f} mm), as for "
                              "a cloud of outliers; no sphere in the data, or noise above inlier_threshold_m")
    rms = float(np.sqrt(np.mean(ri * ri)))
    if rms > max_rms_rel * r:
        raise EstimationError(f"{where}: the points scatter {rms * 1000:.1f} mm (RMS) about a sphere of radius "
                              f"{r * 1000:.1f} mm, more than {100 * max_rms_rel:.0f}% of it: a blob of outliers, "
                              "not a ball (or a ball too small for this depth noise)")

    # Determinacy: covariance of the parameters at the solution, over the inliers.
    d = p[inl] - c
    nrm = np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    J = -d / nrm if radius is not None else np.column_stack([-d / nrm, -np.ones(n_in)])
    k = J.shape[1]
    s2 = max(float(ri @ ri) / max(n_in - k, 1), 1e-12)
    JtJ = J.T @ J
    try:
        cond = np.linalg.cond(JtJ)
        cov = s2 * np.linalg.inv(JtJ) if cond < 1e12 else None
    except np.linalg.LinAlgError:
        cov = None
    if cov is None or not np.isfinite(cov).all():
        raise EstimationError(f"{where}: the {n_in} inliers cover too small a part of the sphere to "
                              "determine it (singular normal equations); scan more of the ball or give the radius")
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    center_std = float(std[:3].max())
    radius_std = 0.0
    if radius is None:
        radius_std = float(std[3])
        # Sagitta of the cap the inliers span: how far the patch bulges out of its best plane.
        normals = d / nrm
        mean_n = normals.mean(axis=0)
        cos_half = np.clip(normals @ (mean_n / max(np.linalg.norm(mean_n), 1e-300)), -1, 1).min()
        sagitta = r * (1.0 - cos_half)
        if radius_std > max_radius_rel_std * r or sagitta < 2.0 * rms:
            raise EstimationError(
                f"{where}: the inliers span too small a patch of the ball to determine its radius "
                f"(cap half-angle {np.degrees(np.arccos(cos_half)):.1f} deg, sagitta {sagitta * 1000:.2f} mm "
                f"vs noise {rms * 1000:.2f} mm, radius std {radius_std * 1000:.2f} mm); scan more of the "
                "ball or give its radius")
    out = SphereFit(center=np.asarray(c, float), radius=float(r), rms_m=rms, inlier_fraction=float(frac),
                    n_points=n, n_inliers=n_in, radius_std_m=radius_std, center_std_m=center_std,
                    radius_fixed=radius is not None)
    if not (np.isfinite(out.center).all() and np.isfinite([out.radius, out.rms_m, radius_std, center_std]).all()):
        raise EstimationError(f"{where}: fit produced non-finite values")  # pragma: no cover - guarded above
    return out


def refine_center(points: Any, center: Any, radius: float, band_m: float = 0.01, min_points: int = 50,
                  max_shift_m: float | None = None) -> np.ndarray | None:
    """Re-estimate a sphere's centre (known radius) from a few points, starting at a predicted centre.

    Used per frame by the lighting pass: the ball's depth points of one frame, in that frame's camera
    coordinates, fix where the ball is relative to the camera far better than the tracked pose does
    (a 0.3 degree pose error moves the ball's image by ~3 px, turning its normals by ~4 degrees).
    Robust geometric least squares (soft-L1, radius fixed), first on the points within ``3 band_m`` of
    the predicted sphere, then within ``band_m`` of the first estimate.

    Parameters
    ----------
    points : (N, 3) array
        Points in metres (NaN rows ignored), any frame; ``center`` in the same frame.
    center : (3,) array
        Predicted centre (metres).
    radius : float
        Known radius (metres).
    band_m : float
        Only points within this distance of the predicted sphere are used.
    min_points : int
        Fewer usable points give None.
    max_shift_m : float, optional
        A refined centre farther than this from the prediction is rejected (None); default ``2 band_m``.

    Returns
    -------
    (3,) ndarray or None
        The refined centre, or None when the points do not support a refinement (too few, or the fit
        moved implausibly far).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    c0 = np.asarray(center, dtype=np.float64).reshape(3)
    if not (np.isfinite(c0).all() and np.isfinite(radius) and radius > 0 and band_m > 0):
        raise AppFusionError(f"refine_center: centre, radius and band must be finite and positive "
                             f"(got {c0.tolist()}, {radius}, {band_m})")
    p = p[np.isfinite(p).all(axis=1)]
    c = c0
    # Two rounds: a wide band (3x) catches the ball when the prediction is off by up to ~band_m, then the
    # band proper around the first estimate.
    for band in (3.0 * band_m, band_m):
        d = np.abs(np.linalg.norm(p - c, axis=1) - radius)
        near = d < band
        q = p[near]
        if len(q) < max(int(min_points), 5):
            return None
        try:
            _shape_check(q, "refine_center")
        except EstimationError:
            return None
        sigma = float(np.clip(1.4826 * np.median(d[near]), 2e-4, band))
        c, _, _ = _refine(q, c, radius, radius, sigma)
        if not np.isfinite(c).all():
            return None
    limit = 2.0 * band_m if max_shift_m is None else max_shift_m
    if np.linalg.norm(c - c0) > limit:
        return None
    return c


# -- points from depth frames ------------------------------------------------------------------------

def in_box(points: np.ndarray, box: Any) -> np.ndarray:
    """Boolean mask (N,) of points (N, 3) inside ``box``.

    ``box`` is either an object with a ``contains(points) -> (N,) bool`` method (the marker module's
    object box) or an axis-aligned box ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` in metres, in the
    frame of the points.
    """
    if hasattr(box, "contains"):
        return np.asarray(box.contains(points), dtype=bool)
    b = np.asarray(box, dtype=np.float64)
    if b.shape != (2, 3) or not np.isfinite(b).all() or (b[1] <= b[0]).any():
        raise AppFusionError("object box must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max, "
                             f"got {b.tolist()}")
    return ((points >= b[0]) & (points <= b[1])).all(axis=-1)


def _check_depth_pose(depth, intrinsics: Intrinsics, pose) -> tuple[np.ndarray, np.ndarray]:
    """The depth image (matching the intrinsics) and a finite 4x4 pose, or a clear error."""
    depth = np.asarray(depth)
    if depth.shape != intrinsics.shape:
        raise AppFusionError(f"depth image of shape {depth.shape} does not match intrinsics {intrinsics.shape}")
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise AppFusionError(f"depth pose must be a finite 4x4 matrix, got shape {pose.shape}")
    return depth, pose


def points_from_depth(depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray,
                      box: Any = None, stride: int = 1) -> np.ndarray:
    """World points (M, 3) of a depth image, optionally cropped to the object box.

    Parameters
    ----------
    depth : (H, W) float array
        Metres, NaN or <= 0 where invalid.
    intrinsics : Intrinsics
        Of the depth camera (lens distortion is ignored, as in :meth:`Intrinsics.backproject`).
    pose : (4, 4) array
        Camera-to-world pose of the depth camera (metres).
    box : optional
        See :func:`in_box`; in the world frame of ``pose``.
    stride : int
        Use every ``stride``-th pixel in both directions.
    """
    depth, pose = _check_depth_pose(depth, intrinsics, pose)
    s = max(int(stride), 1)
    z = depth[::s, ::s].astype(np.float64)
    rays = intrinsics.rays()[::s, ::s].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    pts = transform_points(pose, rays[ok] * z[ok][:, None])
    if box is not None:
        pts = pts[in_box(pts, box)]
    return pts


class PointReservoir:
    """Uniform random sample of at most ``capacity`` points out of all points offered (reservoir sampling).

    Keeps memory constant over a long environment pass while every point offered has the same chance
    of being kept. Rows have ``dim`` columns (3 for points; more to keep attributes with each point,
    e.g. a normal).
    """

    def __init__(self, capacity: int = 200_000, seed: int = 0, dim: int = 3):
        if capacity < 1:
            raise AppFusionError(f"point reservoir capacity must be positive, got {capacity}")
        if dim < 1:
            raise AppFusionError(f"point reservoir rows must have at least one column, got {dim}")
        self.capacity = int(capacity)
        self.dim = int(dim)
        self._buf = np.empty((self.capacity, self.dim))
        self._n = 0          # points stored
        self.seen = 0        # points offered
        self._rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return self._n

    def add(self, points: np.ndarray) -> None:
        """Offer points (M, dim) (rows of ``dim`` numbers: a point, or a point with attributes)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, self.dim)
        free = self.capacity - self._n
        if free > 0:
            k = min(free, len(p))
            self._buf[self._n:self._n + k] = p[:k]
            self._n += k
            self.seen += k
            p = p[k:]
        if len(p):
            # Algorithm R, vectorised: point number t (0-based) replaces slot j ~ U{0..t} if j < capacity.
            t = self.seen + np.arange(len(p))
            j = (self._rng.random(len(p)) * (t + 1)).astype(np.int64)
            keep = j < self.capacity
            self._buf[j[keep]] = p[keep]
            self.seen += len(p)

    @property
    def points(self) -> np.ndarray:
        """The kept rows, (n, dim) (a view)."""
        return self._buf[:self._n]


def fit_sphere_from_depth(frames: Iterable[tuple[np.ndarray, Intrinsics, np.ndarray]], box: Any = None,
                          radius: float | None = None, stride: int = 2, capacity: int = 200_000,
                          **kwargs) -> SphereFit:
    """Fit the ball straight from depth frames: back-project, crop to the object box, fit.

    Parameters
    ----------
    frames : iterable of (depth, intrinsics, pose)
        Depth images (metres) with their camera intrinsics and camera-to-world poses.
    box : optional
        Object box (see :func:`in_box`) in the world frame; without it every valid pixel counts.
    radius : float, optional
        Known ball radius (metres).
    stride : int
        Pixel stride of the back-projection.
    capacity : int
        Points kept at most (uniform reservoir sample over all frames).
    **kwargs
        Passed to :func:`fit_sphere`.
    """
    res = PointReservoir(capacity)
    for depth, intr, pose in frames:
        res.add(points_from_depth(depth, intr, pose, box, stride))
    return fit_sphere(res.points, radius=radius, where=kwargs.pop("where", "sphere fit from depth"), **kwargs)


# -- the mirror ball: specular spot and silhouette (paper §4.3, with the depth sensor's physics) ------
#
# A structured-light (or time-of-flight) depth camera sees a mirror only where the mirror reflects its
# own emitter into its camera: the surface normal there is the bisector of the directions to the
# camera and to the emitter (the "specular spot", a few degrees wide). Elsewhere on the ball the pattern
# is reflected away: no depth, except sparse wrong returns, typically *behind* the surface (multi-path).
# Two cues follow that a plain sphere fit to the depth points cannot use:
#
# - each spot point p has a known normal n (the bisector), so p = c + R n is linear in the centre c and
#   the radius R; wrong returns are far from that model (their bisector is not their normal);
# - the ball leaves a hole in the depth image against the background (the support plane behind it).
#   The hole's edge is the ball's silhouette except on the side away from the emitter, where the ball's
#   shadow (the background the emitter cannot see) widens it. A ray through the silhouette is tangent
#   to the ball: its distance to c is R.
#
# Assumptions (true for Kinect v1 on a chrome ball on a paper-covered table; documented in
# docs/lighting-pass.md): the background right beside the ball on the emitter side returns depth and
# lies outside the object box (the support plane or farther); the emitter position in the depth
# camera's frame is known (session meta ``emitter_position_m``); the ball is the only thing in the box.

def _box_bounds(box: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) corners of an axis-aligned box given as an object with ``lo``/``hi`` or a (2, 3) array."""
    if box is None:
        return None
    if hasattr(box, "lo") and hasattr(box, "hi"):
        return np.asarray(box.lo, float), np.asarray(box.hi, float)
    if hasattr(box, "contains"):
        return None
    b = np.asarray(box, dtype=np.float64)
    if b.shape != (2, 3):
        return None
    return b[0], b[1]


def bisector_normals(points: Any, emitter: Any) -> np.ndarray:
    """Normals of a mirror at its specular-spot depth points: the bisector of the directions to the
    camera (the origin) and to the emitter (paper §4.3; the structured-light geometry of §6).

    Parameters
    ----------
    points : (N, 3) array
        Depth points in the depth camera's frame, metres.
    emitter : (3,) array
        Emitter position in the same frame, metres (Kinect v1: ``[0.075, 0, 0]``).

    Returns
    -------
    (N, 3) ndarray
        Unit normals in the depth camera's frame (pointing towards the camera side).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    e = np.asarray(emitter, dtype=np.float64).reshape(3)
    to_cam = -p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-12)
    to_em = e - p
    to_em /= np.maximum(np.linalg.norm(to_em, axis=1, keepdims=True), 1e-12)
    h = to_cam + to_em
    return h / np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)


@dataclass
class BallCues:
    """What one depth frame says about a mirror ball, in the world (marker) frame.

    Attributes
    ----------
    spots : (M, 6) float64 ndarray
        Depth points inside the object box (``[:, :3]``, metres) with the specular-spot normal each would
        have (``[:, 3:]``, unit): candidates, most of them wrong returns that the fit rejects.
    rays : (K, 7) float64 ndarray
        Silhouette rays: origin (the depth camera's centre, ``[:, :3]``), unit direction (``[:, 3:6]``)
        and the angle of one pixel (``[:, 6]``, radians; sets the ray's uncertainty).
    """

    spots: np.ndarray
    rays: np.ndarray


def _step_directions(emitter: Any) -> list[tuple[int, int]]:
    """Pixel steps (du, dv) from the hole to the background that cross the silhouette, not the shadow."""
    steps = [(1, 0), (-1, 0), (0, 1), (0, -1)]
    if emitter is None:
        return steps
    e = np.asarray(emitter, float).reshape(3)[:2]
    ne = float(np.linalg.norm(e))
    if ne < 1e-3:            # (nearly) coaxial emitter, e.g. time of flight: no shadow beside the ball
        return steps
    e = e / ne
    return [st for st in steps if st[0] * e[0] + st[1] * e[1] > 0.5]


def _project_rect(points: np.ndarray, pose: np.ndarray, intr: Intrinsics, pad: float
                  ) -> tuple[int, int, int, int] | None:
    """Pixel rectangle (x0, x1, y0, y1), end-exclusive, holding the projections of world points, grown by
    ``pad`` pixels and clipped to the image; None when a point is behind the camera."""
    cc = (points - pose[:3, 3]) @ pose[:3, :3]
    if not (cc[:, 2] > 1e-6).all():
        return None
    u = intr.fx * cc[:, 0] / cc[:, 2] + intr.cx
    v = intr.fy * cc[:, 1] / cc[:, 2] + intr.cy
    W, H = intr.width, intr.height
    return (int(np.clip(np.floor(u.min() - pad), 0, W)), int(np.clip(np.ceil(u.max() + pad) + 1, 0, W)),
            int(np.clip(np.floor(v.min() - pad), 0, H)), int(np.clip(np.ceil(v.max() + pad) + 1, 0, H)))


def ball_cues_from_depth(depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray, box: Any,
                         emitter: Any = None, near: tuple[Any, float] | None = None) -> BallCues:
    """Specular-spot candidates and silhouette rays of a mirror ball in one depth frame (paper §4.3).

    Parameters
    ----------
    depth : (H, W) float array
        Metres, NaN or <= 0 where invalid (a mirror gives no depth except at its specular spot).
    intrinsics : Intrinsics
        Of the depth camera (lens distortion ignored, as in :func:`points_from_depth`).
    pose : (4, 4) array
        Camera-to-world pose of the depth camera (world = marker frame).
    box : object box
        See :func:`in_box`; holds the ball. Valid depth outside it is background.
    emitter : (3,) array, optional
        Emitter position in the depth camera's frame (metres). Without it no spot candidates are made
        (their normals are unknown) and the hole's edge is taken on all sides (no shadow modelled).
    near : (centre, radius), optional
        A predicted ball (world frame, metres): only the image region around it (grown by 60% of the
        radius and 4 pixels) is looked at (per-frame location; much faster on large images).

    Returns
    -------
    BallCues
        Silhouette rays: every invalid pixel whose neighbour towards the emitter (in the image) is valid
        background, through the midpoint of the two pixels, kept when the ray meets the box in front
        of that background.
    """
    depth, pose = _check_depth_pose(depth, intrinsics, pose)
    if box is None:
        raise AppFusionError("mirror-ball cues need the object box (it separates the ball from the background)")
    Rw, t = pose[:3, :3], pose[:3, 3]
    bounds = _box_bounds(box)
    H, W = depth.shape
    x0, x1, y0, y1 = 0, W, 0, H
    cube = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], float)
    if bounds is not None:
        # only the image rectangle that can show the box (plus a pixel for the neighbours)
        lo, hi = bounds
        rect = _project_rect(0.5 * (lo + hi) + 0.5 * (hi - lo) * cube, pose, intrinsics, 2.0)
        if rect is not None:
            x0, x1, y0, y1 = rect
    if near is not None:
        c_n, r_n = np.asarray(near[0], float).reshape(3), float(near[1])
        rect = _project_rect(c_n + 1.6 * r_n * cube, pose, intrinsics, 4.0)
        if rect is not None:
            x0, x1, y0, y1 = max(x0, rect[0]), min(x1, rect[1]), max(y0, rect[2]), min(y1, rect[3])
    if x1 - x0 < 2 or y1 - y0 < 2:
        return BallCues(spots=np.empty((0, 6)), rays=np.empty((0, 7)))
    z = np.asarray(depth[y0:y1, x0:x1], dtype=np.float32)
    valid = np.isfinite(z) & (z > 0)
    zz = np.where(valid, z, np.float32(0.0))
    xr = ((np.arange(x0, x1) - intrinsics.cx) / intrinsics.fx).astype(np.float32)[None, :]
    yr = ((np.arange(y0, y1) - intrinsics.cy) / intrinsics.fy).astype(np.float32)[:, None]
    R32 = Rw.astype(np.float32)
    # world coordinates of every pixel, component by component: p_w = R (x z, y z, z) + t
    pw = [zz * (R32[k, 0] * xr + R32[k, 1] * yr + R32[k, 2]) + np.float32(t[k]) for k in range(3)]
    if bounds is not None:
        lo, hi = bounds
        inbox = valid.copy()
        for k in range(3):
            inbox &= (pw[k] >= lo[k]) & (pw[k] <= hi[k])
    else:
        inbox = np.zeros(z.shape, bool)
        vv, uu = np.nonzero(valid)
        inbox[vv, uu] = in_box(np.stack([pw[k][vv, uu] for k in range(3)], axis=1).astype(np.float64), box)
    bg = valid & ~inbox
    vv, uu = np.nonzero(inbox)
    zv = z[vv, uu].astype(np.float64)
    pc = np.stack([(uu + x0 - intrinsics.cx) / intrinsics.fx * zv, (vv + y0 - intrinsics.cy) / intrinsics.fy * zv,
                   zv], axis=1)
    pw_in = pc @ Rw.T + t
    # spot candidates (world point + world bisector normal)
    if emitter is not None and len(pc):
        nrm = bisector_normals(pc, emitter) @ Rw.T
        spots = np.hstack([pw_in, nrm])
    else:
        spots = np.empty((0, 6))
    # silhouette rays: hole pixel -> background neighbour towards the emitter
    inv = ~valid
    out = []
    h, w = z.shape
    for du, dv in _step_directions(emitter):
        ys, ye = max(0, -dv), h - max(0, dv)
        xs, xe = max(0, -du), w - max(0, du)
        a = inv[ys:ye, xs:xe] & bg[ys + dv:ye + dv, xs + du:xe + du]
        py, px = np.nonzero(a)
        if not len(py):
            continue
        py, px = py + ys, px + xs
        um = px + x0 + 0.5 * du                                  # midpoint of the two pixels
        vm = py + y0 + 0.5 * dv
        d = np.stack([(um - intrinsics.cx) / intrinsics.fx, (vm - intrinsics.cy) / intrinsics.fy,
                      np.ones(len(um))], axis=1)
        zb = z[py + dv, px + du].astype(np.float64)              # background depth (z) beside the hole
        out.append(np.hstack([d, zb[:, None]]))
    if out:
        r = np.concatenate(out)
        far = r[:, 3] * np.linalg.norm(r[:, :3], axis=1)         # range of the background along the ray
        d = r[:, :3] / np.linalg.norm(r[:, :3], axis=1, keepdims=True)
        dw = d @ Rw.T
        if bounds is not None:
            lo, hi = bounds
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (lo - t) / dw
                t2 = (hi - t) / dw
            tmin = np.nanmax(np.minimum(t1, t2), axis=1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=1)
            keep = (tmax >= np.maximum(tmin, 0.0)) & (np.maximum(tmin, 0.0) < far)
            dw = dw[keep]
        pix = 1.0 / max(min(intrinsics.fx, intrinsics.fy), 1e-9)
        rays_out = np.hstack([np.broadcast_to(t, dw.shape), dw, np.full((len(dw), 1), pix)])
    else:
        rays_out = np.empty((0, 7))
    return BallCues(spots=spots, rays=rays_out)


def _ray_residuals(c: np.ndarray, R: float, rays: np.ndarray) -> np.ndarray:
    """Signed distances (metres) from the centre to each silhouette ray, minus the radius."""
    return np.linalg.norm(np.cross(c - rays[:, :3], rays[:, 3:6]), axis=1) - R


def _ray_sigma(c: np.ndarray, rays: np.ndarray, floor: float = 1e-4) -> np.ndarray:
    """Uncertainty (metres) of each silhouette ray at the ball: the hole's edge is known to +-half a pixel
    (uniform: sigma 0.29 px), widened a little for pose error."""
    return np.maximum(0.35 * rays[:, 6] * np.linalg.norm(c - rays[:, :3], axis=1), floor)


def _spot_residuals(c: np.ndarray, R: float, spots: np.ndarray) -> np.ndarray:
    """(M, 3) vector residuals p - c - R n of specular-spot candidates (metres)."""
    return spots[:, :3] - c - R * spots[:, 3:6]


def _mirror_starts(spots: np.ndarray, rays: np.ndarray, radius: float | None, r_range: tuple[float, float],
                   tau_s: float, tau_r: float, n_hyp: int, rng: np.random.Generator,
                   n_keep: int = 3) -> list[tuple[np.ndarray, float]]:
    """RANSAC over specular spots: one spot fixes the centre when the radius is known (c = p - R n), two
    spots with different normals fix both (p_i - p_j = R (n_i - n_j)). Scored by an MSAC cost over spots
    and silhouette rays together; the ``n_keep`` best distinct hypotheses."""
    m = len(spots)
    if m < (1 if radius is not None else 2):
        return []
    P, N = spots[:, :3], spots[:, 3:6]
    if radius is not None:
        k = rng.choice(m, size=min(n_hyp, m), replace=False)
        R = np.full(len(k), float(radius))
        C = P[k] - R[:, None] * N[k]
    else:
        i, j = rng.integers(0, m, size=(2, n_hyp))
        dn, dp = N[i] - N[j], P[i] - P[j]
        nn = (dn * dn).sum(axis=1)
        ok = nn > 0.1 ** 2                                 # normals at least ~6 degrees apart
        i, j, dn, dp, nn = i[ok], j[ok], dn[ok], dp[ok], nn[ok]
        R = (dp * dn).sum(axis=1) / nn
        ok = (R >= r_range[0]) & (R <= r_range[1]) & (np.linalg.norm(dp - R[:, None] * dn, axis=1) < 2 * tau_s)
        i, j, R = i[ok], j[ok], R[ok]
        C = 0.5 * (P[i] + P[j] - R[:, None] * (N[i] + N[j]))
    if not len(R):
        return []
    cost = np.zeros(len(R))
    chunk = max(1, int(2e6 // max(m + len(rays), 1)))
    for s in range(0, len(R), chunk):
        c, r = C[s:s + chunk], R[s:s + chunk]
        e = np.linalg.norm(P[None] - c[:, None] - r[:, None, None] * N[None], axis=2)
        cost[s:s + chunk] = np.minimum(e * e, tau_s * tau_s).sum(axis=1) / tau_s ** 2
        if len(rays):
            dr = np.linalg.norm(np.cross(c[:, None] - rays[None, :, :3], rays[None, :, 3:6]), axis=2) - r[:, None]
            cost[s:s + chunk] += np.minimum(dr * dr, tau_r * tau_r).sum(axis=1) / tau_r ** 2
    out: list[tuple[np.ndarray, float]] = []
    for k in np.argsort(cost, kind="stable"):
        if all(np.linalg.norm(C[k] - co) > tau_s or abs(R[k] - ro) > tau_s for co, ro in out):
            out.append((C[k].copy(), float(R[k])))
            if len(out) == n_keep:
                break
    return out


def _cone_start(rays: np.ndarray, r_range: tuple[float, float], radius: float | None
                ) -> tuple[np.ndarray, float] | None:
    """A start from silhouette rays alone: per view (rays sharing an origin) the cone of tangent rays,
    ``d . a = cos(alpha)`` (linear in ``a / cos(alpha)``), whose axis passes through the centre; the axes
    of all views meet at the centre (least squares), and ``R = |c - o| sin(alpha)``."""
    if len(rays) < 8:
        return None
    _, inv = np.unique(np.round(rays[:, :3], 9), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    axes, origins, sines = [], [], []
    for g in range(int(inv.max()) + 1):
        d = rays[inv == g, 3:6]
        if len(d) < 6:
            continue
        keep = np.ones(len(d), bool)
        w = None
        for _ in range(3):                      # refit without the rays far from the cone
            w, *_ = np.linalg.lstsq(d[keep], np.ones(int(keep.sum())), rcond=None)
            r = d @ w - 1.0
            mad = 1.4826 * np.median(np.abs(r[keep])) + 1e-9
            keep = np.abs(r) < 3.0 * mad
            if keep.sum() < 6:
                break
        nw = float(np.linalg.norm(w)) if w is not None else 0.0
        if not np.isfinite(nw) or nw <= 1.0:
            continue
        axes.append(w / nw)
        origins.append(rays[inv == g][0, :3])
        sines.append(np.sqrt(max(1.0 - 1.0 / nw ** 2, 0.0)))
    if len(axes) < 2:
        return None
    A, O = np.array(axes), np.array(origins)
    M = np.eye(3)[None] - A[:, :, None] * A[:, None, :]        # projectors orthogonal to each axis
    lhs, rhs = M.sum(axis=0), np.einsum("kij,kj->i", M, O)
    if np.linalg.cond(lhs) > 1e8:
        return None
    c = np.linalg.solve(lhs, rhs)
    R = float(radius) if radius is not None else float(np.median(np.linalg.norm(c - O, axis=1) * np.array(sines)))
    if not (np.isfinite(c).all() and np.isfinite(R) and r_range[0] <= R <= r_range[1]):
        return None
    return c, R


def _mirror_lsq(spots: np.ndarray, rays: np.ndarray, c0: np.ndarray, r0: float, radius: float | None,
                plane_z: float | None, s_spot: float, f_scale: float = 2.0
                ) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """Robust (soft-L1) joint least squares over spot and ray residuals, each divided by its sigma.

    Unknowns: centre and radius; the radius is dropped when given, ``c_z`` when ``plane_z`` is set
    (the ball rests on the plane: ``c_z = plane_z + R``). Returns centre, radius, the final Jacobian of
    the sigma-scaled residuals with respect to the free unknowns, and the scaled residuals.
    """
    sig_r = _ray_sigma(c0, rays) if len(rays) else np.empty(0)

    def unpack(x):
        if radius is None:
            R = x[-1]
            xy = x[:-1]
        else:
            R = radius
            xy = x
        cz = plane_z + R if plane_z is not None else xy[2]
        return np.array([xy[0], xy[1], cz]), R

    def fun(x):
        c, R = unpack(x)
        rs = (_spot_residuals(c, R, spots) / s_spot).ravel()
        rr = _ray_residuals(c, R, rays) / sig_r if len(rays) else np.empty(0)
        return np.concatenate([rs, rr])

    x0 = [c0[0], c0[1]] + ([] if plane_z is not None else [c0[2]]) + ([r0] if radius is None else [])
    x0 = np.asarray(x0, float)
    res = least_squares(fun, x0, loss="soft_l1", f_scale=f_scale, method="trf", x_scale=np.full(len(x0), 0.01),
                        max_nfev=100)
    c, R = unpack(res.x)
    # Jacobian of the plain (non-robust) scaled residuals, by central differences (4 unknowns at most)
    h = 1e-6
    J = np.empty((len(res.fun), len(res.x)))
    for k in range(len(res.x)):
        e = np.zeros(len(res.x))
        e[k] = h
        J[:, k] = (fun(res.x + e) - fun(res.x - e)) / (2 * h)
    return c, float(R), J, fun(res.x)


def fit_mirror_ball(spots: Any, rays: Any, radius: float | None = None, *, on_plane: bool | str = "auto",
                    plane_z: float = 0.0, plane_tol_m: float = 0.003, spot_sigma_m: float = 0.003,
                    radius_range_m: tuple[float, float] = (0.01, 0.5), start: tuple[Any, float] | None = None,
                    min_spots: int = 10, min_rays: int = 30, max_radius_rel_std: float = 0.02,
                    max_spots: int = 20000, max_rays: int = 20000, n_hypotheses: int = 512, seed: int = 0,
                    where: str = "mirror-ball fit") -> SphereFit:
    """Fit a mirror ball to specular-spot points with known normals and to silhouette rays (paper §4.3).

    The paper fits "a perfect sphere to the captured geometry using least squares"; on a mirror the
    captured geometry is only the specular spot plus wrong returns (see the section comment above), so
    this fit uses the physics of the sensor instead: spot points lie at ``c + R n`` with ``n`` the
    emitter/camera bisector, silhouette rays are tangent to the ball. Both are combined in one robust
    least-squares problem (residuals divided by their uncertainty: ``spot_sigma_m`` for spots, a third
    of a pixel at the ball for rays), started from a RANSAC over the spots and refined on bands that
    shrink to 3 sigma of the residuals.

    Parameters
    ----------
    spots : (M, 6) array
        Spot candidates: world point and unit bisector normal (:attr:`BallCues.spots`). May be empty.
    rays : (K, 7) array
        Silhouette rays (:attr:`BallCues.rays`). May be empty.
    radius : float, optional
        Known radius (metres; e.g. the user's ``--ball-radius``); then it is not fitted.
    on_plane : bool or "auto"
        Constrain the ball to rest on the support plane ``z = plane_z`` (centre height = radius).
        ``"auto"``: only when the unconstrained fit agrees (``|c_z - plane_z - R|`` within
        ``plane_tol_m`` plus 3 standard errors); the result says which in ``on_plane``.
    plane_z : float
        Height of the support plane in the world frame (0 in the marker frame).
    plane_tol_m : float
        Gap accepted as "resting on the plane" besides the statistical error (paper, print, pose bias).
    spot_sigma_m : float
        Uncertainty of a spot point's ``p - R n`` (depth noise at the spot and the spot's width).
    radius_range_m : (float, float)
        Plausible radii; a result outside is an error.
    start : (centre, radius), optional
        Starting sphere; default from the RANSAC (or a geometric fit of the spot points).
    min_spots, min_rays : int
        The result must agree with at least this many spots or this many rays.
    max_radius_rel_std : float
        Largest accepted standard error of the fitted radius, relative to it.
    max_spots, max_rays : int
        Larger inputs are subsampled (deterministically with ``seed``).
    n_hypotheses : int
        RANSAC hypotheses.
    seed : int
        Random seed (subsampling, RANSAC).
    where : str
        Prefix of error messages.

    Returns
    -------
    SphereFit
        With ``method="mirror"``, ``n_spots``/``n_rays`` the inliers, ``on_plane`` and ``plane_gap_m``.

    Raises
    ------
    EstimationError
        Too few cues, no sphere agreeing with enough of them, a radius outside the range or not
        determined by the cues.
    """
    S = np.asarray(spots, dtype=np.float64).reshape(-1, 6) if np.size(spots) else np.empty((0, 6))
    Q = np.asarray(rays, dtype=np.float64).reshape(-1, 7) if np.size(rays) else np.empty((0, 7))
    S = S[np.isfinite(S).all(axis=1)]
    Q = Q[np.isfinite(Q).all(axis=1)]
    if radius is not None:
        radius = float(radius)
        if not (np.isfinite(radius) and radius > 0):
            raise AppFusionError(f"{where}: the given radius must be a positive number of metres, got {radius}")
    if on_plane not in (True, False, "auto"):
        raise AppFusionError(f"{where}: on_plane must be True, False or 'auto', got {on_plane!r}")
    if not (spot_sigma_m > 0 and plane_tol_m >= 0):
        raise AppFusionError(f"{where}: spot_sigma_m must be > 0 and plane_tol_m >= 0")
    if len(S) < min_spots and len(Q) < min_rays:
        raise EstimationError(f"{where}: too few cues of the ball: {len(S)} depth points in the box and "
                              f"{len(Q)} silhouette rays (need {min_spots} or {min_rays}); is the ball in the "
                              "object box and the emitter position right?")
    if (np.abs(S[:, :3]).max(initial=0) > MAX_COORD_M) or (np.abs(Q[:, :3]).max(initial=0) > MAX_COORD_M):
        raise EstimationError(f"{where}: coordinates beyond {MAX_COORD_M:g} m; points must be in metres")
    rng = np.random.default_rng(seed)
    if len(S) > max_spots:
        S = S[rng.choice(len(S), size=max_spots, replace=False)]
    if len(Q) > max_rays:
        Q = Q[rng.choice(len(Q), size=max_rays, replace=False)]

    s_spot = float(spot_sigma_m)
    tau_s = 2.5 * s_spot
    tau_r = 4.0 * float(np.median(_ray_sigma(np.zeros(3), Q))) if len(Q) else 0.004
    tau_r = max(tau_r, 0.002)
    if start is not None:
        c0 = np.asarray(start[0], float).reshape(3)
        cands = [(c0, float(radius if radius is not None else start[1]))]
    else:
        cands = _mirror_starts(S, Q, radius, radius_range_m, tau_s, tau_r, n_hypotheses, rng)
        cone = _cone_start(Q, radius_range_m, radius)
        if cone is not None:
            cands.append(cone)
        if len(S) >= 10:
            try:
                g = fit_sphere(S[:, :3], radius=radius, max_rms_rel=0.3, min_inlier_fraction=0.05,
                               radius_range_m=radius_range_m, max_radius_rel_std=1.0, where=where)
                cands.append((g.center, g.radius))
            except EstimationError:
                pass
    if not cands:
        raise EstimationError(f"{where}: no sphere hypothesis from {len(S)} spot candidates "
                              f"({len(Q)} silhouette rays); the ball's specular spot was not seen")

    def refine(c, R, plane, rounds=5):
        band_s, band_r = 4.0 * tau_s, 2.0 * tau_r
        si = np.zeros(len(S), bool)
        ri = np.zeros(len(Q), bool)
        for it in range(rounds):
            es = np.linalg.norm(_spot_residuals(c, R, S), axis=1) if len(S) else np.empty(0)
            er = np.abs(_ray_residuals(c, R, Q)) if len(Q) else np.empty(0)
            si, ri = es < band_s, er < band_r
            if si.sum() < 4 and ri.sum() < 8:
                break
            c, R, J, f = _mirror_lsq(S[si], Q[ri], c, R, radius, plane, s_spot)
            if not (np.isfinite(c).all() and np.isfinite(R)):
                raise EstimationError(f"{where}: least squares diverged")
            # shrink the bands to 3 sigma of this round's residuals (MAD), never below the model's sigma
            es = np.linalg.norm(_spot_residuals(c, R, S[si]), axis=1) if si.any() else np.empty(0)
            er = np.abs(_ray_residuals(c, R, Q[ri])) if ri.any() else np.empty(0)
            # (the median length of a 3-D Gaussian residual is 1.54 sigma; of a 1-D one, sigma / 1.4826)
            if len(es):
                band_s = float(np.clip(3.0 * np.median(es) / 1.54, 2.0 * s_spot, band_s))
            if len(er):
                band_r = float(np.clip(3.0 * 1.4826 * np.median(er), 0.75 * tau_r, band_r))
        es = np.linalg.norm(_spot_residuals(c, R, S), axis=1) if len(S) else np.empty(0)
        er = np.abs(_ray_residuals(c, R, Q)) if len(Q) else np.empty(0)
        cost = float(np.minimum((es / tau_s) ** 2, 1.0).sum() + np.minimum((er / tau_r) ** 2, 1.0).sum())
        return c, float(R), cost, es < band_s, er < band_r

    # every start gets one round; the best by MSAC cost gets the full refinement
    best = None
    for c, R in cands:
        try:
            out = refine(np.asarray(c, float), float(R), None, rounds=1)
        except EstimationError:
            continue
        if best is None or out[2] < best[2]:
            best = out
    if best is None:
        raise EstimationError(f"{where}: every sphere hypothesis diverged")
    c, R, _, si, ri = refine(best[0], best[1], None)

    def stats(c, R, si, ri, plane):
        _, _, J, f = _mirror_lsq(S[si], Q[ri], c, R, radius, plane, s_spot)
        dof = max(len(f) - J.shape[1], 1)
        s2 = max(float(f @ f) / dof, 1e-12)
        JtJ = J.T @ J
        try:
            cov = s2 * np.linalg.inv(JtJ) if np.linalg.cond(JtJ) < 1e12 else None
        except np.linalg.LinAlgError:
            cov = None
        return cov

    gap = float(c[2] - plane_z - R)
    on = False
    if on_plane is True or on_plane == "auto":
        cov = stats(c, R, si, ri, None)
        if on_plane is True:
            on = True
        elif cov is not None:
            k = cov.shape[0]
            # gap = c_z - R: its variance from the covariance (c_z is unknown 2, R the last when fitted)
            g = np.zeros(k)
            g[2] = 1.0
            if radius is None:
                g[-1] = -1.0
            gap_std = float(np.sqrt(max(g @ cov @ g, 0.0)))
            on = abs(gap) <= plane_tol_m + 3.0 * gap_std
        if on:
            c1, R1, _, si1, ri1 = refine(np.array([c[0], c[1], plane_z + R]), R, plane_z)
            c, R, si, ri = c1, R1, si1, ri1
    n_s, n_r = int(si.sum()), int(ri.sum())
    if n_s < min_spots and n_r < min_rays:
        raise EstimationError(f"{where}: no sphere agrees with enough cues: {n_s} of {len(S)} spot candidates and "
                              f"{n_r} of {len(Q)} silhouette rays (need {min_spots} or {min_rays})")
    if radius is None and not (radius_range_m[0] <= R <= radius_range_m[1]):
        raise EstimationError(f"{where}: fitted radius {R * 1000:.1f} mm is outside the plausible range "
                              f"{radius_range_m[0] * 1000:.0f}-{radius_range_m[1] * 1000:.0f} mm")
    cov = stats(c, R, si, ri, plane_z if on else None)
    if cov is None or not np.isfinite(cov).all():
        raise EstimationError(f"{where}: the cues do not determine the ball (singular normal equations): "
                              f"{n_s} spots, {n_r} silhouette rays; scan the ball from more directions")
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    radius_std = float(std[-1]) if radius is None else 0.0
    center_std = float(std[:2 if on else 3].max())
    if radius is None and radius_std > max_radius_rel_std * R:
        raise EstimationError(f"{where}: the radius is poorly determined ({R * 1000:.1f} +- {radius_std * 1000:.1f} mm "
                              f"from {n_s} spots and {n_r} silhouette rays); scan the ball from more directions "
                              "or give its radius")
    res = np.concatenate([np.linalg.norm(S[si, :3] - c, axis=1) - R, _ray_residuals(c, R, Q[ri])])
    rms = float(np.sqrt(np.mean(res * res))) if len(res) else 0.0
    n_all = len(S) + len(Q)
    return SphereFit(center=np.asarray(c, float), radius=float(R), rms_m=rms,
                     inlier_fraction=float((n_s + n_r) / max(n_all, 1)), n_points=n_all, n_inliers=n_s + n_r,
                     radius_std_m=radius_std, center_std_m=center_std, radius_fixed=radius is not None,
                     method="mirror", n_spots=n_s, n_rays=n_r, on_plane=bool(on), plane_gap_m=gap)


def locate_ball(rays: Any, center: Any, radius: float, band_m: float = 0.006, min_rays: int = 8,
                lateral_sigma_m: float = 0.005, range_sigma_m: float = 0.002,
                max_shift_m: float = 0.015) -> np.ndarray | None:
    """Re-locate a ball of known radius in ONE frame from its silhouette rays (lighting pass, §4.3).

    The tracked pose puts the ball where the fitted centre projects; a pose error of 1-2 mm moves the
    ball against the camera and turns every mirror normal by ``error / R`` (3 degrees for 2 mm on a 35 mm
    ball, 6 degrees in the reflected direction). The silhouette measures the ball's direction from the
    camera to a fraction of a pixel; its distance matters little (a range error shifts the reflected
    directions by ``R / distance`` of it) and is kept near the prediction by a prior.

    Parameters
    ----------
    rays : (K, 7) array
        The frame's silhouette rays (:attr:`BallCues.rays`), in the frame of ``center``.
    center : (3,) array
        Predicted centre (the fitted centre, in the world frame of this frame's pose), metres.
    radius : float
        Ball radius, metres.
    band_m : float
        Only rays within this distance of the sphere's silhouette are used (first within three times it
        of the prediction, then within it of the first estimate).
    min_rays : int
        Fewer rays in the band give None.
    lateral_sigma_m, range_sigma_m : float
        Prior standard deviations of the prediction across and along the line of sight.
    max_shift_m : float
        A result farther than this from the prediction is refused (None).

    Returns
    -------
    (3,) ndarray or None
    """
    Q = np.asarray(rays, dtype=np.float64).reshape(-1, 7) if np.size(rays) else np.empty((0, 7))
    c0 = np.asarray(center, dtype=np.float64).reshape(3)
    if not (np.isfinite(c0).all() and np.isfinite(radius) and radius > 0 and band_m > 0):
        raise AppFusionError(f"locate_ball: centre, radius and band must be finite and positive "
                             f"(got {c0.tolist()}, {radius}, {band_m})")
    Q = Q[np.isfinite(Q).all(axis=1)]
    if len(Q) < max(int(min_rays), 3):
        return None
    o = Q[:, :3].mean(axis=0)
    e3 = c0 - o
    dist = float(np.linalg.norm(e3))
    if dist <= radius:
        return None
    e3 /= dist
    e1 = np.cross(e3, [0.0, 0.0, 1.0]) if abs(e3[2]) < 0.9 else np.cross(e3, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    B = np.stack([e1, np.cross(e3, e1), e3], axis=1)
    prior = np.array([lateral_sigma_m, lateral_sigma_m, range_sigma_m])
    x = np.zeros(3)
    # two rounds: rays within 3 bands of the prediction (catches a prediction off by a band), then
    # within one band of the first estimate
    for band in (3.0 * band_m, band_m):
        c = c0 + B @ x
        use = Q[np.abs(_ray_residuals(c, radius, Q)) < band]
        if len(use) < max(int(min_rays), 3):
            return None
        sig = _ray_sigma(c, use)

        def fun(x, use=use, sig=sig):
            return np.concatenate([_ray_residuals(c0 + B @ x, radius, use) / sig, x / prior])

        x = least_squares(fun, x, loss="soft_l1", f_scale=2.0, method="trf", x_scale=np.full(3, 1e-3),
                          max_nfev=50).x
    c = c0 + B @ x
    if not np.isfinite(c).all() or np.linalg.norm(c - c0) > max_shift_m:
        return None
    return c
