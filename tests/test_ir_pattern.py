"""The IR emitter's pattern map (calibration.ir_pattern): calibrated from the white sheet, kept only
when it predicts held-out distances, divided out of IR samples, saved beside the profile."""

from __future__ import annotations

import numpy as np
import pytest

from appfusion.errors import AppFusionError, CalibrationError
from calibration.ir_pattern import EmitterPattern, estimate_pattern
from calibration.ir_profile import IRProfile
from calibration.ir_response import calibrate_ir
from test_ir_calibration import E, INTR, TRUE, Scanner


class GridScanner(Scanner):
    """The same sheet scanner with a pattern the camera resolves: a field smooth over ~1.5 cells on a
    grid in emitter directions (tangent plane) with the camera's pixel pitch, offset from the pixels
    by a fraction of a cell (as the synthetic scanner's emitter)."""

    def __init__(self, seed=0, **over):
        super().__init__(seed, **over)
        from scipy.ndimage import gaussian_filter
        from scipy.special import gammaincinv, ndtr

        self.gcell = 1.0 / INTR.fx
        g = gaussian_filter(self.rng.standard_normal((400, 500)), 1.5, mode="wrap")
        g /= g.std()
        self.field = gammaincinv(self.p["k"], ndtr(g)) * self.p["theta"]

    def t_at(self, dirs):
        u = dirs[..., 0] / dirs[..., 2] / self.gcell - 0.37
        v = dirs[..., 1] / dirs[..., 2] / self.gcell - 0.29
        i = np.clip(np.rint(v).astype(int) + 200, 0, 399)
        j = np.clip(np.rint(u).astype(int) + 250, 0, 499)
        return self.field[i, j]


@pytest.fixture(scope="module")
def grid_scanner():
    return GridScanner(seed=4)


@pytest.fixture(scope="module")
def grid_profile(grid_scanner):
    return calibrate_ir(grid_scanner.frames(dists=(0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2), per_dist=2), E,
                        sheet_albedo=TRUE["albedo"])


def _spread(x):
    x = x[np.isfinite(x)]
    return float(np.std(x) / np.mean(x)), float(np.mean(x))


def test_a_resolved_pattern_is_mapped_and_divided_out(grid_profile, grid_scanner):
    st = grid_profile.fit["pattern"]
    assert st["used"] and grid_profile.pattern is not None
    assert st["lambda"] >= 0.8 and st["coverage"] > 0.9
    assert st["heldout_cv"] < 0.35 * st["heldout_cv_without"], st
    # an unseen tilted sheet between the calibration distances: the samples' spread falls from the
    # pattern's ~45 % to a fraction of it, and their mean stays the sheet's BRDF
    for dist in (0.65, 1.05):
        ir, depth = grid_scanner.sheet(dist, tilt=np.radians(15))
        with_map = grid_profile.apply_frame(ir, depth, INTR, E)[20:-20, 20:-20]
        pat, grid_profile.pattern = grid_profile.pattern, None
        try:
            without = grid_profile.apply_frame(ir, depth, INTR, E)[20:-20, 20:-20]
        finally:
            grid_profile.pattern = pat
        cv_with, m_with = _spread(with_map)
        cv_without, _ = _spread(without)
        assert cv_without > 0.35 and cv_with < 0.3 * cv_without, (dist, cv_with, cv_without)
        assert abs(m_with * np.pi / TRUE["albedo"] - 1) < 0.02, (dist, m_with)


def test_a_pattern_finer_than_the_pixels_is_not_kept():
    """The default test scanner's field has cells of 0.12 degrees, 0.6 pixel: no map predicts it."""
    prof = calibrate_ir(Scanner(seed=1).frames(), E, sheet_albedo=TRUE["albedo"])
    st = prof.fit["pattern"]
    assert not st["used"] and prof.pattern is None
    assert st["heldout_cv"] > 0.5 * st["heldout_cv_without"]
    off = calibrate_ir(Scanner(seed=1).frames(), E, sheet_albedo=TRUE["albedo"], pattern=False)
    assert off.pattern is None and "pattern" not in off.fit


