"""The bench runner (JSON contract, budgets, failing stages, sweeps), the Pareto analysis and plot, and the
numerical-stability stage (appfusion/bench)."""

from __future__ import annotations

import json
import math
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appfusion.bench import METRICS
from appfusion.bench.pareto import BenchError, default_on_front, pareto_front, plot_sweeps, validate_sweep
from appfusion.bench.runner import BenchContext, format_stage_table, format_table, run_bench, write_json


def _pts(*te, values=None):
    values = values or list(range(len(te)))
    return [{"value": v, "ms_per_frame": t, "error": e} for v, (t, e) in zip(values, te)]


def _sweep(points, default):
    return validate_sweep("k", {"metric": "err", "default": default, "points": points})


# -- Pareto front -------------------------------------------------------------------------------

def test_pareto_front_hand_made():
    pts = _pts((10, 1.0), (20, 0.5), (30, 0.6), (40, 0.1), (15, 1.2), (20, 0.5), (50, 0.1), (5, None))
    # (30, 0.6) by (20, 0.5); (15, 1.2) by (10, 1.0); (50, 0.1) by (40, 0.1); None: failed, never on it;
    # the two equal (20, 0.5) points both stay
    assert pareto_front(pts) == [0, 1, 5, 3]
    assert pareto_front(_pts((1, 2.0))) == [0]
    assert pareto_front(_pts((1, None))) == []
    # same time: only the lower error survives
    assert pareto_front(_pts((10, 0.3), (10, 0.2), (12, 0.1))) == [1, 2]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 30), st.integers(0, 30)), min_size=1, max_size=25))
def test_pareto_front_properties(te):
    """Front points dominate each other nowhere; every other point is dominated by a front point."""
    pts = _pts(*[(float(t), float(e)) for t, e in te])
    front = pareto_front(pts)
    dom = lambda a, b: a[0] <= b[0] and a[1] <= b[1] and a != b  # noqa: E731
    for i in front:
        assert not any(dom(te[j], te[i]) for j in range(len(te)))
    for i in set(range(len(te))) - set(front):
        assert any(dom(te[j], te[i]) for j in front)


def test_default_on_front_true_false_and_tolerance():
    pts = _pts((10, 1.0), (20, 0.5), (30, 0.6), (40, 0.1), values=[8, 16, 24, 32])
    assert default_on_front(_sweep(pts, 16)) is True
    assert default_on_front(_sweep(pts, 32)) is True          # slowest but most accurate
    assert default_on_front(_sweep(pts, 24)) is False         # 16 is faster and more accurate
    # within timing noise: a point 5 % faster with the same error does not knock the default off ...
    near = _pts((20, 0.5), (21, 0.5), values=["a", "b"])
    assert default_on_front(_sweep(near, "b")) is True
    assert default_on_front(_sweep(near, "b"), time_tol=0.0) is False
    # ... one 15 % faster does
    far = _pts((17, 0.5), (20, 0.5), values=["a", "b"])
    assert default_on_front(_sweep(far, "b")) is False
    # a point more accurate but not clearly faster leaves it on (benefit of the doubt)
    assert default_on_front(_sweep(_pts((19.5, 0.1), (20, 0.5), values=["a", "b"]), "b")) is True
    # default not measured, or failed
    assert default_on_front(_sweep(pts, 99)) is None
    assert default_on_front(_sweep(_pts((1, None), (2, 0.1), values=[1, 2]), 1)) is None


def test_validate_sweep_names_what_is_wrong():
    with pytest.raises(BenchError, match="'n'.*lacks points"):
        validate_sweep("n", {"metric": "e", "default": 1})
    with pytest.raises(BenchError, match="point 1 .*ms_per_frame"):
        validate_sweep("n", {"metric": "e", "default": 1, "points": _pts((1, 0.1), (float("nan"), 0.1))})
    with pytest.raises(BenchError, match="error must be"):
        validate_sweep("n", {"metric": "e", "default": 1, "points": _pts((1, -0.1))})
    with pytest.raises(BenchError, match="value must be"):
        validate_sweep("n", {"metric": "e", "default": 1, "points": [{"value": [1], "ms_per_frame": 1, "error": 0}]})
    sw = validate_sweep("n", {"metric": "e", "default": np.int64(2),
                              "points": [{"value": np.int64(2), "ms_per_frame": np.float32(1.5), "error": np.float64(0.1)}]})
    assert sw["default"] == 2 and type(sw["points"][0]["value"]) is int and sw["points"][0]["ms_per_frame"] == 1.5


