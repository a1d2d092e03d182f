"""``appfusion devices``: list attached depth sensors, the driver serving each, and fixes for problems."""

from __future__ import annotations

import json
import sys


def register(sub) -> None:
    p = sub.add_parser(
        "devices", help="list attached depth sensors and diagnose USB, permission and library problems",
        description="Lists the depth sensors on USB (Kinect v1, PrimeSense/Asus Xtion, Luxonis OAK, Orbbec, "
                    "Azure Kinect) by vendor:product id, says which appfusion driver serves each (openni2, "
                    "depthai, azure-kinect-recording-only, none), opens each once to check permissions, and "
                    "prints the command that fixes each problem found. Exit status 1 when a problem is an error.")
    p.add_argument("--json", action="store_true", help="print the report as JSON (for machines)")
    p.add_argument("--all", action="store_true", help="also list USB devices that are not depth sensors")
    p.add_argument("--no-open", action="store_true",
                   help="do not open devices (skips the permission check and serial numbers)")
    p.add_argument("--udev-rules", action="store_true",
                   help="print where the shipped udev rules are and the command that installs them")
    p.set_defaults(func=run)


def run(args) -> int:
    from drivers.usb_discovery import discover, format_table, udev_install_command, udev_rules_path

    if args.udev_rules:
        print(f"udev rules: {udev_rules_path()}")
        print(f"install:    {udev_install_command()}")
        print("then unplug and replug the sensor")
        return 0
    report = discover(probe_open=not args.no_open, include_all=args.all)
    if args.json:
        json.dump(report.to_json(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_table(report))
    return 0 if report.ok else 1
