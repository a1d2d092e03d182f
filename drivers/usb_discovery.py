"""Which depth sensors are plugged in, which appfusion driver serves each, and what stops them working.

``appfusion devices`` is the front end. Devices are recognised by USB vendor:product id (pyusb);
each recognised device is opened once (and closed again, nothing is claimed or configured) to find
permission problems before a capture does. The diagnoses, each with the command that fixes it:

- no libusb backend for pyusb (``sudo apt install libusb-1.0-0``);
- permission denied opening a device (install the shipped udev rules, ``drivers/udev/99-appfusion.rules``);
- OpenNI2 missing for a Kinect v1 / PrimeSense / Orbbec sensor (``sudo apt install libopenni2-0``),
  or OpenNI2 present without a driver for the attached sensor (Kinect v1: libfreenect's
  ``libFreenectDriver.so``; Orbbec: Orbbec's own OpenNI2 driver);
- depthai missing for a Luxonis OAK.

Device ids (checked against libfreenect, libfreenect2, the Azure Kinect SDK's udev rules and the
depthai/OpenNI2 sources):

=========  =========  ==========================================================
vendor     product    device
=========  =========  ==========================================================
045e       02ae       Kinect v1 (Xbox 360) camera      -> openni2
045e       02ad/02b0  Kinect v1 audio / tilt motor     -> (not used)
045e       02bf       Kinect for Windows v1 camera     -> openni2
045e       02be/02c3/02bb  Kinect for Windows audio   -> (not used)
045e       02c4/02d8  Kinect v2                        -> none (libfreenect2)
045e       097c/097d  Azure Kinect depth / colour      -> azure-kinect-recording-only
045e       097a/097b  Azure Kinect USB hubs; 097e microphone array
1d27       0600/0601/0609  PrimeSense PS1080 (Carmine, Asus Xtion) -> openni2
03e7       2485       Luxonis OAK, Myriad X not booted -> depthai (boots it, re-enumerates as f63b)
03e7       f63b       Luxonis OAK, booted              -> depthai
2bc5       any        Orbbec                           -> openni2 (with Orbbec's driver)
=========  =========  ==========================================================
"""

from __future__ import annotations

import ctypes
import errno
import importlib.metadata
import importlib.util
import os
import platform
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable

__all__ = ["KnownDevice", "KNOWN_DEVICES", "identify", "UsbDevice", "Problem", "Environment", "Report",
           "discover", "probe_environment", "find_backend", "udev_rules_path", "udev_install_command",
           "format_table"]

#: appfusion drivers a device can be served by
DRIVERS = ("openni2", "depthai", "azure-kinect-recording-only", "none")


@dataclass(frozen=True)
class KnownDevice:
    """One USB id appfusion recognises.

    Attributes
    ----------
    vendor_id, product_id : int
        USB ids; ``product_id`` None matches any product of the vendor.
    family : str
        Sensor family ("Kinect v1", "Azure Kinect", ...), shared by the USB devices of one sensor.
    part : str
        What this USB device is within the sensor ("camera", "audio", "motor", "hub", ...).
    driver : str
        The appfusion driver serving it, one of :data:`DRIVERS` ("none" for parts no driver uses).
    primary : bool
        True for the USB device a driver opens to capture (the camera), False for auxiliary parts.
    note : str
        Shown beside the device.
    """

    vendor_id: int
    product_id: int | None
    family: str
    part: str
    driver: str
    primary: bool = True
    note: str = ""

    @property
    def name(self) -> str:
        return f"{self.family} {self.part}"


