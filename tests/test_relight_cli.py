"""``nefii relight`` end to end on a tiny fitted run; the relit ground truth reproduced with the true
materials; environment files (.exr, .hdr) and bad input."""
import json
import math

import numpy as np
import pytest
import torch

from fit_fixtures import relight_envs, scene_material, scene_mesh, stopped_after_first_call, write_rendered_scene
from nefii.cli.main import main
from nefii.data import load_scene
from nefii.errors import InputError
from nefii.raycast import MeshGeometry
from nefii.io.exr import read_exr, write_exr
from nefii.relight.environment import load_environment, read_envmap
from nefii.relight.pathtracer import PathSettings
from nefii.relight.render import render_relit
from nefii.relight.scoring import score_view, tone_map
from nefii.relight.cameras import views_from_transforms


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_rendered_scene(tmp_path_factory.mktemp("scene"), res=16, n_train=6, n_test=2, relight=True)


@pytest.fixture(scope="module")
def fitted(scene, tmp_path_factory):
    run = tmp_path_factory.mktemp("fit") / "run"
    assert main(["fit", str(scene), "--out", str(run), "--preset", "tiny", "--quiet"]) == 0
    return run


def test_relight_writes_images_grids_and_merged_metrics(scene, fitted, capsys):
    args = ["--spp", "4", "--max-bounces", "3", "--quiet"]
    assert main(["relight", str(fitted), "--envmap", str(scene / "relight" / "dusk.exr"), *args]) == 0
    out = fitted / "relight"
    for k in (0, 1):
        rgba = read_exr(out / "dusk" / f"{k}.exr")
        assert rgba.shape == (16, 16, 4) and np.isfinite(rgba).all()
        assert 0.1 < rgba[..., 3].mean() < 0.9 and rgba[..., :3].max() > 0
        for name in (f"{k}.png", f"{k}_grid.png"):
            assert (out / "dusk" / name).is_file()
    metrics = json.loads((out / "metrics.json").read_text())
    dusk = metrics["dusk"]
    assert isinstance(dusk["psnr"], float) and isinstance(dusk["ssim"], float)
    assert [v["index"] for v in dusk["views"]] == [0, 1]
    assert dusk["psnr"] == pytest.approx(np.mean([v["psnr"] for v in dusk["views"]]))
    assert len(dusk["albedo_scale"]) == 3 and "eval has not run" in dusk["albedo_scale_source"]
    assert "albedo scale" in capsys.readouterr().out

    # after eval, its albedo scale is used; a second environment joins the first in metrics.json
    assert main(["eval", str(fitted), "--spp", "2", "--quiet"]) == 0
    assert main(["relight", str(fitted), "--envmap", str(scene / "relight" / "dawn.exr"), *args]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"dusk", "dawn"}
    views = json.loads((fitted / "eval" / "metrics.json").read_text())["views"]
    want = np.mean([v["albedo_scale"] for v in views], 0)
    assert np.allclose(metrics["dawn"]["albedo_scale"], want, rtol=1e-6)
    assert "eval" in metrics["dawn"]["albedo_scale_source"]
    assert json.loads((out / "dawn" / "render.json").read_text())["albedo_scale"] == metrics["dawn"]["albedo_scale"]

    # turned: written beside, not scored; other cameras, another folder
    assert main(["relight", str(fitted), "--envmap", str(scene / "relight" / "dusk.exr"), "--rotate", "90",
                 "--exposure", "1", "--out", str(fitted / "other"), "--cameras", str(scene / "transforms_train.json"),
                 *args]) == 0
    assert sorted(p.name for p in (fitted / "other" / "dusk_rot90_ev+1").glob("*.exr")) == \
        [f"{k}.exr" for k in range(6)]
    assert not (fitted / "other" / "metrics.json").exists()


