"""The one interface shared by live devices (``drivers/``) and recordings (``replay/``).

A :class:`Source` is a context manager that yields :class:`~appfusion.frame.Frame` objects. It says
which streams it has and which can run together (a Kinect v1 cannot stream IR and RGB at once, so a
scan of it runs the paper's passes one after another), and exposes the device controls it has.
Recordings are also seekable and have a length.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any, Iterator

from .errors import SourceError
from .frame import Frame, Intrinsics


@dataclass(frozen=True)
class StreamCaps:
    """What a source can stream.

    Attributes
    ----------
    streams : frozenset of str
        Streams the source has at all ("depth", "ir", "rgb").
    together : tuple of frozenset
        Maximal sets of streams that can run at the same time. A Kinect v1 has
        ``({"depth", "ir"}, {"depth", "rgb"})``; an Azure Kinect has ``({"depth", "ir", "rgb"},)``.
    rates : dict
        Nominal frame rate per stream (Hz).
    """

    streams: frozenset[str]
    together: tuple[frozenset[str], ...]
    rates: dict[str, float] = field(default_factory=dict)

    def can_stream(self, wanted: set[str] | frozenset[str]) -> bool:
        """True if all ``wanted`` streams can run at the same time."""
        return any(set(wanted) <= g for g in self.together)

    @property
    def ir_and_rgb_together(self) -> bool:
        """True if IR and RGB come in the same frames (the IR and RGB passes can run as one)."""
        return self.can_stream({"ir", "rgb"})

    @classmethod
    def all_together(cls, streams, rates=None) -> "StreamCaps":
        s = frozenset(streams)
        return cls(s, (s,), dict(rates or {}))


@dataclass
class Control:
    """A device control (IR emitter, exposure, ...).

    Attributes
    ----------
    name : str
    kind : {"bool", "int", "float", "choice"}
    value : Any
        Current value.
    limits : tuple, optional
        (min, max) for numbers, or the allowed values for "choice".
    unit : str
    """

    name: str
    kind: str
    value: Any
    limits: tuple | None = None
    unit: str = ""


class Source(abc.ABC):
    """Base class of every frame source.

    Subclasses implement :meth:`_open`, :meth:`_close`, :meth:`_frames` and :attr:`caps`;
    recordings also implement :meth:`__len__` and :meth:`seek`.
    """

    #: human-readable name of the device or recording
    name: str = "source"
    #: True for recordings (seekable, finite), False for live devices
    is_recording: bool = False

    def __init__(self):
        self._is_open = False

    # -- lifecycle -----------------------------------------------------------------------------
    def open(self) -> "Source":
        if not self._is_open:
            self._open()
            self._is_open = True
        return self

    def close(self) -> None:
        if self._is_open:
            try:
                self._close()
            finally:
                self._is_open = False

    @property
    def is_open(self) -> bool:
        return self._is_open

    def __enter__(self) -> "Source":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def __iter__(self) -> Iterator[Frame]:
        if not self._is_open:
            self.open()
        return self._frames()

    # -- description ---------------------------------------------------------------------------
    @property
    @abc.abstractmethod
    def caps(self) -> StreamCaps:
        """Streams this source has and which can run together."""

    @property
    def intrinsics(self) -> dict[str, Intrinsics]:
        """Intrinsics per stream name (may be empty before :meth:`open` for devices)."""
        return {}

    @property
    def meta(self) -> dict[str, Any]:
        """Free-form description (device model, serial, depth scale, baseline, ...)."""
        return {}

    # -- controls ------------------------------------------------------------------------------
    @property
    def controls(self) -> dict[str, Control]:
        """Controls the device has; empty for recordings."""
        return {}

    def set_control(self, name: str, value: Any) -> None:
        """Set a device control, e.g. ``set_control("emitter", False)``."""
        if name not in self.controls:
            have = ", ".join(sorted(self.controls)) or "none"
            raise SourceError(f"{self.name}: no control {name!r} (this source has: {have})")
        self._set_control(name, value)

    def _set_control(self, name: str, value: Any) -> None:  # pragma: no cover - overridden by drivers
        raise SourceError(f"{self.name}: control {name!r} cannot be set")

    # -- recordings ----------------------------------------------------------------------------
    def __len__(self) -> int:
        raise TypeError(f"{type(self).__name__} is a live source and has no length")

    def seek(self, index: int) -> None:
        """Make the next frame yielded the one at ``index`` (recordings only)."""
        raise SourceError(f"{self.name}: a live source cannot seek")

    # -- to implement --------------------------------------------------------------------------
    @abc.abstractmethod
    def _open(self) -> None: ...

    @abc.abstractmethod
    def _close(self) -> None: ...

    @abc.abstractmethod
    def _frames(self) -> Iterator[Frame]: ...


class WrappedSource(Source):
    """A source that hands streams, intrinsics, meta and controls through to ``inner`` and opens and
    closes it; subclasses change what they need (the GUI's paced player, the live scan's device with
    the marker layout added). ``_frames`` iterates ``inner``."""

    def __init__(self, inner: Source):
        super().__init__()
        self.inner = inner
        self.name = getattr(inner, "name", "source")

    @property
    def caps(self):
        return self.inner.caps

    @property
    def intrinsics(self):
        return self.inner.intrinsics

    @property
    def meta(self):
        return self.inner.meta

    @property
    def controls(self):
        return self.inner.controls

    def set_control(self, name, value):
        return self.inner.set_control(name, value)

    def _open(self) -> None:
        self.inner.open()
        self.name = getattr(self.inner, "name", self.name)

    def _close(self) -> None:
        self.inner.close()

    def _frames(self) -> Iterator[Frame]:
        return iter(self.inner)


class IndexedRecording(Source):
    """A recording whose frames can be decoded one by one: ``frame(i)`` and ``__len__``.

    Gives the seek / iterate behaviour shared by the recording readers: :meth:`seek` takes
    negative indices from the end and ``len`` for the end; iteration decodes frames from the current
    position, and a frame that fails to decode raises its
    :class:`~appfusion.errors.SessionFormatError`, or with ``skip_bad`` is skipped and listed in
    ``bad_frames`` as ``(path, line, reason)``. Subclasses set ``self._pos = 0``, ``self.skip_bad``
    and ``self.bad_frames`` in their constructor.
    """

    is_recording = True

    @abc.abstractmethod
    def frame(self, index: int) -> Frame:
        """Decode frame ``index``."""

    @abc.abstractmethod
    def __len__(self) -> int: ...

    def seek(self, index: int) -> None:
        """Make the next frame yielded the one at ``index`` (negative: from the end; ``len``: the end)."""
        n = len(self)
        if not -n <= index <= n:
            raise IndexError(f"{self.name}: cannot seek to frame {index} (the recording has {n} frames)")
        self._pos = index + n if index < 0 else index

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    def _frames(self) -> Iterator[Frame]:
        from .errors import SessionFormatError

        while self._pos < len(self):
            i = self._pos
            self._pos += 1
            try:
                yield self.frame(i)
            except SessionFormatError as e:
                if not self.skip_bad:
                    raise
                self.bad_frames.append((e.path, e.line, e.reason))