_MS, _PS, _MOVIDIUS, _ORBBEC = 0x045E, 0x1D27, 0x03E7, 0x2BC5
KNOWN_DEVICES: tuple[KnownDevice, ...] = (
    KnownDevice(_MS, 0x02AE, "Kinect v1", "camera", "openni2"),
    KnownDevice(_MS, 0x02AD, "Kinect v1", "audio", "none", False, "not used by appfusion"),
    KnownDevice(_MS, 0x02B0, "Kinect v1", "tilt motor", "none", False, "not used by appfusion"),
    KnownDevice(_MS, 0x02BF, "Kinect for Windows v1", "camera", "openni2"),
    KnownDevice(_MS, 0x02BE, "Kinect for Windows v1", "audio", "none", False, "not used by appfusion"),
    KnownDevice(_MS, 0x02C3, "Kinect for Windows v1", "audio", "none", False, "not used by appfusion"),
    KnownDevice(_MS, 0x02BB, "Kinect for Windows v1", "audio", "none", False, "not used by appfusion"),
    KnownDevice(_MS, 0x02D8, "Kinect v2", "sensor", "none", True,
                "not supported (needs libfreenect2); appfusion cannot capture from it"),
    KnownDevice(_MS, 0x02C4, "Kinect v2 (preview)", "sensor", "none", True,
                "not supported (needs libfreenect2); appfusion cannot capture from it"),
    KnownDevice(_MS, 0x097C, "Azure Kinect", "depth camera", "azure-kinect-recording-only", True,
                "no live capture: record with k4arecorder (Azure Kinect SDK), then open the .mkv"),
    KnownDevice(_MS, 0x097D, "Azure Kinect", "colour camera", "azure-kinect-recording-only", False,
                "recorded together with the depth camera by k4arecorder"),
    KnownDevice(_MS, 0x097E, "Azure Kinect", "microphone array", "none", False, "not used by appfusion"),
    KnownDevice(_MS, 0x097A, "Azure Kinect", "USB 3 hub", "none", False, "internal hub"),
    KnownDevice(_MS, 0x097B, "Azure Kinect", "USB 2 hub", "none", False, "internal hub"),
    KnownDevice(_PS, 0x0600, "PrimeSense PS1080 (Carmine / Asus Xtion)", "camera", "openni2"),
    KnownDevice(_PS, 0x0601, "PrimeSense PS1080 (Carmine / Asus Xtion Pro Live)", "camera", "openni2"),
    KnownDevice(_PS, 0x0609, "PrimeSense PS1080 (Carmine 1.09)", "camera", "openni2"),
    KnownDevice(_MOVIDIUS, 0x2485, "Luxonis OAK", "camera (Myriad X not booted)", "depthai", True,
                "depthai boots it; it then re-enumerates as 03e7:f63b"),
    KnownDevice(_MOVIDIUS, 0xF63B, "Luxonis OAK", "camera (booted)", "depthai"),
    KnownDevice(_ORBBEC, None, "Orbbec", "depth camera", "openni2", True,
                "needs Orbbec's OpenNI2 driver; Debian's libopenni2-0 only drives PrimeSense-based sensors"),
)


def identify(vendor_id: int, product_id: int) -> KnownDevice | None:
    """The :class:`KnownDevice` entry for a USB id, or None (exact product ids win over vendor-wide ones)."""
    exact = wild = None
    for k in KNOWN_DEVICES:
        if k.vendor_id == vendor_id:
            if k.product_id == product_id:
                exact = k
            elif k.product_id is None:
                wild = k
    return exact or wild


# ---------------------------------------------------------------------------------------------
# results
# ---------------------------------------------------------------------------------------------
#: USB speed codes of pyusb (usb.util.SPEED_*) -> text
_SPEEDS = {1: "1.5 Mb/s", 2: "12 Mb/s", 3: "480 Mb/s", 4: "5 Gb/s", 5: "10 Gb/s"}


@dataclass
class UsbDevice:
    """One attached USB device as discovery saw it.

    Attributes
    ----------
    bus, address : int or None
        USB bus number and device address.
    vendor_id, product_id : int
    known : KnownDevice or None
        What appfusion knows about this id (None for unrelated devices, listed only with ``--all``).
    serial : str or None
        Serial number string, when the device could be opened and has one.
    speed : str or None
        Link speed, e.g. "5 Gb/s" (USB 3), when the backend reports it.
    status : {"ok", "no-permission", "open-failed", "not-probed"}
        Result of opening the device once.
    error : str or None
        The error opening gave.
    """

    bus: int | None
    address: int | None
    vendor_id: int
    product_id: int
    known: KnownDevice | None = None
    serial: str | None = None
    speed: str | None = None
    status: str = "not-probed"
    error: str | None = None

    @property
    def usb_id(self) -> str:
        return f"{self.vendor_id:04x}:{self.product_id:04x}"

    @property
    def location(self) -> str:
        if self.bus is None or self.address is None:
            return "?"
        return f"{self.bus:03d}:{self.address:03d}"

    @property
    def name(self) -> str:
        return self.known.name if self.known else "(not a depth sensor)"

    @property
    def driver(self) -> str:
        return self.known.driver if self.known else "none"

    def to_json(self) -> dict[str, Any]:
        d = {"bus": self.bus, "address": self.address, "usb_id": self.usb_id,
             "vendor_id": self.vendor_id, "product_id": self.product_id,
             "family": self.known.family if self.known else None,
             "part": self.known.part if self.known else None,
             "driver": self.driver, "primary": bool(self.known and self.known.primary),
             "serial": self.serial, "speed": self.speed, "status": self.status, "error": self.error,
             "note": self.known.note if self.known else ""}
        return d