def test_add_sweep_checks_default_and_duplicates(tmp_path):
    ctx = BenchContext(workdir=tmp_path, stage="s")
    ctx.add_sweep("n", "err", 2, _pts((1, 0.2), (2, 0.1), values=[1, 2]))
    assert ctx.extra["sweeps"]["n"]["default"] == 2
    with pytest.raises(BenchError, match="already reported"):
        ctx.add_sweep("n", "err", 2, _pts((1, 0.2), (2, 0.1), values=[1, 2]))
    with pytest.raises(BenchError, match="default 3 is not among"):
        ctx.add_sweep("m", "err", 3, _pts((1, 0.2), values=[1]))


def test_pareto_plot_is_a_png(tmp_path):
    sweeps = {"a": _sweep(_pts((10, 1.0), (20, 0.01), (30, 0.02), values=[1, 2, 3]), 2),
              "b": {**_sweep(_pts((1, 0.5), (2, None), values=["x", "y"]), "x"), "stage": "fake"}}
    out = plot_sweeps(sweeps, tmp_path / "sub" / "p.png", title="t")
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    import cv2
    img = cv2.imread(str(out))
    assert img.shape[1] > img.shape[0] > 300                     # two subplots side by side
    with pytest.raises(BenchError, match="no sweeps"):
        plot_sweeps({}, tmp_path / "q.png")


# -- the runner ------------------------------------------------------------------------------------

@pytest.fixture
def fake_stages(monkeypatch):
    """Installs stage modules appfusion.bench.stages.{good,boom,alien,slow,nan} for the runner to import."""
    def add(name, run, budget=None):
        mod = types.ModuleType(f"appfusion.bench.stages.{name}")
        mod.run = run
        if budget is not None:
            mod.BUDGET_S = budget
        monkeypatch.setitem(sys.modules, mod.__name__, mod)

    def good(ctx):
        assert ctx.quick and ctx.budget_s == 7.0 and ctx.stage == "good" and ctx.time_left() <= 7.0
        ctx.extra["good"] = {"note": np.float64(1.5), "arr": np.arange(3)}
        ctx.add_sweep("knob", "white_err", 2, _pts((1.0, 0.3), (2.0, 0.1), (3.0, 0.2), values=[1, 2, 3]))
        ctx.note("white_err", "measured on a fake stage")
        with pytest.raises(BenchError, match="unknown metric 'nonsense'"):
            ctx.note("nonsense", "x")
        return {"white_err": np.float32(0.004), "ate_mm": 3}

    def boom(ctx):
        ctx.note("ate_mm", "from the failing stage")
        ctx.add_sweep("half", "e", 1, _pts((1.0, 0.3), values=[1]))
        raise RuntimeError("synthetic failure")

    def slow(ctx):
        time.sleep(0.05)
        return {}

    add("good", good, (7.0, 70.0))
    add("boom", boom)
    add("alien", lambda ctx: {"not_a_metric": 1.0})
    add("slow", slow, (0.01, 0.01))
    add("nan", lambda ctx: {"chamfer_mm": float("nan")})


