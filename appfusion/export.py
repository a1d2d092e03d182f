"""Export of a scan (paper §6 post-processing): mesh, UV atlas, texture maps, glTF/OBJ/PLY.

- The mesh comes from the sampled points by ball pivoting (Bernardini et al. 1999, as in §6) or is the
  TSDF mesh, whichever the pipeline measured better (:func:`mesh_from_points`).
- Point attributes are transferred to mesh vertices: normals by :class:`appfusion.points.NormalField`,
  rho_s, alpha and clusters from the nearest point; a UV atlas is computed with
  Open3D (UVAtlas), and per-vertex attributes are baked into textures. rho_d, which has the detail,
  is taken per texel instead: each texel's surface position is baked and the points' rho_d fitted
  there (:func:`texel_values`, session 33; ``docs/img/rho_d_texture_texels.png``: the demo label's
  stripe, per vertex on the left).
- Written files (``out_dir``): ``object.glb`` (glTF 2.0 binary), ``object.obj`` + ``object.mtl``,
  ``points.ply`` (binary PLY with every per-point attribute), and the exact Ward maps beside them:
  ``rho_d.png`` (sRGB) and ``rho_d.exr``, ``rho_s.exr``/``rho_s.png``, ``alpha.exr``/``alpha.png``,
  ``clusters.png``.

Ward to glTF mapping (glTF has no Ward lobe): baseColor = rho_d (sRGB texture); metallic = 0;
roughness = sqrt(alpha) — glTF squares its roughness into the GGX alpha, and a Ward lobe of roughness
alpha matches a GGX/Beckmann lobe of the same slope spread near the peak; the specular intensity
rho_s has no core-glTF slot, so it is carried in the material's ``extras`` (per cluster) and in
``rho_s.exr``. The exact parameters are always the Ward maps beside the .glb. A cluster whose lobe is
GGX (the model ladder's third rung, ``result.model``) maps exactly: glTF's lobe is GGX, and
roughness = sqrt(alpha) is its own definition (glTF's Fresnel term aside); ``extras`` names each
cluster's model.
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")

import numpy as np

from .errors import EstimationError
from .frame import linear_to_srgb
from .result import ScanResult, json_float

#: distinct colours for cluster maps (RGB 0..1)
CLUSTER_COLOURS = np.array([
    [0.90, 0.10, 0.10], [0.10, 0.60, 0.95], [0.20, 0.80, 0.20], [0.95, 0.80, 0.10],
    [0.70, 0.20, 0.90], [0.10, 0.85, 0.80], [0.95, 0.50, 0.10], [0.55, 0.55, 0.55],
], np.float32)


def cluster_colours(labels: np.ndarray) -> np.ndarray:
    """RGB colour (0..1) per label, cycling through :data:`CLUSTER_COLOURS`."""
    return CLUSTER_COLOURS[np.asarray(labels) % len(CLUSTER_COLOURS)]


def mesh_from_points(positions: np.ndarray, normals: np.ndarray, radii_factor=(1.5, 3.0, 6.0)):
    """Triangle mesh from oriented points by ball pivoting (paper §6), holes left as they are.

    Parameters
    ----------
    positions, normals : (P, 3) ndarray
    radii_factor : sequence of float
        Ball radii as multiples of the mean nearest-neighbour spacing.

    Returns
    -------
    vertices (V, 3) float32, faces (F, 3) int32
    """
    import open3d as o3d

    if len(positions) < 4:
        raise EstimationError(f"ball pivoting needs at least 4 points, got {len(positions)}")
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(positions, np.float64)))
    pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    spacing = float(np.mean(pc.compute_nearest_neighbor_distance()))
    radii = o3d.utility.DoubleVector([spacing * f for f in radii_factor])
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pc, radii)
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.triangles, np.int32)


def transfer_to_vertices(positions: np.ndarray, values: np.ndarray, vertices: np.ndarray, k: int = 4,
                         nearest: bool = False) -> np.ndarray:
    """Per-point values (P, ...) to mesh vertices (V, ...) by inverse-distance weighting of k neighbours.

    With ``nearest=True`` the nearest point's value is copied (for labels).
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(positions)
    if nearest or k == 1:
        _, idx = tree.query(vertices, k=1)
        return values[idx]
    d, idx = tree.query(vertices, k=min(k, len(positions)))
    w = 1.0 / np.maximum(d, 1e-6)
    w /= w.sum(axis=1, keepdims=True)
    v = values[idx]
    return np.einsum("vk,vk...->v...", w, v).astype(values.dtype, copy=False)