@dataclass
class Problem:
    """Something that stops (severity "error") or may stop ("warning") a device from working.

    Attributes
    ----------
    severity : {"error", "warning", "info"}
    what : str
        The problem, in one sentence.
    fix : str
        The command or step that fixes it (empty for "info").
    devices : list of str
        USB ids ("vvvv:pppp") of the devices it concerns; empty for general problems.
    """

    severity: str
    what: str
    fix: str = ""
    devices: list[str] = field(default_factory=list)


@dataclass
class Environment:
    """Libraries the drivers need, as found on this machine.

    Attributes
    ----------
    usb_backend : str or None
        pyusb backend in use ("libusb1", "libusb0", "openusb", "custom") or None.
    openni2_library : str or None
        Path of libOpenNI2 (None: not found).
    openni2_drivers : list of str
        File names in OpenNI2's ``Drivers`` folder (e.g. ``libPS1080.so``).
    depthai_version : str or None
        Installed depthai version (None: not installed).
    platform : str
        ``sys.platform``.
    """

    usb_backend: str | None = None
    openni2_library: str | None = None
    openni2_drivers: list[str] = field(default_factory=list)
    depthai_version: str | None = None
    platform: str = sys.platform


@dataclass
class Report:
    """The outcome of :func:`discover`: devices, problems with fixes, and the environment."""

    devices: list[UsbDevice]
    problems: list[Problem]
    environment: Environment

    @property
    def ok(self) -> bool:
        """True when no problem is an error."""
        return not any(p.severity == "error" for p in self.problems)

    def to_json(self) -> dict[str, Any]:
        return {"devices": [d.to_json() for d in self.devices],
                "problems": [asdict(p) for p in self.problems],
                "environment": asdict(self.environment),
                "ok": self.ok}


# ---------------------------------------------------------------------------------------------
# environment
# ---------------------------------------------------------------------------------------------
def find_backend():
    """The first pyusb backend that loads: (backend, name) or (None, None)."""
    import usb.backend.libusb0
    import usb.backend.libusb1
    import usb.backend.openusb

    for name, mod in (("libusb1", usb.backend.libusb1), ("libusb0", usb.backend.libusb0),
                      ("openusb", usb.backend.openusb)):
        try:
            b = mod.get_backend()
        except Exception:  # a broken library install must not stop discovery
            b = None
        if b is not None:
            return b, name
    return None, None


def _library_dirs() -> list[Path]:
    dirs = []
    for var in ("OPENNI2_REDIST64", "OPENNI2_REDIST"):
        if os.environ.get(var):
            dirs.append(Path(os.environ[var]))
    machine = platform.machine()
    triples = {"x86_64": "x86_64-linux-gnu", "aarch64": "aarch64-linux-gnu", "armv7l": "arm-linux-gnueabihf"}
    if sys.platform.startswith("linux"):
        t = triples.get(machine)
        if t:
            dirs += [Path("/usr/lib") / t, Path("/lib") / t]
        dirs += [Path("/usr/lib"), Path("/usr/local/lib"), Path("/lib"), Path("/lib64")]
    elif sys.platform == "darwin":
        dirs += [Path("/usr/local/lib"), Path("/opt/homebrew/lib")]
    return dirs