def test_json_contract_and_failing_stage(tmp_path, fake_stages, monkeypatch):
    import appfusion.bench.runner as R

    # every real stage exists now: a listed stage without a module is reported as "not built yet"
    monkeypatch.setattr(R, "STAGES", R.STAGES + ["notyet"])
    logs = []
    rep = run_bench(tmp_path / "w", quick=True, stages=["boom", "good", "alien", "slow", "nan", "notyet"],
                    log=logs.append, plot=tmp_path / "pareto.png")
    # every metric, with its unit, goal and direction; null where no stage measured it
    assert set(rep["metrics"]) == set(METRICS)
    for k, m in rep["metrics"].items():
        assert set(m) == {"value", "unit", "goal", "better"}
        assert (m["unit"], m["goal"], m["better"]) == METRICS[k]
    assert rep["metrics"]["white_err"]["value"] == pytest.approx(0.004)
    assert rep["metrics"]["ate_mm"]["value"] == 3.0
    assert rep["metrics"]["normal_err_deg"]["value"] is None
    assert rep["metrics"]["chamfer_mm"]["value"] is None          # NaN is reported as null, with a warning
    assert "chamfer_mm was nan" in rep["stages"]["nan"]["warnings"][0]
    assert rep["metrics"]["peak_rss_mb"]["value"] > 10
    # the failing stage is reported, the others ran
    assert rep["stages"]["boom"]["status"] == "error" and "synthetic failure" in rep["stages"]["boom"]["error"]
    assert rep["stages"]["good"]["status"] == "ok"
    assert rep["stages"]["alien"]["status"] == "error" and "not_a_metric" in rep["stages"]["alien"]["error"]
    assert rep["stages"]["notyet"]["status"] == "not built yet"
    assert any("boom FAILED" in line for line in logs)
    # budgets: the slow stage overran and was warned about
    assert rep["stages"]["slow"]["over_budget"] is True and rep["stages"]["good"]["over_budget"] is False
    assert any("WARNING: stage slow" in line and "budget" in line for line in logs)
    # sweeps: moved to the top level with their stage, front and default check; the failing stage's dropped
    assert "sweeps" not in rep["extra"] and set(rep["sweeps"]) == {"knob"}
    sw = rep["sweeps"]["knob"]
    assert sw["stage"] == "good" and sw["front"] == [1, 2] and sw["default_on_front"] is True
    assert rep["defaults_on_front"] == {"knob": True}
    # notes: the good stage's kept, the failing stage's dropped; printed under the table
    assert rep["notes"] == {"white_err": "measured on a fake stage"}
    assert "* white_err: measured on a fake stage" in format_table(rep)
    assert rep["plot"] and (tmp_path / "pareto.png").stat().st_size > 5000
    # strict JSON round trip (numpy values converted, no NaN)
    write_json(rep, tmp_path / "out" / "r.json")
    back = json.loads((tmp_path / "out" / "r.json").read_text(), parse_constant=lambda c: pytest.fail(c))
    assert back["extra"]["good"] == {"note": 1.5, "arr": [0, 1, 2]}
    assert back["metrics"]["chamfer_mm"]["value"] is None
    for key in ("metrics", "notes", "stages", "sweeps", "defaults_on_front", "extra", "quick", "seconds", "budget_s", "plot", "host"):
        assert key in back
    table = format_table(rep) + "\n" + format_stage_table(rep)
    assert "white_err" in table and "OVER BUDGET" in table and "knob (good)" in table


def test_unknown_stage_name_is_an_error(tmp_path):
    with pytest.raises(BenchError, match="unknown stage 'nonsense'"):
        run_bench(tmp_path, stages=["nonsense"], log=lambda s: None)


def test_default_off_front_is_warned(tmp_path, monkeypatch):
    mod = types.ModuleType("appfusion.bench.stages.offfront")
    mod.run = lambda ctx: ctx.add_sweep("k2", "e", 3, _pts((1.0, 0.1), (5.0, 0.2), values=[1, 3])) and {}
    monkeypatch.setitem(sys.modules, mod.__name__, mod)
    logs = []
    rep = run_bench(tmp_path, stages=["offfront"], log=logs.append)
    assert rep["defaults_on_front"] == {"k2": False} and rep["plot"] is None
    assert any("not on the measured Pareto front" in line for line in logs)


# -- the stability stage's pieces ----------------------------------------------------------------

