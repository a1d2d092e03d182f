"""Environment maps from a mirror ball (paper §4.3): accumulation, coverage, fill, file I/O, previews.

The lighting pass maps every calibrated (white-balanced, linear) RGB pixel that sees the fitted mirror
ball to the direction it reflects, and folds its radiance into that direction's texel of an octahedral
map of two squares (``(2, N, N, 3)``, the paper's 2 x 128^2, :mod:`appfusion.octahedral`) as a running
weighted mean with weight ``w_o . n`` (the paper, after [LKG*03]; the same update as the HBSAB, §5.1
Eq. 3)::

    L_new = (L * W + sum_k l_k w_k) / (W + sum_k w_k),    W_new = W + sum_k w_k.

Memory is constant: a weight and a mean per texel. A mirror reflects ``rho_mirror`` of the light
(1 by default; a chrome ball reflects about 0.6-0.7, measure it or leave 1 and accept that the map is
scaled by it), which is divided out. Pixels seen at grazing angles (``w_o . n < min_cos``) are skipped:
their footprint smears over many texels. Each pixel is supersampled over its footprint (``s x s``
sub-rays, each with the pixel's value and weight ``w_o . n / s^2``) so that a 640x480 camera fills the
map without holes.

The map lives in the world (marker) frame: directions are in marker coordinates (z up, out of the
support plane), so it is captured once per marker set and reused by later scans (paper §4.3).

Texels never seen (below the support plane, behind the user, in the cone behind the ball) keep
``coverage == False``; :meth:`EnvMap.fill` can inpaint them and marks them in ``filled``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
import cv2  # noqa: E402  (the variable must be set before cv2 is imported)
import numpy as np  # noqa: E402

from . import octahedral as octa  # noqa: E402
from .errors import AppFusionError, EstimationError  # noqa: E402
from .frame import REC709_LUMA, Intrinsics, linear_to_srgb  # noqa: E402

#: version of the .npz layout written by :meth:`EnvMap.save_npz`
NPZ_VERSION = 1


class EnvMapFileError(AppFusionError):
    """An environment-map file is missing, damaged or not of a known format (names the file)."""

    def __init__(self, path: str | os.PathLike, message: str):
        self.path = os.fspath(path)
        super().__init__(f"{self.path}: {message}")


# -- the map ---------------------------------------------------------------------------------------

@dataclass
class EnvMap:
    """An environment map on two octahedral squares, in the marker frame.

    Attributes
    ----------
    radiance : (2, N, N, 3) float32 ndarray
        Linear RGB radiance per texel, in units of the reference white of §4.2 (a white circle = 1),
        divided by the mirror's reflectance. 0 where neither measured nor filled.
    weight : (2, N, N) float32 ndarray, optional
        Sum of sample weights ``w_o . n`` per texel (0 = never seen). Default: 1 where measured.
    coverage : (2, N, N) bool ndarray, optional
        Texels measured (weight above the threshold used when the map was made). Default: all.
    filled : (2, N, N) bool ndarray, optional
        Texels whose radiance was filled in (inpainted), not measured. Never overlaps ``coverage``.
        Default: none.
    frame : str
        Frame of the directions: ``"marker"`` (world of the scan) unless loaded from elsewhere.
    meta : dict
        JSON-serialisable provenance (rho_mirror, sphere, views, fill method, ...).
    """

    radiance: np.ndarray
    weight: np.ndarray | None = None
    coverage: np.ndarray | None = None
    filled: np.ndarray | None = None
    frame: str = "marker"
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        self.radiance = np.asarray(self.radiance, dtype=np.float32)
        r = self.radiance
        if r.ndim != 4 or r.shape[0] != 2 or r.shape[1] != r.shape[2] or r.shape[3] != 3 or r.shape[1] < 2:
            raise AppFusionError(f"environment map radiance must have shape (2, N, N, 3), got {r.shape}")
        shp = r.shape[:3]
        if self.coverage is None:
            self.coverage = np.ones(shp, bool) if self.filled is None else ~np.asarray(self.filled, bool)
        if self.filled is None:
            self.filled = np.zeros(shp, bool)
        if self.weight is None:
            self.weight = np.asarray(self.coverage, np.float32)
        self.weight = np.asarray(self.weight, dtype=np.float32)
        self.coverage = np.asarray(self.coverage, dtype=bool)
        self.filled = np.asarray(self.filled, dtype=bool)
        for name in ("weight", "coverage", "filled"):
            if getattr(self, name).shape != shp:
                raise AppFusionError(f"environment map {name} must have shape {shp}, got {getattr(self, name).shape}")
        if not np.isfinite(r).all() or not np.isfinite(self.weight).all():
            raise AppFusionError("environment map contains NaN or infinite values")
        if (self.coverage & self.filled).any():
            raise AppFusionError("environment map: a texel cannot be both measured (coverage) and filled")

    # -- geometry ----------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Side N of each square."""
        return int(self.radiance.shape[1])

    def directions(self) -> np.ndarray:
        """Unit direction of every texel (marker frame), shape (2, N, N, 3)."""
        return octa.sphere_directions(self.n)

    def solid_angles(self) -> np.ndarray:
        """Solid angle (sr) of every texel, shape (2, N, N); sums to 4 pi."""
        return octa.sphere_solid_angles(self.n)

    @property
    def known(self) -> np.ndarray:
        """Texels with a value (measured or filled), (2, N, N) bool."""
        return self.coverage | self.filled

    def coverage_fraction(self) -> float:
        """Fraction of the sphere's solid angle that was measured (0..1)."""
        w = self.solid_angles()
        return float(w[self.coverage].sum() / w.sum())

    def energy(self, mask: np.ndarray | None = None) -> np.ndarray:
        """Integral of radiance over solid angle, ``sum L * d omega`` (RGB, shape (3,)).

        Parameters
        ----------
        mask : (2, N, N) bool, optional
            Texels to integrate over; default all texels with a value (measured or filled).
        """
        m = self.known if mask is None else np.asarray(mask, bool)
        return (self.radiance[m] * self.solid_angles()[m][:, None]).sum(axis=0).astype(np.float64)

    def sample(self, d: np.ndarray) -> np.ndarray:
        """Bilinearly interpolated radiance in directions ``d`` (..., 3) (marker frame); shape (..., 3)."""
        return octa.sample_sphere_map(self.radiance, d)

    def to_latlong(self, height: int | None = None, width: int | None = None) -> np.ndarray:
        """Lat-long radiance image (H, W, 3) float32 (row 0 = zenith +z; see :mod:`appfusion.octahedral`).

        Default height 2N, width 2 x height.
        """
        height = int(height or 2 * self.n)
        return octa.sphere_to_latlong(self.radiance, height, width).astype(np.float32)

    def _mask_latlong(self, height: int, width: int | None = None) -> np.ndarray:
        """Per lat-long pixel: 2 = measured, 1 = filled, 0 = unknown (nearest texel)."""
        code = self.coverage.astype(np.uint8) * 2 + self.filled.astype(np.uint8)
        idx = octa.sphere_texel_index(octa.latlong_directions(height, width), self.n)
        return code.reshape(-1)[idx]

    # -- fill --------------------------------------------------------------------------------------
    def fill(self, method: str = "harmonic", value: Any = None) -> "EnvMap":
        """A copy with the unmeasured texels filled in and marked in ``filled``.

        Parameters
        ----------
        method : {"harmonic", "nearest", "constant"}
            ``"harmonic"``: membrane (Laplace) inpainting on the sphere's texel graph, both squares and the
            seam between them: every unknown texel becomes the average of its neighbours, the measured
            texels fixed (smooth, no seams). ``"nearest"``: the nearest measured direction's value.
            ``"constant"``: ``value`` (RGB or scalar; default the solid-angle-weighted mean of the
            measured texels).

        Raises
        ------
        EstimationError
            If nothing was measured.
        """
        cov = self.coverage
        if not cov.any():
            raise EstimationError("environment map: nothing measured, nothing to fill from")
        out = self.radiance.copy()
        unknown = ~cov
        if not unknown.any():
            return EnvMap(out, self.weight.copy(), cov.copy(), np.zeros_like(cov), self.frame,
                          {**self.meta, "fill": method})
        if method == "harmonic":
            out[unknown] = _harmonic_fill(self.radiance, cov)
        elif method == "nearest":
            from scipy.spatial import cKDTree
            d = self.directions()
            _, j = cKDTree(d[cov]).query(d[unknown])
            out[unknown] = self.radiance[cov][j]
        elif method == "constant":
            if value is None:
                w = self.solid_angles()[cov]
                value = (self.radiance[cov] * w[:, None]).sum(axis=0) / w.sum()
            out[unknown] = np.broadcast_to(np.asarray(value, np.float32), (int(unknown.sum()), 3))
        else:
            raise AppFusionError(f"environment map fill: unknown method {method!r} (harmonic, nearest, constant)")
        return EnvMap(out, self.weight.copy(), cov.copy(), unknown, self.frame, {**self.meta, "fill": method})

    # -- files -------------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike, **kwargs) -> Path:
        """Save by suffix: ``.npz`` (lossless with masks), ``.exr`` or ``.hdr`` (lat-long)."""
        path = Path(path)
        suf = path.suffix.lower()
        if suf == ".npz":
            return self.save_npz(path)
        if suf == ".exr":
            return self.export_exr(path, **kwargs)
        if suf == ".hdr":
            return self.export_hdr(path, **kwargs)
        raise EnvMapFileError(path, "unknown environment-map suffix (use .npz, .exr or .hdr)")

    def save_npz(self, path: str | os.PathLike) -> Path:
        """Lossless .npz with radiance, weight, both masks, frame and meta (written atomically)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, version=np.int64(NPZ_VERSION), radiance=self.radiance, weight=self.weight,
                            coverage=self.coverage, filled=self.filled, frame=np.str_(self.frame),
                            meta=np.str_(json.dumps(self.meta, default=_json_default)))
        os.replace(tmp, path)
        return path

    def export_exr(self, path: str | os.PathLike, height: int | None = None, alpha: bool = True) -> Path:
        """Lat-long OpenEXR (float32), by default RGBA with alpha = 1 measured, 0.5 filled, 0 unknown."""
        path = Path(path)
        h = int(height or 2 * self.n)
        img = self.to_latlong(h)[..., ::-1]                     # RGB -> BGR for OpenCV
        if alpha:
            a = self._mask_latlong(h).astype(np.float32) / 2.0
            img = np.concatenate([img, a[..., None]], axis=-1)
        return _imwrite(path, np.ascontiguousarray(img, dtype=np.float32))

    def export_hdr(self, path: str | os.PathLike, height: int | None = None) -> Path:
        """Lat-long Radiance RGBE .hdr (no masks; about 1% precision)."""
        path = Path(path)
        h = int(height or 2 * self.n)
        img = np.maximum(self.to_latlong(h), 0.0)[..., ::-1]
        return _imwrite(path, np.ascontiguousarray(img, dtype=np.float32))

    @classmethod
    def from_latlong(cls, img: np.ndarray, n: int = 128, frame: str = "marker",
                     rotation: np.ndarray | None = None, known: np.ndarray | None = None,
                     meta: dict[str, Any] | None = None) -> "EnvMap":
        """An EnvMap from a lat-long radiance image (H, W, 3), with :func:`octahedral.latlong_to_sphere`.

        Parameters
        ----------
        img : (H, W, 3) float array
            Linear RGB radiance, row 0 = zenith (+z), column 0 at azimuth -pi.
        n : int
            Side of the squares.
        frame : str
            Frame the directions are in after ``rotation``.
        rotation : (3, 3) array, optional
            Rotation taking the image's directions into ``frame`` (e.g. to align a downloaded map).
        known : (H, W) float array, optional
            Per-pixel coverage code in [0, 1] (1 measured, 0.5 filled, 0 unknown), e.g. an EXR alpha.
        """
        img = np.asarray(img, dtype=np.float32)
        if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 2 or img.shape[1] < 2:
            raise AppFusionError(f"lat-long environment image must have shape (H, W, 3), got {img.shape}")
        if not np.isfinite(img).all():
            raise AppFusionError("lat-long environment image contains NaN or infinite values")
        n = int(n)
        if n < 2:
            raise AppFusionError(f"environment map side must be at least 2, got {n}")
        sub = 2
        d = octa.sphere_directions(n * sub)
        if rotation is not None:
            R = np.asarray(rotation, dtype=np.float64)
            if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
                raise AppFusionError("lat-long rotation must be a 3x3 rotation matrix")
            d = d @ R  # direction in the image = R^T d_frame
        rad = octa.sample_latlong(img, d).reshape(2, n, sub, n, sub, 3).mean(axis=(2, 4))
        if known is None:
            cov = np.ones((2, n, n), bool)
            filled = np.zeros((2, n, n), bool)
        else:
            k = octa.sample_latlong(np.asarray(known, np.float32), d).reshape(2, n, sub, n, sub).mean(axis=(2, 4))
            cov = k > 0.75
            filled = (k > 0.25) & ~cov
            rad = np.where((cov | filled)[..., None], rad, 0.0)
        return cls(rad.astype(np.float32), cov.astype(np.float32), cov, filled, frame, dict(meta or {}))

    @classmethod
    def load(cls, path: str | os.PathLike, n: int = 128, frame: str = "marker") -> "EnvMap":
        """Load a map saved by :meth:`save` (.npz), or any lat-long .exr / .hdr (then of side ``n``)."""
        path = Path(path)
        if not path.exists():
            raise EnvMapFileError(path, "no such environment-map file")
        suf = path.suffix.lower()
        if suf == ".npz":
            return cls._load_npz(path)
        if suf in (".exr", ".hdr"):
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise EnvMapFileError(path, f"cannot be read as an {suf[1:].upper()} image (damaged or not an image)")
            img = img.astype(np.float32)
            if img.ndim != 3 or img.shape[2] not in (3, 4):
                raise EnvMapFileError(path, f"expected a colour lat-long image, got shape {img.shape}")
            known = img[..., 3] if img.shape[2] == 4 else None
            rgb = np.ascontiguousarray(img[..., 2::-1])
            if not np.isfinite(rgb).all():
                raise EnvMapFileError(path, "contains NaN or infinite radiance")
            try:
                return cls.from_latlong(rgb, n, frame, known=known, meta={"source": str(path)})
            except AppFusionError as e:
                raise EnvMapFileError(path, str(e)) from None
        raise EnvMapFileError(path, "unknown environment-map suffix (use .npz, .exr or .hdr)")

    @classmethod
    def _load_npz(cls, path: Path) -> "EnvMap":
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in ("radiance", "weight", "coverage", "filled") if k not in z.files]
                if missing:
                    raise EnvMapFileError(path, f"not an environment map: missing arrays {missing}")
                version = int(z["version"]) if "version" in z.files else NPZ_VERSION
                if version > NPZ_VERSION:
                    raise EnvMapFileError(path, f"written by a newer appfusion (version {version} > {NPZ_VERSION})")
                arrays = {k: z[k] for k in ("radiance", "weight", "coverage", "filled")}
                frame = str(z["frame"]) if "frame" in z.files else "marker"
                meta = json.loads(str(z["meta"])) if "meta" in z.files else {}
        except EnvMapFileError:
            raise
        except Exception as e:  # zip/npy damage surfaces as many exception types
            raise EnvMapFileError(path, f"damaged or not an .npz environment map ({type(e).__name__}: {e})") from None
        try:
            return cls(arrays["radiance"], arrays["weight"], arrays["coverage"], arrays["filled"], frame, meta)
        except AppFusionError as e:
            raise EnvMapFileError(path, str(e)) from None

    # -- previews ----------------------------------------------------------------------------------
    def preview(self, scale: int = 2, exposure: float | None = None, latlong: bool = True,
                label: str | None = None) -> np.ndarray:
        """Tone-mapped picture with the coverage mask, uint8 RGB (H, W, 3).

        Top: the two squares (upper, lower hemisphere) side by side; below: the lat-long view. Measured
        texels are tone-mapped (exposure, Reinhard, sRGB), filled texels are tinted blue and hatched,
        unknown texels are a grey checkerboard.

        Parameters
        ----------
        scale : int
            Pixels per texel of the squares.
        exposure : float, optional
            Multiplier before tone mapping; default maps the median measured luminance to 0.3.
        latlong : bool
            Add the lat-long view below the squares.
        label : str, optional
            Text drawn at the top left.
        """
        if exposure is None:
            exposure = self.auto_exposure()
        n = self.n
        code = self.coverage.astype(np.uint8) * 2 + self.filled.astype(np.uint8)
        sq = [_tone(self.radiance[f], exposure, code[f]) for f in (0, 1)]
        gap = np.full((n, max(1, n // 32), 3), 255, np.uint8)
        top = np.concatenate([sq[0], gap, sq[1]], axis=1)
        top = cv2.resize(top, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        parts = [top]
        if latlong:
            h = top.shape[1] // 2
            ll = _tone(self.to_latlong(h, top.shape[1]), exposure, self._mask_latlong(h, top.shape[1]))
            parts += [np.full((max(2, scale * 2), top.shape[1], 3), 255, np.uint8), ll]
        img = np.ascontiguousarray(np.concatenate(parts, axis=0))
        if label:
            _text(img, label, (6, 18))
        return img

    def auto_exposure(self) -> float:
        """Exposure that maps the median measured (else known) luminance to 0.3."""
        m = self.coverage if self.coverage.any() else self.known
        if not m.any():
            return 1.0
        lum = self.radiance[m] @ REC709_LUMA.astype(np.float32)
        med = float(np.median(lum))
        return 0.3 / med if med > 1e-12 else 1.0

    def save_preview(self, path: str | os.PathLike, **kwargs) -> Path:
        """Write :meth:`preview` as a PNG."""
        return _imwrite(Path(path), self.preview(**kwargs)[..., ::-1])


def filling_strip(maps: list[tuple[str, "EnvMap"]], exposure: float | None = None, scale: int = 1,
                  columns: int | None = None) -> np.ndarray:
    """Previews of maps in a grid (e.g. after 1, 4, 16, all views), one exposure, uint8 RGB.

    Each panel is labelled with its text and measured solid-angle coverage; ``columns`` panels per row
    (default all in one row).
    """
    if not maps:
        raise AppFusionError("filling_strip: no maps given")
    if exposure is None:
        exposure = maps[-1][1].auto_exposure()
    panels = [m.preview(scale=scale, exposure=exposure, label=f"{text}  {100 * m.coverage_fraction():.0f}% seen")
              for text, m in maps]
    h = max(p.shape[0] for p in panels)
    w = max(p.shape[1] for p in panels)
    panels = [np.pad(p, ((0, h - p.shape[0]), (0, w - p.shape[1]), (0, 0)), constant_values=255) for p in panels]
    cols = len(panels) if not columns else max(1, int(columns))
    blank = np.full_like(panels[0], 255)
    rows = []
    for r in range(0, len(panels), cols):
        row = panels[r:r + cols] + [blank] * (cols - len(panels[r:r + cols]) if r else 0)
        gap = np.full((h, 6, 3), 255, np.uint8)
        rows.append(np.concatenate([x for p in row for x in (p, gap)][:-1], axis=1))
    out = []
    for r in rows:
        out += [r, np.full((6, rows[0].shape[1], 3), 255, np.uint8)]
    return np.concatenate(out[:-1], axis=0)


# -- the accumulator ---------------------------------------------------------------------------------

class EnvMapAccumulator:
    """Running weighted mean of radiance samples per texel of a (2, N, N) octahedral map (§4.3, §5.1 Eq. 3).

    Parameters
    ----------
    n : int
        Side of each square (the paper: 128).
    rho_mirror : float or (3,) array
        Reflectance of the mirror ball (RGB or grey), divided out of every sample. 1 = perfect mirror.
    min_cos : float
        Samples with ``w_o . n`` below this are skipped (grazing views smear).
    min_weight : float
        A texel counts as measured when its summed weight exceeds this.
    exclude_viewer_deg : float
        Skip samples whose reflected direction lies within this angle of the direction from the ball to
        the camera: there the ball shows the camera and the user holding it (paper §4.3: "lighting
        occlusion by the user"). 0 (default) keeps them, as the paper does, relying on the multi-view
        average; 15-20 degrees removes the user's reflection when the views surround the ball.
    pixel_sigma : float, optional
        Weight the ``s x s`` sub-rays of a pixel by a Gaussian of this standard deviation (pixels) about
        the pixel's centre instead of equally (None, a box). The map is the scene blurred twice by a
        pixel's footprint (the camera integrates over the pixel, the splat spreads it again); a tapered
        splat (0.3-0.4 px) sharpens edges at almost no cost in noise, narrower ones (0.15 px) sharpen
        more but leave each texel fewer samples (noisier with few views).
    """

    def __init__(self, n: int = 128, rho_mirror: float | np.ndarray = 1.0, min_cos: float = 0.1,
                 min_weight: float = 0.0, exclude_viewer_deg: float = 0.0, pixel_sigma: float | None = None):
        n = int(n)
        if n < 2:
            raise AppFusionError(f"environment map side must be at least 2, got {n}")
        rho = np.broadcast_to(np.asarray(rho_mirror, dtype=np.float64), (3,)).copy()
        if not (np.isfinite(rho).all() and (rho > 0).all() and (rho <= 1.5).all()):
            raise AppFusionError(f"mirror reflectance rho_mirror must be in (0, 1.5], got {rho_mirror}")
        if not 0.0 <= min_cos < 1.0:
            raise AppFusionError(f"min_cos must be in [0, 1), got {min_cos}")
        self.n = n
        self.rho_mirror = rho
        self.min_cos = float(min_cos)
        if not 0.0 <= exclude_viewer_deg < 90.0:
            raise AppFusionError(f"exclude_viewer_deg must be in [0, 90), got {exclude_viewer_deg}")
        self.exclude_viewer_deg = float(exclude_viewer_deg)
        self.min_weight = float(min_weight)
        if pixel_sigma is not None and not (np.isfinite(pixel_sigma) and pixel_sigma > 0):
            raise AppFusionError(f"pixel_sigma must be a positive number of pixels or None, got {pixel_sigma}")
        self.pixel_sigma = None if pixel_sigma is None else float(pixel_sigma)
        self._w = np.zeros(2 * n * n)              # summed weights
        self._mean = np.zeros((2 * n * n, 3))      # weighted mean radiance
        self._blur = np.zeros(2 * n * n)           # summed weight x footprint variance (add_view)
        self.n_samples = 0
        self.n_views = 0

    def add_samples(self, directions: np.ndarray, radiance: np.ndarray, weights: np.ndarray) -> int:
        """Fold samples into the map (vectorised with ``np.bincount``).

        Parameters
        ----------
        directions : (M, 3) array
            Directions in the map's frame (need not be unit).
        radiance : (M, 3) array
            Linear radiance of each sample (already divided by the mirror's reflectance).
        weights : (M,) array
            Non-negative weights.

        Returns
        -------
        int
            Number of samples used (finite, positive weight).
        """
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        v = np.asarray(radiance, dtype=np.float64).reshape(-1, 3)
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if not (len(d) == len(v) == len(w)):
            raise AppFusionError(f"add_samples: {len(d)} directions, {len(v)} radiances, {len(w)} weights")
        ok = np.isfinite(d).all(axis=1) & np.isfinite(v).all(axis=1) & np.isfinite(w) & (w > 0)
        ok &= (d * d).sum(axis=1) > 0
        if not ok.all():
            d, v, w = d[ok], v[ok], w[ok]
        if not len(w):
            return 0
        self._update(*self._bin(d, v, w))
        self.n_samples += len(w)
        return len(w)

    def _bin(self, d: np.ndarray, v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-texel sums of weights (2N^2,) and of weighted radiance (2N^2, 3) of samples."""
        idx = octa.sphere_texel_index(d, self.n)
        size = 2 * self.n * self.n
        sw = np.bincount(idx, weights=w, minlength=size)
        svw = np.stack([np.bincount(idx, weights=w * v[:, c], minlength=size) for c in range(3)], axis=1)
        return sw, svw

    def _update(self, sw: np.ndarray, svw: np.ndarray) -> None:
        """Running weighted mean: L_new = (L W + sum v w) / (W + sum w), as an increment for accuracy."""
        hit = sw > 0
        wn = self._w[hit] + sw[hit]
        self._mean[hit] += (svw[hit] - sw[hit, None] * self._mean[hit]) / wn[:, None]
        self._w[hit] = wn

    def add_view(self, rgb_linear: np.ndarray, intrinsics: Intrinsics, pose_rgb: np.ndarray,
                 center: np.ndarray, radius: float, supersample: int | str = "auto",
                 mask: np.ndarray | None = None) -> int:
        """Accumulate one calibrated RGB image of the mirror ball (paper §4.3).

        For every pixel whose ray meets the sphere (analytic ray-sphere intersection), with ``n`` the
        sphere normal there and ``w_o`` the direction back to the camera, the pixel's radiance divided by
        ``rho_mirror`` is added to the texel of the reflected direction ``r = 2 (w_o . n) n - w_o`` with
        weight ``w_o . n`` (skipped below ``min_cos``, and within ``exclude_viewer_deg`` of the direction
        to the camera). Each pixel is split into ``s x s`` sub-rays that carry its value, each with weight
        ``w_o . n / s^2`` (or ``w_o . n`` times the normalised Gaussian ``pixel_sigma`` weight of its
        offset), so that the pixel's footprint on the map is covered.

        Parameters
        ----------
        rgb_linear : (H, W, 3) float array
            White-balanced linear RGB (§4.2); NaN pixels are skipped.
        intrinsics : Intrinsics
            Of the RGB camera; lens distortion (``dist``) is undone with OpenCV.
        pose_rgb : (4, 4) array
            Camera-to-world pose of the RGB camera (world = marker frame), metres.
        center : (3,) array
            Sphere centre in the world frame, metres.
        radius : float
            Sphere radius, metres.
        supersample : int or "auto"
            Sub-rays per pixel side. "auto" picks the smallest ``s`` whose sub-ray spacing in reflected
            direction at the ball's centre is at most half a texel (1..16).
        mask : (H, W) bool, optional
            Pixels allowed to contribute (e.g. not saturated, not the user's hand).

        Returns
        -------
        int
            Number of sub-ray samples accumulated.
        """
        rgb = np.asarray(rgb_linear)
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise AppFusionError(f"lighting pass: RGB image must have shape (H, W, 3), got {rgb.shape}")
        if rgb.shape[:2] != intrinsics.shape:
            raise AppFusionError(f"lighting pass: RGB image of shape {rgb.shape[:2]} does not match "
                                 f"intrinsics {intrinsics.shape}")
        if rgb.dtype == np.uint8:
            raise AppFusionError("lighting pass: RGB must be linear float (decode sRGB and white-balance first)")
        if mask is not None and np.asarray(mask).shape != intrinsics.shape:
            raise AppFusionError(f"lighting pass: mask of shape {np.asarray(mask).shape} does not match "
                                 f"intrinsics {intrinsics.shape}")
        T = np.asarray(pose_rgb, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise AppFusionError("lighting pass: RGB pose must be a finite 4x4 camera-to-world matrix")
        c = np.asarray(center, dtype=np.float64)
        radius = float(radius)
        if c.shape != (3,) or not (np.isfinite(c).all() and np.isfinite(radius) and radius > 0):
            raise AppFusionError(f"lighting pass: sphere centre/radius must be finite, radius > 0 "
                                 f"(got {c.tolist()}, {radius})")
        Rw = T[:3, :3]
        cc = Rw.T @ (c - T[:3, 3])                      # sphere centre in the camera frame
        dist = float(np.linalg.norm(cc))
        if dist <= radius * 1.0001:
            raise AppFusionError(f"lighting pass: the camera is inside the mirror ball "
                                 f"({dist * 1000:.1f} mm from its centre, radius {radius * 1000:.1f} mm)")
        self.n_views += 1
        box = _sphere_bbox(cc, radius, intrinsics)
        if box is None:
            return 0
        x0, x1, y0, y1 = box
        s = self._supersample(supersample, dist, radius, intrinsics)

        # Pre-pass, one ray per pixel: keep the pixels whose footprint may meet the sphere (the centre
        # ray meets the sphere grown by a pixel's footprint at the ball's distance).
        ys, xs = np.mgrid[y0:y1, x0:x1]
        pix_y, pix_x = ys.reshape(-1), xs.reshape(-1)
        d = _pixel_rays(intrinsics, pix_x.astype(np.float64), pix_y.astype(np.float64))
        grown = radius + 1.5 * dist / min(intrinsics.fx, intrinsics.fy)
        b = d @ cc
        keep = b * b - (dist * dist - grown * grown) > 0
        if mask is not None:
            keep &= np.asarray(mask, bool)[pix_y, pix_x]
        pix_y, pix_x = pix_y[keep], pix_x[keep]
        vals = rgb[pix_y, pix_x].astype(np.float64)
        keep = np.isfinite(vals).all(axis=1)
        pix_y, pix_x, vals = pix_y[keep], pix_x[keep], vals[keep]
        if not len(vals):
            return 0

        # s x s sub-rays per kept pixel, processed in chunks of pixels so the arrays stay in cache.
        off = (np.arange(s) + 0.5) / s - 0.5
        oy, ox = np.meshgrid(off, off, indexing="ij")
        ox, oy = ox.reshape(1, -1), oy.reshape(1, -1)
        if self.pixel_sigma is None:
            kern = np.full(s * s, 1.0 / (s * s))
        else:
            kern = np.exp(-(ox * ox + oy * oy).reshape(-1) / (2.0 * self.pixel_sigma ** 2))
            kern /= kern.sum()
        to_cam = -cc / dist                              # camera-frame direction from the ball to the camera
        cos_viewer = np.cos(np.radians(self.exclude_viewer_deg))
        idx: list[np.ndarray] = []
        wts: list[np.ndarray] = []
        wv: list[np.ndarray] = []
        wb: list[np.ndarray] = []
        # footprint variance per image axis, px^2: the camera integrates over its pixel (a box, 1/12)
        # and the splat spreads the value again (the kernel's own variance); map_blur_var
        f_px = math.sqrt(intrinsics.fx * intrinsics.fy)
        footprint_var = 1.0 / 12.0 + float(np.sum(kern * (ox * ox).reshape(-1)))
        chunk = max(1, 16384 // (s * s))
        for k in range(0, len(vals), chunk):
            px, py, pv = pix_x[k:k + chunk], pix_y[k:k + chunk], vals[k:k + chunk]
            su = (px[:, None] + ox).reshape(-1)
            sv = (py[:, None] + oy).reshape(-1)
            src = np.repeat(np.arange(len(pv)), s * s)
            ksub = np.tile(kern, len(pv))
            d = _pixel_rays(intrinsics, su, sv)
            # Analytic ray-sphere intersection |t d - cc| = R, nearest root t = b - sqrt(b^2 - |cc|^2 + R^2).
            b = d @ cc
            disc = b * b - (dist * dist - radius * radius)
            hit = disc > 0
            d, b, disc, src, ksub = d[hit], b[hit], disc[hit], src[hit], ksub[hit]
            t = b - np.sqrt(disc)
            front = t > 0
            d, t, src, ksub = d[front], t[front], src[front], ksub[front]
            nrm = (t[:, None] * d - cc) / radius         # outward unit normal
            cos_o = -(d * nrm).sum(axis=1)               # w_o . n with w_o = -d
            ok = cos_o >= max(self.min_cos, 1e-6)
            if not ok.any():
                continue
            d, t, nrm, cos_o, src, ksub = d[ok], t[ok], nrm[ok], cos_o[ok], src[ok], ksub[ok]
            refl = d + 2.0 * cos_o[:, None] * nrm         # r = d - 2 (d . n) n
            if self.exclude_viewer_deg > 0:
                ok = refl @ to_cam < cos_viewer
                refl, t, cos_o, src, ksub = refl[ok], t[ok], cos_o[ok], src[ok], ksub[ok]
            refl_w = refl @ Rw.T                          # into the world (marker) frame
            w = cos_o * ksub
            idx.append(octa.sphere_texel_index(refl_w, self.n))
            wts.append(w)
            wv.append(pv[src] * (w[:, None] / self.rho_mirror))
            wb.append(w * footprint_var * _reflection_gain2(t / f_px, cos_o, radius))
        if not idx:
            return 0
        idx, w, wv = np.concatenate(idx), np.concatenate(wts), np.concatenate(wv)
        size = 2 * self.n * self.n
        sw = np.bincount(idx, weights=w, minlength=size)
        svw = np.stack([np.bincount(idx, weights=wv[:, c], minlength=size) for c in range(3)], axis=1)
        self._blur += np.bincount(idx, weights=np.concatenate(wb), minlength=size)
        self._update(sw, svw)
        self.n_samples += len(w)
        return len(w)

    def _supersample(self, supersample: int | str, dist: float, radius: float, intr: Intrinsics) -> int:
        if supersample == "auto":
            # reflected-direction step of one pixel at the ball's centre: 2 * (pixel on the ball) / R;
            # two sub-rays per texel there (fewer alias: each view then hits texels unevenly, measured
            # 4.9% -> 4.2% median error at 320x240 with 40 views), more towards the rim where the
            # mapping stretches radially by 1 / (w_o . n)
            step = 2.0 * (dist - radius) / (min(intr.fx, intr.fy) * radius)
            texel = np.sqrt(4.0 * np.pi / (2 * self.n * self.n))
            return int(np.clip(np.ceil(2.0 * step / texel), 1, 16))
        s = int(supersample)
        if s < 1 or s > 16:
            raise AppFusionError(f"lighting pass: supersample must be 1..16 or 'auto', got {supersample}")
        return s

    @property
    def weight(self) -> np.ndarray:
        """Summed weights, (2, N, N) float64 (a view)."""
        return self._w.reshape(2, self.n, self.n)

    def envmap(self, meta: dict[str, Any] | None = None) -> EnvMap:
        """The current map (a copy): measured texels where the summed weight exceeds ``min_weight``."""
        n = self.n
        w = self._w.reshape(2, n, n)
        cov = w > self.min_weight
        rad = np.where(cov[..., None], self._mean.reshape(2, n, n, 3), 0.0).astype(np.float32)
        m = {"rho_mirror": self.rho_mirror.tolist(), "min_cos": self.min_cos,
             "exclude_viewer_deg": self.exclude_viewer_deg, "pixel_sigma": self.pixel_sigma,
             "blur_var_rad2": map_blur_var(rad, cov, self._blur.reshape(2, n, n), w),
             "n_samples": int(self.n_samples),
             "n_views": int(self.n_views), "units": "linear RGB relative to the reference white (paper 4.2)"}
        m.update(meta or {})
        return EnvMap(rad, w.astype(np.float32), cov, np.zeros_like(cov), "marker", m)


# -- the map's own blur ----------------------------------------------------------------------------------

def _reflection_gain2(d_px: np.ndarray, cos_o: np.ndarray, radius: float) -> np.ndarray:
    """Mean squared change of the reflected direction per pixel of image displacement, rad^2 / px^2.

    ``d_px`` is the size of a pixel at the hit (metres, ``t / f``). Across the plane of incidence a
    step ``d_px`` turns the mirror's normal by ``d_px / R`` and the reflection by ``2 cos_o`` times
    that; along it the footprint is stretched by ``1 / cos_o`` and the reflection turns by twice the
    normal. The mean of the two axes' squares.
    """
    g = 2.0 * d_px / radius
    return 0.5 * g * g * (cos_o * cos_o + 1.0 / (cos_o * cos_o))


def map_blur_var(radiance: np.ndarray, coverage: np.ndarray, blur_sum: np.ndarray, weight: np.ndarray) -> float:
    """Variance per axis (rad^2) of the blur a captured map carries, where its detail is (§4.3, beyond the paper).

    Every texel of a mirror-ball map is the scene seen through a kernel: the camera integrates over
    its pixel, the splat of :meth:`EnvMapAccumulator.add_view` spreads the pixel again, and the
    texel averages what lands in it. Their variances add: per texel the weighted mean of the first
    two (accumulated per sample from the ball's geometry, :func:`_reflection_gain2`) plus
    ``Omega / 12`` for the texel. A sharp lobe read against the map then sees the scene through a
    lobe widened by that variance (:func:`effective_alpha`). One number for the map: the texels'
    variances weighted by the squared gradient of the luminance times the solid angle, i.e. where
    blurring changes the map (a flat sky's inside does not count, a lamp's rim does).

    Returns 0 for a map without measured texels.
    """
    n = radiance.shape[1]
    Om = octa.sphere_solid_angles(n)
    cov = np.asarray(coverage, bool) & (np.asarray(weight) > 0)
    if not cov.any():
        return 0.0
    var = np.where(cov, np.asarray(blur_sum) / np.maximum(weight, 1e-300), 0.0) + Om / 12.0
    lum = radiance.astype(np.float64).mean(axis=-1)
    g2 = np.zeros_like(lum)
    for f in range(2):
        gy, gx = np.gradient(lum[f])
        g2[f] = gx * gx + gy * gy
    wt = np.where(cov, g2 * Om, 0.0)
    if not wt.sum() > 0:
        return float(np.mean(var[cov]))
    return float((wt * var).sum() / wt.sum())


def effective_alpha(alpha, blur_var: float):
    """Ward roughness to read a blurred map with so that S matches the sharp scene's (§5.3, beyond the paper).

    Near its peak the Ward lobe is a Gaussian of variance ``2 alpha^2`` per axis in the reflected
    direction (``exp(-tan^2 theta_h / alpha^2)`` with ``theta_h`` half the angle to the mirror
    direction); a map blurred by a kernel of variance ``v`` (:func:`map_blur_var`) widens it to
    ``2 alpha^2 + v``. Reading the map with ``alpha' = sqrt(alpha^2 - v / 2)`` undoes that to first
    order, whatever the lights' shapes; floored at ``alpha / 2``. Demo (alpha 0.06, v 6.6e-4 rad^2
    measured against the truth map): the pooled rho_s slope 1.9 % high without.
    """
    a = np.asarray(alpha, dtype=np.float64)
    out = np.sqrt(np.maximum(a * a - 0.5 * max(float(blur_var), 0.0), 0.25 * a * a))
    return float(out) if out.ndim == 0 else out


# -- helpers -------------------------------------------------------------------------------------------

def _pixel_rays(intr: Intrinsics, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit camera-frame rays (M, 3) of pixel coordinates u, v (M,), lens distortion undone with OpenCV."""
    if intr.dist and any(intr.dist):
        pts = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-10)
        xy = cv2.undistortPointsIter(pts, intr.K, np.asarray(intr.dist, np.float64), None, None, crit).reshape(-1, 2)
        x, y = xy[:, 0], xy[:, 1]
    else:
        x = (u - intr.cx) / intr.fx
        y = (v - intr.cy) / intr.fy
    inv = 1.0 / np.sqrt(x * x + y * y + 1.0)
    d = np.empty((len(x), 3))
    d[:, 0] = x * inv
    d[:, 1] = y * inv
    d[:, 2] = inv
    return d


def _sphere_bbox(cc: np.ndarray, radius: float, intr: Intrinsics) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, x1, y0, y1), end-exclusive, holding the sphere's image; None if off-screen."""
    corners = cc + radius * 1.02 * np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    if (corners[:, 2] <= 1e-6).any():
        if cc[2] + radius <= 0:
            return None                                   # entirely behind the camera
        return 0, intr.width, 0, intr.height               # straddles the image plane: whole image
    u = intr.fx * corners[:, 0] / corners[:, 2] + intr.cx
    v = intr.fy * corners[:, 1] / corners[:, 2] + intr.cy
    pad = 2 + (4 if intr.dist and any(intr.dist) else 0)
    x0 = int(max(np.floor(u.min()) - pad, 0))
    x1 = int(min(np.ceil(u.max()) + pad + 1, intr.width))
    y0 = int(max(np.floor(v.min()) - pad, 0))
    y1 = int(min(np.ceil(v.max()) + pad + 1, intr.height))
    if x0 >= x1 or y0 >= y1:
        return None
    return x0, x1, y0, y1


def _neighbour_graph(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Edges (i, j) between adjacent texels of a (2, n, n) map: 4-neighbours in each square, plus each
    border texel to the same texel of the other square (both squares' borders are the equator)."""
    idx = np.arange(2 * n * n).reshape(2, n, n)
    a = [idx[:, :, :-1].ravel(), idx[:, :-1, :].ravel()]
    b = [idx[:, :, 1:].ravel(), idx[:, 1:, :].ravel()]
    border = np.zeros((n, n), bool)
    border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
    a.append(idx[0][border])
    b.append(idx[1][border])
    return np.concatenate(a), np.concatenate(b)


def _harmonic_fill(rad: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Solve the graph Laplace equation for the unknown texels with the measured ones fixed; (U, 3)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    n = rad.shape[1]
    size = 2 * n * n
    ia, ib = _neighbour_graph(n)
    A = sp.coo_matrix((np.ones(2 * len(ia)), (np.r_[ia, ib], np.r_[ib, ia])), shape=(size, size)).tocsr()
    deg = np.asarray(A.sum(axis=1)).ravel()
    L = sp.diags(deg) - A
    known = cov.reshape(-1)
    U = np.flatnonzero(~known)
    K = np.flatnonzero(known)
    Luu = L[U][:, U].tocsc()
    rhs = -(L[U][:, K] @ rad.reshape(-1, 3)[K].astype(np.float64))
    return splu(Luu).solve(rhs).astype(np.float32)


def _tone(rad: np.ndarray, exposure: float, code: np.ndarray) -> np.ndarray:
    """Tone-map radiance (..., 3) with exposure + Reinhard + sRGB; overlay the coverage code
    (2 measured, 1 filled: blue tint + hatching, 0 unknown: grey checkerboard). uint8 (H, W, 3)."""
    x = np.maximum(np.asarray(rad, np.float32) * float(exposure), 0.0)
    img = linear_to_srgb(x / (1.0 + x))
    h, w = code.shape
    yy, xx = np.mgrid[0:h, 0:w]
    filled = code == 1
    if filled.any():
        tint = 0.55 * img + 0.45 * np.array([0.25, 0.45, 1.0], np.float32)
        hatch = ((xx + yy) % 6) < 2
        img = np.where(filled[..., None], np.where(hatch[..., None], tint * 0.7, tint), img)
    unknown = code == 0
    if unknown.any():
        checker = np.where(((xx // 4 + yy // 4) % 2 == 0)[..., None], 0.35, 0.5).astype(np.float32)
        img = np.where(unknown[..., None], checker, img)
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def _text(img: np.ndarray, text: str, org: tuple[int, int]) -> None:
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)


def _imwrite(path: Path, img: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    try:
        ok = cv2.imwrite(str(tmp), img)
    except cv2.error as e:
        raise EnvMapFileError(path, f"cannot write image: {e}") from None
    if not ok:
        raise EnvMapFileError(path, "cannot write image (unsupported format or unwritable folder)")
    os.replace(tmp, path)
    return path


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