def find_openni2(dirs: Iterable[Path] | None = None) -> tuple[str | None, list[str]]:
    """Locate libOpenNI2 and the driver modules in its ``OpenNI2/Drivers`` folder.

    Returns
    -------
    (str or None, list of str)
        The library's path (or None) and the file names of the drivers found next to it.
    """
    names = {"win32": ["OpenNI2.dll"], "darwin": ["libOpenNI2.dylib"]}.get(
        sys.platform, ["libOpenNI2.so", "libOpenNI2.so.0"])
    for d in (list(dirs) if dirs is not None else _library_dirs()):
        for n in names:
            lib = d / n
            if lib.is_file():
                drv = d / "OpenNI2" / "Drivers"
                found = sorted(p.name for p in drv.iterdir()) if drv.is_dir() else []
                return str(lib), found
    if dirs is None and sys.platform.startswith("linux"):
        try:  # a library the dynamic loader finds elsewhere (LD_LIBRARY_PATH, ld.so.conf)
            ctypes.CDLL("libOpenNI2.so.0")
            return "libOpenNI2.so.0 (via the dynamic loader)", []
        except OSError:
            pass
    return None, []


def probe_environment(backend_name: str | None = None) -> Environment:
    """Find the USB backend, OpenNI2 and depthai on this machine (imports nothing heavy)."""
    if backend_name is None:
        _, backend_name = find_backend()
    lib, drivers = find_openni2()
    version = None
    if importlib.util.find_spec("depthai") is not None:
        try:
            version = importlib.metadata.version("depthai")
        except importlib.metadata.PackageNotFoundError:
            version = "unknown"
    return Environment(backend_name, lib, drivers, version, sys.platform)


# ---------------------------------------------------------------------------------------------
# udev
# ---------------------------------------------------------------------------------------------
def udev_rules_path() -> Path:
    """The udev rules file shipped with appfusion (``drivers/udev/99-appfusion.rules``)."""
    return Path(__file__).resolve().parent / "udev" / "99-appfusion.rules"


def udev_install_command() -> str:
    """The exact shell command that installs the shipped udev rules and applies them."""
    return (f"sudo install -m 0644 {udev_rules_path()} /etc/udev/rules.d/99-appfusion.rules && "
            "sudo udevadm control --reload-rules && sudo udevadm trigger")


# ---------------------------------------------------------------------------------------------
# discovery
# ---------------------------------------------------------------------------------------------
def _probe(dev, d: UsbDevice) -> None:
    """Open ``dev`` once (reading its serial number), record the outcome in ``d``, close it again."""
    import usb.core
    import usb.util

    try:
        dev._ctx.managed_open()  # pyusb opens lazily; this is the open every driver does first
        d.status = "ok"
        if getattr(dev, "iSerialNumber", 0):
            try:
                d.serial = usb.util.get_string(dev, dev.iSerialNumber)
            except (usb.core.USBError, ValueError, NotImplementedError):
                pass  # some devices stall string requests; the serial is only informative
    except usb.core.USBError as e:
        code = getattr(e, "backend_error_code", None)
        d.error = str(e)
        # libusb: LIBUSB_ERROR_ACCESS = -3 (errno EACCES); libusb0 reports EPERM/EACCES
        d.status = "no-permission" if (e.errno in (errno.EACCES, errno.EPERM) or code == -3) else "open-failed"
    except NotImplementedError:
        d.status = "not-probed"
    finally:
        try:
            usb.util.dispose_resources(dev)
        except Exception:
            pass


def list_usb_devices(backend, probe_open: bool = True, include_all: bool = False) -> list[UsbDevice]:
    """Enumerate USB devices with pyusb through ``backend``.

    Parameters
    ----------
    backend : usb.backend.IBackend
    probe_open : bool
        Open each recognised device once to check permissions (and read its serial number).
    include_all : bool
        Also list devices appfusion does not recognise (never opened).

    Returns
    -------
    list of UsbDevice
        Sorted by bus and address.
    """
    import usb.core

    out = []
    for dev in usb.core.find(find_all=True, backend=backend):
        vid, pid = int(dev.idVendor), int(dev.idProduct)
        known = identify(vid, pid)
        if known is None and not include_all:
            continue
        d = UsbDevice(getattr(dev, "bus", None), getattr(dev, "address", None), vid, pid, known,
                      speed=_SPEEDS.get(getattr(dev, "speed", None) or 0))
        if known is not None and probe_open:
            _probe(dev, d)
        out.append(d)
    out.sort(key=lambda d: (d.bus if d.bus is not None else 999, d.address if d.address is not None else 999))
    return out


