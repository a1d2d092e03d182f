"""TUM RGB-D benchmark folders (Sturm et al., IROS 2012) as a seekable Source.

A TUM sequence is a folder with ``rgb.txt`` and ``depth.txt`` (``timestamp path`` lines after ``#``
comments), the images they name (colour PNG, 16-bit depth PNG at 5000 units per metre) and
optionally ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, camera-to-world).

- Colour and depth are associated as TUM's ``associate.py`` does: all pairs closer than
  ``max_difference`` (20 ms) are taken greedily, closest first; unmatched images are dropped.
  A frame's timestamp is its depth image's.
- Poses come from ``groundtruth.txt``: interpolated (linear translation, slerp rotation) between
  the two samples around the frame time when they are at most 0.1 s apart, else the nearest sample
  if within 1 ms, else None.
- Intrinsics: ``camera.json`` in the folder if present (Open3D ``PinholeCameraIntrinsic`` JSON or
  ``width/height/fx/fy/cx/cy``), else the PrimeSense default fx = fy = 525, cx = 319.5, cy = 239.5
  at 640x480 that TUM's depth registration uses (the calibrated freiburg1 values, 517.3/516.5/
  318.6/255.3, differ: put them in a camera.json to use them). TUM depth is registered to colour,
  so ``depth_to_rgb`` is the identity.

Our own sessions (:mod:`replay.session`) open with this reader too (their rgb/depth part).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from appfusion.errors import SessionFormatError
from appfusion.frame import Intrinsics

from ._paired import Item, PairedReader, default_intrinsics, read_camera_json
from .session import parse_groundtruth, parse_index

#: TUM depth PNG units per metre
TUM_DEPTH_UNITS_PER_M = 5000.0
#: largest colour/depth time difference associated (seconds), as in TUM's associate.py
MAX_DIFFERENCE_S = 0.02


def associate(first: np.ndarray, second: np.ndarray, max_difference: float = MAX_DIFFERENCE_S) -> np.ndarray:
    """Match two lists of timestamps like TUM's ``associate.py``.

    All pairs ``(a, b)`` with ``|a - b| < max_difference`` are considered, closest first; each
    timestamp is used at most once.

    Parameters
    ----------
    first, second : (N,), (M,) float arrays
        Timestamps in seconds, sorted ascending.
    max_difference : float
        Seconds.

    Returns
    -------
    (K, 2) int ndarray
        Index pairs ``(i, j)`` into ``first`` and ``second``, sorted by ``first[i]``.
    """
    a = np.asarray(first, dtype=np.float64)
    b = np.asarray(second, dtype=np.float64)
    if a.size == 0 or b.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    lo = np.searchsorted(b, a - max_difference, side="left")
    hi = np.searchsorted(b, a + max_difference, side="right")
    cnt = hi - lo
    ii = np.repeat(np.arange(a.size), cnt)
    jj = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(lo, cnt)
    diff = np.abs(a[ii] - b[jj])
    keep = diff < max_difference
    ii, jj, diff = ii[keep], jj[keep], diff[keep]
    order = np.lexsort((jj, ii, diff))
    used_a = np.zeros(a.size, bool)
    used_b = np.zeros(b.size, bool)
    out = []
    for k in order:  # greedy over candidate pairs (a few per frame), not over pixels
        i, j = ii[k], jj[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            out.append((i, j))
    out.sort()
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def interpolate_poses(times: np.ndarray, gt_t: np.ndarray, gt_p: np.ndarray, max_gap: float = 0.1,
                      exact: float = 1e-3) -> list[np.ndarray | None]:
    """Poses at ``times`` from a sampled trajectory.

    Linear interpolation of the translation and spherical linear interpolation of the rotation
    between the samples around each time, when they are at most ``max_gap`` seconds apart; else
    the nearest sample within ``exact`` seconds; else None.

    Parameters
    ----------
    times : (N,) float array
        Seconds.
    gt_t : (M,) float array
        Sample times, strictly increasing.
    gt_p : (M, 4, 4) float array
        Camera-to-world poses.

    Returns
    -------
    list of (4, 4) ndarray or None
    """
    from scipy.spatial.transform import Rotation

    times = np.asarray(times, dtype=np.float64)
    out: list[np.ndarray | None] = [None] * len(times)
    m = len(gt_t)
    if m == 0 or len(times) == 0:
        return out
    j1 = np.searchsorted(gt_t, times, side="left")
    j0 = j1 - 1
    near = np.where((j0 >= 0) & ((j1 >= m) | (np.abs(gt_t[np.clip(j0, 0, m - 1)] - times)
                                              <= np.abs(gt_t[np.clip(j1, 0, m - 1)] - times))),
                    np.clip(j0, 0, m - 1), np.clip(j1, 0, m - 1))
    for k in np.nonzero(np.abs(gt_t[near] - times) <= exact)[0]:
        out[k] = gt_p[near[k]].copy()
    inner = (j0 >= 0) & (j1 < m)
    inner[inner] = (gt_t[j1[inner]] - gt_t[j0[inner]]) <= max_gap + 1e-9
    idx = np.nonzero(inner)[0]
    if idx.size:
        a0, a1 = j0[idx], j1[idx]
        alpha = (times[idx] - gt_t[a0]) / (gt_t[a1] - gt_t[a0])
        r0 = Rotation.from_matrix(gt_p[a0, :3, :3])
        r1 = Rotation.from_matrix(gt_p[a1, :3, :3])
        rot = r0 * Rotation.from_rotvec((r0.inv() * r1).as_rotvec() * alpha[:, None])
        T = np.tile(np.eye(4), (idx.size, 1, 1))
        T[:, :3, :3] = rot.as_matrix()
        T[:, :3, 3] = (1 - alpha)[:, None] * gt_p[a0, :3, 3] + alpha[:, None] * gt_p[a1, :3, 3]
        for k, Tk in zip(idx, T):
            out[k] = Tk
    return out


def _camera_intrinsics(folder: Path, depth_sample: Path | None, rgb_sample: Path | None):
    cam = folder / "camera.json"
    if cam.is_file():
        K = read_camera_json(cam)
        return {"depth": K, "rgb": K}, str(cam)
    return ({"depth": default_intrinsics(depth_sample), "rgb": default_intrinsics(rgb_sample)},
            "PrimeSense default (525, 525, 319.5, 239.5 at 640x480)")


class TUMReader(PairedReader):
    """A TUM RGB-D folder (``rgb.txt`` + ``depth.txt``) as a seekable Source.

    Parameters
    ----------
    path : path-like
        The sequence folder.
    skip_bad : bool
        Skip (and list in :attr:`bad_frames`) bad index lines and missing or undecodable images
        instead of raising :class:`SessionFormatError`.
    max_difference : float
        Colour/depth association window (seconds), default 0.02.
    depth_units_per_m : float
        Depth PNG scale, default 5000.
    intrinsics : Intrinsics, optional
        Override the intrinsics of both streams.
    """

    format_name = "tum"

    def __init__(self, path: str | os.PathLike, skip_bad: bool = False, max_difference: float = MAX_DIFFERENCE_S,
                 depth_units_per_m: float = TUM_DEPTH_UNITS_PER_M, intrinsics: Intrinsics | None = None):
        super().__init__(path, skip_bad)
        self.name = f"tum:{self.path}"
        self.units_per_m = float(depth_units_per_m)
        if not self.path.is_dir():
            raise SessionFormatError(self.path, "not a directory (a TUM sequence is a folder with rgb.txt and depth.txt)")
        idx = {}
        for s, fname in (("rgb", "rgb.txt"), ("depth", "depth.txt")):
            p = self.path / fname
            try:
                data = p.read_bytes()
            except FileNotFoundError:
                raise SessionFormatError(p, "missing: a TUM sequence needs rgb.txt and depth.txt") from None
            entries, bad, _dropped = parse_index(data, p, skip_bad=self.skip_bad)
            self.bad_frames.extend(bad)
            idx[s] = (p, entries)
        (rp, rgb), (dp, dep) = idx["rgb"], idx["depth"]
        pairs = associate(np.array([e[2] for e in rgb]), np.array([e[2] for e in dep]), max_difference)
        for i, j in pairs:
            r, d = rgb[i], dep[j]
            self.items.append(Item(timestamp=d[2], depth=self.path / d[3], rgb=self.path / r[3], depth_index=dp,
                                   depth_line=d[0], rgb_index=rp, rgb_line=r[0], rgb_timestamp=r[2]))
        first = self.items[0] if self.items else None
        if intrinsics is not None:
            self._intrinsics, src = {"depth": intrinsics, "rgb": intrinsics}, "given"
        else:
            self._intrinsics, src = _camera_intrinsics(self.path, first and first.depth, first and first.rgb)
        gp = self.path / "groundtruth.txt"
        times = np.array([it.timestamp for it in self.items])
        if gp.is_file():
            gt_t, gt_p, bad, _ = parse_groundtruth(gp.read_bytes(), gp, skip_bad=self.skip_bad)
            self.bad_frames.extend(bad)
            self.poses = interpolate_poses(times, gt_t, gt_p)
        else:
            self.poses = [None] * len(self.items)
        self._meta = {"device": f"TUM RGB-D sequence {self.path.name}", "intrinsics_source": src,
                      "associated": len(self.items), "rgb_images": len(rgb), "depth_images": len(dep),
                      "max_difference_s": max_difference, "groundtruth": gp.is_file(),
                      "emitter_position_m": [0.075, 0.0, 0.0]}
        self._finish()

    @classmethod
    def from_files(cls, rgb: Sequence[str | os.PathLike], depth: Sequence[str | os.PathLike],
                   timestamps: Sequence[float] | None = None, intrinsics: Intrinsics | None = None,
                   depth_units_per_m: float = TUM_DEPTH_UNITS_PER_M, skip_bad: bool = False) -> "TUMReader":
        """TUM-encoded colour/depth image pairs given as file lists (no index files).

        Parameters
        ----------
        rgb, depth : sequences of path-like, equal length
            Colour and 16-bit depth images of each frame.
        timestamps : sequence of float, optional
            Seconds; default 30 Hz from 0.
        intrinsics : Intrinsics, optional
            Default: the PrimeSense default, rescaled to the image size.
        """
        if len(rgb) != len(depth):
            raise SessionFormatError(os.fspath(depth[0]) if depth else "<no files>",
                                     f"{len(rgb)} colour images but {len(depth)} depth images")
        if not depth:
            raise SessionFormatError("<no files>", "no images given")
        self = cls.__new__(cls)
        PairedReader.__init__(self, Path(depth[0]).parent, skip_bad)
        self.name = f"tum-files:{Path(depth[0]).name}"
        self.units_per_m = float(depth_units_per_m)
        ts = np.arange(len(depth)) / 30.0 if timestamps is None else np.asarray(timestamps, dtype=np.float64)
        self.items = [Item(timestamp=float(t), depth=Path(d), rgb=Path(r)) for t, r, d in zip(ts, rgb, depth)]
        self.poses = [None] * len(self.items)
        if intrinsics is not None:
            self._intrinsics, src = {"depth": intrinsics, "rgb": intrinsics}, "given"
        else:
            self._intrinsics = {"depth": default_intrinsics(Path(depth[0])), "rgb": default_intrinsics(Path(rgb[0]))}
            src = "PrimeSense default (525, 525, 319.5, 239.5 at 640x480)"
        self._meta = {"device": "TUM-encoded image pairs", "intrinsics_source": src,
                      "emitter_position_m": [0.075, 0.0, 0.0]}
        self._finish()
        return self