def test_stability_pieces_match_the_engine():
    from appfusion import octahedral as octa
    from appfusion.bench.stages import stability as S
    from appfusion.sphere_fit import algebraic_fit

    rng = np.random.default_rng(1)
    assert S.condition_number(np.diag([1.0, 1e-3])) == pytest.approx(1e3)
    assert S.condition_number(np.array([[1.0, 100.0], [1.0, 100.0 + 1e-9]])) > 1e6
    assert S.condition_number(np.diag([1.0, 1e-3]), equilibrate=True) == pytest.approx(1.0)
    p = S.sphere_cap(500, 60.0, 0.002, rng)
    c, r, cond = S.kasa_fit(p)
    c_ref, r_ref = algebraic_fit(p)
    assert np.allclose(c, c_ref, atol=1e-12) and r == pytest.approx(r_ref, rel=1e-12) and cond > 1
    # uncentred float32 Kasa at 0.75 m loses far more than the centred one
    c32u = S.kasa_fit(p, np.float32, centred=False)[0]
    c32c = S.kasa_fit(p, np.float32, centred=True)[0]
    assert np.abs(c32u - c).max() > 5 * np.abs(c32c - c).max()
    # the solid-angle recomputation is the engine's in float64
    assert np.allclose(S.solid_angles(16, 8), octa.hemi_solid_angles(16, 8), rtol=1e-13, atol=0)
    # D(n) of a constant environment L = 1 is 1 for every normal (cosine integral / pi)
    env = np.ones((2, 16, 16, 3))
    nr = rng.normal(size=(20, 3))
    nr /= np.linalg.norm(nr, axis=1, keepdims=True)
    assert np.allclose(S.d_quadrature(env, nr), 1.0, rtol=2e-3)
    # the tangent gradient of D vanishes for a constant environment (up to the horizon's texel steps),
    # and (1/pi) * pi/2 = 0.5 along +x when only the x > 0 half of the sky is lit
    assert np.linalg.norm(S.d_normal_gradient(np.ones((2, 64, 64, 3)), nr[0])) < 2e-2
    half = np.ones((2, 64, 64, 3)) * (octa.sphere_directions(64)[..., :1] > 0)
    g = S.d_normal_gradient(half, np.array([0.0, 0.0, 1.0]))
    assert g[0] == pytest.approx(0.5, rel=0.02) and abs(g[1]) < 1e-2


def test_hbsab_sweep_matches_the_protocol_function():
    """The sweep's error at a resolution is the §5.1 protocol error of appfusion.ir_synth (same pairs)."""
    from appfusion.bench.stages import stability as S
    from appfusion.ir_synth import protocol_alpha_errors, protocol_pairs

    wi, wo = protocol_pairs(120_000, seed=3)
    pts = S.hbsab_sweep(wi, wo, (16,), (0.1, 0.4))
    ref = protocol_alpha_errors((0.1, 0.4), pairs=(wi, wo), rho_d=S.PROTOCOL_RHO_D, rho_s=S.PROTOCOL_RHO_S,
                                hbsab_n=16)
    assert pts[0]["value"] == 16 and pts[0]["ms_per_frame"] > 0
    assert pts[0]["error"] == pytest.approx(max(abs(e) for e in ref.values()), rel=1e-6, abs=1e-12)


def test_rho_s_rows_flag_float32_running_sums():
    from appfusion.bench.stages import stability as S

    rows = S.rho_s_rows(np.random.default_rng(0), n=400_000, frame=20_000)
    glossy, matte = rows
    assert glossy["cond"] < 1.5 < matte["cond"]                   # matte: the numerator cancels
    assert glossy["f32_rel_diff"] > 1e-5                          # per-sample float32 running sums drift
    assert "per frame" in glossy["note"]