def _sysfs_devices(root: Path, include_all: bool) -> list[UsbDevice]:
    """USB devices listed from Linux sysfs (used when pyusb has no backend); never opened."""
    out = []
    if not root.is_dir():
        return out
    for p in sorted(root.iterdir()):
        try:
            vid = int((p / "idVendor").read_text().strip(), 16)
            pid = int((p / "idProduct").read_text().strip(), 16)
        except (OSError, ValueError):
            continue  # an interface entry, not a device
        known = identify(vid, pid)
        if known is None and not include_all:
            continue

        def read(name, conv=str):
            try:
                return conv((p / name).read_text().strip())
            except (OSError, ValueError):
                return None
        speed = read("speed")
        out.append(UsbDevice(read("busnum", int), read("devnum", int), vid, pid, known,
                             serial=read("serial"), speed=f"{speed} Mb/s" if speed else None))
    return out


def _diagnose(devices: list[UsbDevice], env: Environment) -> list[Problem]:
    problems: list[Problem] = []
    known = [d for d in devices if d.known is not None]
    if env.usb_backend is None:
        fix = {"darwin": "brew install libusb", "win32": "pip install libusb-package (or install libusb-1.0.dll)"}.get(
            env.platform, "sudo apt install libusb-1.0-0")
        problems.append(Problem("error", "pyusb found no libusb backend, so USB devices cannot be opened "
                                         "(the list, if any, comes from sysfs and permissions are unchecked)", fix))
    denied = [d for d in known if d.status == "no-permission"]
    if denied:
        fix = (udev_install_command() + "  # then unplug and replug the device"
               if env.platform.startswith("linux") else "run as an administrator or give the user access to the device")
        problems.append(Problem("error", "permission denied opening " + ", ".join(
            f"{d.name} ({d.usb_id} at {d.location})" for d in denied), fix, [d.usb_id for d in denied]))
    for d in known:
        if d.status == "open-failed":
            fix = ("bind the WinUSB driver to it with Zadig" if env.platform == "win32"
                   else "replug the device; close other programs using it")
            problems.append(Problem("error", f"cannot open {d.name} ({d.usb_id}): {d.error}", fix, [d.usb_id]))

    def ids(pred):
        return [d for d in known if d.known.primary and pred(d.known)]

    onis = ids(lambda k: k.driver == "openni2")
    if onis and env.openni2_library is None:
        problems.append(Problem("error", "OpenNI2 (libOpenNI2) is not installed; the openni2 driver needs it for "
                                + ", ".join(sorted({d.known.family for d in onis})),
                                "sudo apt install libopenni2-0", [d.usb_id for d in onis]))
    elif onis:
        drivers = [n.lower() for n in env.openni2_drivers]
        kin = ids(lambda k: k.family.startswith("Kinect") and k.driver == "openni2")
        if kin and not any("freenect" in n for n in drivers):
            problems.append(Problem(
                "error", f"OpenNI2 at {env.openni2_library} has no Kinect v1 driver (libFreenectDriver) among its "
                         f"drivers ({', '.join(env.openni2_drivers) or 'none'})",
                "build libfreenect (github.com/OpenKinect/libfreenect) with `cmake -DBUILD_OPENNI2_DRIVER=ON .. && "
                "make`, then `sudo cp lib/OpenNI2-FreenectDriver/libFreenectDriver.so* "
                f"{Path(env.openni2_library).parent / 'OpenNI2' / 'Drivers'}/`", [d.usb_id for d in kin]))
        ps = ids(lambda k: k.vendor_id == _PS)
        if ps and drivers and not any("ps1080" in n for n in drivers):
            problems.append(Problem("error", "OpenNI2 has no PrimeSense driver (libPS1080)",
                                    "sudo apt install --reinstall libopenni2-0", [d.usb_id for d in ps]))
        ob = ids(lambda k: k.vendor_id == _ORBBEC)
        if ob and not any("orbbec" in n for n in drivers):
            problems.append(Problem("warning", "OpenNI2 has no Orbbec driver; Debian's libopenni2-0 cannot open "
                                               "Orbbec cameras",
                                    "install Orbbec's OpenNI2 SDK and put its Drivers/liborbbec.so into "
                                    f"{Path(env.openni2_library).parent / 'OpenNI2' / 'Drivers'}",
                                    [d.usb_id for d in ob]))
    oaks = ids(lambda k: k.driver == "depthai")
    if oaks and env.depthai_version is None:
        problems.append(Problem("error", "the depthai Python package is not installed; the depthai driver needs it "
                                         "for the Luxonis OAK", f"{sys.executable} -m pip install 'depthai>=3.12,<4'",
                                [d.usb_id for d in oaks]))
    for d in ids(lambda k: k.driver == "azure-kinect-recording-only"):
        problems.append(Problem("info", f"{d.name} ({d.usb_id}): appfusion reads Azure Kinect recordings only; "
                                        "record with `k4arecorder -d NFOV_UNBINNED -c 720p -r 30 scan.mkv` "
                                        "and open scan.mkv", "", [d.usb_id]))
    for d in ids(lambda k: k.family.startswith("Kinect v2")):
        problems.append(Problem("info", f"{d.name} ({d.usb_id}) is not supported by appfusion", "", [d.usb_id]))
    return problems


