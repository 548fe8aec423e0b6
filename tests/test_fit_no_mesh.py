"""A dataset without a mesh: ``nefii fit`` reconstructs its geometry first (``RUN/geometry``) and fits on it."""
import json

from fit_fixtures import write_rendered_scene
from nefii.cli.main import main
from nefii.fit.outputs import load_run


def test_fit_without_a_mesh_reconstructs_the_geometry_first(tmp_path, capsys):
    scene = write_rendered_scene(tmp_path / "scene", res=16, n_train=6, n_test=1)
    (scene / "mesh.ply").unlink()
    run = tmp_path / "run"
    fit = ["fit", str(scene), "--out", str(run), "--preset", "tiny", "--quiet", "--set", "steps=6",
           "--set", "threads=1", "--set", "exposure=per_view", "--set", "seed=3"]
    assert main(fit) == 0
    out = capsys.readouterr().out
    assert "the dataset has no mesh: reconstructing" in out and "nefii geometry: done" in out
    stage = out.split("nefii geometry: NeuS", 1)[1].splitlines()[0]
    assert "device cpu, 1 threads" in stage and "a gain per view" in stage, "the fit's threads and gains reach it"
    geo = run / "geometry"
    assert json.loads((geo / "config.json").read_text())["seed"] == 3, "the fit's seed seeds its reconstruction"
    for name in ("sdf.pt", "mesh.ply", "run.json"):
        assert (geo / name).is_file(), name
    fitted = load_run(run)
    assert fitted.geometry.folder == geo.resolve() and fitted.mesh == (geo / "mesh.ply").resolve()
    assert main(["eval", str(run), "--spp", "1", "--quiet"]) == 0

    # the reconstruction is reused, not made again, when the fit goes on
    stamp = (geo / "sdf.pt").stat().st_mtime_ns
    assert main([*fit, "--resume"]) == 0
    assert "using the geometry reconstructed from its images" in capsys.readouterr().out
    assert (geo / "sdf.pt").stat().st_mtime_ns == stamp


def test_a_fit_stopped_in_its_geometry_stage_goes_on_from_it(tmp_path, monkeypatch, capsys):
    import nefii.cli.geometry as geometry_cli
    scene = write_rendered_scene(tmp_path / "scene", res=16, n_train=6, n_test=1)
    (scene / "mesh.ply").unlink()
    run = tmp_path / "run"
    fit = ["fit", str(scene), "--out", str(run), "--preset", "tiny", "--quiet", "--set", "steps=6",
           "--set", "threads=1"]
    real = geometry_cli.run

    def stopped(args):            # the stage ran to its last checkpoint and was stopped before writing its outputs
        assert real(args) == 0
        (args.out / "sdf.pt").unlink()
        (args.out / "mesh.ply").unlink()
        raise KeyboardInterrupt

    monkeypatch.setattr(geometry_cli, "run", stopped)
    assert main(fit) == 130
    assert (run / "run.json").is_file(), "the fit's folder is a fit run from the geometry stage on"
    assert not (run / "model.pt").exists()
    monkeypatch.setattr(geometry_cli, "run", real)
    capsys.readouterr()
    assert main(fit) == 0, "the same command goes on (no --resume needed: the fit had no step yet)"
    assert "nefii geometry: resumed from" in capsys.readouterr().out
    assert (run / "model.pt").is_file() and (run / "geometry" / "sdf.pt").is_file()


def test_the_gpu_fits_reconstruction_takes_the_gpu_geometry_preset(tmp_path, monkeypatch, capsys):
    import nefii.cli.geometry as geometry_cli
    scene = write_rendered_scene(tmp_path / "scene", res=16, n_train=6, n_test=1)
    (scene / "mesh.ply").unlink()
    presets = []

    def stage(args):                                          # the stage is only asked for; nothing is reconstructed
        presets.append(args.preset)
        return 1

    monkeypatch.setattr(geometry_cli, "run", stage)
    assert main(["fit", str(scene), "--out", str(tmp_path / "run"), "--preset", "gpu", "--quiet"]) != 0
    assert presets == ["gpu"]
    assert "preset gpu" in capsys.readouterr().out
