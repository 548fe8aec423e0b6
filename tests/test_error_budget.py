"""benchmarks.error_budget's fit rows run at the current trainer (each substitute still fits the model's
interfaces): a few steps of every row on a tiny synthetic scene, scored."""
from __future__ import annotations

import math

import pytest
import torch

from nefii.cli.main import main
from nefii.synth import scenes

pytest.importorskip("mitsuba")


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("budget") / "scene"
    assert main(["synth", scenes.smallest_scene(), "--out", str(out), "--res", "24", "--views", "3",
                 "--test-views", "1", "--spp", "2", "--env-height", "32"]) == 0
    return out


@pytest.mark.parametrize("row", ["drift", "roughness_alone", "light_known", "albedo_known", "material_known",
                                 "indirect_known", "full"])
def test_every_fit_row_runs_and_scores(row, tiny_scene, tmp_path):
    from benchmarks.error_budget import fit_row

    scores = fit_row(tiny_scene, row, 0, tmp_path / row, steps=3, drift_steps=3, eval_spp=1,
                     device=torch.device("cpu"), extra=["batch_pixels=64", "unobserved_points=64",
                                                        "background_pixels=16", "secondary_buffer=4096",
                                                        # the light solve due at every step (the true-light rows
                                                        # must turn it off: it solves SG amplitudes)
                                                        "light_solve_every=1", "light_solve_pixels=64"])
    assert math.isfinite(scores["albedo_psnr"]) and math.isfinite(scores["roughness_mse"])
    if row in ("drift", "roughness_alone"):
        assert math.isfinite(scores["drift_glossy"]) or math.isfinite(scores["drift_rough"])


def test_albedo_known_reads_the_true_albedo_and_learns_the_roughness(tiny_scene):
    """The albedo_known row's material: albedo is the scene's at every point, roughness the field's (with
    its gradient), the warm-up's override still applied."""
    from benchmarks.error_budget import TrueAlbedo
    from nefii.data.material import MaterialOnMesh, load_material
    from nefii.fields.encodings import HashGrid
    from nefii.fields.material import MaterialField
    from nefii.raycast import MeshGeometry, Rays

    mesh = MeshGeometry.from_file(tiny_scene / "mesh.ply")
    v = torch.from_numpy(mesh.vertices).float()
    lo, hi = v.min(0).values, v.max(0).values
    centre = (lo + hi) / 2
    dirs = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    hit = mesh.intersect(Rays(centre + 3 * (hi - lo).norm() * dirs, -dirs))
    x, n = hit.position[hit.valid], hit.normal[hit.valid]
    assert len(x) > 10
    lookup = MaterialOnMesh(load_material(tiny_scene), mesh)
    field = MaterialField(HashGrid(4, 2, 12, 4, 32), 16, 2, (lo, hi))
    m = TrueAlbedo(field, lookup)(x, n)
    assert torch.allclose(m.albedo, lookup(x, n).albedo.to(m.albedo))
    m.roughness.sum().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in field.parameters())
    assert torch.all(TrueAlbedo(field, lookup)(x, n, roughness_override=0.5).roughness == 0.5)


def test_adopt_records_a_finished_run_as_a_row(tmp_path, monkeypatch):
    """``adopt`` copies a run's masked eval figures into the row's scores.json, naming the run it came from."""
    import json
    import sys

    from benchmarks import error_budget

    run = tmp_path / "run"
    (run / "eval").mkdir(parents=True)
    masked = {"albedo_psnr": 27.5, "roughness_mse": 0.031}
    (run / "eval" / "metrics.json").write_text(json.dumps({"masked": masked, "whole_image": {"albedo_psnr": 1.0}}))
    monkeypatch.setattr(sys, "argv", ["error_budget", "adopt", str(run), str(tmp_path / "scene_x"), "full",
                                      "--seed", "1", "--out", str(tmp_path / "rows")])
    error_budget.main()
    blob = json.loads((tmp_path / "rows" / "scene_x" / "full_s1" / "scores.json").read_text())
    assert blob["scores"] == masked and blob["seed"] == 1 and blob["row"] == "full" and blob["source"] == str(run)


def test_the_table_keeps_its_rows_and_reads_them_back_with_new_ones(tmp_path, monkeypatch):
    """``table`` writes every row it read to a rows file beside the table; given that file and a runs folder, a
    row of the folder replaces the file's row of the same scene, row and seed, and the others stay."""
    import json

    from benchmarks import common, error_budget

    monkeypatch.setattr(common, "RESULTS", tmp_path / "results")
    monkeypatch.setattr(error_budget, "RESULTS", tmp_path / "results")

    def put(root, row, seed, psnr):
        error_budget.save_row(error_budget.row_folder(root, tmp_path / "scene_x", row, seed), tmp_path / "scene_x",
                              row, seed, {"albedo_psnr": psnr, "roughness_mse": 0.02})

    put(tmp_path / "old", "full", 0, 27.0)
    put(tmp_path / "old", "light_known", 0, 30.0)
    error_budget.table([tmp_path / "old"], "here")
    rows_file = tmp_path / "results" / error_budget.ROWS_FILE
    assert len(rows_file.read_text().splitlines()) == 2
    put(tmp_path / "new", "full", 0, 28.0)
    put(tmp_path / "new", "full", 1, 29.0)
    error_budget.table([rows_file, tmp_path / "new"], "here")
    rows = [json.loads(line) for line in rows_file.read_text().splitlines()]
    assert {(r["row"], r["seed"]): r["scores"]["albedo_psnr"] for r in rows} == {
        ("full", 0): 28.0, ("full", 1): 29.0, ("light_known", 0): 30.0}
    md = (tmp_path / "results" / "error_budget.md").read_text()
    assert "| full | 28.50 ± 0.50 |" in md and "| light_known | 30.00 (1 seed) |" in md