def test_dataset_lights_renders_every_relit_environment_under_its_own_map(scene, fitted, tmp_path):
    out = tmp_path / "lights"
    assert main(["relight", str(fitted), "--dataset-lights", "--out", str(out), "--spp", "4", "--max-bounces", "2",
                 "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {*relight_envs(), "dataset_lights"}
    for env in relight_envs():
        assert [v["index"] for v in metrics[env]["views"]] == [0, 1] and (out / env / "1.exr").is_file()
        assert all(isinstance(metrics[env][k], float) for k in ("psnr", "ssim", "psnr_h", "psnr_l"))
        assert metrics[env]["envmap"] == f"the dataset's map of '{env}'"
    assert metrics["dataset_lights"]["view_count"] == 4 and metrics["dataset_lights"]["format"] == "nerf"


def test_true_materials_reproduce_the_relit_ground_truth(scene):
    """The pipeline's conventions (cameras, env file, mapping) against the fixture's independent
    renderer (SG light evaluated in closed form, direct light with visibility): with the true
    materials and one bounce the relit views match, and a map turned by 180 degrees does not."""
    data = load_scene(scene, "test")
    mesh = scene_mesh()
    geometry = MeshGeometry(mesh.vertices, mesh.faces, threads=1)
    for relit in data.relit:
        assert relit.name in relight_envs()
        for turn, spp, lo, hi in ((0.0, 64, 24.0, math.inf), (180.0, 16, -math.inf, 20.0)):
            env = load_environment(scene / "relight" / f"{relit.name}.exr", rotate=turn)
            for v in range(len(data)):
                img = render_relit(geometry, scene_material, env, data.cameras.c2w[v], data.cameras.K[v], 16, 16,
                                   spp, torch.Generator().manual_seed(v), PathSettings(max_bounces=1))
                p, _ = score_view(img.rgb.numpy(), relit.images[v].numpy(), data.ground_truth.mask[v].numpy())
                assert lo < p < hi, (relit.name, turn, v, p)


def test_views_from_transforms_match_the_dataset(scene):
    views = views_from_transforms(scene / "transforms_test.json")
    data = load_scene(scene, "test")
    assert views.indices == data.indices
    assert torch.allclose(views.cameras.c2w, data.cameras.c2w) and torch.allclose(views.cameras.K, data.cameras.K)


def test_hdr_matches_a_file_written_by_mitsuba(tmp_path):
    """RGBE through OpenCV (BGR turned to RGB) against Mitsuba's writer: within RGBE's 8-bit mantissa."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    rng = np.random.default_rng(0)
    img = np.exp(rng.normal(0.0, 2.0, (8, 16, 3))).astype(np.float32)
    img[0, 0], img[0, 1], img[0, 2] = (1, 0, 0), (0, 1, 0), (0, 0, 1)
    mi.Bitmap(img, mi.Bitmap.PixelFormat.RGB).write(str(tmp_path / "sky.hdr"))
    got = read_envmap(tmp_path / "sky.hdr")
    assert got.shape == img.shape
    assert np.all(np.abs(got - img) <= img.max(-1, keepdims=True) / 128.0)
    assert np.array_equal(got[0, :3], np.eye(3, dtype=np.float32))


def test_envmap_warnings_and_tone_curve(tmp_path):
    write_exr(tmp_path / "square.exr", np.full((8, 8, 3), 0.5, np.float32))
    with pytest.warns(UserWarning, match="not a 2:1"):
        assert read_envmap(tmp_path / "square.exr").shape == (8, 8, 3)
    neg = np.full((4, 8, 3), 0.5, np.float32)
    neg[0, 0, 0] = -1.0
    write_exr(tmp_path / "neg.exr", neg)
    with pytest.warns(UserWarning, match="negative"):
        assert read_envmap(tmp_path / "neg.exr").min() == 0.0
    x = np.array([0.0, 0.5, 0.8, 0.81, 2.0, 1e6], np.float32)
    y = tone_map(x)
    assert np.allclose(y[:3], x[:3]) and np.all(np.diff(y) > 0) and y[-1] <= 1.0
    assert y[3] == pytest.approx(0.81, abs=1e-3)  # slope 1 at the knee


def _bad_files(tmp_path):
    nan = np.ones((4, 8, 3), np.float32)
    nan[1, 2, 0] = np.nan
    write_exr(tmp_path / "nan.exr", nan)
    write_exr(tmp_path / "black.exr", np.zeros((4, 8, 3), np.float32))
    (tmp_path / "garbage.hdr").write_bytes(b"#?RGBE\nnot really\n")
    (tmp_path / "garbage.exr").write_bytes(b"\x76\x2f\x31\x01 nope")
    (tmp_path / "sky.png").write_bytes(b"")
    return {"nan.exr": "NaN or infinite", "black.exr": "black everywhere", "garbage.hdr": "not a readable",
            "garbage.exr": "not a readable", "sky.png": "unsupported", "missing.exr": "not found"}


def test_bad_envmaps_are_input_errors(tmp_path):
    for name, problem in _bad_files(tmp_path).items():
        with pytest.raises(InputError, match=problem) as e:
            load_environment(tmp_path / name)
        assert e.value.path == str(tmp_path / name)


def test_relight_bad_input_is_one_line_exit_2_and_writes_nothing(scene, fitted, tmp_path, capsys):
    cases = [(["--envmap", str(tmp_path / name)], name) for name in _bad_files(tmp_path)]
    cases += [(["--envmap", str(scene / "relight" / "dusk.exr"), "--spp", "0"], "--spp"),
              (["--envmap", str(scene / "relight" / "dusk.exr"), "--max-bounces", "0"], "--max-bounces"),
              (["--envmap", str(scene / "relight" / "dusk.exr"), "--cameras", str(tmp_path / "no.json")], "no.json")]
    out = tmp_path / "out"
    for extra, named in cases:
        rc = main(["relight", str(fitted), "--out", str(out), "--quiet", *extra])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and err[0].startswith("nefii relight: error: ") and named in err[0], err
    rc = main(["relight", str(tmp_path / "no_run"), "--envmap", str(scene / "relight" / "dusk.exr"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "model.pt" in err[0]
    assert not out.exists()


def test_an_interrupted_relight_goes_on_and_matches_an_uninterrupted_one(scene, fitted, tmp_path, monkeypatch, capsys):
    import nefii.cli.relight as relight_cli
    args = ["--envmap", str(scene / "relight" / "dusk.exr"), "--spp", "4", "--max-bounces", "2", "--quiet",
            "--albedo-scale", "none"]
    assert main(["relight", str(fitted), *args, "--out", str(tmp_path / "straight")]) == 0
    real = relight_cli.render_relit
    monkeypatch.setattr(relight_cli, "render_relit", stopped_after_first_call(real))
    assert main(["relight", str(fitted), *args, "--out", str(tmp_path / "resumed")]) == 130
    assert not (tmp_path / "resumed" / "dusk").exists()
    assert [p.name for p in (tmp_path / "resumed" / ".dusk.partial").glob("[0-9].json")] == ["0.json"]
    monkeypatch.setattr(relight_cli, "render_relit", real)
    capsys.readouterr()
    assert main(["relight", str(fitted), *args, "--out", str(tmp_path / "resumed")]) == 0
    assert "1 of 2 views already rendered" in capsys.readouterr().out
    assert not (tmp_path / "resumed" / ".dusk.partial").exists()
    for name in ("0.exr", "1.exr", "0_grid.png", "1_grid.png", "render.json"):
        assert (tmp_path / "resumed" / "dusk" / name).read_bytes() == (tmp_path / "straight" / "dusk" / name).read_bytes()
    a, b = (json.loads((tmp_path / d / "metrics.json").read_text())["dusk"] for d in ("straight", "resumed"))
    assert a == b
