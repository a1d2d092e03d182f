"""``appfusion calibrate``: device calibrations from recorded sessions.

``appfusion calibrate ir SESSION --out profile.json`` fits the IR background, response curve and
emitter model (paper §6) from the session's ``ir-calibration`` pass (emitter-off frames, then a white
sheet at several distances) and writes the device profile the IR pass uses (``calibration.ir_profile``).
"""

from __future__ import annotations

from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="calibrate a device from a recorded session",
                       description="Device calibrations computed from a recorded session.")
    what = p.add_subparsers(dest="what", metavar="WHAT")
    ir = what.add_parser("ir", help="IR background, response curve and emitter model (paper §6)",
                         description="Fit the IR background level (emitter-off frames), the response curve "
                                     "and the emitter's intensity model (white sheet at several distances) "
                                     "from the session's ir-calibration pass, and save a JSON device profile.")
    ir.add_argument("session", type=Path, help="session folder (replay.session format)")
    ir.add_argument("--out", type=Path, required=True, help="profile JSON to write")
    ir.add_argument("--model", choices=["shifted_gamma", "flat"], default=None,
                    help="emitter model: shifted_gamma (Kinect v1 dot pattern, default) or flat (flood light, "
                         "time of flight); default from the session's meta 'ir_emitter_model' if present")
    ir.add_argument("--sheet-albedo", type=float, default=1.0,
                    help="IR albedo of the white sheet (default 1: reflectances relative to the sheet)")
    ir.add_argument("--pass", dest="pass_name", default="ir-calibration",
                    help="name of the pass holding the calibration frames (default ir-calibration)")
    ir.add_argument("--saturation", type=float, default=1023.0, help="raw IR level where the sensor clips")
    ir.set_defaults(func=run_ir)
    p.set_defaults(func=lambda args: (p.print_help(), 1)[1])


def run_ir(args) -> int:
    from appfusion.errors import CalibrationError, PassMissingError
    from calibration.ir_response import calibrate_ir
    from replay.session import SessionReader

    if not args.session.exists():
        raise CalibrationError(f"{args.session}: no such session folder")
    reader = SessionReader(args.session)
    meta = reader.meta
    model = args.model or meta.get("extra", {}).get("ir_emitter_model") or "shifted_gamma"
    with reader:
        frames = (f for f in reader if f.pass_name == args.pass_name)
        try:
            profile = calibrate_ir(frames, meta.get("emitter_position_m"), model=model,
                                   sheet_albedo=args.sheet_albedo, device=str(meta.get("device", "")),
                                   saturation=args.saturation)
        except CalibrationError as e:
            if "no frames" in str(e):
                raise PassMissingError(f"{args.session}: no frames in pass {args.pass_name!r}") from None
            raise CalibrationError(f"{args.session}: {e}") from None
    profile.save(args.out)
    print(f"IR profile ({profile.emitter_model}): background {profile.background:.2f} counts "
          f"(noise {profile.noise_sigma:.2f}), gamma {profile.gamma:.4f}, gain {profile.gain:.4g}"
          + (f", k {profile.k:.3f}, shift/theta {profile.shift / profile.theta:.3f}"
             if profile.emitter_model == "shifted_gamma" else ""))
    pat = profile.fit.get("pattern")
    if pat:
        from calibration.ir_pattern import describe

        print(f"emitter pattern map: {describe(pat)}; "
              + (f"wrote {profile.pattern_file} beside the profile" if pat["used"] else
                 "not kept: it does not predict held-out distances well enough"))
    print(f"wrote {args.out}")
    return 0
