"""Export of a scan result: ball-pivoting mesh, UV atlas, textures, .glb/.obj/.ply that load back."""

from __future__ import annotations

import numpy as np
import pytest

from appfusion.export import export_result, mesh_from_points, transfer_to_vertices
from appfusion.result import ScanResult


def _sphere_result(n=4000, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pos = 0.05 * d + [0, 0, 0.05]
    labels = (d[:, 2] > 0).astype(np.int32)  # top half glossy (1), bottom matte (0)
    rho_d = np.stack([0.2 + 0.6 * (d[:, 0] > 0), np.full(n, 0.3), np.full(n, 0.5)], 1)
    return ScanResult(pos, d, rho_d, labels, rho_s=[[0.0, 0.0, 0.0], [0.3, 0.3, 0.3]], alpha=[0.5, 0.1],
                      alpha_sigma=[0.01, 0.002])


def test_transfer_nearest_and_idw():
    pos = np.array([[0, 0, 0], [1, 0, 0.0]])
    vals = np.array([[1.0], [3.0]])
    v = np.array([[0.0, 0, 0], [0.5, 0, 0]])
    out = transfer_to_vertices(pos, vals, v, k=2)
    assert out[0, 0] == pytest.approx(1.0, abs=1e-4) and out[1, 0] == pytest.approx(2.0)
    np.testing.assert_array_equal(transfer_to_vertices(pos, np.array([5, 7]), v, nearest=True), [5, 5])


def test_result_roundtrip(tmp_path):
    r = _sphere_result(500)
    r.info["session"] = "x"
    p = r.save(tmp_path / "result.npz")
    back = ScanResult.load(tmp_path)
    np.testing.assert_array_equal(back.labels, r.labels)
    np.testing.assert_allclose(back.alpha, r.alpha)
    assert back.info["session"] == "x" and back.envmap is None
    with pytest.raises(ValueError, match="labels"):
        ScanResult(r.positions, r.normals, r.rho_d, r.labels + 5, r.rho_s, r.alpha)
    # rho_s's standard error: NaN where unknown, kept through save/load, shown in the report's table
    assert r.rho_s_sigma.shape == (2, 3) and np.isnan(r.rho_s_sigma).all() and np.isnan(back.rho_s_sigma).all()
    r.rho_s_sigma = np.array([[np.nan] * 3, [0.002, 0.0021, 0.0025]], np.float32)
    back = ScanResult.load(r.save(tmp_path / "result.npz"))
    np.testing.assert_array_equal(back.rho_s_sigma, r.rho_s_sigma)
    from appfusion.report import write_report

    html = write_report(tmp_path, back).read_text()
    assert "rho_s standard error" in html and "0.0020, 0.0021, 0.0025" in html and "—" in html
    # a cluster the model ladder made diffuse shows no alpha of its own (the IR fit's, marked unused)
    back.model = ["diffuse", "ward"]
    html = write_report(tmp_path, back).read_text()
    assert "<td>diffuse</td><td>— <small>(IR fit 0.5000 ± 0.0100, unused)</small></td>" in html
    assert "<td>ward</td><td>0.1000 ± 0.0020</td>" in html
    with pytest.raises(ValueError, match="rho_s_sigma"):
        ScanResult(r.positions, r.normals, r.rho_d, r.labels, r.rho_s, r.alpha, rho_s_sigma=np.zeros((3, 3)))


def test_export_writes_loadable_glb_obj_ply(tmp_path):
    import trimesh

    r = _sphere_result()
    V, F = mesh_from_points(r.positions, r.normals)
    assert len(F) > 2000
    r.mesh_vertices, r.mesh_faces = V, F
    files = export_result(r, tmp_path, texture_size=256)
    scene = trimesh.load(files["glb"])
    geom = list(scene.geometry.values())[0]
    mat = geom.visual.material
    assert mat.baseColorTexture is not None and mat.baseColorTexture.size == (256, 256)
    assert mat.metallicRoughnessTexture is not None
    # texture lookup at the vertices reproduces rho_d where it varies (red channel 0.2 vs 0.8 by side of x)
    uv = geom.visual.uv
    tex = np.asarray(mat.baseColorTexture.convert("RGB"), np.float32) / 255
    h, w = tex.shape[:2]
    px = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
    py = np.clip(((1 - uv[:, 1]) * h).astype(int), 0, h - 1)
    red = tex[py, px, 0]
    x = geom.vertices[:, 0]
    far = np.abs(x) > 0.015
    from appfusion.frame import srgb_to_linear
    lin = srgb_to_linear(red)
    assert np.median(lin[far & (x > 0)]) == pytest.approx(0.8, abs=0.05)
    assert np.median(lin[far & (x < 0)]) == pytest.approx(0.2, abs=0.05)
    obj = trimesh.load(files["obj"], force="mesh")
    assert len(obj.faces) == len(F)
    ply = files["ply"].read_bytes()
    assert ply.startswith(b"ply\n") and b"element vertex 4000" in ply and b"property int cluster" in ply
    for k in ("rho_d", "rho_s", "alpha", "clusters"):
        assert (tmp_path / f"{k}.png").stat().st_size > 0
    assert (tmp_path / "rho_d.exr").exists()


def test_rho_d_texture_holds_the_points_detail_on_a_coarse_mesh(tmp_path):
    """rho_d is baked per texel from the points (export.texel_values), not per vertex: stripes ~4 mm
    wide on a mesh whose vertices are ~15 mm apart stay in the texture; the vertex normals are the
    points' normal field's."""
    import cv2
    import open3d as o3d

    r = _sphere_result(20000)
    r.rho_d[:, 1] = np.where(np.sin(40 * r.normals[:, 2]) > 0, 0.8, 0.1)
    m = o3d.geometry.TriangleMesh.create_sphere(radius=0.05, resolution=10)
    m.translate([0, 0, 0.05])
    r.mesh_vertices, r.mesh_faces = np.asarray(m.vertices), np.asarray(m.triangles)
    export_result(r, tmp_path, texture_size=256)
    tex = cv2.imread(str(tmp_path / "rho_d.exr"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    g = tex[..., 1][tex[..., 2] > 0.4]                      # covered texels (blue is 0.5 on the object)
    assert len(g) > 10000 and g.min() >= 0.1 - 1e-6 and g.max() <= 0.8 + 1e-6
    # texels at either stripe value: 0.59 (per-vertex baking: 0.29)
    assert np.mean((np.abs(g - 0.1) < 0.05) | (np.abs(g - 0.8) < 0.05)) > 0.5
    # the .glb's vertex normals are the points' normal field at each vertex (exact radial normals here)
    import trimesh

    geom = list(trimesh.load(tmp_path / "object.glb").geometry.values())[0]
    radial = geom.vertices - [0, 0, 0.05]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    err = np.degrees(np.arccos(np.clip(np.einsum("vc,vc->v", geom.vertex_normals, radial), -1, 1)))
    assert np.median(err) < 0.05                            # inverse distance over 4 points: 0.41
    # the same, measured by evaluate.export_error against a truth folder (a finer sphere, same stripes)
    import json

    from appfusion.errors import AppFusionError
    from appfusion.evaluate import export_error

    t = o3d.geometry.TriangleMesh.create_sphere(radius=0.05, resolution=60)
    t.translate([0, 0, 0.05])
    t.compute_vertex_normals()
    tv = np.asarray(t.vertices)
    tn = (tv - [0, 0, 0.05]) / 0.05
    trd = np.stack([0.2 + 0.6 * (tn[:, 0] > 0), np.where(np.sin(40 * tn[:, 2]) > 0, 0.8, 0.1), np.full(len(tv), 0.5)], 1)
    (tmp_path / "ses" / "truth").mkdir(parents=True)
    np.savez(tmp_path / "ses" / "truth" / "object.npz", vertices=tv, faces=np.asarray(t.triangles), vertex_normals=tn,
             rho_d=trd)
    (tmp_path / "ses" / "truth" / "materials.json").write_text(json.dumps({"materials": []}))
    e = export_error(tmp_path, tmp_path / "ses")
    assert e["export_normal_err_deg"] < 0.05
    assert e["export_rho_d_median_rel_err"] < 0.02
    with pytest.raises(AppFusionError, match="object.glb: not found"):
        export_error(tmp_path / "ses", tmp_path / "ses")


def test_texture_look_ups_for_more_triangles_than_opencv_maps_take():
    """export_error reads rho_d.exr at every triangle's centroid: a mesh of over 32767 triangles (the
    vase's 43k) needs more look-ups than OpenCV's remap takes in one column; the look-ups are bilinear,
    OpenGL v (0 = bottom row), edges replicated."""
    from appfusion.evaluate import sample_texture

    rng = np.random.default_rng(4)
    H, W = 48, 64
    tex = rng.random((H, W, 3)).astype(np.float32)
    uv = rng.random((40001, 2))
    got = sample_texture(tex, uv)
    assert got.shape == (40001, 3)
    x, y = uv[:, 0] * W - 0.5, (1 - uv[:, 1]) * H - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    # OpenCV's bilinear remap rounds the sub-pixel position to 1/32 of a pixel (INTER_TAB_SIZE)
    fx, fy = np.round((x - x0) * 32)[:, None] / 32, np.round((y - y0) * 32)[:, None] / 32

    def at(yy, xx):
        return tex[np.clip(yy, 0, H - 1), np.clip(xx, 0, W - 1)]

    ref = ((1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1))
           + fy * ((1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1)))
    close = np.abs(got - ref) < 1e-4                          # (a float32 map rounds a few positions the
    assert close.mean() > 0.999 and np.abs(got - ref).max() < 0.03, close.mean()   # other way: 1/32 px)
    np.testing.assert_allclose(sample_texture(tex, [[0.0, 1.0]])[0], tex[0, 0], atol=1e-6)


def test_convergence_figure_marks_the_exported_values(tmp_path):
    """The report's convergence figure: the live sweep's running estimates as lines, the exported
    clusters (after a colour split, more of them than the running estimates had) as markers."""
    from PIL import Image

    from appfusion.report import fig_convergence

    hist = {"alpha": [(15, [0.048]), (30, [0.049]), (60, [0.051])],
            "rho_s": [(10, [[0.33, 0.33, 0.34]]), (20, [[0.335, 0.336, 0.337]])]}
    final = {"alpha": np.array([0.062, 0.35]), "rho_s": np.array([[0.357] * 3, [0.0] * 3])}
    p = fig_convergence(hist, tmp_path / "c.png", final=final)
    a = np.asarray(Image.open(p).convert("RGB")).astype(int)
    assert a.shape[0] > 100 and a.shape[1] > 300
    # markers in the second cluster's colour (matplotlib C1, orange) appear only with the final values
    orange = (np.abs(a - np.array([255, 127, 14])).sum(-1) < 60).sum()
    q = fig_convergence(hist, tmp_path / "d.png")
    b = np.asarray(Image.open(q).convert("RGB")).astype(int)
    assert orange > 20 and (np.abs(b - np.array([255, 127, 14])).sum(-1) < 60).sum() == 0
    fig_convergence({}, tmp_path / "e.png", final=final)             # no history: markers only


def test_hbsab_figure_keeps_each_clusters_column(tmp_path):
    """A cluster without an HBSAB (None) keeps its column in the report's figure; the next cluster's
    HBSAB and fitted lobe stay in theirs (they had moved one column left, beside the first's fit)."""
    from PIL import Image

    from appfusion.report import fig_hbsabs

    yy, xx = np.mgrid[-1:1:32j, -1:1:32j]
    h = np.exp(-(xx ** 2 + yy ** 2) / 0.1)
    p = fig_hbsabs([None, h], [None, 0.9 * h], tmp_path / "h.png", lobes=["diffuse", "ggx"])
    a = np.asarray(Image.open(p).convert("RGB")).astype(int)
    H, W = a.shape[:2]
    dark = (a.sum(-1) < 200)                                          # inferno's dark end: an image was drawn
    left, right = dark[:, : W // 2], dark[:, W // 2:]
    assert right[: H // 2].mean() > 0.2 and right[H // 2:].mean() > 0.2    # cluster 1: HBSAB and fit
    assert left.mean() < 0.02                                         # cluster 0: nothing drawn


def test_info_describes_a_scan_output_folder(tmp_path, capsys):
    """`appfusion info OUT` on a scan's output: the materials with their standard errors (none where
    unknown), the mesh, the files and the errors against truth; --json alike; a broken result.npz is
    one clear error."""
    import json

    from appfusion.cli import main

    r = _sphere_result(500)
    r.rho_s_sigma = np.array([[np.nan] * 3, [0.002, 0.0021, 0.0025]], np.float32)
    r.save(tmp_path / "result.npz")
    (tmp_path / "metrics.json").write_text(json.dumps({"rho_s_rel_err": 0.0412, "cluster_to_material": {"0": 1}}))
    assert main(["info", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "scan result" in out and "points      500" in out
    assert "cluster 1: ward" in out and "rho_s 0.3000 ± 0.0020, 0.3000 ± 0.0021, 0.3000 ± 0.0025" in out
    assert "cluster 0: ward" in out and "rho_s 0.0000, 0.0000, 0.0000" in out     # no standard error known
    assert "against truth rho_s_rel_err 0.0412" in out and "result.npz" in out
    assert main(["info", "--json", str(tmp_path / "result.npz")]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["clusters"][1]["rho_s_sigma"] == pytest.approx([0.002, 0.0021, 0.0025], rel=1e-5)
    assert d["clusters"][0]["rho_s_sigma"] == [None, None, None] and d["metrics"]["rho_s_rel_err"] == 0.0412
    r.model = ["diffuse", "ward"]                       # the model ladder's lower rung: no alpha of its own
    r.save(tmp_path / "result.npz")
    assert main(["info", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "cluster 0: diffuse" in out and "alpha - (IR fit 0.5000 ± 0.0100, unused)  rho_s 0\n" in out
    (tmp_path / "result.npz").write_bytes(b"not a zip")
    assert main(["info", str(tmp_path)]) == 2
    assert "not a readable scan result" in capsys.readouterr().err


def test_manifold_mesh_lets_a_pinched_mesh_be_unwrapped():
    """UVAtlas refuses a non-manifold mesh (a TSDF fused from few noisy frames made one: session 26):
    export removes the triangles on non-manifold edges and all but the largest fan at a pinched
    vertex, and the rest unwraps; a manifold mesh passes unchanged."""
    import open3d as o3d

    from appfusion.export import bake_textures, manifold_mesh

    grid = o3d.geometry.TriangleMesh.create_box(0.02, 0.02, 0.02).subdivide_midpoint(2)
    V = np.asarray(grid.vertices, np.float32)
    F = np.asarray(grid.triangles, np.int64)
    V0, F0 = manifold_mesh(V, F)
    assert np.array_equal(V0, V) and np.array_equal(F0, F)
    # a second box touching the first at one corner only (a pinched vertex), and a fin on an edge
    V2 = np.vstack([V, V + np.float32(0.02)])
    corner = int(np.argmin(np.linalg.norm(V2[len(V):] - V.max(0), axis=1))) + len(V)
    far = int(np.argmin(np.linalg.norm(V - V.max(0), axis=1)))
    F2 = np.vstack([F, np.where(F + len(V) == corner, far, F + len(V))])
    e = F[0]
    fin = np.vstack([V2, [[0.01, -0.01, 0.03]]]).astype(np.float32)
    F3 = np.vstack([F2, [[e[0], e[1], len(V2)]]])
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(fin.astype(np.float64)), o3d.utility.Vector3iVector(F3.astype(np.int32)))
    assert not m.is_vertex_manifold() and not m.is_edge_manifold()
    Vm, Fm = manifold_mesh(fin, F3)
    mm = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(Vm.astype(np.float64)), o3d.utility.Vector3iVector(Fm.astype(np.int32)))
    assert mm.is_vertex_manifold() and mm.is_edge_manifold()
    assert len(F) <= len(Fm) < len(F3)                       # one box's triangles are all kept at least
    uvs, tex = bake_textures(Vm, Fm, {"a": np.ones((len(Vm), 3), np.float32)}, size=32)
    assert uvs.shape == (len(Fm), 3, 2) and tex["a"].shape == (32, 32, 3)