@pytest.mark.slow
def test_cli_bench_stability_json(tmp_path):
    """``appfusion bench --quick --stage stability --json FILE --plot FILE`` (the real stage, ~10-20 s)."""
    from appfusion.cli import main

    out, png = tmp_path / "b.json", tmp_path / "p.png"
    t0 = time.perf_counter()
    rc = main(["bench", "--quick", "--stage", "stability", "--json", str(out), "--plot", str(png),
               "--workdir", str(tmp_path / "w")])
    assert rc == 0
    rep = json.loads(out.read_text())
    assert rep["stages"]["stability"]["status"] == "ok"
    assert all(m["value"] is None for k, m in rep["metrics"].items() if k != "peak_rss_mb")
    rows = rep["extra"]["stability"]["rows"]
    est = {r["estimator"].split()[0] for r in rows}
    assert {"sphere_fit", "ward_fit", "rho_s", "D(n)", "octahedral"} <= est
    for r in rows:
        assert r["cond"] >= 1.0 and (r["f32_rel_diff"] is None or 0 <= r["f32_rel_diff"] < 1e-2), r
    assert set(rep["sweeps"]) == {"hbsab_n", "envmap_n"}
    for knob, sw in rep["sweeps"].items():
        assert sw["stage"] == "stability" and len(sw["points"]) >= 3   # points may be skipped for time
        assert isinstance(rep["defaults_on_front"][knob], bool)
        errs = [p["error"] for p in sw["points"]]
        assert errs[0] > 10 * min(errs)                           # resolution matters: the sweep measures something
    # D(n) error falls with the env-map resolution
    env_err = [p["error"] for p in rep["sweeps"]["envmap_n"]["points"]]
    assert all(b < a for a, b in zip(env_err, env_err[1:]))
    assert png.read_bytes()[:4] == b"\x89PNG" and rep["plot"] == str(png)
    assert math.isfinite(rep["seconds"]) and time.perf_counter() - t0 < 300   # a hang guard, not a timing


# -- the end-to-end scan stage ---------------------------------------------------------------------

def test_scan_stage_session_cache(tmp_path, monkeypatch):
    """The stage's session is rendered once (into a temporary sibling, renamed into place) and reused; an
    interrupted render (no truth/scene.json) is rendered again."""
    import replay.synth as RS
    from appfusion.bench.stages import scan as S

    calls = []

    def fake_render(scene, out, frames, size, seed, detail, quality, show_progress, cache_dir):
        calls.append((scene, Path(out).name, frames, tuple(size), seed, detail, quality))
        (Path(out) / "truth").mkdir(parents=True)
        (Path(out) / "truth" / "scene.json").write_text("{}")
        return Path(out)

    monkeypatch.setattr(RS, "render_session", fake_render)
    root = tmp_path / "sessions"
    p1, t1 = S.cached_session(root, "two-material", 12, (320, 240), 3, log=lambda s: None)
    p2, t2 = S.cached_session(root, "two-material", 12, (320, 240), 3, log=lambda s: None)
    assert p1 == p2 == root / "two-material-320x240-12f-test-test-seed3" and t2 == 0.0 and len(calls) == 1
    assert calls[0][1].startswith(".two-material-320x240-12f") and calls[0][1].endswith(".tmp")
    assert sorted(x.name for x in root.iterdir()) == [p1.name]            # no temporary folder left
    (p1 / "truth" / "scene.json").unlink()                                # interrupted: rendered again
    S.cached_session(root, "two-material", 12, (320, 240), 3, log=lambda s: None)
    assert len(calls) == 2
    S.cached_session(root, "two-material", 12, (320, 240), 4, log=lambda s: None)   # other seed, other session
    assert len(calls) == 3 and len(list(root.iterdir())) == 2


def test_scan_stage_timer_restores_and_reports_failures():
    from appfusion import evaluate as ev
    from appfusion.bench.stages import scan as S
    from appfusion.pipeline import ScanRunner

    orig = {a: getattr(ScanRunner, a) for a in S._TIMED}
    orig_eval = ev.evaluate_result
    with S.stage_timer() as st:
        assert ScanRunner._stage_geometry is not orig["_stage_geometry"]
        obj = types.SimpleNamespace()
        with pytest.raises(AttributeError):
            ScanRunner._stage_geometry(obj, 0, 1, "geometry")           # a stage that raises
    assert all(getattr(ScanRunner, a) is f for a, f in orig.items()) and ev.evaluate_result is orig_eval
    assert st["geometry"] >= 0 and st["failed"][0][0] == "geometry"


