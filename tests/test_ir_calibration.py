"""IR calibration (paper §6): background, response curve, shifted-Gamma / flat emitter, profile I/O.

The calibration frames come from a small generator written here, independent of the library: a
fronto-parallel Lambertian sheet, the Kinect v1 emitter 7.5 cm beside the camera, incident intensity
``x = (t + 3.4) / (57.7 d)`` with ``t ~ Gamma(1.6, 2.8)`` a fixed random field over emitter directions,
``raw = gain * radiance^0.9 + b0 + noise``, rounded and clipped to 10 bits. The calibration must
estimate these parameters, never read them.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from appfusion.cli import main
from appfusion.errors import CalibrationError
from appfusion.frame import Frame, Intrinsics
from calibration.ir_background import estimate_background
from calibration.ir_profile import IRProfile
from calibration.ir_response import calibrate_ir

E = np.array([0.075, 0.0, 0.0])
INTR = Intrinsics(320, 240, 287.5, 287.5, 159.5, 119.5)
TRUE = dict(gamma=0.9, k=1.6, theta=2.8, shift=3.4, scale=57.7, b0=63.4, noise=1.5, gain=4500.0, albedo=0.9)


class Scanner:
    """Independent forward model of the Kinect v1 IR channel looking at a planar sheet."""

    def __init__(self, seed=0, flat=False, **over):
        self.p = dict(TRUE, **over)
        self.rng = np.random.default_rng(seed)
        self.flat = flat
        self.cell = np.radians(0.12)                     # resolution of the emitter's random field
        n = int(np.ceil(np.radians(80) / self.cell))
        self.field = self.rng.gamma(self.p["k"], self.p["theta"], size=(n, n))

    def t_at(self, dirs):
        ax = np.arctan2(dirs[..., 0], dirs[..., 2])
        ay = np.arctan2(dirs[..., 1], dirs[..., 2])
        n = self.field.shape[0]
        i = np.clip(((ay + np.radians(40)) / self.cell).astype(int), 0, n - 1)
        j = np.clip(((ax + np.radians(40)) / self.cell).astype(int), 0, n - 1)
        return self.field[i, j]

    def sheet(self, dist, emitter=True, tilt=0.0):
        p = self.p
        u, v = np.meshgrid(np.arange(INTR.width), np.arange(INTR.height))
        ray = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], -1)
        nrm = np.array([0.0, np.sin(tilt), -np.cos(tilt)])
        # plane n . X = n . (0, 0, dist)
        z = (nrm @ np.array([0, 0, dist])) / (ray @ nrm)
        P = ray * z[..., None]
        L = E - P
        d = np.linalg.norm(L, axis=-1)
        cos_i = (L @ nrm) / d
        if self.flat:
            x = 1.0 / (0.8 * d * d)
        else:
            x = (self.t_at(P - E) + p["shift"]) / (p["scale"] * d)
        rad = x * cos_i * p["albedo"] / np.pi if emitter else 0.0 * d
        raw = p["gain"] * np.power(rad, p["gamma"]) + p["b0"] + self.rng.normal(0, p["noise"], d.shape)
        ir = np.clip(np.round(raw), 0, 1023).astype(np.float32)
        depth = (z + self.rng.normal(0, 0.0005, z.shape)).astype(np.float32)
        return ir, depth

    def frames(self, dists=(0.5, 0.7, 0.9, 1.1, 1.3), n_off=6, per_dist=2):
        out = []
        i = 0
        for _ in range(n_off):
            ir, _ = self.sheet(1.0, emitter=False)
            out.append(Frame(i, i / 30, ir=ir, depth=None, ir_intrinsics=INTR, emitter=False,
                             pass_name="ir-calibration"))
            i += 1
        for dd in dists:
            for _ in range(per_dist):
                ir, depth = self.sheet(dd)
                out.append(Frame(i, i / 30, ir=ir, depth=depth, depth_intrinsics=INTR, ir_intrinsics=INTR,
                                 emitter=True, pass_name="ir-calibration"))
                i += 1
        return out


@pytest.fixture(scope="module")
def scanner():
    return Scanner(seed=1)


@pytest.fixture(scope="module")
def profile(scanner):
    return calibrate_ir(scanner.frames(), E, sheet_albedo=TRUE["albedo"])


def test_background_is_the_histogram_mode():
    rng = np.random.default_rng(3)
    frames = [np.round(41.3 + rng.normal(0, 2.0, (120, 160))) for _ in range(8)]
    frames[0][:10] = 900                      # a few hot pixels do not move the mode
    bg = estimate_background(frames)
    assert abs(bg.level - 41.3) < 0.3
    assert 1.6 < bg.noise_sigma < 2.6
    one = estimate_background(frames[:1])
    assert abs(one.level - 41.3) < 1.0


def test_background_errors():
    with pytest.raises(CalibrationError, match="no emitter-off"):
        estimate_background([])
    with pytest.raises(CalibrationError, match="shape"):
        estimate_background([np.zeros((4, 4)), np.zeros((5, 4))])
    with pytest.raises(CalibrationError, match="no finite"):
        estimate_background([np.full((4, 4), np.nan)])


def test_calibration_recovers_forward_model(profile):
    p = profile
    assert abs(p.background - TRUE["b0"]) < 1.0
    assert abs(p.gamma - TRUE["gamma"]) / TRUE["gamma"] < 0.02
    assert abs(p.k - TRUE["k"]) / TRUE["k"] < 0.15
    r_true = TRUE["shift"] / TRUE["theta"]
    assert abs(p.fit["shift_over_theta"] - r_true) / r_true < 0.15
    assert abs(p.k * p.theta + p.shift - 1.0) < 1e-9          # normalisation E[x](1 m) = 1
    assert abs(p.emitter_cv - np.sqrt(1.6) * 2.8 / (1.6 * 2.8 + 3.4)) < 0.05
    assert 1.0 < p.noise_sigma < 2.0


def test_apply_gives_the_sheet_brdf_at_new_distances(profile, scanner):
    """Samples of an unseen (tilted) sheet average to albedo / pi at any distance."""
    for dist in (0.6, 1.2):
        ir, depth = scanner.sheet(dist, tilt=np.radians(20))
        s = profile.apply_frame(ir, depth, INTR, E)
        core = s[20:-20, 20:-20]
        m = np.nanmean(core)
        assert abs(m * np.pi / TRUE["albedo"] - 1) < 0.015, (dist, m)


def test_profile_roundtrip_and_errors(profile, tmp_path):
    path = tmp_path / "p.json"
    profile.save(path)
    q = IRProfile.load(path)
    assert q == profile
    raw = np.array([100.0, 500.0, 1023.0, np.nan])
    s, ok = q.apply(raw, 0.8, 0.9)
    assert ok.tolist() == [True, True, False, False]
    assert s[1] > s[0] > 0
    d = json.loads(path.read_text())
    d["gamma"] = -1
    path.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match="positive"):
        IRProfile.load(path)
    path.write_text("{\n  \"gamma\": ")
    with pytest.raises(CalibrationError, match=r"p.json:2: not valid JSON"):
        IRProfile.load(path)
    d["gamma"] = 0.9
    d["bogus"] = 1
    path.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match="unknown field"):
        IRProfile.load(path)
    with pytest.raises(CalibrationError, match="emitter model"):
        IRProfile(emitter_model="laser")


def test_calibration_errors(scanner):
    fr = scanner.frames(dists=(0.6, 0.8), n_off=2, per_dist=1)
    with pytest.raises(CalibrationError, match="no emitter-off"):
        calibrate_ir([f for f in fr if f.emitter], E)
    with pytest.raises(CalibrationError, match="1 distance"):
        calibrate_ir([f for f in fr if f.index != 3], E)     # off frames + the sheet at 0.6 m only
    with pytest.raises(CalibrationError, match="no emitter-on"):
        calibrate_ir([f for f in fr if not f.emitter], E)
    with pytest.raises(CalibrationError, match="no frames"):
        calibrate_ir([], E)
    with pytest.raises(CalibrationError, match="unknown emitter model"):
        calibrate_ir(fr, E, model="laser")
    for bad in (0.0, float("nan")):
        with pytest.raises(CalibrationError, match="sheet albedo must be positive"):
            calibrate_ir(fr, E, sheet_albedo=bad)
        with pytest.raises(CalibrationError, match="saturation must be a positive raw IR level"):
            calibrate_ir(fr, E, saturation=bad - 1)


def test_flat_emitter_model():
    sc = Scanner(seed=2, flat=True, gain=600.0)
    p = calibrate_ir(sc.frames(n_off=3, per_dist=1), E, model="flat", sheet_albedo=TRUE["albedo"])
    assert p.emitter_model == "flat" and p.falloff_exponent == 2.0 and p.k is None
    assert abs(p.gamma - 0.9) < 0.018
    assert p.emitter_cv == 0.0
    ir, depth = sc.sheet(0.75)
    m = np.nanmean(p.apply_frame(ir, depth, INTR, E)[20:-20, 20:-20])
    assert abs(m * np.pi / TRUE["albedo"] - 1) < 0.01


def test_calibrate_command(tmp_path, scanner):
    from replay.session import SessionWriter

    sess = tmp_path / "calib"
    with SessionWriter(sess, device="synthetic-kinect1", intrinsics={"depth": INTR, "ir": INTR},
                       depth_to_ir=np.eye(4), depth_to_rgb=np.eye(4), emitter_position_m=tuple(E)) as w:
        w.event(0.0, "pass", "ir-calibration")
        for f in scanner.frames(dists=(0.5, 0.8, 1.1), n_off=3, per_dist=1):
            w.write(f)
    out = tmp_path / "profile.json"
    assert main(["calibrate", "ir", str(sess), "--out", str(out), "--sheet-albedo", "0.9"]) == 0
    p = IRProfile.load(out)
    assert abs(p.gamma - 0.9) < 0.03 and abs(p.background - TRUE["b0"]) < 1.0
    assert p.device == "synthetic-kinect1"
    assert main(["calibrate", "ir", str(tmp_path / "missing"), "--out", str(out)]) == 2
