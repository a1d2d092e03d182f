"""Synthetic scanner: whole sessions (format, passes, truth, determinism) and the CLI."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from appfusion.cli import main
from replay.session import SessionReader, parse_groundtruth
from replay.synth import render_session
from replay.synth.scanner import CALIB_DISTANCES_M, CALIB_FRAMES_EACH, CALIB_OFF_FRAMES

N_CALIB = CALIB_OFF_FRAMES + len(CALIB_DISTANCES_M) * CALIB_FRAMES_EACH
SIZE = (80, 60)


def _digest(path):
    h = hashlib.sha256()
    for f in sorted(p for p in path.rglob("*") if p.is_file() and p.suffix in (".png", ".txt", ".npz", ".exr")):
        if f.name == "scene.json":
            continue
        h.update(f.relative_to(path).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def kinect_session(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "two"
    return render_session("two-material", out, frames=3, size=SIZE, seed=4, detail="test", show_progress=False)


def test_session_reads_back_with_passes_events_and_streams(kinect_session):
    r = SessionReader(kinect_session)
    assert len(r) == N_CALIB + 3 * 3
    passes = [v for _, k, v in r.events if k == "pass"]
    assert passes == ["ir-calibration", "environment", "geometry", "rgb"]
    assert [v for _, k, v in r.events if k == "emitter"] == ["off", "on"]
    assert r.meta["extra"]["markers"] == {"radius_m": 0.025, "key_radius_m": 0.035, "layout": "square",
                                          "side_m": 0.30}
    assert r.intrinsics["depth"].width == SIZE[0] and r.intrinsics["rgb"].fx == pytest.approx(525 * SIZE[0] / 640)
    np.testing.assert_allclose(r.depth_to_rgb[:3, 3], [-0.025, 0, 0])
    assert r.meta["emitter_position_m"] == [0.075, 0.0, 0.0]
    want = {"ir-calibration": {"depth", "ir"}, "environment": {"depth", "rgb"}, "geometry": {"depth", "ir"},
            "rgb": {"depth", "rgb"}}
    seen = {}
    for f in r:
        assert f.pose is None  # the engine never gets poses from the session
        seen.setdefault(f.pass_name, set()).update(f.streams)
        assert set(f.streams) == want[f.pass_name]
        if f.pass_name == "ir-calibration" and not f.emitter:
            assert np.isnan(f.depth).all() and f.ir.max() < 80
    assert seen.keys() == want.keys()


def test_truth_folder(kinect_session):
    t = kinect_session / "truth"
    r = SessionReader(kinect_session)
    times, poses, bad, _ = parse_groundtruth((t / "groundtruth.txt").read_bytes())
    assert not bad and len(times) == len(r)
    np.testing.assert_allclose(times, r.timestamps, atol=1e-6)
    assert np.allclose(np.diff(times[:5]), 1 / 30, atol=1e-6)
    # poses look at the object from 0.4-1 m during the object passes
    sc = json.loads((t / "scene.json").read_text())
    assert sc["seed"] == 4 and sc["scene"] == "two-material"
    obj = np.load(t / "object.npz")
    assert set(obj.files) >= {"vertices", "faces", "vertex_normals", "rho_d", "material_id", "ir_rho_d"}
    assert obj["rho_d"].shape == obj["vertices"].shape and set(np.unique(obj["material_id"])) == {0, 1}
    assert np.allclose(np.linalg.norm(obj["vertex_normals"], axis=1), 1.0)
    mats = json.loads((t / "materials.json").read_text())["materials"]
    assert [m["lobe"] for m in mats] == ["ward", "ward"] and mats[1]["alpha"] == 0.06
    mk = json.loads((t / "markers.json").read_text())
    assert mk["centres_m"][0] == [0.15, 0.15, 0.0] and mk["centres_m"][2] == [-0.15, -0.15, 0.0]
    assert len(mk["white_radiance_rgb"]["object"]) == 4
    ir = json.loads((t / "ir_model.json").read_text())
    assert ir["k"] == 1.6 and ir["theta"] == 2.8 and ir["gamma"] == 0.9 and ir["gain"] > 0
    from replay.synth.envmaps import load_latlong

    for name in ("office", "sunset"):
        # scene.json names the files relative to truth/ (it named the renamed temporary folder before)
        assert sc["envmap_files"][name] == {"exr": f"envmaps/{name}.exr", "hdr": f"envmaps/{name}.hdr"}
        exr, hdr = load_latlong(t / "envmaps" / f"{name}.exr"), load_latlong(t / "envmaps" / f"{name}.hdr")
        assert exr.shape == (256, 512, 3) and hdr.shape == (256, 512, 3)
        assert np.median(np.abs(hdr / np.maximum(exr, 1e-6) - 1)) < 0.01  # RGBE keeps ~1% precision
    views = json.loads((t / "references" / "views.json").read_text())
    assert len(views["views"]) == 3 and views["environment"] == "sunset"
    ref = load_latlong(t / "references" / "view-1.exr")
    assert ref.shape == (SIZE[1], SIZE[0], 3) and ref.max() > 0
    frames = json.loads((t / "frames.json").read_text())["frames"]
    rgbf = [f for f in frames if "exposure" in f]
    assert rgbf and all(len(f["wb_gains"]) == 3 for f in rgbf)
    assert sum("sheet_distance_m" in f for f in frames) == len(CALIB_DISTANCES_M) * CALIB_FRAMES_EACH


def test_markers_visible_and_unsaturated(kinect_session):
    """The white circles are the white reference: in most RGB frames at least one is seen unsaturated."""
    r = SessionReader(kinect_session)
    ok = 0
    n = 0
    for f in r:
        if f.rgb is None:
            continue
        n += 1
        bright = f.rgb.max(axis=2)
        ok += int((bright > 60).sum() > 3 and (bright >= 255).sum() == 0)
    assert n == 6 and ok >= 5


def test_same_seed_same_bytes_also_with_two_worker_processes(kinect_session, tmp_path, monkeypatch):
    import tempfile

    scratch = tmp_path / "scratch"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    again = render_session("two-material", tmp_path / "again", frames=3, size=SIZE, seed=4, detail="test",
                           show_progress=False, workers=2)
    assert _digest(again) == _digest(kinect_session)
    # the light-transport cache made for the workers is removed (it leaked ~0.4 MB per render before)
    assert not list(scratch.glob("synth-lighting-*"))


def test_a_longer_colour_pass_leaves_the_other_passes_bytes_alone(kinect_session, tmp_path, capsys):
    """``rgb_frames`` (``appfusion synth --rgb-frames``) samples the rgb pass's orbit more densely; every
    frame of the other passes is byte for byte the default render's."""
    longer = render_session("two-material", tmp_path / "long", frames=3, size=SIZE, seed=4, detail="test",
                            show_progress=False, references=False, rgb_frames=7)
    a, b = SessionReader(kinect_session), SessionReader(longer)
    fa, fb = list(a), list(b)
    assert [f.pass_name for f in fb].count("rgb") == 7 and [f.pass_name for f in fa].count("rgb") == 3
    other_a = [f for f in fa if f.pass_name != "rgb"]
    other_b = [f for f in fb if f.pass_name != "rgb"]
    assert len(other_a) == len(other_b) > 0
    for x, y in zip(other_a, other_b):
        assert x.timestamp == y.timestamp and set(x.streams) == set(y.streams)
        for s in x.streams:
            np.testing.assert_array_equal(getattr(x, s), getattr(y, s), err_msg=f"{x.pass_name} {x.timestamp} {s}")
    ts_b = np.array([f.timestamp for f in fb if f.pass_name == "rgb"])
    assert np.allclose(np.diff(ts_b), 1 / 30, rtol=0, atol=2e-6)  # timestamps kept to the microsecond
    scene = json.loads((longer / "truth" / "scene.json").read_text())
    assert scene["rgb_frames"] == 7 and scene["frames_per_pass"] == 3
    assert [p["frames"] for p in scene["passes"] if p["name"] == "rgb"] == [7]
    assert main(["synth", "sphere", str(tmp_path / "z"), "--quiet", "--rgb-frames", "0"]) == 2
    err = capsys.readouterr().err
    assert "frames of the colour pass must be within 1-100000" in err and "Traceback" not in err
    assert not (tmp_path / "z").exists()