def test_profile_saves_its_pattern_beside_it(grid_profile, tmp_path):
    path = tmp_path / "dev" / "kinect.json"
    grid_profile.save(path)
    assert (tmp_path / "dev" / "kinect.pattern.npz").exists()
    back = IRProfile.load(path)
    assert back.pattern_file == "kinect.pattern.npz"
    assert np.array_equal(back.pattern.values, grid_profile.pattern.values)
    assert back.pattern.cell == grid_profile.pattern.cell and back.pattern.origin == grid_profile.pattern.origin
    (tmp_path / "dev" / "kinect.pattern.npz").unlink()
    with pytest.raises(CalibrationError, match="kinect.pattern.npz.*not found"):
        IRProfile.load(path)
    good = (tmp_path / "dev" / "kinect.pattern.npz")
    grid_profile.save(path)
    data = good.read_bytes()
    for bad in (b"not a zip", data[: len(data) // 2]):          # garbage, a truncated copy
        good.write_bytes(bad)
        with pytest.raises(CalibrationError, match="kinect.pattern.npz: not a valid emitter pattern"):
            IRProfile.load(path)


def test_lookup_outside_the_map_and_bad_maps():
    pat = EmitterPattern(np.full((3, 4), 2.0), np.ones((3, 4), np.uint16), 0.01, (1.5, 1.0))
    assert pat.lookup(np.array([0.0, 5.0]), np.array([0.0, 0.0])).tolist() == [2.0, 1.0]
    # every way off the map, non-finite directions included, reads 1; the shape is kept
    u = np.array([[-0.03, 0.03, np.nan, np.inf], [-np.inf, 0.0, 0.0, 0.0]])
    v = np.array([[0.0, 0.0, 0.0, 0.0], [0.0, -0.02, 0.02, np.nan]])
    assert pat.lookup(u, v).tolist() == [[1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]]
    # inside, the cell of cells(): a map of distinct values, directions away from cell boundaries
    rng = np.random.default_rng(3)
    big = EmitterPattern(rng.uniform(0.5, 1.5, (40, 60)), np.ones((40, 60), np.uint16), 0.01, (30.2, 19.7))
    uu, vv = rng.uniform(-0.35, 0.35, 5000), rng.uniform(-0.25, 0.25, 5000)
    row, col = big.cells(uu, vv)
    ok = (np.abs(uu / 0.01 + 30.2 - np.round(uu / 0.01 + 30.2)) < 0.49) & (np.abs(vv / 0.01 + 19.7 - np.round(vv / 0.01 + 19.7)) < 0.49)
    ins = (row >= 0) & (row < 40) & (col >= 0) & (col < 60)
    ref = np.where(ins, big.values[np.clip(row, 0, 39), np.clip(col, 0, 59)], 1.0)
    assert ins.any() and (~ins).any()
    np.testing.assert_array_equal(big.lookup(uu, vv)[ok], ref[ok])
    P = np.array([[0.075, 0.0, 0.5], [0.0, 0.0, np.nan]])
    assert pat.lookup_points(P, E).tolist() == [2.0, 1.0]
    with pytest.raises(CalibrationError, match="positive"):
        EmitterPattern(np.zeros((2, 2)), np.ones((2, 2)), 0.01)
    with pytest.raises(CalibrationError, match="same shape"):
        EmitterPattern(np.ones((2, 2)), np.ones((3, 2)), 0.01)
    with pytest.raises(CalibrationError, match="cell size"):
        EmitterPattern(np.ones((2, 2)), np.ones((2, 2)), -1.0)
    with pytest.raises(CalibrationError, match="usable"):
        estimate_pattern(np.zeros((10, 2)), np.ones(10), np.zeros(10, int), 0.01)
    with pytest.raises(CalibrationError, match="too large"):
        estimate_pattern(np.array([[0.0, 0.0], [10.0, 0.0]] * 60), np.ones(120), np.arange(120) % 2, 1e-4)


def test_ir_pass_divides_the_pattern_and_checks_it():
    """add_samples takes the pattern values; clipped samples stay out of the texel means."""
    from appfusion.hbsab import CH_SAT, CH_W, CH_WV
    from appfusion.ir_pass import IRPass

    rng = np.random.default_rng(2)
    P = rng.normal(size=(512, 3))
    P /= np.linalg.norm(P, axis=1, keepdims=True)
    N = P.copy()
    P *= 0.05
    prof = IRProfile(emitter_model="shifted_gamma", background=0.0, gamma=1.0, gain=100.0, k=1.6,
                     theta=0.355, shift=0.431, saturation=1000.0)
    plain = IRPass(P, N, prof, min_leaf=64)
    prof.pattern = EmitterPattern(np.ones((2, 2)), np.ones((2, 2), np.uint16), 0.01)
    ip = IRPass(P, N, prof, min_leaf=64)
    assert ip.cut.emitter[0] == "pattern" and plain.cut.emitter[0] != "pattern"
    cam = np.array([0.0, 0.0, 0.6])
    idx = np.flatnonzero(P[:, 2] > 0.03)
    raw = np.full(len(idx), 200.0)
    raw[:5] = 1000.0                                   # clipped
    em = cam + [0.075, 0, 0]
    plain.add_samples(idx, P[idx], cam, em, raw)
    ip.add_samples(idx, P[idx], cam, em, raw, pattern=np.full(len(idx), 2.0))
    a, b = plain.cut.leaves.data.astype(float), ip.cut.leaves.data.astype(float)
    assert ip.stats["saturated"] == plain.stats["saturated"] == 5
    assert np.isclose(a[CH_SAT].sum(), b[CH_SAT].sum()) and b[CH_SAT].sum() > 0
    # clipped samples: in the plain pass's means, out of the pattern pass's (their weight is WSAT)
    assert np.isclose(b[CH_W].sum(), a[CH_W].sum() - a[CH_SAT].sum(), rtol=1e-5)
    unclipped = (a[CH_SAT] == 0) & (a[CH_W] > 0)
    assert np.allclose(b[CH_WV][unclipped], a[CH_WV][unclipped] / 2.0, rtol=1e-5)   # divided by 2
    with pytest.raises(AppFusionError, match="pattern"):
        ip.add_samples(idx, P[idx], cam, em, raw, pattern=np.zeros(len(idx)))


def test_calibrate_command_writes_the_pattern_beside_the_profile(tmp_path, grid_scanner, capsys):
    from appfusion.cli import main
    from replay.session import SessionWriter

    sess = tmp_path / "calib"
    with SessionWriter(sess, device="synthetic-kinect1", intrinsics={"depth": INTR, "ir": INTR},
                       depth_to_ir=np.eye(4), depth_to_rgb=np.eye(4), emitter_position_m=tuple(E)) as w:
        w.event(0.0, "pass", "ir-calibration")
        for f in grid_scanner.frames(dists=(0.5, 0.6, 0.7, 0.8, 0.9, 1.0), n_off=3, per_dist=1):
            w.write(f)
    out = tmp_path / "dev" / "profile.json"
    assert main(["calibrate", "ir", str(sess), "--out", str(out), "--sheet-albedo", "0.9"]) == 0
    said = capsys.readouterr().out
    assert "emitter pattern map" in said and "profile.pattern.npz" in said, said
    p = IRProfile.load(out)
    assert p.pattern is not None and p.fit["pattern"]["used"]
