"""Live depth cameras as :class:`appfusion.source.Source` objects, and a factory that opens them by name.

Device names (:func:`open_device`)::

    openni2                 first OpenNI2 device attached (Kinect v1 via libfreenect, PrimeSense, Xtion)
    openni2:Dummy           OpenNI2's DummyDevice (no hardware; 320x240 depth + RGB)
    openni2:URI             an OpenNI2 device URI (``list_devices()``), or openni2:FILE.oni
    depthai                 first Luxonis OAK device (OAK-D, OAK-D Pro)
    depthai:MXID            the OAK with this MX id / name / IP address
    depthai-replay:DIR      messages recorded by a DepthAISource with record_dir=DIR (.mcap)

Which streams each scanning pass needs (:func:`streams_for_pass`) follows the paper: geometry and the
IR reflectometry need depth + IR (§4.1, §5.1-5.2), the RGB pass depth + RGB (§5.3), the environment
map RGB of the mirror ball plus depth to place it (§4.3), the IR calibration IR frames (§6).
Which passes a live scan records on a device (:func:`live_pass_plan`) follows from its capability
model: a Kinect v1 / PrimeSense (IR and colour not at once) records geometry and rgb separately, a
device that streams depth, IR and RGB together one combined ``scan`` pass.
"""

from __future__ import annotations

from typing import Any

from appfusion.errors import SourceError
from appfusion.source import Source, StreamCaps

__all__ = ["open_device", "parse_device_name", "streams_for_pass", "live_pass_plan", "is_device_name",
           "PASS_STREAMS", "SCHEMES"]

#: streams each scanning pass needs, in order of preference (docs/conventions.md "Scanning passes")
PASS_STREAMS: dict[str, tuple[frozenset[str], ...]] = {
    "geometry": (frozenset({"depth", "ir"}),),
    "ir-calibration": (frozenset({"depth", "ir"}), frozenset({"ir"})),
    "environment": (frozenset({"depth", "rgb"}),),
    "rgb": (frozenset({"depth", "rgb"}),),
    "scan": (frozenset({"depth", "ir", "rgb"}),),
}

#: a depth + colour camera without any IR stream (the OpenNI2 DummyDevice, an Xtion without IR access)
#: runs ``scan`` on depth + RGB: geometry and rho_d from the same frames, no IR reflectometry (like a
#: TUM / Redwood recording)
SCAN_WITHOUT_IR = frozenset({"depth", "rgb"})

#: device name schemes :func:`open_device` knows
SCHEMES = ("openni2", "depthai", "depthai-replay")


def streams_for_pass(name: str, caps: StreamCaps) -> frozenset[str]:
    """The streams a device with capabilities ``caps`` should run for scanning pass ``name``.

    ``scan`` (depth, IR and RGB in one pass) needs a device that streams all three together; on a
    Kinect v1 it raises :class:`~appfusion.errors.SourceError` saying to record the ``geometry`` and
    ``rgb`` passes separately. A device with no IR stream at all runs ``scan`` on depth + RGB
    (:data:`SCAN_WITHOUT_IR`).
    """
    if name not in PASS_STREAMS:
        raise SourceError(f"unknown scanning pass {name!r} (known: {', '.join(PASS_STREAMS)})")
    options = PASS_STREAMS[name]
    if name == "scan" and "ir" not in caps.streams:
        options = options + (SCAN_WITHOUT_IR,)
    for want in options:
        if want <= caps.streams and caps.can_stream(want):
            return want
    need = " or ".join("{" + ", ".join(sorted(w)) + "}" for w in options)
    can = " or ".join("{" + ", ".join(sorted(g)) + "}" for g in caps.together)
    hint = " (record the geometry and rgb passes one after the other instead)" if name == "scan" else ""
    raise SourceError(f"pass {name!r} needs {need} at once, but the device can stream {can}{hint}")


def live_pass_plan(caps: StreamCaps, envmap: bool = False, ir_profile: bool = False) -> list[str]:
    """The scanning passes a live scan records on a device with capabilities ``caps``, in order.

    Parameters
    ----------
    caps : StreamCaps
        The opened device's capability model.
    envmap : bool
        An environment map of the same markers is reused (``--envmap``): no ``environment`` pass.
    ir_profile : bool
        A saved IR device profile is reused (``--ir-profile``): no ``ir-calibration`` pass.

    Returns
    -------
    list of str
        ``ir-calibration`` (§6, devices with IR), ``environment`` (§4.3, devices with RGB), then the
        object: ``geometry`` then ``rgb`` (§4.1/§5.1-5.2 then §5.3) on a device that cannot stream IR
        and colour at once (Kinect v1, PrimeSense), one ``scan`` pass on a device that streams depth,
        IR and RGB together (OAK-D Pro) or has no IR at all (depth + RGB), ``geometry`` alone on a
        device without colour.

    Raises
    ------
    SourceError
        The device has no depth stream (nothing to track or reconstruct with).
    """
    have = caps.streams
    if "depth" not in have:
        raise SourceError("a scan needs a depth stream, but the device streams only "
                          + (", ".join(sorted(have)) or "nothing"))
    ir, rgb = "ir" in have, "rgb" in have
    plan = []
    if ir and not ir_profile:
        plan.append("ir-calibration")
    if rgb and not envmap:
        plan.append("environment")
    if ir and rgb:
        plan += ["scan"] if caps.can_stream({"depth", "ir", "rgb"}) else ["geometry", "rgb"]
    elif rgb:
        plan.append("scan")
    else:
        plan.append("geometry")
    for name in plan:  # every pass must be streamable: raises with the reason otherwise
        streams_for_pass(name, caps)
    return plan


def parse_device_name(name: str) -> tuple[str, str]:
    """Split ``"scheme[:rest]"`` into (scheme, rest); raise SourceError for an unknown scheme."""
    scheme, _, rest = str(name).partition(":")
    scheme = scheme.strip().lower()
    if scheme not in SCHEMES:
        raise SourceError(f"unknown device {name!r}: expected one of "
                          + ", ".join(f"{s}[:...]" for s in SCHEMES))
    return scheme, rest


def is_device_name(name: str) -> bool:
    """True if ``name`` names a live device (``openni2...``, ``depthai...``) rather than a file."""
    scheme = str(name).partition(":")[0].strip().lower()
    return scheme in SCHEMES


def open_device(name: str, **options: Any) -> Source:
    """Create the source for a device name (not yet opened; use it as a context manager).

    Parameters
    ----------
    name : str
        ``openni2``, ``openni2:Dummy``, ``openni2:URI``, ``depthai``, ``depthai:MXID`` or
        ``depthai-replay:DIR`` (see the module docstring).
    **options
        Passed to :class:`~drivers.openni2_source.OpenNI2Source` or
        :class:`~drivers.depthai_source.DepthAISource`; ``streams`` is accepted by both.

    Raises
    ------
    SourceError
        Unknown scheme.
    """
    scheme, rest = parse_device_name(name)
    if scheme == "openni2":
        from drivers.openni2_source import OpenNI2Source

        return OpenNI2Source(rest or None, **options)
    from drivers.depthai_source import DepthAISource

    if scheme == "depthai-replay":
        if not rest:
            raise SourceError("depthai-replay: give the recording folder, e.g. depthai-replay:/data/oak1")
        return DepthAISource(replay_dir=rest, **options)
    return DepthAISource(rest or None, **options)