def test_allinone_device_streams_everything_every_frame(tmp_path):
    p = render_session("sphere", tmp_path / "aio", frames=1, size=SIZE, seed=1, detail="test", device="allinone",
                       references=False, show_progress=False)
    r = SessionReader(p)
    assert [v for _, k, v in r.events if k == "pass"] == ["ir-calibration", "environment", "scan"]
    assert r.caps.ir_and_rgb_together
    for f in r:
        assert set(f.streams) == {"depth", "ir", "rgb"}


def test_cli_list_and_errors(tmp_path, capsys):
    assert main(["synth", "list"]) == 0
    out = capsys.readouterr().out
    for name in ("sphere", "vase", "pepper", "two-material", "ggx-sphere", "ggx-two-material", "matte"):
        assert name in out
    assert main(["synth", "teapot", str(tmp_path / "x")]) == 2
    assert "unknown synthetic scene 'teapot'" in capsys.readouterr().err
    assert main(["synth", "sphere", str(tmp_path / "y"), "--size", "640by480"]) == 2
    assert "--size" in capsys.readouterr().err
    for args, msg in [(["--seed", "-1"], "the seed must be an integer in [0, 2^32)"),
                      (["--frames", "0"], "frames per pass must be >= 1"),
                      (["--workers", "0"], "--workers must be at least 1")]:
        assert main(["synth", "sphere", str(tmp_path / "z"), "--quiet", *args]) == 2
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err, err
    assert not (tmp_path / "z").exists()


