"""Open any supported recording by path: our sessions, TUM RGB-D, Redwood/Open3D folders, Azure Kinect MKV.

Detection (:func:`detect_format`), in this order:

=================  ===================================================================
``"session"``      a directory with ``meta.json`` (:class:`replay.session.SessionReader`)
``"tum"``          a directory with ``rgb.txt`` and ``depth.txt`` but no ``meta.json``
                   (:class:`replay.tum.TUMReader`; with only one of them, the reader
                   names the missing one)
``"redwood"``      a directory with ``depth/`` and ``color/`` (or ``rgb/``/``image/``)
                   sub-folders (:class:`replay.redwood.RedwoodReader`)
``"azure-mkv"``    a ``.mkv`` file (``replay.azure_kinect.AzureKinectReader``, imported lazily)
=================  ===================================================================

A path given as ``meta.json``, ``rgb.txt`` or ``depth.txt`` stands for its folder.
"""

from __future__ import annotations

import os
from pathlib import Path

from appfusion.errors import SourceError
from appfusion.source import Source

#: format name -> what it is, for messages and ``appfusion info``
FORMATS = {
    "session": "appfusion session (directory with meta.json)",
    "tum": "TUM RGB-D folder (rgb.txt + depth.txt)",
    "redwood": "Redwood/Open3D folder (color/ + depth/)",
    "azure-mkv": "Azure Kinect recording (.mkv)",
}


class UnknownFormatError(SourceError):
    """A path is not a recording in any format :func:`open_recording` knows."""


def _known() -> str:
    return "; ".join(FORMATS.values())


def _resolve(path: str | os.PathLike) -> Path:
    p = Path(path)
    if p.is_file() and p.name in ("meta.json", "rgb.txt", "depth.txt"):
        return p.parent
    return p


def detect_format(path: str | os.PathLike) -> str:
    """Name of the recording format at ``path``: ``"session"``, ``"tum"``, ``"redwood"`` or ``"azure-mkv"``.

    Raises
    ------
    UnknownFormatError
        If ``path`` does not exist or is none of these; the message names the path and the
        formats known.
    """
    p = _resolve(path)
    if not p.exists():
        raise UnknownFormatError(f"{p}: no such file or directory (known recording formats: {_known()})")
    if p.is_file():
        if p.suffix.lower() == ".mkv":
            return "azure-mkv"
        raise UnknownFormatError(f"{p}: not a recording this program reads (known formats: {_known()})")
    if (p / "meta.json").is_file():
        return "session"
    if (p / "rgb.txt").is_file() or (p / "depth.txt").is_file():
        return "tum"  # with one index missing, TUMReader says which
    colour = [c for c in ("color", "rgb", "image") if (p / c).is_dir()]
    if (p / "depth").is_dir() and colour:
        return "redwood"
    if (p / "depth").is_dir() or colour:
        # half of a Redwood/Open3D folder: name the missing half rather than "no known format"
        has, missing = ((f"{colour[0]}/", "depth/ (the depth images)") if colour else
                        ("depth/", "color/ (or rgb/, image/: the colour images)"))
        raise UnknownFormatError(f"{p}: has {has} but no {missing} sub-folder: not a complete Redwood/Open3D "
                                 f"folder (known formats: {_known()})")
    raise UnknownFormatError(f"{p}: a directory of no known recording format (known formats: {_known()})")


def open_recording(path: str | os.PathLike, skip_bad: bool = False) -> Source:
    """Open a recording of any supported format as a seekable :class:`~appfusion.source.Source`.

    Parameters
    ----------
    path : path-like
        Session or TUM/Redwood folder, or ``.mkv`` file.
    skip_bad : bool
        Skip damaged frames (listed in the reader's ``bad_frames``) instead of raising.

    Raises
    ------
    UnknownFormatError
        Unknown format (the message lists the known ones).
    SessionFormatError
        The recording is damaged (file and line named).
    """
    fmt = detect_format(path)
    p = _resolve(path)
    if fmt == "session":
        from .session import SessionReader

        return SessionReader(p, skip_bad=skip_bad)
    if fmt == "tum":
        from .tum import TUMReader

        return TUMReader(p, skip_bad=skip_bad)
    if fmt == "redwood":
        from .redwood import RedwoodReader

        return RedwoodReader(p, skip_bad=skip_bad)
    try:
        from .azure_kinect import AzureKinectReader
    except ImportError as e:  # pragma: no cover - depends on the optional reader module
        raise SourceError(f"{p}: cannot read Azure Kinect recordings: {e}") from None
    return AzureKinectReader(p, skip_bad=skip_bad)
