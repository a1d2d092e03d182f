"""Recordings: the appfusion session format and readers of foreign RGB-D recordings.

- :mod:`replay.session`: :class:`~replay.session.SessionWriter` / :class:`~replay.session.SessionReader`
  (our crash-safe, lossless, TUM-compatible format; spec in ``docs/session-format.md``) and
  :func:`~replay.session.copy_session`.
- :mod:`replay.tum`, :mod:`replay.redwood`, ``replay.azure_kinect``: TUM RGB-D folders,
  Redwood/Open3D folders, Azure Kinect MKV files.
- :mod:`replay.open`: :func:`~replay.open.open_recording` / :func:`~replay.open.detect_format`.

The names below are imported lazily, so ``import replay`` stays cheap.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "open_recording": "replay.open", "detect_format": "replay.open", "UnknownFormatError": "replay.open",
    "SessionWriter": "replay.session", "SessionReader": "replay.session", "copy_session": "replay.session",
    "TUMReader": "replay.tum", "RedwoodReader": "replay.redwood",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'replay' has no attribute {name!r}")
