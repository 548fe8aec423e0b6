"""nefii export and nefii view on a tiny fitted run whose material is made to vary.

The bake is held to the material field itself: the baked textures, looked up at points of the
mesh through the asset's own UVs, must reproduce ``model.material`` there. The GLB is read both
through trimesh and through its raw glTF JSON and buffers (glTF's UV convention, Y-up axes).
The viewer test opens the page in headless Chromium (SwiftShader WebGL) and skips itself where
Chromium or the pinned three.js release is not available.
"""
import base64
import io
import json
import math
import re
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from chromium import find_chromium, open_page
from fit_fixtures import write_rendered_scene
from nefii.cli.main import main
from nefii.errors import InputError
from nefii.export.asset import Z_UP_TO_Y_UP
from nefii.export.bake import push_pull, rasterise
from nefii.export.three import locate_three, module_sources
from nefii.fit.model import material_at
from nefii.fit.outputs import load_run
from nefii.io.exr import read_exr
from nefii.io.images import srgb_to_linear

TEX = 256


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny fit whose material field is then given texture (20 steps leave it nearly constant)."""
    tmp = tmp_path_factory.mktemp("export")
    scene = write_rendered_scene(tmp / "scene", res=16)
    run = tmp / "run"
    assert main(["fit", str(scene), "--out", str(run), "--preset", "tiny", "--quiet"]) == 0
    blob = torch.load(run / "model.pt", weights_only=True)
    g = torch.Generator().manual_seed(1)
    state = blob["state"]
    state["material.encoding.table"] = torch.randn(state["material.encoding.table"].shape, generator=g)
    for k in ("material.net.0.weight", "material.net.2.weight", "material.net.4.weight"):
        state[k] = 2.0 * state[k]
    # two marked lobes to find in the viewer's background: red towards world +Y, green at the zenith
    for k, axis, rgb in ((0, [0.0, 1.0, 0.0], [50.0, 1e-6, 1e-6]), (1, [0.0, 0.0, 1.0], [1e-6, 50.0, 1e-6])):
        state["env.axis_raw"][k] = torch.tensor(axis)
        state["env.log_sharpness"][k] = math.log(200.0)
        state["env.log_amplitude"][k] = torch.tensor(rgb).log()
    torch.save(blob, run / "model.pt")
    return run


@pytest.fixture(scope="module")
def glb(run, tmp_path_factory):
    out = tmp_path_factory.mktemp("glb") / "asset.glb"
    assert main(["export", str(run), "--out", str(out), "--texture-size", str(TEX), "--quiet"]) == 0
    return out


# ---------------------------------------------------------------- helpers
def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((np.asarray(a, np.float64) - b) ** 2)))


def bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Texture lookup as a GPU does it: ``uv`` in glTF convention (v down), texel centres at +0.5, clamped."""
    H, W = img.shape[:2]
    x, y = uv[:, 0] * W - 0.5, uv[:, 1] * H - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    if img.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]

    def at(r, c):
        return img[np.clip(r, 0, H - 1), np.clip(c, 0, W - 1)]

    return (at(y0, x0) * (1 - fx) * (1 - fy) + at(y0, x0 + 1) * fx * (1 - fy)
            + at(y0 + 1, x0) * (1 - fx) * fy + at(y0 + 1, x0 + 1) * fx * fy)


def read_glb(path: Path) -> tuple[dict, bytes]:
    """The JSON and BIN chunks of a binary glTF."""
    data = path.read_bytes()
    magic, version, length = struct.unpack("<4sII", data[:12])
    assert magic == b"glTF" and version == 2 and length == len(data)
    n, kind = struct.unpack("<I4s", data[12:20])
    assert kind == b"JSON"
    doc = json.loads(data[20:20 + n])
    m, kind = struct.unpack("<I4s", data[20 + n:28 + n])
    assert kind == b"BIN\x00"
    return doc, data[28 + n:28 + n + m]