def test_scan_stage_metrics_notes_and_ball_fallback(tmp_path, monkeypatch):
    """The stage's contract with a stand-in for run_scan: evaluation names become scan_* metrics, quick
    notes are set, and a failed mirror-ball fit is retried with the ball's radius (and said so)."""
    from appfusion.bench.stages import scan as S
    from appfusion.errors import EstimationError
    import appfusion.pipeline as P

    for scene, frames, seed in (("two-material", 40, 0), ("matte", 40, 0), ("sphere", 12, 1),
                                ("ggx-two-material", 40, 0)):
        session = tmp_path / "sessions" / S.session_name(scene, frames, (320, 240), seed, "test", "test")
        (session / "truth").mkdir(parents=True)
        (session / "truth" / "scene.json").write_text(json.dumps({"ball": {"radius_m": 0.035}}))
    seen = []
    monkeypatch.setattr(S, "fast_sweep", lambda session: {"tracked": 0.75, "frames": [], "seconds": 0.1})

    def fake_run_scan(sess, out, config, envmap=None, progress=False, log=print):
        seen.append(config.ball_radius_m)
        if config.ball_radius_m is None:
            raise EstimationError("lighting pass sphere fit: the inliers span too small a patch")
        Path(out).mkdir(parents=True, exist_ok=True)
        time.sleep(0.05)
        (Path(out) / "metrics.json").write_text(json.dumps(
            {"relit_rel_rmse": 0.25, "ate_mm": 1.5, "chamfer_mm": 0.3, "label_accuracy": 0.9,
             "envmap_median_rel_err": float("nan"), "alpha_sharpest_rel_err": 0.1}))
        return "summary"

    monkeypatch.setattr(P, "run_scan", fake_run_scan)
    ctx = BenchContext(workdir=tmp_path, quick=True, stage="scan", log=lambda s: None)
    got = S.run(ctx)
    # the two-material scan, the matte one, then the two-material scan rerun with a colour option
    assert seen == [None, 0.035, None, 0.035, 0.035]
    assert got["relit_rel_rmse"] == 0.25 and got["scan_ate_mm"] == 1.5 and got["scan_label_accuracy"] == 0.9
    assert got["scan_envmap_median_rel_err"] is None and got["scan_rho_s_rel_err"] is None   # NaN / missing
    assert got["demo_scan_s"] >= 0.05 and set(got) <= set(METRICS)
    assert got["fast_sweep_tracked"] == 0.75 and ctx.extra["scan"]["fast_sweep"]["session"]["frames"] == 12
    assert got["skip_wavelet_saving"] is None                     # no result.npz from the stand-in
    e = ctx.extra["scan"]
    assert e["fallback"]["ball_radius_m"] == 0.035 and "sphere fit" in e["fallback"]["error"]
    assert e["evaluation"]["alpha_sharpest_rel_err"] == 0.1 and e["session"]["demo"] is False
    assert "small session" in ctx.notes["demo_scan_s"] and "radius given" in ctx.notes["relit_rel_rmse"]
    assert e["matte"]["fallback"]["ball_radius_m"] == 0.035 and "radius given" in ctx.notes["scan_matte_rho_s"]
    assert got["scan_matte_relit_rel_rmse"] == 0.25 and got["scan_matte_rho_s"] is None   # not in the stand-in's metrics
    assert 0.0 <= got["skip_lighting_saving"] <= 1.0
    assert e["skip_rerun"]["stages_reused"] == [] and "normal_refine_rounds None -> 0" in e["skip_rerun"]["what"]
    # the GGX two-material scan is the full bench's: null under --quick, and said why
    assert all(got[k] is None and "full bench only" in ctx.notes[k] for k in S.GGX_METRICS.values())
    assert "ggx" not in e
    # ... where it runs, another scene's scan (_scene_scan): its evaluation, models and messages
    info = {}
    ev = S._scene_scan(ctx, {**S.GGX_SESSION_FULL, "frames": 40, "size": (320, 240), "detail": "test",
                             "quality": "test"}, "ggx", S.GGX_METRICS, info)
    assert ev["label_accuracy"] == 0.9 and info["ggx"]["evaluation"] == ev
    assert info["ggx"]["session"]["scene"] == "ggx-two-material" and info["ggx"]["fallback"]["ball_radius_m"] == 0.035
    assert "radius given" in ctx.notes["scan_ggx_label_accuracy"]


