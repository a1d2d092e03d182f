"""Tests of drivers.usb_discovery and ``appfusion devices`` with a synthetic pyusb backend (no hardware)."""

from __future__ import annotations

import array
import errno
import json
import re
from types import SimpleNamespace

import pytest
import usb.backend
import usb.core

from appfusion import cli
from drivers import usb_discovery as ud
from drivers.usb_discovery import Environment, KNOWN_DEVICES, discover, format_table, identify


class FakeBackend(usb.backend.IBackend):
    """A pyusb backend presenting synthetic devices.

    Each device is a dict: vid, pid, bus, address, optional serial (str), speed (pyusb code),
    open_error (a USBError to raise from open_device).
    """

    def __init__(self, devices):
        super().__init__()
        self.devices = [SimpleNamespace(**d) for d in devices]
        self.opened, self.closed = [], []

    def enumerate_devices(self):
        return iter(self.devices)

    def get_device_descriptor(self, dev):
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0, bDeviceProtocol=0,
            bMaxPacketSize0=64, idVendor=dev.vid, idProduct=dev.pid, bcdDevice=0x0100, iManufacturer=0,
            iProduct=0, iSerialNumber=3 if getattr(dev, "serial", None) else 0, bNumConfigurations=1,
            address=dev.address, bus=dev.bus, port_number=1, port_numbers=(1,), speed=getattr(dev, "speed", 3))

    def open_device(self, dev):
        err = getattr(dev, "open_error", None)
        if err is not None:
            raise err
        self.opened.append((dev.vid, dev.pid))
        return dev

    def close_device(self, dev_handle):
        self.closed.append((dev_handle.vid, dev_handle.pid))

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        # GET_DESCRIPTOR (6) of a string (type 3): index 0 lists LANGIDs, others hold UTF-16LE text
        assert bRequest == 6 and wValue >> 8 == 3, "only string descriptors are read"
        if wValue & 0xFF == 0:
            desc = bytes([4, 3, 0x09, 0x04])
        else:
            text = dev_handle.serial.encode("utf-16-le")
            desc = bytes([2 + len(text), 3]) + text
        n = min(len(desc), len(data))
        data[:n] = array.array("B", desc[:n])
        return n


DENIED = usb.core.USBError("Access denied (insufficient permissions)", -3, errno.EACCES)
BROKEN = usb.core.USBError("Input/Output Error", -1, errno.EIO)

ALL_OK_ENV = Environment(usb_backend="custom", openni2_library="/usr/lib/x86_64-linux-gnu/libOpenNI2.so.0",
                         openni2_drivers=["libFreenectDriver.so", "libPS1080.so.0", "liborbbec.so"],
                         depthai_version="3.12.0", platform="linux")


def _env(**changes) -> Environment:
    return Environment(**{**ALL_OK_ENV.__dict__, **changes})


def _zoo():
    return FakeBackend([
        dict(vid=0x045E, pid=0x02AE, bus=1, address=5, serial="A00366911191046A"),  # Kinect v1 camera
        dict(vid=0x045E, pid=0x02AD, bus=1, address=6),                              # its audio
        dict(vid=0x045E, pid=0x02B0, bus=1, address=4),                              # its motor
        dict(vid=0x1D27, pid=0x0601, bus=2, address=3, open_error=DENIED),           # Xtion, no permission
        dict(vid=0x03E7, pid=0x2485, bus=2, address=9, speed=4),                     # OAK, unbooted
        dict(vid=0x2BC5, pid=0x0401, bus=3, address=2),                              # Orbbec Astra
        dict(vid=0x045E, pid=0x097C, bus=4, address=7, speed=4),                     # Azure Kinect depth
        dict(vid=0x045E, pid=0x097D, bus=4, address=8, speed=4),                     # Azure Kinect colour
        dict(vid=0x046D, pid=0xC077, bus=1, address=2),                              # a mouse
    ])