def accessor(doc: dict, blob: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    arr = np.frombuffer(blob, dtype, acc["count"] * width, start)
    return arr.reshape(acc["count"], width) if width > 1 else arr


def image(doc: dict, blob: bytes, texture: int) -> np.ndarray:
    img = doc["images"][doc["textures"][texture]["source"]]
    view = doc["bufferViews"][img["bufferView"]]
    assert img["mimeType"] == "image/png"
    start = view.get("byteOffset", 0)
    pil = Image.open(io.BytesIO(blob[start:start + view["byteLength"]]))
    assert pil.mode == "RGB"
    return np.asarray(pil, np.float32) / 255.0


def field_at(run: Path, points_world: np.ndarray, normals_world: np.ndarray):
    n = normals_world / np.linalg.norm(normals_world, axis=-1, keepdims=True)
    m = material_at(load_run(run).model, torch.from_numpy(np.ascontiguousarray(points_world)).float(),
                    torch.from_numpy(np.ascontiguousarray(n)).float())
    return m.albedo.numpy(), m.roughness.numpy()


# ---------------------------------------------------------------- the GLB
def test_glb_loads_with_trimesh_with_pbr_textures_of_the_asked_size(glb):
    scene = trimesh.load(glb)
    (mesh,) = scene.geometry.values()
    mat = mesh.visual.material
    assert isinstance(mat, trimesh.visual.material.PBRMaterial)
    assert mat.baseColorTexture.size == (TEX, TEX)
    assert mat.metallicRoughnessTexture.size == (TEX, TEX)
    assert mesh.visual.uv.shape == (len(mesh.vertices), 2)
    assert len(mesh.faces) == 1292
    for name in ("envmap.exr", "README.txt"):
        assert (glb.parent / name).is_file()
    assert "Environment Texture" in (glb.parent / "README.txt").read_text()


def test_glb_material_axes_and_bake_match_the_field(glb, run):
    doc, blob = read_glb(glb)
    (material,) = doc["materials"]
    pbr = material["pbrMetallicRoughness"]
    assert pbr["metallicFactor"] == 0.0 and pbr["roughnessFactor"] == 1.0
    (prim,) = doc["meshes"][0]["primitives"]
    pos = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
    uv = accessor(doc, blob, prim["attributes"]["TEXCOORD_0"]).astype(np.float64)
    normal = accessor(doc, blob, prim["attributes"]["NORMAL"]).astype(np.float64)
    faces = accessor(doc, blob, prim["indices"]).reshape(-1, 3).astype(np.int64)
    base = image(doc, blob, pbr["baseColorTexture"]["index"])
    mr = image(doc, blob, pbr["metallicRoughnessTexture"]["index"])
    assert base.shape == mr.shape == (TEX, TEX, 3)
    assert (mr[..., 2] == 0).all() and (mr[..., 0] == 1).all()           # B metallic 0, R unused 255

    # Y-up: the file's (x, y, z) is the world's (x, z, -y); the mesh is the frozen one
    world = pos @ Z_UP_TO_Y_UP
    frozen = trimesh.load(load_run(run).mesh, force="mesh", process=False)
    assert np.allclose(np.sort(world, 0)[[0, -1]], np.sort(frozen.vertices, 0)[[0, -1]], atol=1e-5)
    assert np.allclose(world[faces].mean((0, 1)), frozen.triangles_center.mean(0), atol=1e-5)
    up = (normal @ Z_UP_TO_Y_UP)[:, 2]
    assert (up[world[:, 2] > world[:, 2].max() - 1e-4] > 0.9).all()      # the top of the ball faces +Z

    # the baked textures at points of the mesh reproduce the material field there
    scores = {}
    nw = normal @ Z_UP_TO_Y_UP
    for name, w in (("centroid", np.full(3, 1 / 3)), ("inner", np.array([0.6, 0.3, 0.1])), ("vertex", None)):
        if w is None:
            p, q, nrm = world, uv, nw
        else:
            p, q, nrm = ((a[faces] * w[:, None]).sum(1) for a in (world, uv, nw))
        albedo, rough = field_at(run, p, nrm)
        assert albedo.std(0).min() > 0.03 and rough.std() > 0.03           # the field does vary
        scores[name] = (psnr(srgb_to_linear(bilinear(base, q)), albedo), psnr(bilinear(mr, q)[:, 1], rough))
        flipped = q * [1, -1] + [0, 1]                                       # the mistake this guards against
        assert psnr(srgb_to_linear(bilinear(base, flipped)), albedo) < 25
    print("bake PSNR (albedo, roughness) dB:", {k: tuple(round(x, 1) for x in v) for k, v in scores.items()})
    for name, (a, r) in scores.items():
        assert a >= 35 and r >= 35, (name, a, r)


def test_the_bake_reads_the_material_along_the_lookup_normals(run):
    """``bake_asset(..., lookup_normals=L)`` bakes what the field gives along L (the ray caster's
    ``lookup_normal``) and keeps the asset's own normals; without L it reads along the asset's normals."""
    from nefii.export.asset import bake_asset

    model = load_run(run).model
    assert model.material.normal_offset > 0
    mesh = trimesh.load(load_run(run).mesh, force="mesh", process=False)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    n = np.asarray(mesh.vertex_normals, np.float32)
    rng = np.random.default_rng(0)
    tilted = n + 0.5 * rng.normal(size=n.shape).astype(np.float32)
    tilted /= np.linalg.norm(tilted, axis=-1, keepdims=True)
    split = bake_asset(model, v, f, n, 64, lookup_normals=tilted)
    along = bake_asset(model, v, f, tilted, 64)
    plain = bake_asset(model, v, f, n, 64)
    np.testing.assert_allclose(split.normals, plain.normals)
    np.testing.assert_allclose(split.textures.albedo, along.textures.albedo, atol=1e-6)
    assert np.abs(split.textures.albedo - plain.textures.albedo).max() > 1e-2


def test_envmap_is_the_recovered_light_in_the_design_mapping(glb, run):
    env = read_exr(glb.parent / "envmap.exr")
    assert env.shape == (512, 1024, 3)
    with torch.no_grad():
        ref = load_run(run).model.env.to_equirect(512, 1024).numpy()
    np.testing.assert_allclose(env, ref, rtol=1e-4, atol=1e-6)  # float32 sums of lobes; export may run on a GPU


# ---------------------------------------------------------------- OBJ
def test_obj_variant_loads_with_trimesh_and_matches_the_glb(run, glb, tmp_path):
    out = tmp_path / "obj" / "thing.obj"
    assert main(["export", str(run), "--out", str(out), "--texture-size", str(TEX), "--quiet"]) == 0
    names = sorted(p.name for p in out.parent.iterdir())
    assert names == ["README.txt", "envmap.exr", "thing.mtl", "thing.obj", "thing_albedo.png", "thing_roughness.png"]
    mesh = trimesh.load(out, process=False)
    assert len(mesh.faces) == 1292
    assert mesh.visual.material.image.size == (TEX, TEX)
    assert "map_Pr thing_roughness.png" in (out.parent / "thing.mtl").read_text()
    (g,) = trimesh.load(glb).geometry.values()
    assert np.allclose(mesh.vertices, g.vertices, atol=1e-5)                 # the same Y-up coordinates
    assert np.allclose(mesh.visual.uv, g.visual.uv, atol=1e-6)
    assert np.array_equal(np.asarray(Image.open(out.parent / "thing_albedo.png").convert("RGB")),
                          np.asarray(g.visual.material.baseColorTexture.convert("RGB")))
    rough = np.asarray(Image.open(out.parent / "thing_roughness.png"))
    assert rough.ndim == 2
    assert np.array_equal(rough, np.asarray(g.visual.material.metallicRoughnessTexture.convert("RGB"))[..., 1])


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("case", ["no_run", "not_a_run", "size_text", "size_small", "size_big", "out_under_file",
                                  "out_is_dir", "suffix"])
def test_bad_input_is_one_line_exit_2_and_writes_nothing(case, run, tmp_path, capsys):
    (tmp_path / "file.txt").write_text("x")
    (tmp_path / "empty_run").mkdir()
    out = tmp_path / "new" / "asset.glb"
    args = {"no_run": [str(tmp_path / "missing"), "--out", str(out)],
            "not_a_run": [str(tmp_path / "empty_run"), "--out", str(out)],
            "size_text": [str(run), "--out", str(out), "--texture-size", "big"],
            "size_small": [str(run), "--out", str(out), "--texture-size", "8"],
            "size_big": [str(run), "--out", str(out), "--texture-size", "100000"],
            "out_under_file": [str(run), "--out", str(tmp_path / "file.txt" / "asset.glb")],
            "out_is_dir": [str(run), "--out", str(tmp_path / "empty_run")],
            "suffix": [str(run), "--out", str(tmp_path / "new" / "asset.obj"), "--format", "glb"]}[case]
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    assert main(["export", *args, "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("nefii export: error: ") and "\n" not in err, err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


@pytest.mark.parametrize("case", ["no_run", "html", "asset_missing", "asset_not_glb", "three_not_npm_tarball"])
def test_view_bad_input_is_one_line_exit_2_and_writes_nothing(case, run, tmp_path, capsys):
    (tmp_path / "not.glb").write_text("solid nothing")
    (tmp_path / "three.tgz").write_bytes(b"not three")
    page = tmp_path / "page" / "view.html"
    args = {"no_run": [str(tmp_path / "missing"), "--out", str(page)],
            "html": [str(run), "--out", str(tmp_path / "view.png")],
            "asset_missing": [str(run), "--out", str(page), "--asset", str(tmp_path / "missing.glb")],
            "asset_not_glb": [str(run), "--out", str(page), "--asset", str(tmp_path / "not.glb")],
            "three_not_npm_tarball": [str(run), "--out", str(page), "--three", str(tmp_path / "three.tgz")]}[case]
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    assert main(["view", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("nefii view: error: ") and "\n" not in err, err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


# ---------------------------------------------------------------- pure parts
def test_rasterise_covers_each_texel_centre_with_its_own_point():
    uv = np.array([[0.1, 0.1], [0.9, 0.15], [0.2, 0.8], [0.95, 0.9]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    size = 32
    t = rasterise(uv, faces, size, margin=0.0)
    centre = np.stack([t.cols + 0.5, t.rows + 0.5], -1) / size
    assert np.allclose((t.bary[:, :, None] * uv[faces[t.triangle]]).sum(1), centre)
    assert (t.bary >= -1e-12).all() and np.allclose(t.bary.sum(-1), 1)
    # with a margin, texels just outside take the nearest point of the quad's edge
    wide = rasterise(uv, faces, size, margin=1.5)
    assert len(wide.rows) > len(t.rows)
    assert (wide.bary >= -1e-12).all()


def test_push_pull_keeps_covered_texels_and_fills_the_rest_without_black():
    rng = np.random.default_rng(0)
    img = rng.uniform(0.2, 0.8, (37, 50, 2))
    mask = rng.uniform(size=(37, 50)) < 0.05
    out = push_pull(np.where(mask[..., None], img, 0.0), mask)
    assert np.array_equal(out[mask], img[mask])
    assert out.min() >= 0.2 and out.max() <= 0.8


# ---------------------------------------------------------------- nefii view
def _three_or_skip():
    try:
        return locate_three(log=lambda s: None)
    except InputError as e:
        pytest.skip(f"three.js unavailable: {e}")


def test_three_modules_form_a_closed_import_map():
    sources = module_sources(_three_or_skip())
    assert {"three", "three/build/three.core.js", "three/examples/jsm/loaders/GLTFLoader.js",
            "three/examples/jsm/loaders/EXRLoader.js", "three/examples/jsm/controls/OrbitControls.js"} <= set(sources)
    for key, text in sources.items():
        for spec in re.findall(r"""\b(?:from|import)\s*\(?\s*['"]([^'"\n]+)['"]""", text):
            assert not spec.startswith("."), (key, spec)                  # every relative import rewritten
            if spec == "three" or spec.startswith(("three/build/", "three/examples/")):
                assert spec in sources, (key, spec)


def test_view_page_renders_the_model_in_headless_chromium(run, glb, tmp_path):
    chromium = find_chromium()
    if chromium is None:
        pytest.skip("no Chromium (Debian: apt-get install chromium)")
    _three_or_skip()
    given = tmp_path / "given.html"                                         # an exported GLB goes in as it is
    assert main(["view", str(run), "--asset", str(glb), "--out", str(given), "--quiet"]) == 0
    assert base64.b64encode(glb.read_bytes()) in given.read_bytes()
    page = tmp_path / "view.html"                                           # by default the page bakes its own
    assert main(["view", str(run), "--out", str(page), "--texture-size", "128", "--quiet"]) == 0
    text = page.read_text()
    imports = json.loads(re.search(r'<script type="importmap">(.*?)</script>', text, re.S).group(1))["imports"]
    assert all(url.startswith("data:") for url in imports.values())          # nothing to fetch: works offline
    assert 'src="http' not in text
    base = np.asarray(trimesh.load(glb).geometry["nefii"].visual.material.baseColorTexture.convert("RGB"))
    with open_page(chromium, page.as_uri() + "#background=0&mode=albedo", tmp_path / "profile") as tab:
        albedo = tab.screenshot()
        tab.evaluate("document.querySelector('input[value=roughness]').click()")
        rough = tab.screenshot()
        tab.evaluate("document.querySelector('input[value=shaded]').click();"
                     "document.getElementById('background').click()")
        shaded = tab.screenshot()
        # the environment as the page shows it, seen from the centre: three's +Y is world +Z, -Z is world +Y
        tab.evaluate("(() => { const v = window.nefiiView; v.renderer.setAnimationLoop(null);"
                     " v.model.visible = false; v.setExposure(-8); return 0; })()")
        seen_env = {}
        for name, look in (("+Y", "0, 0, -1"), ("-Y", "0, 0, 1"), ("+X", "1, 0, 0"), ("+Z", "0, 1, 1e-4")):
            tab.evaluate("(() => { const v = window.nefiiView; v.camera.position.set(0, 0, 0);"
                         f" v.camera.lookAt({look}); v.renderer.render(v.scene, v.camera); return 0; }})()")
            img = tab.screenshot().astype(int)
            h, w = img.shape[:2]
            seen_env[name] = img[h // 2 - 4:h // 2 + 4, w // 2 - 4:w // 2 + 4].reshape(-1, 3).mean(0)
    h, w = albedo.shape[:2]
    centre = (slice(h // 4, 3 * h // 4), slice(w // 4, 3 * w // 4))
    obj = albedo[centre].max(-1) > 8                                         # the background is black
    assert obj.mean() > 0.15, "the model does not show in the centre of the page"
    seen = albedo[centre][obj].reshape(-1, 3).astype(int)
    for c in range(3):                                                       # colours come from the texture
        assert base[..., c].min() - 3 <= np.median(seen[:, c]) <= base[..., c].max() + 3
    grey = rough[centre][obj].astype(int)
    assert np.abs(grey[:, 0] - grey[:, 1]).max() <= 2 and np.abs(grey[:, 1] - grey[:, 2]).max() <= 2
    assert not np.array_equal(grey, seen.reshape(grey.shape))
    assert shaded[centre].reshape(-1, 3).std(0).max() > 5                    # lit model over the environment
    red, green = seen_env["+Y"], seen_env["+Z"]
    assert red[0] > 60 and red[0] > 2 * max(red[1], red[2]), seen_env              # world +Y: the red lobe
    assert green[1] > 60 and green[1] > 2 * max(green[0], green[2]), seen_env      # world +Z: the green one
    for name in ("-Y", "+X"):
        assert seen_env[name].max() < 30, seen_env                                 # nothing bright elsewhere