def test_view_samples_and_truth_free_wavelet_skip():
    """Points a camera samples: in the image and within 80 degrees of the normal; lazy tables report the
    mirror nodes a one-sided view set needs, with the same S as eager tables."""
    from appfusion.bench.stages.scan import view_samples, wavelet_skip
    from appfusion.frame import Intrinsics
    from replay.synth.camera import look_at
    from appfusion.rgb_synth import synthetic_envmap

    K = Intrinsics(160, 120, 140.0, 140.0, 79.5, 59.5)
    g = np.stack(np.meshgrid(np.linspace(-0.1, 0.1, 21), np.linspace(-0.1, 0.1, 21)), -1).reshape(-1, 2)
    P = np.c_[g, np.zeros(len(g))]
    N = np.tile([0.0, 0.0, 1.0], (len(P), 1))
    N[:10] = [0.0, 0.0, -1.0]                                       # facing away: never sampled
    pose = look_at(np.array([0.0, -0.3, 0.4]), np.zeros(3))
    idx, wo = view_samples(P, N, pose, K)
    assert 300 < len(idx) < len(P) and idx.min() >= 10
    assert np.allclose(np.linalg.norm(wo, axis=1), 1) and (wo[:, 2] > 0).all()
    far = look_at(np.array([2.0, 0.0, 0.05]), np.array([2.0, 1.0, 0.05]))    # looking away
    assert len(view_samples(P, N, far, K)[0]) == 0
    env = synthetic_envmap(16, seed=2)
    labels = np.zeros(len(P), np.int64)
    w = wavelet_skip(env, P, N, labels, np.array([0.3]), np.array([True]), [pose], K)
    assert 0 < w["nodes_built"] < w["nodes_total"] and w["max_rel_diff"] < 5e-3 and w["samples"] == len(idx)
    assert w["eager_cpu_s"] > 0 and w["saving"] is not None
    assert w["node_work_saved"] == pytest.approx(1 - w["nodes_built"] / w["nodes_total"])   # one alpha
    none = wavelet_skip(env, P, N, labels, np.array([0.3]), np.array([False]), [pose], K)
    assert none["saving"] is None and "no specular" in none["note"]