def test_identify_table():
    assert identify(0x045E, 0x02AE).family == "Kinect v1" and identify(0x045E, 0x02AE).driver == "openni2"
    assert identify(0x045E, 0x02BF).driver == "openni2"
    assert identify(0x045E, 0x02B0).driver == "none" and not identify(0x045E, 0x02B0).primary
    for pid in (0x0600, 0x0601, 0x0609):
        assert identify(0x1D27, pid).driver == "openni2"
    assert identify(0x03E7, 0x2485).driver == identify(0x03E7, 0xF63B).driver == "depthai"
    assert identify(0x2BC5, 0x0401).family == "Orbbec" and identify(0x2BC5, 0x0660).driver == "openni2"
    assert identify(0x045E, 0x097C).driver == "azure-kinect-recording-only"
    assert identify(0x045E, 0x097D).part == "colour camera"
    assert identify(0x045E, 0x097A).driver == "none"
    assert identify(0x046D, 0xC077) is None and identify(0x045E, 0x0040) is None  # mouse, Microsoft mouse
    assert all(k.driver in ud.DRIVERS for k in KNOWN_DEVICES)
    assert len({(k.vendor_id, k.product_id) for k in KNOWN_DEVICES}) == len(KNOWN_DEVICES)


def test_discover_lists_drivers_and_permission_problem():
    backend = _zoo()
    report = discover(backend=backend, env=ALL_OK_ENV)
    by_id = {d.usb_id: d for d in report.devices}
    assert "046d:c077" not in by_id and len(report.devices) == 8
    assert by_id["045e:02ae"].driver == "openni2" and by_id["045e:02ae"].serial == "A00366911191046A"
    assert by_id["045e:02ae"].status == "ok" and by_id["045e:02ae"].location == "001:005"
    assert by_id["1d27:0601"].status == "no-permission"
    assert by_id["03e7:2485"].driver == "depthai" and by_id["03e7:2485"].speed == "5 Gb/s"
    assert by_id["2bc5:0401"].driver == "openni2"
    assert by_id["045e:097c"].driver == "azure-kinect-recording-only"
    assert [d.bus for d in report.devices] == sorted(d.bus for d in report.devices)
    # every device that was opened was closed again; the mouse was never touched
    assert sorted(backend.opened) == sorted(backend.closed)
    assert (0x046D, 0xC077) not in backend.opened
    errors = [p for p in report.problems if p.severity == "error"]
    assert len(errors) == 1 and not report.ok
    perm = errors[0]
    assert "permission denied" in perm.what and "1d27:0601" in perm.what and perm.devices == ["1d27:0601"]
    assert f"sudo install -m 0644 {ud.udev_rules_path()} /etc/udev/rules.d/99-appfusion.rules" in perm.fix
    assert "udevadm control --reload-rules" in perm.fix and "udevadm trigger" in perm.fix
    infos = [p for p in report.problems if p.severity == "info"]
    assert any("k4arecorder" in p.what and p.devices == ["045e:097c"] for p in infos)
    text = format_table(report)
    assert "PERMISSION DENIED" in text and "azure-kinect-recording-only" in text and "depthai" in text
    assert "fix: sudo install" in text
    js = report.to_json()
    assert json.loads(json.dumps(js)) == js and js["ok"] is False


def test_include_all_and_no_open():
    backend = _zoo()
    report = discover(backend=backend, env=ALL_OK_ENV, include_all=True, probe_open=False)
    assert len(report.devices) == 9
    mouse = next(d for d in report.devices if d.usb_id == "046d:c077")
    assert mouse.known is None and mouse.driver == "none"
    assert backend.opened == [] and all(d.status == "not-probed" for d in report.devices)
    assert report.ok  # nothing was opened, so no permission problem can be known


def test_missing_libraries():
    backend = _zoo()
    report = discover(backend=backend, env=_env(openni2_library=None, openni2_drivers=[], depthai_version=None))
    fixes = {p.fix for p in report.problems if p.severity == "error"}
    assert "sudo apt install libopenni2-0" in fixes
    oni = next(p for p in report.problems if p.fix == "sudo apt install libopenni2-0")
    assert set(oni.devices) == {"045e:02ae", "1d27:0601", "2bc5:0401"}  # cameras only, not audio/motor
    dai = next(p for p in report.problems if "depthai" in p.what)
    assert "pip install 'depthai" in dai.fix and dai.devices == ["03e7:2485"]


def test_openni2_without_the_right_drivers():
    backend = _zoo()
    env = _env(openni2_drivers=["libDummyDevice.so.0", "libOniFile.so.0", "libPS1080.so.0", "libPSLink.so.0"])
    report = discover(backend=backend, env=env)
    kin = next(p for p in report.problems if "Kinect v1 driver" in p.what)
    assert kin.severity == "error" and kin.devices == ["045e:02ae"]
    assert "BUILD_OPENNI2_DRIVER=ON" in kin.fix and "/usr/lib/x86_64-linux-gnu/OpenNI2/Drivers" in kin.fix
    orb = next(p for p in report.problems if "Orbbec" in p.what)
    assert orb.severity == "warning" and orb.devices == ["2bc5:0401"]
    assert not any("PrimeSense driver" in p.what for p in report.problems)


