"""Errors raised by appfusion.

Every error a user can cause (a corrupt file, a missing stream, an unplugged device, wrong units)
is an :class:`AppFusionError` whose message names what is wrong and where. The CLI prints the
message alone, without a traceback, and exits with status 2.
"""

from __future__ import annotations

import os


class AppFusionError(Exception):
    """Base class of all errors appfusion raises on purpose."""


class SessionFormatError(AppFusionError):
    """A recording on disk is damaged or not of the expected format.

    Parameters
    ----------
    path : str or os.PathLike
        The file that is wrong.
    message : str
        What is wrong with it.
    line : int, optional
        1-based line number inside ``path`` where the problem is, for index and text files.
    """

    def __init__(self, path: str | os.PathLike, message: str, line: int | None = None):
        self.path = os.fspath(path)
        self.line = line
        self.reason = message
        where = self.path if line is None else f"{self.path}:{line}"
        super().__init__(f"{where}: {message}")


class SourceError(AppFusionError):
    """A frame source (device or recording) cannot deliver what was asked of it."""


class DeviceError(SourceError):
    """A live device is missing, unplugged, busy, or lacks permissions or libraries."""


class CalibrationError(AppFusionError):
    """A calibration cannot be computed from the data given (too little, degenerate)."""


class EstimationError(AppFusionError):
    """An estimator cannot produce a result from its input (degenerate or empty data)."""


class PassMissingError(AppFusionError):
    """A recording lacks a scanning pass that a requested result needs."""