@pytest.mark.slow
def test_scan_stage_end_to_end_small_session(tmp_path, monkeypatch):
    """The real stage on a small session (320 x 240, 16 frames per pass, 2000 points; ~30 s): every
    metric it owns is reported, the report is written, the timing adds up, and the session is cached."""
    from appfusion.bench.stages import scan as S

    monkeypatch.setattr(S, "QUICK_SESSION", {"scene": "two-material", "frames": 16, "size": (320, 240),
                                              "detail": "test", "quality": "test"})
    monkeypatch.setattr(S, "MATTE_SESSION", {"scene": "matte", "frames": 16, "size": (320, 240),
                                              "detail": "test", "quality": "test"})
    monkeypatch.setattr(S, "QUICK_POINTS", 2000)
    monkeypatch.setattr(S, "QUICK_TEXTURE", 64)
    monkeypatch.setattr(S, "FAST_SWEEP_SESSION", {**S.FAST_SWEEP_SESSION, "frames": 8})
    ctx = BenchContext(workdir=tmp_path, quick=True, stage="scan", log=lambda s: None)
    t0 = time.perf_counter()
    got = S.run(ctx)
    # the scan itself within 60 s (28-30 s alone on a 2-core machine of session 6); rendering the
    # session first is the synthetic scanner's cost and varies with the machine (the whole call was
    # 55 s alone there, 61 s beside the rest of the suite), so it is printed, not bounded
    print(f"scan stage {time.perf_counter() - t0:.1f} s, of which the scan {ctx.extra['scan']['wall_s']:.1f} s")
    assert ctx.extra["scan"]["wall_s"] < 150                  # a regression guard (5x), not a timing
    assert set(got) == {"relit_rel_rmse", "demo_scan_s", "skip_lighting_saving", "skip_wavelet_saving", "skip_rerun_saving",
                        "scan_ir_pattern_heldout_cv", "fast_sweep_tracked", *S.SCAN_METRICS.values(),
                        *S.MATTE_METRICS.values(), *S.GGX_METRICS.values()}
    fast = ctx.extra["scan"]["fast_sweep"]
    assert len(fast["frames"]) == 8 and 0 < got["fast_sweep_tracked"] <= 1
    # the matte scene (no lobe) is scanned too: its rho_s over its area, rho_d and relit error
    mt = ctx.extra["scan"]["matte"]
    print(f"matte scan {mt['wall_s']:.1f} s: model {mt['model']}, rho_s {got['scan_matte_rho_s']}, "
          f"rho_d {got['scan_matte_rho_d_median_rel_err']}, relit {got['scan_matte_relit_rel_rmse']}")
    assert got["scan_matte_rho_s"] is not None and got["scan_matte_rho_s"] >= 0 and mt["model"]
    assert 0 < got["scan_matte_rho_d_median_rel_err"] < 1 and 0 < got["scan_matte_relit_rel_rmse"] < 10
    for k, v in got.items():
        assert v is None or math.isfinite(v), k
    assert 0 < got["relit_rel_rmse"] < 10 and got["scan_chamfer_mm"] > 0 and got["scan_normal_err_deg"] > 0
    e = ctx.extra["scan"]
    # the emitter pattern map predicts held-out sheet distances far better than the pattern's spread
    assert got["scan_ir_pattern_heldout_cv"] < 0.5 * e["ir_pattern"]["heldout_cv_without"], e["ir_pattern"]
    assert got["demo_scan_s"] == pytest.approx(e["wall_s"], abs=0.02)
    st = e["stage_s"]
    assert {"ir-calibration", "environment", "geometry", "rgb", "evaluation", "export"} <= set(st)
    assert sum(st.values()) == pytest.approx(e["wall_s"], rel=0.01, abs=0.05)
    assert 0 < got["skip_lighting_saving"] < 1 and e["skip_lighting"]["saved_s"] == pytest.approx(st["environment"], abs=0.01)
    # a rerun with a colour option recomputes the colour stage alone, with the same relit error
    rr = e["skip_rerun"]
    assert rr["stages_reused"] == ["ir-calibration", "environment", "geometry", "ir"], rr
    assert 0 < got["skip_rerun_saving"] < 1 and rr["rerun_s"] < rr["first_s"]
    assert rr["relit_rel_rmse_rerun"] == pytest.approx(rr["relit_rel_rmse_first"], rel=0.02), rr
    sw = e["skip_wavelet"]["scan_clusters"]
    if sw.get("saving") is not None:
        assert sw["nodes_built"] <= sw["nodes_total"] and sw["max_rel_diff"] < 5e-3
    # the label's rho_s error also in units of its standard error (finite: every cluster has one)
    assert math.isfinite(e["evaluation"]["rho_s_err_sigmas"]) and e["evaluation"]["rho_s_err_sigmas"] >= 0
    # the exported files' own errors (evaluate.export_error), also in metrics.json
    assert 0 <= got["scan_export_normal_err_deg"] < 3 and 0 <= got["scan_export_rho_d_median_rel_err"] < 0.2
    out = tmp_path / "scan"
    assert (out / "report.html").exists() and (out / "result.npz").exists() and (out / "metrics.json").exists()
    assert S.cached_session(tmp_path / "sessions", "two-material", 16, (320, 240), 0)[1] == 0.0
