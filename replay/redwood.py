"""Open3D / Redwood RGB-D folders as a seekable Source.

Layout (Open3D's former ``TestData/RGBD``, the Redwood datasets of Choi et al.)::

    color/ (or rgb/, image/)   colour images, JPG or PNG, sorted by name
    depth/                     16-bit depth PNGs in millimetres (0 = invalid)
    rgbd.match                 optional: "depth/00000.png color/00000.jpg" per frame
    trajectory.log             optional poses (Open3D log format), else odometry.log
    camera_*.json              optional intrinsics (Open3D PinholeCameraIntrinsic JSON)

Open3D's log format is, per frame, a line of three integers (the first is the frame number) and
the 4 x 4 camera-to-world pose on the next four lines. Frames are timed at 30 Hz (frame i at
i / 30 s). Without a camera JSON the PrimeSense default (525, 525, 319.5, 239.5 at 640x480) is
used. Depth is registered to colour: ``depth_to_rgb`` is the identity.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from appfusion.errors import SessionFormatError

from ._paired import Item, PairedReader, default_intrinsics, read_camera_json
from .session import _split_lines

#: Redwood depth PNG units per metre (millimetres)
REDWOOD_DEPTH_UNITS_PER_M = 1000.0
COLOR_DIRS = ("color", "rgb", "image")
IMAGE_EXTS = (".jpg", ".jpeg", ".png")
LOG_FILES = ("trajectory.log", "odometry.log")


def parse_log(data: bytes | str, path: str | os.PathLike = "trajectory.log") -> dict[int, np.ndarray]:
    """Parse an Open3D trajectory log: ``i j n`` then a 4x4 matrix, per entry.

    Returns
    -------
    dict of int -> (4, 4) float64 ndarray
        Pose (camera to world, metres) by frame number (the first integer of each entry).

    Raises
    ------
    SessionFormatError
        Naming the file and line of a malformed entry.
    """
    lines, partial = _split_lines(data)
    if partial:
        lines.append(partial)
    rows = [(no, t.split()) for no, t in lines if t.strip() and not t.lstrip().startswith("#")]
    out: dict[int, np.ndarray] = {}
    k = 0
    while k < len(rows):
        no, head = rows[k]
        if len(head) != 3:
            raise SessionFormatError(path, f"expected an entry header of three integers, got {len(head)} fields", no)
        try:
            frame = int(head[0])
            int(head[1]), int(head[2])
        except ValueError:
            raise SessionFormatError(path, "entry header fields must be integers", no) from None
        if k + 5 > len(rows):
            raise SessionFormatError(path, "entry is cut short: a 4x4 matrix needs four lines", no)
        m = np.empty((4, 4))
        for r in range(4):
            rno, vals = rows[k + 1 + r]
            if len(vals) != 4:
                raise SessionFormatError(path, f"matrix row must have 4 numbers, got {len(vals)}", rno)
            try:
                m[r] = [float(v) for v in vals]
            except ValueError:
                raise SessionFormatError(path, "matrix entry is not a number", rno) from None
        if not np.all(np.isfinite(m)) or not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
            raise SessionFormatError(path, "matrix is not a finite rigid transform (last row must be 0 0 0 1)", no)
        if frame in out:
            raise SessionFormatError(path, f"frame {frame} appears twice", no)
        out[frame] = m
        k += 5
    return out


def _list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and not p.name.startswith("."))


class RedwoodReader(PairedReader):
    """An Open3D/Redwood folder (``color/`` + ``depth/``) as a seekable Source.

    Parameters
    ----------
    path : path-like
        The folder.
    skip_bad : bool
        Skip (and list in :attr:`bad_frames`) missing or undecodable images instead of raising.
    fps : float
        Frame rate used for timestamps (Hz), default 30.
    depth_units_per_m : float
        Depth PNG scale, default 1000 (millimetres).
    trajectory : path-like, optional
        Pose log to use; default ``trajectory.log``, else ``odometry.log``, else no poses.
    """

    format_name = "redwood"

    def __init__(self, path: str | os.PathLike, skip_bad: bool = False, fps: float = 30.0,
                 depth_units_per_m: float = REDWOOD_DEPTH_UNITS_PER_M, trajectory: str | os.PathLike | None = None):
        super().__init__(path, skip_bad)
        self.name = f"redwood:{self.path}"
        self.units_per_m = float(depth_units_per_m)
        if not fps > 0:
            raise SessionFormatError(self.path, f"frame rate must be positive, got {fps}")
        ddir = self.path / "depth"
        cdir = next((self.path / c for c in COLOR_DIRS if (self.path / c).is_dir()), None)
        if not ddir.is_dir() or cdir is None:
            raise SessionFormatError(self.path, "not a Redwood/Open3D folder: needs depth/ and color/ sub-folders")
        match = self.path / "rgbd.match"
        if match.is_file():
            lines, partial = _split_lines(match.read_bytes())
            if partial:
                lines.append(partial)
            for no, text in lines:
                tok = text.split()
                if not tok or text.lstrip().startswith("#"):
                    continue
                if len(tok) != 2:
                    self._problem(match, no, f"expected 'depth_path color_path', got {text.strip()[:60]!r}")
                    continue
                d, c = tok
                if d.startswith(tuple(f"{x}/" for x in COLOR_DIRS)) and c.startswith("depth/"):
                    d, c = c, d  # some tools write colour first
                self.items.append(Item(timestamp=0.0, depth=self.path / d, rgb=self.path / c,
                                       depth_index=match, depth_line=no, rgb_index=match, rgb_line=no))
            src_pairs = "rgbd.match"
        else:
            depth, color = _list_images(ddir), _list_images(cdir)
            if len(depth) != len(color):
                by_stem = {p.stem: p for p in color}
                common = [d for d in depth if d.stem in by_stem]
                if not common:
                    raise SessionFormatError(self.path, f"{len(depth)} depth images and {len(color)} colour images "
                                                        f"with no names in common: cannot pair them")
                depth, color = common, [by_stem[d.stem] for d in common]
            self.items = [Item(timestamp=0.0, depth=d, rgb=c) for d, c in zip(depth, color)]
            src_pairs = "sorted file names"
        for i, it in enumerate(self.items):
            it.timestamp = i / fps
        # poses
        log = Path(trajectory) if trajectory is not None else next(
            (self.path / n for n in LOG_FILES if (self.path / n).is_file()), None)
        self.poses = [None] * len(self.items)
        if log is not None:
            try:
                poses = parse_log(log.read_bytes(), log)
            except FileNotFoundError:
                raise SessionFormatError(log, "trajectory file is missing") from None
            self.poses = [poses.get(i) for i in range(len(self.items))]
        # intrinsics
        cams = sorted(self.path.glob("camera*.json")) + sorted(self.path.glob("intrinsic*.json"))
        if cams:
            K = read_camera_json(cams[0])
            self._intrinsics = {"depth": K, "rgb": K}
            isrc = str(cams[0])
        else:
            first = self.items[0] if self.items else None
            self._intrinsics = {"depth": default_intrinsics(first and first.depth),
                                "rgb": default_intrinsics(first and first.rgb)}
            isrc = "PrimeSense default (525, 525, 319.5, 239.5 at 640x480)"
        self._meta = {"device": f"Redwood/Open3D RGB-D folder {self.path.name}", "intrinsics_source": isrc,
                      "pose_source": None if log is None else str(log), "pairs_from": src_pairs, "fps": fps,
                      "emitter_position_m": [0.075, 0.0, 0.0]}
        self._finish()