def manifold_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh made manifold for UV unwrapping: triangles on non-manifold edges removed (Open3D),
    then at each non-manifold vertex (fans of triangles that meet only at that point) every fan but
    the largest removed. UVAtlas refuses a non-manifold mesh, and it finds adjacency by position, so
    splitting such a vertex in two at one place does not help. A TSDF mesh fused with a short
    truncation from 12 noisy frames had 3 non-manifold edges and 2 such vertices in 8559 triangles
    (session 26; 6 triangles removed).

    Returns
    -------
    vertices (V', 3) float32, faces (F', 3) int64: unchanged when the mesh is manifold already.
    """
    import open3d as o3d
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    def legacy(V, F):
        return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(V, np.float64)),
                                         o3d.utility.Vector3iVector(np.asarray(F, np.int32)))

    m = legacy(vertices, faces)
    if m.is_edge_manifold() and m.is_vertex_manifold():
        return np.asarray(vertices, np.float32), np.asarray(faces, np.int64)
    for _ in range(4):
        m.remove_non_manifold_edges()
        m.remove_degenerate_triangles()
        F = np.asarray(m.triangles).astype(np.int64)
        bad = np.asarray(m.get_non_manifold_vertices())
        if len(bad) == 0:
            break
        drop = np.zeros(len(F), bool)
        for v in bad:
            # the fans around v: its triangles joined where they share an edge through v, i.e. one of
            # their two other vertices (connected components of the triangle-vertex graph)
            tris = np.flatnonzero((F == v).any(axis=1))
            other = F[tris][F[tris] != v].reshape(-1, 2)
            _, ov = np.unique(other, return_inverse=True)
            nt = len(tris)
            g = coo_matrix((np.ones(2 * nt), (np.repeat(np.arange(nt), 2), nt + ov.reshape(-1))),
                           shape=(nt + ov.max() + 1,) * 2)
            fan = connected_components(g, directed=False)[1][:nt]
            drop[tris[fan != np.argmax(np.bincount(fan))]] = True
        m = legacy(np.asarray(m.vertices), F[~drop])
    m.remove_unreferenced_vertices()
    return np.asarray(m.vertices, np.float32), np.asarray(m.triangles).astype(np.int64)


def bake_textures(vertices, faces, attrs: dict[str, np.ndarray], size: int = 1024):
    """UV-unwrap a mesh (Open3D UVAtlas) and bake per-vertex attributes into textures.

    Returns
    -------
    uvs : (F, 3, 2) float32 per-corner texture coordinates (OpenGL convention: v = 0 is the image's
        bottom row)
    textures : dict name -> (size, size, C) float32
    """
    import open3d as o3d

    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(np.asarray(vertices, np.float32))
    m.triangle.indices = o3d.core.Tensor(np.asarray(faces, np.int64))
    for name, a in attrs.items():
        a = np.asarray(a, np.float32)
        m.vertex[name] = o3d.core.Tensor(a if a.ndim == 2 else a[:, None])
    m.compute_uvatlas(size=size, parallel_partitions=max(1, min(4, os.cpu_count() or 1)),
                      nthreads=os.cpu_count() or 1)
    tex = m.bake_vertex_attr_textures(size, set(attrs), margin=2.0, fill=0.0)
    uvs = m.triangle.texture_uvs.numpy().astype(np.float32)
    return uvs, {k: v.numpy().astype(np.float32) for k, v in tex.items()}


def texel_values(positions: np.ndarray, normals: np.ndarray, values: np.ndarray, texel_positions: np.ndarray,
                 covered: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """A texture of per-point values taken at each texel's own place on the surface (beyond the paper).

    Baking per-vertex values interpolates them over the triangles, so a texture holds no more detail
    than the mesh's vertices (the demo: 3501 vertices, ~4 mm apart, for 100k points ~1 mm apart). Here
    the texels' surface positions are baked instead (linear over each triangle, so exact) and each
    covered texel takes the points' value there by :func:`appfusion.points.interpolate_mls`.

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        The scan's points and unit normals.
    values : (N, C) array
        Per-point values.
    texel_positions : (H, W, 3) array
        Baked surface positions (metres).
    covered : (H, W) bool
        Texels on (or within the bake's margin of) a triangle.
    fallback : (H, W, C) array
        The values elsewhere (e.g. the per-vertex bake).

    Returns
    -------
    (H, W, C) float32
    """
    from .points import interpolate_mls

    out = np.array(fallback, np.float32)
    if covered.any():
        out[covered] = interpolate_mls(positions, normals, np.asarray(values, np.float32),
                                       np.asarray(texel_positions)[covered])
    return out


def _write_png(path: Path, img_linear01: np.ndarray, srgb: bool = True) -> None:
    import cv2

    img = linear_to_srgb(img_linear01) if srgb else np.clip(img_linear01, 0, 1)
    img8 = np.round(img * 255).astype(np.uint8)
    if img8.ndim == 3 and img8.shape[2] == 3:
        img8 = img8[..., ::-1]
    if not cv2.imwrite(str(path), img8):
        raise OSError(f"could not write {path}")


def _write_exr(path: Path, img: np.ndarray) -> None:
    import cv2

    img = np.asarray(img, np.float32)
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")


def write_ply_points(path: Path, result: ScanResult) -> None:
    """Binary little-endian PLY of the sampled points with every per-point attribute."""
    P = len(result.positions)
    rs, al = result.point_rho_s(), result.point_alpha()
    fields = [("x", result.positions[:, 0]), ("y", result.positions[:, 1]), ("z", result.positions[:, 2]),
              ("nx", result.normals[:, 0]), ("ny", result.normals[:, 1]), ("nz", result.normals[:, 2]),
              ("rho_d_r", result.rho_d[:, 0]), ("rho_d_g", result.rho_d[:, 1]), ("rho_d_b", result.rho_d[:, 2]),
              ("rho_s_r", rs[:, 0]), ("rho_s_g", rs[:, 1]), ("rho_s_b", rs[:, 2]), ("alpha", al)]
    srgb = np.round(linear_to_srgb(result.rho_d) * 255).astype(np.uint8)
    dt = [(n, "<f4") for n, _ in fields] + [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("cluster", "<i4")]
    arr = np.empty(P, dtype=dt)
    for n, v in fields:
        arr[n] = v
    arr["red"], arr["green"], arr["blue"] = srgb[:, 0], srgb[:, 1], srgb[:, 2]
    arr["cluster"] = result.labels
    types = {"<f4": "float", "u1": "uchar", "<i4": "int"}
    header = ["ply", "format binary_little_endian 1.0", "comment appfusion scan: linear rho_d, rho_s, lobe roughness alpha (Ward or GGX per cluster: result.npz model)",
              f"element vertex {P}"] + [f"property {types[t]} {n}" for n, t in dt] + ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        f.write(arr.tobytes())


def write_obj(path: Path, vertices, faces, uvs, normals, texture_name: str, result: ScanResult) -> None:
    """OBJ with per-corner UVs and an MTL referencing the rho_d / rho_s maps."""
    F = len(faces)
    vt = uvs.reshape(-1, 2)
    lines = [f"mtllib {path.stem}.mtl", "o object"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in vt]
    lines += [f"vn {x:.5f} {y:.5f} {z:.5f}" for x, y, z in normals]
    lines.append("usemtl appearance")
    fi = faces + 1
    ti = np.arange(F * 3).reshape(F, 3) + 1
    lines += [f"f {a}/{ta}/{a} {b}/{tb}/{b} {c}/{tc}/{c}" for (a, b, c), (ta, tb, tc) in zip(fi, ti)]
    path.write_text("\n".join(lines) + "\n")
    ks = np.clip(result.rho_s.mean(axis=0), 0, 1) if result.n_clusters else np.zeros(3)
    a = float(np.mean(result.alpha)) if result.n_clusters else 0.3
    ns = max(1.0, 2.0 / max(a * a, 1e-4) - 2.0)  # Phong exponent with the same lobe width as Ward alpha
    path.with_suffix(".mtl").write_text(
        "# appfusion: OBJ/MTL cannot hold a Ward BRDF; rho_s.exr and alpha.exr beside this file are exact\n"
        "newmtl appearance\nKa 0 0 0\nKd 1 1 1\n"
        f"Ks {ks[0]:.4f} {ks[1]:.4f} {ks[2]:.4f}\nNs {ns:.1f}\nillum 2\n"
        f"map_Kd {texture_name}\nmap_Ks rho_s.png\n")


def export_result(result: ScanResult, out_dir: str | os.PathLike, texture_size: int = 1024) -> dict[str, Path]:
    """Write the mesh, textures and point cloud of a scan; returns the paths written by kind.

    The result must carry a mesh (``mesh_vertices``/``mesh_faces``); see :func:`mesh_from_points`.
    """
    import trimesh
    from PIL import Image

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    V, F = np.asarray(result.mesh_vertices, np.float32), np.asarray(result.mesh_faces, np.int64)
    if len(V) == 0 or len(F) == 0:
        raise EstimationError("export: the scan result has no mesh (too few points for a surface?)")
    V, F = manifold_mesh(V, F)                               # UVAtlas needs a manifold mesh
    # vertex normals as the relighting shades them (points.NormalField: the nearest point's normal
    # tilted by its gradient to the vertex). Median error against the truth, inverse distance over 4
    # points -> the field (session 33): demo 0.225 -> 0.080 degrees, pepper 0.348 -> 0.288, vase
    # 0.339 -> 0.270
    from .points import NormalField

    vn = NormalField(result.positions, result.normals)(V)
    attrs = {
        "rho_d": transfer_to_vertices(result.positions, result.rho_d, V),
        "rho_s": transfer_to_vertices(result.positions, result.point_rho_s(), V, nearest=True),
        "alpha": transfer_to_vertices(result.positions, result.point_alpha(), V, nearest=True),
        "cluster": cluster_colours(transfer_to_vertices(result.positions, result.labels, V, nearest=True)),
    }
    attrs["position"] = V
    attrs["covered"] = np.ones(len(V), np.float32)
    uvs, tex = bake_textures(V, F, attrs, size=texture_size)
    tex["rho_d"] = texel_values(result.positions, result.normals, result.rho_d, tex.pop("position"),
                                tex.pop("covered")[..., 0] > 0.5, tex["rho_d"])
    written: dict[str, Path] = {}
    _write_png(out / "rho_d.png", tex["rho_d"])
    _write_exr(out / "rho_d.exr", tex["rho_d"])
    _write_png(out / "rho_s.png", tex["rho_s"])
    _write_exr(out / "rho_s.exr", tex["rho_s"])
    _write_png(out / "alpha.png", tex["alpha"][..., 0], srgb=False)
    _write_exr(out / "alpha.exr", tex["alpha"][..., 0])
    _write_png(out / "clusters.png", tex["cluster"], srgb=False)
    for k in ("rho_d", "rho_s", "alpha", "clusters"):
        written[f"{k}_png"] = out / f"{k}.png"

    # glTF: unshare vertices per corner so each corner has its own UV (atlas seams)
    corner_v = V[F.reshape(-1)]
    corner_n = vn[F.reshape(-1)]
    corner_uv = uvs.reshape(-1, 2)
    faces_c = np.arange(len(corner_v)).reshape(-1, 3)
    rough = np.sqrt(np.clip(tex["alpha"][..., 0], 1e-4, 1.0))
    mr = np.stack([np.zeros_like(rough), rough, np.zeros_like(rough)], axis=-1)  # R unused, G rough, B metal
    base_img = Image.fromarray(np.round(linear_to_srgb(tex["rho_d"]) * 255).astype(np.uint8))
    mr_img = Image.fromarray(np.round(mr * 255).astype(np.uint8))
    material = trimesh.visual.material.PBRMaterial(
        name="appfusion_ward", baseColorTexture=base_img, metallicRoughnessTexture=mr_img,
        metallicFactor=0.0, roughnessFactor=1.0)
    # Open3D's baked textures put UV (0, 0) at the image's bottom-left row, the OpenGL convention that
    # trimesh's TextureVisuals and OBJ also use (trimesh flips v for glTF itself).
    uv_gl = corner_uv
    tm = trimesh.Trimesh(vertices=corner_v, faces=faces_c, vertex_normals=corner_n, process=False,
                         visual=trimesh.visual.TextureVisuals(uv=uv_gl, material=material))
    tm.metadata["extras"] = {
        "appfusion": {"model": "rho_d/pi + rho_s * f(alpha), f per cluster: Ward 1992 isotropic or GGX "
                               "(Smith G1, no Fresnel); see cluster_model",
                      "cluster_model": list(result.model),
                      "rho_s": result.rho_s.tolist(), "alpha": result.alpha.tolist(),
                      "alpha_sigma": result.alpha_sigma.tolist(),
                      "rho_s_sigma": [[json_float(v) for v in row]
                                      for row in result.rho_s_sigma],
                      "roughness_mapping": "gltf_roughness = sqrt(alpha) (exact for GGX clusters, the lobe "
                                           "of the same peak width for Ward clusters)"}}
    glb = out / "object.glb"
    glb.write_bytes(trimesh.exchange.gltf.export_glb(trimesh.Scene(tm), include_normals=True))
    written["glb"] = glb
    obj = out / "object.obj"
    write_obj(obj, V, F.astype(np.int64), np.stack([uv_gl[:, 0], uv_gl[:, 1]], 1).reshape(-1, 3, 2), vn,
              "rho_d.png", result)
    written["obj"] = obj
    ply = out / "points.ply"
    write_ply_points(ply, result)
    written["ply"] = ply
    return written