def test_all_good_single_oak():
    backend = FakeBackend([dict(vid=0x03E7, pid=0xF63B, bus=1, address=3, serial="14442C10D13EABCE00")])
    report = discover(backend=backend, env=ALL_OK_ENV)
    assert report.ok and report.problems == []
    (d,) = report.devices
    assert (d.name, d.driver, d.status, d.serial) == ("Luxonis OAK camera (booted)", "depthai", "ok", "14442C10D13EABCE00")


def test_other_open_error():
    backend = FakeBackend([dict(vid=0x1D27, pid=0x0609, bus=1, address=3, open_error=BROKEN)])
    report = discover(backend=backend, env=ALL_OK_ENV)
    assert report.devices[0].status == "open-failed"
    p = next(p for p in report.problems if p.severity == "error")
    assert "Input/Output Error" in p.what and "replug" in p.fix


def test_no_backend_falls_back_to_sysfs(tmp_path, monkeypatch):
    monkeypatch.setattr(ud, "find_backend", lambda: (None, None))
    dev = tmp_path / "2-1"
    dev.mkdir()
    for name, value in (("idVendor", "045e"), ("idProduct", "02ae"), ("busnum", "2"), ("devnum", "7"),
                        ("serial", "A00366911191046A"), ("speed", "480")):
        (dev / name).write_text(value + "\n")
    (tmp_path / "2-1:1.0").mkdir()  # an interface entry: no ids
    report = discover(env=_env(usb_backend=None), sysfs_root=tmp_path)
    (d,) = report.devices
    assert (d.usb_id, d.location, d.serial, d.status) == ("045e:02ae", "002:007", "A00366911191046A", "not-probed")
    p = report.problems[0]
    assert p.severity == "error" and "no libusb backend" in p.what and p.fix == "sudo apt install libusb-1.0-0"


def test_udev_rules_cover_every_known_device():
    text = ud.udev_rules_path().read_text()
    rules = [line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    exact, vendor_wide = set(), set()
    for line in rules:
        if "GOTO" in line or line.startswith("LABEL"):
            continue
        assert re.fullmatch(r'ATTRS\{idVendor\}=="[0-9a-f]{4}"(, ATTRS\{idProduct\}=="[0-9a-f]{4}")?, '
                            r'MODE="0666", TAG\+="uaccess"', line), line
        vid = line.split('"')[1]
        if "idProduct" in line:
            exact.add((vid, line.split('"')[3]))
        else:
            vendor_wide.add(vid)
    for k in KNOWN_DEVICES:
        vid = f"{k.vendor_id:04x}"
        assert vid in vendor_wide or (k.product_id is not None and (vid, f"{k.product_id:04x}") in exact), k
    assert 'SUBSYSTEM!="usb", GOTO="appfusion_end"' in text and 'LABEL="appfusion_end"' in text
    assert "udevadm control --reload-rules" in text


def test_find_openni2(tmp_path):
    assert ud.find_openni2([tmp_path]) == (None, [])
    (tmp_path / "libOpenNI2.so.0").write_bytes(b"")
    (tmp_path / "OpenNI2" / "Drivers").mkdir(parents=True)
    (tmp_path / "OpenNI2" / "Drivers" / "libPS1080.so.0").write_bytes(b"")
    lib, drivers = ud.find_openni2([tmp_path / "missing", tmp_path])
    assert lib == str(tmp_path / "libOpenNI2.so.0") and drivers == ["libPS1080.so.0"]


def test_cli_devices(monkeypatch, capsys):
    real = ud.discover
    monkeypatch.setattr(ud, "discover", lambda **kw: real(backend=_zoo(), env=ALL_OK_ENV, **kw))
    assert cli.main(["devices", "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert {d["usb_id"] for d in out["devices"]} >= {"045e:02ae", "1d27:0601", "03e7:2485"}
    assert out["ok"] is False and any("udevadm" in p["fix"] for p in out["problems"])
    assert cli.main(["devices"]) == 1
    text = capsys.readouterr().out
    assert text.splitlines()[0].split()[:3] == ["BUS:ADDR", "USB", "ID"] and "PERMISSION DENIED" in text
    assert cli.main(["devices", "--no-open"]) == 0
    capsys.readouterr()
    assert cli.main(["devices", "--udev-rules"]) == 0
    assert str(ud.udev_rules_path()) in capsys.readouterr().out