def discover(backend=None, env: Environment | None = None, probe_open: bool = True, include_all: bool = False,
             sysfs_root: str | os.PathLike = "/sys/bus/usb/devices") -> Report:
    """List attached depth sensors, the appfusion driver of each, and problems with their fixes.

    Parameters
    ----------
    backend : usb.backend.IBackend, optional
        pyusb backend to enumerate with; by default the first of libusb1, libusb0, openusb that loads.
        Tests pass a custom backend presenting synthetic devices.
    env : Environment, optional
        Libraries found on the machine; by default :func:`probe_environment`.
    probe_open : bool, default True
        Open each recognised device once to find permission problems.
    include_all : bool, default False
        Also list USB devices that are not depth sensors.
    sysfs_root : path-like
        Where Linux lists USB devices; read only when no pyusb backend loads.

    Returns
    -------
    Report
    """
    name = "custom" if backend is not None else None
    if backend is None:
        backend, name = find_backend()
    if env is None:
        env = probe_environment(name)
    if backend is not None:
        devices = list_usb_devices(backend, probe_open=probe_open, include_all=include_all)
    else:
        devices = _sysfs_devices(Path(sysfs_root), include_all)
    return Report(devices, _diagnose(devices, env), env)


# ---------------------------------------------------------------------------------------------
# text output
# ---------------------------------------------------------------------------------------------
_STATUS_TEXT = {"ok": "ok", "no-permission": "PERMISSION DENIED", "open-failed": "CANNOT OPEN",
                "not-probed": "-"}


def format_table(report: Report) -> str:
    """A fixed-width table of the devices followed by problems and their fixes."""
    lines = []
    rows = [("BUS:ADDR", "USB ID", "DEVICE", "DRIVER", "SPEED", "STATUS", "SERIAL")]
    for d in report.devices:
        rows.append((d.location, d.usb_id, d.name, d.driver, d.speed or "-", _STATUS_TEXT.get(d.status, d.status),
                     d.serial or "-"))
    if len(rows) == 1:
        lines.append("No depth sensor found on USB (Kinect v1, PrimeSense/Xtion, Luxonis OAK, Orbbec, Azure Kinect).")
    else:
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        for r in rows:
            lines.append("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
        notes = [(d.usb_id, d.known.note) for d in report.devices if d.known and d.known.note]
        for uid, note in dict(notes).items():
            lines.append(f"  {uid}: {note}")
    env = report.environment
    lines.append("")
    lines.append(f"USB backend: {env.usb_backend or 'none'}; OpenNI2: {env.openni2_library or 'not found'}"
                 + (f" (drivers: {', '.join(env.openni2_drivers)})" if env.openni2_drivers else "")
                 + f"; depthai: {env.depthai_version or 'not installed'}")
    for p in report.problems:
        lines.append("")
        lines.append(f"{p.severity.upper()}: {p.what}")
        if p.fix:
            lines.append(f"  fix: {p.fix}")
    return "\n".join(lines)