def test_info_command_and_contact_sheet(kinect_session, tmp_path, capsys):
    import importlib.util

    if importlib.util.find_spec("appfusion.commands.info") is not None:
        assert main(["info", str(kinect_session)]) == 0
        out = capsys.readouterr().out
        assert "environment" in out and "geometry" in out
    from replay.synth.contact import contact_sheet

    png = contact_sheet(kinect_session, tmp_path / "sheet.png", tile_width=80)
    import cv2

    img = cv2.imread(str(png))
    assert img.shape == (120, 320, 3) and img.std() > 5


def test_demo_session_is_generated_once(tmp_path, monkeypatch):
    """demo_session renders into a temporary folder, renames it into place, and reuses it afterwards."""
    import replay.synth.scanner as S

    calls = []

    def fake_render(scene, out, **kw):
        calls.append((scene, kw["size"], kw["frames"]))
        (out / "truth").mkdir(parents=True)
        (out / "truth" / "scene.json").write_text("{}")
        return out

    monkeypatch.setattr(S, "render_session", fake_render)
    p1 = S.demo_session(tmp_path)
    p2 = S.demo_session(tmp_path)
    assert p1 == p2 == tmp_path / "synth-demo-two-material" and (p1 / "truth" / "scene.json").exists()
    assert calls == [("two-material", (640, 480), S.DEMO_FRAMES)]


def test_ggx_two_material_is_the_capsule_with_a_ggx_paint():
    """``ggx-two-material``: the two-material capsule (same mesh, albedo and label) whose paint is a
    GGX lobe, so one object carries lobes of two shapes."""
    from replay.synth.objects import build_object

    ward, ggx = build_object("two-material", "test"), build_object("ggx-two-material", "test")
    assert ggx.name == "ggx-two-material"
    np.testing.assert_array_equal(ward.vertices, ggx.vertices)
    np.testing.assert_array_equal(ward.rho_d, ggx.rho_d)
    np.testing.assert_array_equal(ward.material_id, ggx.material_id)
    label, paint = ggx.materials.to_json()
    assert label == ward.materials.to_json()[0]
    assert paint["lobe"] == "ggx" and paint["alpha"] == 0.08 and paint["rho_s"] == [0.3, 0.3, 0.3]
    assert ggx.vertices[ggx.material_id == 1, 2].min() >= 0.075 - 1e-9          # the paint is the top


def test_matte_scene_and_the_false_lobe_metric(tmp_path):
    """The ``matte`` scene has one material without a lobe in colour or IR, and ``evaluate_result``'s
    ``matte_rho_s`` is the exported rho_s over that material's area: 0 for a diffuse export, the
    lobe's strength times the fraction it covers for a false one; its alpha is not judged."""
    from appfusion.evaluate import evaluate_result
    from appfusion.result import ScanResult
    from replay.synth.objects import build_object

    obj = build_object("matte", detail="test")
    (m,) = obj.materials.to_json()
    assert m["rho_s"] == [0.0, 0.0, 0.0] and m["ir_rho_s"] == 0.0
    assert np.all(obj.material_id == 0) and obj.rho_d.std(axis=0).min() > 0.05   # printed, not plain
    truth = tmp_path / "session" / "truth"
    truth.mkdir(parents=True)
    np.savez_compressed(truth / "object.npz", **obj.truth_arrays())
    (truth / "materials.json").write_text(json.dumps({"materials": obj.materials.to_json()}))
    P, N = obj.vertices.astype(np.float32), obj.normals.astype(np.float32)
    upper = (P[:, 2] > 0.06).astype(np.int32)                 # two clusters on the one material
    def result(rho_s):
        return ScanResult(P, N, obj.rho_d.astype(np.float32), upper, np.asarray(rho_s, np.float32),
                          np.array([0.3, 0.3], np.float32), np.zeros(2, np.float32),
                          mesh_vertices=P, mesh_faces=obj.faces)
    e = evaluate_result(result([[0, 0, 0], [0, 0, 0]]), tmp_path / "session", relight=False)
    assert e["matte_rho_s"] == 0.0
    assert np.isnan(e["rho_s_rel_err"]) and np.isnan(e["alpha_cluster_rel_err"]) and "alpha_sharpest_rel_err" not in e
    e = evaluate_result(result([[0, 0, 0], [0.02, 0.04, 0.03]]), tmp_path / "session", relight=False)
    assert e["matte_rho_s"] == pytest.approx(0.03 * upper.mean(), rel=1e-5)
