"""TensoIR's layout (a folder a view, metadata.json + rgba.png): read as its NeRF-style twin, fitted, bad input named."""
import json

import numpy as np
import pytest

from fit_fixtures import write_rendered_scene
from nefii.cli.main import main
from nefii.data import load_scene
from nefii.data.load import detect_format
from nefii.errors import InputError
from nefii.io.images import write_png

GL = np.diag([1.0, -1.0, -1.0, 1.0])


def write_tensoir(twin, root, relight: dict | None = None):
    """``twin`` (a nefii scene) rewritten in TensoIR's layout, its views as 8-bit sRGB RGBA PNGs; ``relight``
    maps an environment's name to the test views lit by it (linear RGB)."""
    for split in ("train", "test"):
        scene = load_scene(twin, split)
        for v in range(len(scene)):
            folder = root / f"{split}_{v:03d}"
            folder.mkdir(parents=True)
            c2w_gl = scene.cameras.c2w[v].numpy() @ GL
            K = scene.cameras.K[v].numpy()
            angle = 2 * np.arctan(0.5 * scene.width / K[0, 0])
            (folder / "metadata.json").write_text(json.dumps({
                "imw": scene.width, "imh": scene.height, "cam_angle_x": float(angle), "envmap": "studio",
                "cam_transform_mat": ",".join(repr(float(x)) for x in c2w_gl.reshape(-1))}))
            alpha = scene.masks[v].numpy().astype(np.float32)[..., None]
            write_png(folder / "rgba.png", np.concatenate([scene.images[v].numpy(), alpha], -1))
            if scene.ground_truth is not None:
                write_png(folder / "albedo.png", np.concatenate([scene.ground_truth.albedo[v].numpy(), alpha], -1))
            for name, images in (relight or {}).items():
                if split == "test":
                    write_png(folder / f"rgba_{name}.png", np.concatenate([images[v], alpha], -1))
            (folder / "normal.png").write_bytes(b"not read")
    return root


@pytest.fixture(scope="module")
def twin_and_tensoir(tmp_path_factory):
    base = tmp_path_factory.mktemp("tensoir")
    twin = write_rendered_scene(base / "twin", res=16, n_train=6, n_test=2, relight=True)
    relit = load_scene(twin, "test").relit
    return twin, write_tensoir(twin, base / "lego", {r.name: r.images.numpy() for r in relit})


def test_tensoir_reads_as_its_nerf_twin(twin_and_tensoir):
    twin, root = twin_and_tensoir
    assert detect_format(root, "train")[0].name == "tensoir" and detect_format(root, "test")[0].name == "tensoir"
    for split in ("train", "test"):
        a, b = load_scene(twin, split), load_scene(root, split)
        assert b.format == "tensoir" and len(a) == len(b) and b.indices == tuple(range(len(a)))
        np.testing.assert_allclose(b.cameras.c2w.numpy(), a.cameras.c2w.numpy(), atol=1e-9)
        np.testing.assert_allclose(b.cameras.K.numpy(), a.cameras.K.numpy(), rtol=1e-9)
        assert np.array_equal(b.masks.numpy(), a.masks.numpy())
        m = a.masks.numpy() & (a.images.numpy() < 0.98).all(-1)       # an 8-bit PNG clips at 1
        diff = np.abs(b.images.numpy() - a.images.numpy())[m]          # 8-bit sRGB against float EXR
        assert diff.max() < 0.02 and diff.mean() < 0.003
        assert b.mesh_path is None
    test_twin, test = load_scene(twin, "test"), load_scene(root, "test")
    m = test_twin.masks.numpy()
    np.testing.assert_allclose(test.ground_truth.albedo.numpy()[m], test_twin.ground_truth.albedo.numpy()[m], atol=0.02)
    assert [r.name for r in test.relit] == [r.name for r in test_twin.relit] and len(test.relit) == 2
    for r, s in zip(test.relit, test_twin.relit):
        lit = m & (s.images.numpy() < 0.98).all(-1)
        assert r.envmap is None and np.abs(r.images.numpy() - s.images.numpy())[lit].max() < 0.02


def test_a_tensoir_scene_fits_on_a_given_mesh_and_evaluates(twin_and_tensoir, tmp_path):
    twin, root = twin_and_tensoir
    run = tmp_path / "run"
    assert main(["fit", str(root), "--out", str(run), "--mesh", str(twin / "mesh.ply"), "--preset", "tiny", "--quiet",
                 "--set", "steps=6", "--set", "threads=1"]) == 0
    assert main(["eval", str(run), "--spp", "1", "--quiet"]) == 0
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    assert isinstance(metrics["masked"]["albedo_psnr"], float) and metrics["masked"]["roughness_mse"] is None
    env = next((twin / "relight").glob("*.exr"))           # TensoIR's maps live outside the scene: --envmap
    assert main(["relight", str(run), "--envmap", str(env), "--spp", "2", "--max-bounces", "2", "--quiet"]) == 0
    scored = json.loads((run / "relight" / "metrics.json").read_text())[env.stem]
    assert [v["index"] for v in scored["views"]] == [0, 1] and isinstance(scored["psnr"], float)


@pytest.mark.parametrize("edit, problem", [
    (lambda m: m.update(cam_transform_mat="1,0,0"), "16 comma-separated numbers, got 3"),
    (lambda m: m.update(cam_transform_mat="a,b"), "16 comma-separated numbers"),
    (lambda m: m.update(imw=32), "imw x imh is 32x16"),
    (lambda m: m.update(cam_angle_x=4.0), "strictly between 0 and pi"),
    (lambda m: m.pop("cam_angle_x"), "'cam_angle_x' must be a number"),
])
def test_bad_metadata_is_named(twin_and_tensoir, tmp_path, edit, problem):
    import shutil
    _, root = twin_and_tensoir
    copy = shutil.copytree(root, tmp_path / "lego")
    path = copy / "train_003" / "metadata.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))
    with pytest.raises(InputError) as e:
        load_scene(copy, "train")
    assert str(path) in str(e.value) and problem in str(e.value)


def test_a_view_without_its_image_or_albedo_is_named(twin_and_tensoir, tmp_path):
    import shutil
    _, root = twin_and_tensoir
    copy = shutil.copytree(root, tmp_path / "lego")
    (copy / "test_001" / "albedo.png").unlink()
    with pytest.raises(InputError, match="albedo missing"):
        load_scene(copy, "test")
    (copy / "train_002" / "rgba.png").unlink()
    with pytest.raises(InputError) as e:
        load_scene(copy, "train")
    assert "train_002" in str(e.value) and "not found" in str(e.value)
