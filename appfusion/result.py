"""The result of a scan: geometry plus the SVBRDF of paper Eq. 1, as plain arrays.

Per sampled point (§4.1): position, normal, diffuse albedo rho_d (RGB) and cluster label (§5.2);
per cluster: specular intensity rho_s (RGB), the lobe (``model``: diffuse, Ward or GGX) and its
roughness alpha (with its uncertainty); the
object mesh; the environment map in the marker frame (§4.3). Saved as one ``result.npz`` that
``appfusion render`` and the GUI read back.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import SessionFormatError


def json_float(v: Any) -> float | None:
    """``float(v)``, or None for NaN, infinity or a value that is no number (JSON has none of these):
    how a result's figures that were not estimated go into ``object.glb``'s extras, ``appfusion info
    --json`` and the bench report."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if np.isfinite(f) else None


@dataclass
class ScanResult:
    """Geometry and appearance of a scanned object (world = marker frame, metres).

    Attributes
    ----------
    positions, normals : (P, 3) float32
        Sampled surface points and their (bilateral-filtered) unit normals.
    rho_d : (P, 3) float32
        Diffuse albedo per point (linear RGB).
    labels : (P,) int32
        Specular cluster of each point, 0..C-1.
    rho_s : (C, 3) float32
        Specular intensity per cluster (linear RGB).
    alpha, alpha_sigma : (C,) float32
        Roughness of each cluster's lobe (``model``) and its 1-sigma uncertainty.
    mesh_vertices : (V, 3) float32, mesh_faces : (F, 3) int32
        Triangle mesh of the object (may be empty until exported).
    envmap : (2, N, N, 3) float32 or None
        Environment radiance in the octahedral layout of :mod:`appfusion.octahedral`.
    model : (C,) list of str
        Reflectance model chosen per cluster: "diffuse", "ward" or "ggx" (the lobe alpha belongs to;
        :data:`appfusion.brdf.LOBES`).
    info : dict
        Free-form provenance (session, frames used per pass, timings).
    rho_s_sigma : (C, 3) float32
        Standard error of each cluster's rho_s as measured (the Ward rung's slope, also for a cluster
        exported as diffuse); NaN where unknown (not measured, or a result saved before session 25).
    """

    positions: np.ndarray
    normals: np.ndarray
    rho_d: np.ndarray
    labels: np.ndarray
    rho_s: np.ndarray
    alpha: np.ndarray
    alpha_sigma: np.ndarray = None
    mesh_vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    mesh_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))
    envmap: np.ndarray | None = None
    model: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    rho_s_sigma: np.ndarray = None

    def __post_init__(self):
        self.positions = np.asarray(self.positions, np.float32).reshape(-1, 3)
        self.normals = np.asarray(self.normals, np.float32).reshape(-1, 3)
        self.rho_d = np.asarray(self.rho_d, np.float32).reshape(-1, 3)
        self.labels = np.asarray(self.labels, np.int32).reshape(-1)
        self.rho_s = np.asarray(self.rho_s, np.float32).reshape(-1, 3)
        self.alpha = np.asarray(self.alpha, np.float32).reshape(-1)
        if self.alpha_sigma is None:
            self.alpha_sigma = np.zeros_like(self.alpha)
        self.alpha_sigma = np.asarray(self.alpha_sigma, np.float32).reshape(-1)
        if self.rho_s_sigma is None:
            self.rho_s_sigma = np.full(self.rho_s.shape, np.nan, np.float32)
        self.rho_s_sigma = np.asarray(self.rho_s_sigma, np.float32).reshape(-1, 3)
        if not self.model:
            self.model = ["ward"] * len(self.alpha)
        P, C = len(self.positions), len(self.alpha)
        for name, a in (("normals", self.normals), ("rho_d", self.rho_d), ("labels", self.labels)):
            if len(a) != P:
                raise ValueError(f"ScanResult: {name} has {len(a)} rows, positions has {P}")
        if len(self.rho_s) != C or len(self.alpha_sigma) != C or len(self.rho_s_sigma) != C:
            raise ValueError(f"ScanResult: rho_s/alpha_sigma/rho_s_sigma must have one row per cluster ({C})")
        if len(self.model) != C or any(m not in ("diffuse", "ward", "ggx") for m in self.model):
            raise ValueError(f"ScanResult: model must name one of diffuse, ward, ggx per cluster ({C}), "
                             f"got {list(self.model)}")
        if P and (self.labels.min() < 0 or self.labels.max() >= C):
            raise ValueError(f"ScanResult: labels must lie in 0..{C - 1}")

    @property
    def n_clusters(self) -> int:
        return len(self.alpha)

    def point_rho_s(self) -> np.ndarray:
        """rho_s of every point, (P, 3)."""
        return self.rho_s[self.labels]

    def point_alpha(self) -> np.ndarray:
        """alpha of every point, (P,)."""
        return self.alpha[self.labels]

    def save(self, path: str | os.PathLike) -> Path:
        """Write ``result.npz`` atomically."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        arrays = {k: v for k, v in asdict(self).items() if isinstance(v, np.ndarray)}
        arrays["model"] = np.array(self.model)
        arrays["info_json"] = np.array(json.dumps(self.info, default=str))
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ScanResult":
        path = Path(path)
        if path.is_dir():
            path = path / "result.npz"
        if not path.exists():
            raise SessionFormatError(path, "no scan result here (run `appfusion scan` first)")
        try:
            z = np.load(path, allow_pickle=False)
            kw = {k: z[k] for k in z.files if k not in ("model", "info_json", "envmap")}
            env = z["envmap"] if "envmap" in z.files and z["envmap"].ndim == 4 else None
            return cls(**kw, envmap=env, model=[str(m) for m in z["model"]],
                       info=json.loads(str(z["info_json"])))
        except Exception as e:  # noqa: BLE001 - zip/npy damage surfaces as many types (BadZipFile, EOFError, ...)
            raise SessionFormatError(path, f"not a readable scan result ({type(e).__name__}: {e}); a copy cut "
                                           f"short or another file: rerun `appfusion scan` into its folder "
                                           f"(its checkpoints are reused)") from None
