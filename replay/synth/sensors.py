"""Sensor models of the synthetic Kinect: depth noise, the IR emitter and camera, the RGB camera.

Depth (Kinect v1 structured light)
    Axial noise of Nguyen, Izadi & Lovell (2012), "Modeling Kinect sensor noise for improved 3D
    reconstruction and tracking" (3DIMPVT), Eq. for sigma_z:
    ``sigma_z(z, theta) = 0.0012 + 0.0019 (z - 0.4)^2 + 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2`` (m)
    with ``theta`` the angle between the surface normal and the ray to the camera. The depth is then
    quantised in disparity, ``d = f b / z`` with ``b = 7.5 cm`` and the native focal length
    ``f = 580 px``, to 1/8 px (the Kinect's sub-pixel step), so a step is
    ``dz = z^2 / (8 f b)`` (1 mm at 0.6 m, 2.9 mm at 1 m). The Gaussian added before quantisation has
    ``sigma_g = sqrt(max(sigma_z^2 - dz^2 / 12, 0))``, so that noise plus quantisation has the
    standard deviation of Nguyen's model (Sheppard's correction). Invalid (NaN): nearer than 0.4 m,
    beyond 4 m, incidence beyond 78 degrees, surfaces the emitter cannot see (the shadow band beside
    objects), nothing hit; on the mirror ball everything except a spot where the normal is within
    5 degrees of the emitter/camera bisector (there: 2 x the noise) and 3% of the other ball pixels
    which get outliers ``|N(0, 2 cm)|`` behind the surface (mirrors give a Kinect garbage depth).

IR (paper §5.1, §6)
    The emitter at ``(0.075, 0, 0)`` in the camera frame sends, towards a surface point at distance
    ``d`` from it, the intensity ``x = (t + 3.4) / (57.7 d)`` of the paper's shifted-Gamma model (§6:
    ``t = -3.4 + 57.7 d x`` with ``t ~ Gamma(k = 1.6, theta = 2.8)``). ``t`` is a stationary random
    field over emitter *directions*: on a grid of 1/580 rad cells (one native pixel), a Gaussian random
    field with a Gaussian correlation of 1.5 cells mapped through the normal CDF and the Gamma quantile
    function (a Gaussian copula: the marginal is exactly Gamma, neighbouring directions are correlated).
    It is fixed per device seed and the same in every frame; a pixel takes the cell its hit point is
    seen in from the emitter (nearest cell). The received radiance is
    ``R = x cos(theta_i) (rho_d_ir / pi + rho_s_ir f(w_i, w_o))`` with ``w_i`` towards the emitter and
    ``w_o`` towards the camera (the 7.5 cm baseline is exact). Counts:
    ``raw = gain R^gamma + b0 + fpn + noise``, gamma = 0.9 (paper §6), gain such that a white sheet
    (rho 0.8) at 0.6 m with the mean ``t`` reads 60% of 1023; ``b0`` the ambient background, ``fpn`` a
    fixed per-pixel offset (sigma 1 count), temporal noise Gaussian with variance
    ``sigma_read^2 + shot * signal``; rounded and clipped to 10 bits. Emitter off: background only.

RGB
    Linear radiance times the exposure and per-channel white-balance gains of the frame, plus shot
    (variance ``v / full_well``) and read noise, clipped, sRGB-encoded to 8 bits. Exposure drifts
    slowly by up to +-20% and the white balance (1.08, 1.0, 0.86) by up to +-3% per channel (sums of
    slow sinusoids, periods 4-15 s), which the markers (white reference, §4.2) must undo.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from appfusion.frame import linear_to_srgb


# -- depth ------------------------------------------------------------------------------------------

@dataclass
class DepthModel:
    """Kinect v1 depth: Nguyen noise, disparity quantisation, invalid regions (all in ``scene.json``)."""

    baseline_m: float = 0.075
    focal_native_px: float = 580.0
    subpixel: int = 8
    z_min_m: float = 0.4
    z_max_m: float = 4.0
    max_incidence_deg: float = 78.0
    a_m: float = 0.0012
    b_per_m: float = 0.0019
    z0_m: float = 0.4
    c_angle: float = 0.0001
    mirror_spot_deg: float = 5.0
    mirror_spot_noise_scale: float = 2.0
    mirror_outlier_fraction: float = 0.03
    mirror_outlier_sigma_m: float = 0.02

    def sigma(self, z, theta=0.0) -> np.ndarray:
        """Nguyen et al. (2012) axial standard deviation (m) at depth z (m), incidence theta (rad)."""
        z = np.asarray(z, dtype=np.float64)
        th = np.clip(np.asarray(theta, dtype=np.float64), 0.0, np.pi / 2 - 1e-3)
        return (self.a_m + self.b_per_m * (z - self.z0_m) ** 2
                + self.c_angle / np.sqrt(np.maximum(z, 1e-3)) * th ** 2 / (np.pi / 2 - th) ** 2)

    def step(self, z) -> np.ndarray:
        """Depth quantisation step (m) at z: one 1/subpixel disparity step."""
        return np.asarray(z, dtype=np.float64) ** 2 / (self.subpixel * self.focal_native_px * self.baseline_m)

    def quantise(self, z) -> np.ndarray:
        fb = self.focal_native_px * self.baseline_m
        disp = fb / np.asarray(z, dtype=np.float64)
        dq = np.round(disp * self.subpixel) / self.subpixel
        with np.errstate(divide="ignore"):
            return np.where(dq > 0, fb / np.where(dq > 0, dq, 1.0), np.nan)

    def apply(self, z: np.ndarray, cos_inc: np.ndarray, valid: np.ndarray, rng: np.random.Generator,
              mirror: np.ndarray | None = None, mirror_cos_spec: np.ndarray | None = None) -> np.ndarray:
        """Measured depth (float32, NaN invalid) from the true z (m) of each pixel.

        Parameters
        ----------
        z : (H, W) true depth along the optical axis (NaN/inf where nothing is hit)
        cos_inc : (H, W) cosine between the surface normal and the ray to the camera
        valid : (H, W) bool, False where the emitter cannot see the point (shadow) or nothing is hit
        mirror : (H, W) bool, pixels on the mirror ball
        mirror_cos_spec : (H, W) cosine between the ball normal and the emitter/camera bisector
        """
        z = np.asarray(z, dtype=np.float64)
        theta = np.arccos(np.clip(cos_inc, -1.0, 1.0))
        ok = valid & np.isfinite(z) & (z >= self.z_min_m) & (z <= self.z_max_m)
        ok &= theta <= np.radians(self.max_incidence_deg)
        zz = np.where(ok, z, 1.0)
        sig = self.sigma(zz, theta)
        if mirror is not None and np.any(mirror):
            spot = mirror & (mirror_cos_spec >= np.cos(np.radians(self.mirror_spot_deg)))
            sig = np.where(spot, sig * self.mirror_spot_noise_scale, sig)
        dz = self.step(zz)
        sg = np.sqrt(np.maximum(sig ** 2 - dz ** 2 / 12.0, 0.0))
        noisy = zz + sg * rng.standard_normal(z.shape)
        if mirror is not None and np.any(mirror):
            out_l = mirror & ~spot & (rng.random(z.shape) < self.mirror_outlier_fraction)
            noisy = np.where(out_l, zz + np.abs(rng.normal(0, self.mirror_outlier_sigma_m, z.shape)), noisy)
            ok &= ~mirror | spot | out_l
        d = self.quantise(np.maximum(noisy, 1e-3))
        return np.where(ok, d, np.nan).astype(np.float32)

    def to_json(self) -> dict:
        return dict(self.__dict__)


# -- IR -----------------------------------------------------------------------------------------

@dataclass
class IRModel:
    """The IR emitter (shifted-Gamma field over directions) and the 10-bit IR camera (truth/ir_model.json)."""

    seed: int = 0
    k: float = 1.6
    theta: float = 2.8
    shift: float = 3.4
    scale: float = 57.7
    gamma: float = 0.9
    b0: float = 48.0
    sigma_fpn: float = 1.0
    sigma_read: float = 1.5
    shot: float = 0.25
    bits: int = 10
    ref_distance_m: float = 0.6
    ref_albedo: float = 0.8
    ref_level: float = 0.6
    cell_rad: float = 1.0 / 580.0
    #: the pattern grid's offset from the camera's pixel grid, cells: a projector's pattern is not
    #: aligned with the camera's rows. With no offset the emitter sits on the camera's x axis, so every
    #: pixel ray's emitter direction fell exactly on a cell boundary in y, and float rounding chose the
    #: row: the field was not a function of direction (14 % per-pixel spread against any fixed map)
    grid_offset_cells: tuple = (0.37, 0.29)
    corr_cells: float = 1.5
    half_extent: tuple = (0.75, 0.6)
    emitter_position_m: tuple = (0.075, 0.0, 0.0)
    _t: np.ndarray | None = field(default=None, repr=False)
    _fpn: dict = field(default_factory=dict, repr=False)

    @property
    def full_scale(self) -> float:
        return float(2 ** self.bits - 1)

    @property
    def gain(self) -> float:
        """Counts per (radiance^gamma): a white sheet at ``ref_distance_m`` with the mean t reads ``ref_level``."""
        x = (self.k * self.theta + self.shift) / (self.scale * self.ref_distance_m)
        R = x * self.ref_albedo / np.pi
        return float((self.ref_level * self.full_scale - self.b0) / R ** self.gamma)

    def pattern(self) -> np.ndarray:
        """The emitter field t over the direction grid, (rows, cols) float32 (generated once)."""
        if self._t is None:
            from scipy.ndimage import gaussian_filter
            from scipy.special import gammaincinv, ndtr

            nx = int(np.ceil(self.half_extent[0] / self.cell_rad)) * 2 + 1
            ny = int(np.ceil(self.half_extent[1] / self.cell_rad)) * 2 + 1
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, 7001]))
            g = gaussian_filter(rng.standard_normal((ny, nx)), self.corr_cells, mode="wrap")
            g /= g.std()
            # Gamma quantile of the normal CDF, tabulated on 8193 normal scores over [-8, 8] (absolute
            # interpolation error < 2e-6 in t) instead of 600k calls of the incomplete-Gamma inverse
            zs = np.linspace(-8.0, 8.0, 8193)
            ts = gammaincinv(self.k, np.clip(ndtr(zs), 1e-300, 1 - 1e-16)) * self.theta
            self._t = np.interp(g, zs, ts).astype(np.float32)
        return self._t

    def t_at(self, v_cam: np.ndarray) -> np.ndarray:
        """Field value for points ``v_cam`` (N, 3) given relative to the emitter in camera axes."""
        t = self.pattern()
        ny, nx = t.shape
        z = np.maximum(v_cam[:, 2], 1e-6)
        ox, oy = self.grid_offset_cells
        ix = np.clip(np.rint(v_cam[:, 0] / z / self.cell_rad - ox).astype(np.int64) + nx // 2, 0, nx - 1)
        iy = np.clip(np.rint(v_cam[:, 1] / z / self.cell_rad - oy).astype(np.int64) + ny // 2, 0, ny - 1)
        return t[iy, ix]

    def incident(self, v_cam: np.ndarray) -> np.ndarray:
        """Emitter intensity x = (t + shift) / (scale d) at points ``v_cam`` (N, 3) relative to the emitter."""
        d = np.linalg.norm(v_cam, axis=1)
        return (self.t_at(v_cam) + self.shift) / (self.scale * d)

    def fpn(self, shape: tuple[int, int]) -> np.ndarray:
        """Fixed per-pixel background offset of this device at an image size (counts)."""
        if shape not in self._fpn:
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, 7002, shape[0], shape[1]]))
            self._fpn[shape] = rng.normal(0.0, self.sigma_fpn, shape)
        return self._fpn[shape]

    def counts(self, radiance: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """10-bit counts (float32) from received radiance (H, W) (0 where nothing comes back)."""
        sig = self.gain * np.maximum(radiance, 0.0) ** self.gamma
        noise = rng.standard_normal(radiance.shape) * np.sqrt(self.sigma_read ** 2 + self.shot * sig)
        raw = sig + self.b0 + self.fpn(radiance.shape) + noise
        return np.clip(np.rint(raw), 0, self.full_scale).astype(np.float32)

    def to_json(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if not k.startswith("_")}
        d["half_extent"] = list(self.half_extent)
        d["grid_offset_cells"] = list(self.grid_offset_cells)
        d["emitter_position_m"] = list(self.emitter_position_m)
        d["gain"] = self.gain
        d["model"] = ("raw = gain * R^gamma + b0 + fpn + N(0, sigma_read^2 + shot * gain * R^gamma), rounded, "
                      "clipped to [0, 2^bits - 1]; R = x cos(theta_i) (rho_d_ir/pi + rho_s_ir f); "
                      "x = (t + shift) / (scale * d_emitter); t ~ Gamma(k, theta) field over emitter directions")
        d["pattern_grid"] = ("t[row, col] at direction (x/z, y/z) = ((col - cols//2 + grid_offset_cells[0]) * "
                             "cell_rad, (row - rows//2 + grid_offset_cells[1]) * cell_rad) from the emitter, "
                             "camera axes; nearest cell")
        return d


# -- RGB ----------------------------------------------------------------------------------------

def _slow(rng: np.random.Generator, t: np.ndarray, periods=(4.0, 15.0), n: int = 3) -> np.ndarray:
    """A slow signal in [-1, 1]: normalised sum of ``n`` sinusoids with periods in ``periods`` seconds."""
    per = rng.uniform(periods[0], periods[1], n)
    amp = rng.uniform(0.5, 1.0, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    s = np.sum(amp * np.sin(2 * np.pi * np.asarray(t)[..., None] / per + ph), axis=-1)
    return s / amp.sum()


@dataclass
class RGBModel:
    """The RGB camera (truth: per-frame exposure and gains in truth/frames.json)."""

    seed: int = 0
    wb_gains: tuple = (1.08, 1.0, 0.86)
    wb_drift: float = 0.03
    exposure_drift: float = 0.20
    full_well: float = 4000.0
    read_sigma: float = 0.002
    headroom: float = 0.8

    def drift(self, t: np.ndarray):
        """Exposure factor (N,) and white-balance gains (N, 3) at times t (s)."""
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 8001]))
        e = 1.0 + self.exposure_drift * _slow(rng, t)
        g = np.stack([self.wb_gains[c] * (1.0 + self.wb_drift * _slow(rng, t)) for c in range(3)], axis=-1)
        return e, g

    def base_exposure(self, max_radiance: float) -> float:
        """Exposure that keeps ``max_radiance`` below ``headroom`` of full scale at the worst drift."""
        worst = (1 + self.exposure_drift) * max(self.wb_gains) * (1 + self.wb_drift)
        return float(self.headroom / (max_radiance * worst))

    def capture(self, radiance: np.ndarray, exposure: float, gains: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """8-bit sRGB image (H, W, 3) uint8 from linear radiance (H, W, 3)."""
        v = radiance * (exposure * np.asarray(gains))
        v = v + rng.standard_normal(v.shape) * np.sqrt(self.read_sigma ** 2 + np.maximum(v, 0) / self.full_well)
        return np.rint(linear_to_srgb(np.clip(v, 0.0, 1.0)) * 255.0).astype(np.uint8)

    def to_json(self) -> dict:
        d = dict(self.__dict__)
        d["wb_gains"] = list(self.wb_gains)
        return d
