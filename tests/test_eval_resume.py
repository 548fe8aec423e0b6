"""An eval stopped part way goes on from the views it scored and writes what an uninterrupted one writes;
``--max-views`` scores a spread subset."""
import json
import shutil

import pytest

from fit_fixtures import stopped_after_first_call, write_rendered_scene
from nefii.cli.main import main
from nefii.data import load_scene
from nefii.evaluate.run import evaluate_run, spread_views
from nefii.fit.outputs import load_run


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval_resume")
    scene = write_rendered_scene(root / "scene", res=16, n_train=6, n_test=3)
    run = root / "run"
    assert main(["fit", str(scene), "--out", str(run), "--preset", "tiny", "--quiet", "--set", "steps=20",
                 "--set", "preview_every=0"]) == 0
    return run


def _outputs(eval_dir):
    return {p.name: p.read_bytes() for p in sorted(eval_dir.iterdir())}


class Stop(Exception):
    pass


def _stop_after(n):
    def progress(views):
        for k, v in enumerate(views):
            if k == n:
                raise Stop
            yield v
    return progress


def test_an_interrupted_eval_resumes_and_matches_an_uninterrupted_one(fitted, tmp_path, capsys):
    assert main(["eval", str(fitted), "--spp", "4", "--quiet"]) == 0
    straight = _outputs(fitted / "eval")
    assert json.loads(straight["metrics.json"])["views"][2]["index"] == 2

    out = tmp_path / "eval"
    run = load_run(fitted)
    scene = load_scene(run.data, "test")
    with pytest.raises(Stop):
        evaluate_run(run, scene, out, 4, 0, progress=_stop_after(2))
    assert not out.exists(), "nothing is written where the eval's results go until every view is scored"
    partial = tmp_path / ".eval.partial"
    assert sorted(p.name for p in partial.glob("[0-9].json")) == ["0.json", "1.json"]

    rendered = []
    lines = []
    evaluate_run(run, scene, out, 4, 0, progress=lambda vs: (rendered.append(v) or v for v in vs), say=lines.append)
    assert rendered == [2], "only the view left is rendered again"
    assert len(lines) == 1 and "2 of 3 views already scored" in lines[0]
    assert not partial.exists()
    assert _outputs(out) == straight, "the resumed eval writes byte for byte what the uninterrupted one wrote"


def test_other_settings_start_the_eval_over(fitted, tmp_path):
    run = load_run(fitted)
    scene = load_scene(run.data, "test")
    out = tmp_path / "eval"
    with pytest.raises(Stop):
        evaluate_run(run, scene, out, 4, 0, progress=_stop_after(2))
    rendered = []
    evaluate_run(run, scene, out, 8, 0, progress=lambda vs: (rendered.append(v) or v for v in vs))
    assert rendered == [0, 1, 2], "views scored at another spp are not reused"
    assert "8 estimator samples" in json.loads((out / "metrics.json").read_text())["notes"]["spp"]


def test_a_view_renders_the_same_whatever_views_come_before_it(fitted, tmp_path):
    run = load_run(fitted)
    scene = load_scene(run.data, "test")
    evaluate_run(run, scene, tmp_path / "all", 4, 0)
    evaluate_run(run, scene, tmp_path / "some", 4, 0, max_views=2)
    for layer in ("rgb", "specular"):
        assert (tmp_path / "all" / f"2_{layer}.exr").read_bytes() == (tmp_path / "some" / f"2_{layer}.exr").read_bytes()
    some = json.loads((tmp_path / "some" / "metrics.json").read_text())
    assert [v["index"] for v in some["views"]] == [0, 2]
    assert "2 of 3 test views" in some["notes"]["views"]
    assert not (tmp_path / "some" / "1_rgb.exr").exists()
    other_seed = tmp_path / "seed1"
    evaluate_run(run, scene, other_seed, 4, 1, max_views=1)
    assert (other_seed / "0_rgb.exr").read_bytes() != (tmp_path / "all" / "0_rgb.exr").read_bytes()


def test_spread_views():
    assert spread_views(5, 0) == [0, 1, 2, 3, 4]
    assert spread_views(5, 9) == [0, 1, 2, 3, 4]
    assert spread_views(200, 3) == [0, 100, 199]
    assert spread_views(3, 1) == [0]


def test_negative_max_views_is_one_line_and_exit_2(fitted, capsys):
    assert main(["eval", str(fitted), "--max-views", "-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--max-views" in err


def test_ctrl_c_keeps_the_views_scored_and_releases_the_run(fitted, tmp_path, monkeypatch, capsys):
    import nefii.evaluate.run as run_module
    real = run_module.render_view
    monkeypatch.setattr(run_module, "render_view", stopped_after_first_call(real))
    assert main(["eval", str(fitted), "--spp", "2", "--quiet"]) == 130
    assert "the same command goes on from them" in capsys.readouterr().err
    assert not (fitted / "run.lock").exists()
    assert [p.name for p in (fitted / ".eval.partial").glob("[0-9].json")] == ["0.json"]
    monkeypatch.setattr(run_module, "render_view", real)
    assert main(["eval", str(fitted), "--spp", "2", "--quiet"]) == 0
    assert "1 of 3 views already scored" in capsys.readouterr().out
    assert not (fitted / ".eval.partial").exists()


def test_material_only_scores_the_full_evals_material_to_the_bit(fitted, tmp_path):
    """``spp = 0`` (``--material-only``) draws the same sub-pixel rays as a full eval's material layers, so its
    albedo and roughness scores are the full eval's exactly; nothing of the colour is scored or written."""
    run = load_run(fitted)
    scene = load_scene(run.data, "test")
    full, material = tmp_path / "full", tmp_path / "material"
    evaluate_run(run, scene, full, 4, 0)
    evaluate_run(run, scene, material, 0, 0)
    a, b = (json.loads((d / "metrics.json").read_text()) for d in (full, material))
    for protocol in ("masked", "whole_image"):
        for key in ("albedo_psnr", "albedo_ssim", "roughness_mse"):
            assert b[protocol][key] is not None and b[protocol][key] == a[protocol][key], (protocol, key)
        for key in ("rgb_psnr", "rgb_ssim", "specular_psnr", "specular_ssim"):
            assert a[protocol][key] is not None and b[protocol][key] is None, (protocol, key)
    assert (material / "0_albedo.exr").read_bytes() == (full / "0_albedo.exr").read_bytes()
    assert not list(material.glob("*_rgb.exr")) and not list(material.glob("*_specular.exr"))
    assert "material only" in b["notes"]["spp"]


def test_material_only_needs_the_ground_truths_material(fitted, tmp_path, capsys):
    """A test split without albedo or roughness maps has nothing a material-only eval could score: a one-line
    error naming the data, exit 2, and no eval written."""
    data = tmp_path / "photos"
    shutil.copytree(load_run(fitted).data, data)
    for p in list((data / "test").glob("*_albedo.exr")) + list((data / "test").glob("*_roughness.exr")):
        p.unlink()
    copy = tmp_path / "run"
    shutil.copytree(fitted, copy, ignore=shutil.ignore_patterns("eval"))
    assert main(["eval", str(copy), "--data", str(data), "--material-only", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--material-only" in err and str(data) in err and len(err.strip().splitlines()) == 1
    assert not (copy / "eval").exists()
