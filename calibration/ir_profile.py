"""IR device profile: background, response curve and emitter model (paper §6), saved as JSON.

Forward model (what the profile describes)
------------------------------------------
A surface point at distance ``d`` from the emitter, lit at ``theta_i`` and with BRDF ``f_r``, gives

    raw = gain * (x cos(theta_i) f_r)^gamma + b0 + noise,                       (response curve)

where ``x`` is the emitter's incident intensity, which depends on the emitter model:

``"shifted_gamma"`` (Kinect v1 structured light, paper §6)
    ``x = (t + shift) / (scale d^p)`` with ``t ~ Gamma(k, theta)``, a random field over emitter
    directions (the dot pattern), ``p = 1`` (the paper's ``t = -3.4 + 57.7 d x``). Mean
    ``E[x](d) = (k theta + shift) / (scale d^p)``.
``"flat"`` (flood illuminators: OAK-D Pro flood light, Azure Kinect ToF)
    ``x = 1 / (scale d^p)`` with ``p = 2`` (inverse square), no random part.

Normalisation. Only ``gain * (theta / scale)^gamma``, ``gamma``, ``k`` and ``shift / theta`` can be
observed (the scale of ``t`` and of ``x`` trade off against ``gain``). A profile therefore fixes
``scale = 1`` and ``k theta + shift = 1`` (shifted Gamma) so that ``E[x](d) = 1 / d^p`` exactly; the
paper's ``(k, theta, shift, scale) = (1.6, 2.8, 3.4, 57.7)`` reads ``(1.6, 0.355, 0.431, 1)`` here
(``shift / theta = 1.214`` in both), with the paper's scale folded into ``gain``.

Apply (what the IR pass uses)
-----------------------------
For a raw value ``raw`` at emitter distance ``d`` and incidence cosine ``cos(theta_i)``:

    radiance = (max(raw - b0, 0) / gain)^(1 / gamma)
    sample   = radiance / (E[x](d) cos(theta_i)) = radiance d^p / cos(theta_i)     (1/sr)

``sample`` is the BRDF value ``f_r(w_i, w_o)`` multiplied by ``x / E[x]`` (mean 1: the emitter's
multiplicative noise, coefficient of variation ``sqrt(k) theta / (k theta + shift)``, ~0.45 for the
Kinect, none for a flat emitter), so averaging samples (HBSAB, §5.1) converges to ``f_r``. A white
sheet of albedo ``sheet_albedo`` gives ``sheet_albedo / pi`` on average. Raw values at or above
``saturation`` are invalid (clipped highlights).

A shifted-Gamma profile may also carry the emitter's *pattern* (:mod:`calibration.ir_pattern`): the
relative intensity ``m`` of the fixed dot pattern over emitter directions, calibrated from the same
sheet frames. Dividing a sample by ``m`` at its emitter direction (:meth:`IRProfile.pattern_at`)
removes most of the multiplicative noise and, above all, its fixed per-direction bias. The map is a
``.npz`` file beside the profile's JSON (``pattern_file``, relative to it).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from appfusion.errors import AppFusionError, CalibrationError
from appfusion.frame import Intrinsics

EMITTER_MODELS = ("shifted_gamma", "flat")
PROFILE_VERSION = 1


@dataclass
class IRProfile:
    """Calibrated IR sensor and emitter (paper §6). Fields are described in the module docstring.

    Attributes
    ----------
    emitter_model : {"shifted_gamma", "flat"}
    background : float
        ``b0``, raw counts.
    noise_sigma : float
        Sensor noise per pixel, counts.
    gamma : float
        Response exponent (paper: 0.9).
    gain : float
        Counts per (unit radiance)^gamma, radiance in units of ``E[x](1 m) = 1``.
    k, theta, shift : float or None
        Shifted-Gamma emitter parameters (normalised: ``k theta + shift = 1``); None for "flat".
    scale : float
        1 (normalisation).
    falloff_exponent : float
        ``p`` in ``x ~ 1 / d^p``: 1 for the shifted-Gamma (paper), 2 for flat emitters.
    sheet_albedo : float
        Albedo assumed for the calibration sheet (absolute scale of the samples).
    saturation : float
        Raw values >= this are discarded.
    emitter_position_m : list of 3 floats
        Emitter position in the depth-camera frame, metres (from the session).
    device : str
    fit : dict
        Diagnostics of the calibration (residuals, distances, frames used).
    pattern_file : str or None
        File name of the emitter pattern map, relative to the profile's JSON (None: no map).
    pattern : calibration.ir_pattern.EmitterPattern or None
        The map itself (not part of the JSON; read from ``pattern_file`` by :meth:`load`).
    """

    emitter_model: str = "shifted_gamma"
    background: float = 0.0
    noise_sigma: float = 0.0
    gamma: float = 1.0
    gain: float = 1.0
    k: float | None = None
    theta: float | None = None
    shift: float | None = None
    scale: float = 1.0
    falloff_exponent: float | None = None
    sheet_albedo: float = 1.0
    saturation: float = 1023.0
    emitter_position_m: list = field(default_factory=lambda: [0.075, 0.0, 0.0])
    device: str = ""
    fit: dict = field(default_factory=dict)
    pattern_file: str | None = None
    pattern: Any = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        if self.emitter_model not in EMITTER_MODELS:
            raise CalibrationError(f"IR profile: unknown emitter model {self.emitter_model!r} "
                                   f"(known: {', '.join(EMITTER_MODELS)})")
        if self.falloff_exponent is None:
            self.falloff_exponent = 1.0 if self.emitter_model == "shifted_gamma" else 2.0
        for name in ("background", "gamma", "gain", "scale", "falloff_exponent", "saturation", "sheet_albedo"):
            v = getattr(self, name)
            if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(float(v)):
                raise CalibrationError(f"IR profile: {name} must be a finite number, got {v!r}")
            setattr(self, name, float(v))
        if self.gamma <= 0 or self.gain <= 0 or self.scale <= 0 or self.sheet_albedo <= 0:
            raise CalibrationError(f"IR profile: gamma, gain, scale and sheet_albedo must be positive "
                                   f"(got {self.gamma}, {self.gain}, {self.scale}, {self.sheet_albedo})")
        if self.emitter_model == "shifted_gamma":
            for name in ("k", "theta", "shift"):
                v = getattr(self, name)
                if v is None or not math.isfinite(float(v)):
                    raise CalibrationError(f"IR profile: shifted-Gamma emitter needs a finite {name}, got {v!r}")
                setattr(self, name, float(v))
            if self.k <= 0 or self.theta <= 0:
                raise CalibrationError(f"IR profile: k and theta must be positive, got {self.k}, {self.theta}")
        e = np.asarray(self.emitter_position_m, dtype=float).reshape(-1)
        if e.shape != (3,) or not np.isfinite(e).all():
            raise CalibrationError(f"IR profile: emitter_position_m must be 3 finite numbers, got {self.emitter_position_m!r}")
        self.emitter_position_m = [float(x) for x in e]

    # -- model ----------------------------------------------------------------------------
    @property
    def mean_intensity_1m(self) -> float:
        """``E[x]`` at 1 m (1 for a normalised profile)."""
        if self.emitter_model == "shifted_gamma":
            return (self.k * self.theta + self.shift) / self.scale
        return 1.0 / self.scale

    def mean_irradiance(self, d) -> np.ndarray:
        """``E[x](d)``, the mean emitter intensity at distance ``d`` (metres) from the emitter."""
        d = np.asarray(d, dtype=np.float64)
        return self.mean_intensity_1m / d ** self.falloff_exponent

    @property
    def emitter_cv(self) -> float:
        """Coefficient of variation of ``x`` (the emitter's multiplicative noise); 0 for flat."""
        if self.emitter_model != "shifted_gamma":
            return 0.0
        return math.sqrt(self.k) * self.theta / (self.k * self.theta + self.shift)

    def linearize(self, raw) -> np.ndarray:
        """Radiance ``(max(raw - b0, 0) / gain)^(1/gamma)`` (units: ``E[x](1 m) = 1``), float32."""
        r = np.asarray(raw, dtype=np.float32)
        u = np.maximum(r - np.float32(self.background), 0.0) * np.float32(1.0 / self.gain)
        return np.power(u, np.float32(1.0 / self.gamma))

    def apply(self, raw, d, cos_i) -> tuple[np.ndarray, np.ndarray]:
        """Reflectance samples from raw IR values (module docstring), vectorised.

        Parameters
        ----------
        raw : array
            Raw IR values, counts.
        d : array
            Distance from the emitter to the surface point, metres (broadcast with ``raw``).
        cos_i : array
            Cosine between the normal and the direction to the emitter.

        Returns
        -------
        samples : float32 array
            BRDF samples, 1/sr (0 where invalid).
        valid : bool array
            Finite input, ``raw < saturation``, ``d > 0``, ``cos_i > 0``.
        """
        raw = np.asarray(raw, dtype=np.float32)
        d = np.asarray(d, dtype=np.float32)
        cos_i = np.asarray(cos_i, dtype=np.float32)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            valid = np.isfinite(raw) & (raw < self.saturation) & (d > 0) & (cos_i > 0) & np.isfinite(d)
            p = self.falloff_exponent
            dp = d if p == 1.0 else (d * d if p == 2.0 else np.power(d, np.float32(p)))
            s = self.linearize(np.where(valid, raw, self.background)) * dp / np.where(valid, cos_i, 1.0)
            s *= np.float32(1.0 / self.mean_intensity_1m)
        return np.where(valid, s, 0.0).astype(np.float32), valid

    def apply_valid(self, raw, d, cos_i) -> np.ndarray:
        """:meth:`apply` without validity checks (all inputs finite, ``d, cos_i > 0``; raw values at
        or above ``saturation`` are treated as clipped there), float32; the IR pass's hot path."""
        raw = np.minimum(np.asarray(raw, dtype=np.float32), np.float32(self.saturation))
        d = np.asarray(d, dtype=np.float32)
        p = self.falloff_exponent
        dp = d if p == 1.0 else (d * d if p == 2.0 else np.power(d, np.float32(p)))
        s = self.linearize(raw)
        s *= dp
        s /= np.asarray(cos_i, dtype=np.float32)
        if self.mean_intensity_1m != 1.0:
            s *= np.float32(1.0 / self.mean_intensity_1m)
        return s

    def apply_frame(self, ir: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics,
                    emitter_position=None, normals: np.ndarray | None = None) -> np.ndarray:
        """Reflectance-sample image of one IR frame registered to its depth image.

        Parameters
        ----------
        ir, depth : (H, W) arrays
            Raw IR (counts) and depth (metres, NaN invalid) on the same pixel grid.
        intrinsics : Intrinsics
            Of the depth/IR camera.
        emitter_position : 3 floats, optional
            Emitter in the camera frame, metres (default: the profile's).
        normals : (H, W, 3) array, optional
            Unit camera-frame normals; default: from depth differences (central, facing the camera).

        Returns
        -------
        (H, W) float32
            BRDF samples (1/sr), NaN where invalid.
        """
        ir = np.asarray(ir)
        depth = np.asarray(depth, dtype=np.float32)
        if ir.shape != depth.shape or depth.shape != intrinsics.shape:
            raise AppFusionError(f"IR profile: IR {ir.shape}, depth {depth.shape} and intrinsics "
                                 f"{intrinsics.shape} must have the same size")
        e = np.asarray(self.emitter_position_m if emitter_position is None else emitter_position, dtype=np.float32)
        P = intrinsics.backproject(depth)
        if normals is None:
            normals = depth_normals(P)
        L = e - P
        d = np.linalg.norm(L, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_i = np.sum(L * normals, axis=-1) / d
        s, ok = self.apply(ir, d, cos_i)
        if self.pattern is not None:
            s = s / self.pattern_at(P, e)
        return np.where(ok, s, np.nan).astype(np.float32)

    def pattern_at(self, P, emitter_position=None) -> np.ndarray:
        """Relative emitter intensity ``m`` at camera-frame points ``P`` (..., 3), float32: the pattern
        map's value at each point's emitter direction (:mod:`calibration.ir_pattern`); 1 without a map."""
        P = np.asarray(P)
        if self.pattern is None:
            return np.ones(P.shape[:-1], dtype=np.float32)
        e = self.emitter_position_m if emitter_position is None else emitter_position
        return self.pattern.lookup_points(P, e)

    # -- persistence ------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("pattern", None)
        d["version"] = PROFILE_VERSION
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any], where: str = "IR profile") -> "IRProfile":
        if not isinstance(d, dict):
            raise CalibrationError(f"{where}: expected a JSON object")
        v = d.get("version", PROFILE_VERSION)
        if v != PROFILE_VERSION:
            raise CalibrationError(f"{where}: profile version {v!r} is not supported (expected {PROFILE_VERSION})")
        known = {f for f in cls.__dataclass_fields__} - {"pattern"}
        unknown = set(d) - known - {"version"}
        if unknown:
            raise CalibrationError(f"{where}: unknown field(s) {sorted(unknown)}")
        try:
            return cls(**{k: v for k, v in d.items() if k in known})
        except CalibrationError as e:
            raise CalibrationError(f"{where}: {e}") from None
        except TypeError as e:
            raise CalibrationError(f"{where}: {e}") from None

    def save(self, path: str | os.PathLike) -> None:
        """Write the profile as JSON (atomically), and its pattern map beside it (``NAME.pattern.npz``)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if self.pattern is not None:
            self.pattern_file = path.stem + ".pattern.npz"
            self.pattern.save(path.parent / self.pattern_file)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=2, default=_json_default) + "\n")
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "IRProfile":
        """Read a profile written by :meth:`save`."""
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as e:
            raise CalibrationError(f"{path}: cannot read IR profile: {e.strerror or e}") from None
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise CalibrationError(f"{path}:{e.lineno}: not valid JSON: {e.msg}") from None
        prof = cls.from_json(d, where=str(path))
        if prof.pattern_file:
            from .ir_pattern import EmitterPattern

            prof.pattern = EmitterPattern.load(path.parent / prof.pattern_file)
        return prof


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def depth_normals(P: np.ndarray, step: int = 3) -> np.ndarray:
    """Unit normals (H, W, 3) of a camera-frame point image (H, W, 3) by central differences over
    ``step`` pixels each side (a wide baseline: 1/cos of a normal tilted by depth noise is biased
    high), oriented towards the camera; NaN where a neighbour is missing."""
    P = np.asarray(P, dtype=np.float32)
    s = int(step)
    dx = np.full_like(P, np.nan)
    dy = np.full_like(P, np.nan)
    dx[:, s:-s] = P[:, 2 * s:] - P[:, :-2 * s]
    dy[s:-s] = P[2 * s:] - P[:-2 * s]
    n = np.cross(dx, dy)
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        flip = np.sum(n * P, axis=-1) > 0
    n[flip] *= -1
    return n
